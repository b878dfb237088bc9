"""`scheimflux simulate` end to end in a temporary folder (small: 4 views, 3 frames)."""

import json
import shlex

import numpy as np
import pytest

from scheimflux.cli._main import main
from scheimflux.io import read_observations
from scheimflux.io._stripes import read_stripes
from scheimflux.simulate._observe import read_truth

_SMALL = ["--views", "4", "--frames", "3", "--no-refine", "--seed", "2"]


def test_simulate_cli(tmp_path, capsys):
    out = tmp_path / "sim"
    assert main(["simulate", "--out", str(out), *_SMALL]) == 0
    text = capsys.readouterr().out
    assert "theta = 13.307 deg" in text and "4 views" in text and "stripe points" in text

    obs = read_observations(out / "observations.json")
    assert len(obs.views) == 4 and obs.stage is not None and len(obs.stage.frames) == 3
    assert obs.nominal.focal_length_mm == 97.0 and obs.nominal.tilt_deg == (3.0, 13.0)
    truth = read_truth(out / "truth.json")
    assert len(truth.board_poses) == 4 and len(truth.scan_px) == 3
    _, mask = obs.corners()
    np.testing.assert_array_equal(mask, np.isfinite(truth.corners_px).all(axis=-1))

    frames = read_stripes(out / "scan_stripes.json")
    assert len(frames) == 3
    for f, g in zip(frames, obs.stage.frames):
        np.testing.assert_array_equal(f, g)
    assert "frames" in json.loads((out / "scan_stripes.json").read_text())

    # refuses to clobber without --overwrite, and leaves the files alone
    before = (out / "truth.json").read_text()
    assert main(["simulate", "--out", str(out), *_SMALL[:-1], "3"]) == 1
    err = capsys.readouterr().err
    assert "exists" in err and "--overwrite" in err and "Traceback" not in err
    assert (out / "truth.json").read_text() == before

    assert main(["simulate", "--out", str(out), *_SMALL[:-1], "3", "--overwrite"]) == 0
    assert (out / "truth.json").read_text() != before  # another seed


def test_simulate_cli_user_errors(tmp_path, capsys):
    assert main(["simulate", "--out", str(tmp_path), "--magnification", "5"]) == 1
    assert "magnification" in capsys.readouterr().err
    assert main(["simulate", "--out", str(tmp_path), "--board", "11by8"]) == 1
    assert "COLSxROWS" in capsys.readouterr().err
    assert main(["simulate", "--out", str(tmp_path), "--lens", "no-such-lens"]) == 1
    assert "no-such-lens" in capsys.readouterr().err
    assert not (tmp_path / "observations.json").exists()


def test_simulate_keeps_every_board_whole(tmp_path, capsys):
    """On the Tessar at ×2 the drawn poses cut 13 of 15 boards: `simulate` picks a square
    that fits (0.184 mm, not 0.225) and slides the cut boards inside, so every corner of
    every view is seen; a square given too large is left cut and the summary says so."""
    small = ["--lens", "tessar", "--magnification", "2", "--frames", "0", "--no-refine"]
    assert main(["simulate", "--out", str(tmp_path / "a"), *small, "--views", "8"]) == 0
    text = capsys.readouterr().out
    assert "0.184 mm squares" in text and "note:" not in text
    _, mask = read_observations(tmp_path / "a" / "observations.json").corners()
    assert mask.shape == (8, 88) and mask.all()

    big = [*small, "--views", "4", "--square-mm", "0.3"]
    assert main(["simulate", "--out", str(tmp_path / "b"), *big]) == 0
    text = capsys.readouterr().out
    _, mask = read_observations(tmp_path / "b" / "observations.json").corners()
    cut = [k for k in range(4) if not mask[k].all()]
    assert cut and f"cuts the board in {len(cut)} view(s)" in text and "--square-mm" in text


def test_the_default_square_of_the_paper_rig_is_unchanged():
    from scheimflux.cli._main import build_parser
    from scheimflux.cli._simulate import _build_rig, _default_square, _target_span
    from scheimflux.targets import Checkerboard

    args = build_parser("simulate").parse_args(["simulate", "--out", "x", "--no-refine"])
    rig = _build_rig(args)
    assert _target_span(Checkerboard(11, 8, 0.3)) == (12.0, 9.0)  # squares across the board
    assert _default_square(rig, 12.0, 9.0, 1.5) == 0.3


def test_simulate_another_camera_and_laser(tmp_path, capsys):
    """`--sensor`, `--pixel-pitch-um`, `--laser-angle-deg` and `--laser-azimuth-deg` build
    that rig: the truth states the sensor and pitch, every traced pixel lies on it, and the
    laser plane's normal leans by the given angle towards the given azimuth (n̂ = (cos α
    cos ψ, cos α sin ψ, sin α) in the camera frame, `laser_plane_from_angles`)."""
    import math

    out = tmp_path / "sim"
    rig = ["--sensor", "2448x2048", "--pixel-pitch-um", "3.45", "--laser-angle-deg", "45",
           "--laser-azimuth-deg", "90", "--lens", "achromat", "--magnification", "1"]  # fmt: skip
    assert main(["simulate", "--out", str(out), *rig, *_SMALL]) == 0
    assert "sensor 2448x2048 px at 0.00345 x 0.00345 mm" in capsys.readouterr().out
    truth = read_truth(out / "truth.json")
    assert truth.rig["sensor"] == [2448, 2048]
    np.testing.assert_allclose(truth.rig["pixel_pitch_mm"], [0.00345, 0.00345])
    n = np.asarray(truth.laser_plane, dtype=float)
    n = n / np.linalg.norm(n)
    a, psi = math.radians(45), math.radians(90)
    np.testing.assert_allclose(n, [math.cos(a) * math.cos(psi), math.cos(a) * math.sin(psi),
                                   math.sin(a)], atol=1e-12)  # fmt: skip
    px = truth.corners_px[np.isfinite(truth.corners_px).all(axis=-1)]
    assert len(px) and (px >= -0.5).all() and (px[:, 0] <= 2447.5).all()
    assert (px[:, 1] <= 2047.5).all()
    obs = read_observations(out / "observations.json")
    assert obs.pixel_pitch_mm == (0.00345, 0.00345)


def test_simulate_rig_options_refused_with_a_reason(tmp_path, capsys):
    cases = [
        (["--sensor", "2448"], "WIDTHxHEIGHT"),
        (["--sensor", "20x20"], "64 to 20000"),
        (["--pixel-pitch-um", "3", "4", "5"], "one or two"),
        (["--pixel-pitch-um", "0"], "0.5 to 50"),
        (["--laser-angle-deg", "0"], "(0, 90]"),
        (["--laser-azimuth-deg", "90"], "needs --laser-angle-deg"),
        (["--bit-depth", "12"], "needs --images"),
        (["--bit-depth", "16", "--images", "--image-ext", "jpg"], "PNG or TIFF"),
        (["--marker-mm", "0.2"], "is for --target charuco"),
        (["--target", "charuco", "--circle-diameter-mm", "0.1"], "circles or acircles"),
        (["--target", "charuco", "--board", "12x9"], "needs 54"),
    ]
    for extra, words in cases:
        assert main(["simulate", "--out", str(tmp_path / "x"), *extra]) == 1, extra
        err = capsys.readouterr().err
        assert words in err and "Traceback" not in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "x").exists()


def _printed_detect_command(capsys) -> list[str]:
    text = capsys.readouterr().out
    assert "sensor 1600x1200 px at 0.0044 x 0.0044 mm" in text
    line = next(s for s in text.splitlines() if s.startswith("next, as from photos: "))
    return shlex.split(line.removeprefix("next, as from photos: "))


_IMAGES = ["--views", "3", "--frames", "2", "--no-refine", "--seed", "2", "--images"]


def test_simulate_images_prints_the_detect_command(tmp_path, capsys, monkeypatch):
    """With --images the summary states the pixel pitch and ends with the `detect`
    command for the rendered images, with the nominal values the observations state
    (pitch, focal length, magnification, tilt in whole degrees, the scan): the detect
    parser reads them back as those values."""
    from scheimflux.cli._main import build_parser

    monkeypatch.chdir(tmp_path)
    small = ["--views", "1", "--frames", "1", "--no-refine", "--seed", "2", "--images"]
    assert main(["simulate", "--out", "sim", *small]) == 0
    words = _printed_detect_command(capsys)
    assert words[:3] == ["scheimflux", "detect", "sim/images"]
    args = build_parser("detect").parse_args(words[1:])
    sim = read_observations("sim/observations.json")
    assert tuple(args.pixel_pitch_mm) == sim.pixel_pitch_mm
    assert args.focal_length_mm == sim.nominal.focal_length_mm == 97.0
    assert args.magnification == sim.nominal.magnification
    assert tuple(args.tilt_deg) == sim.nominal.tilt_deg == (3.0, 13.0)
    assert args.scan == "sim/images/scan" and args.out == "obs.json"
    assert args.gauge_radius_mm == sim.stage.gauge_radius_mm
    assert args.delta_omega_deg == sim.stage.delta_omega_deg


@pytest.mark.slow
def test_the_printed_detect_command_reads_the_images(tmp_path, capsys, monkeypatch):
    """Run as printed, the detect command finds every board (simulate keeps them whole
    on the sensor) and the scan, and records the nominal values. 45 s."""
    monkeypatch.chdir(tmp_path)
    assert main(["simulate", "--out", "sim", *_IMAGES]) == 0
    words = _printed_detect_command(capsys)
    assert main(words[1:]) == 0
    obs = read_observations("obs.json")
    sim = read_observations("sim/observations.json")
    assert obs.pixel_pitch_mm == sim.pixel_pitch_mm and obs.nominal == sim.nominal
    assert len(obs.views) == 3 and not obs.dropped
    assert obs.stage is not None and len(obs.stage.frames) == 2
    assert obs.stage.gauge_radius_mm == sim.stage.gauge_radius_mm


@pytest.mark.parametrize(
    "extra",
    [
        ["--target", "charuco", "--board", "9x7", "--dictionary", "DICT_5X5_100"],
        ["--target", "circles", "--board", "7x6", "--circle-diameter-mm", "0.1"],
        ["--target", "acircles", "--board", "4x9"],
    ],
    ids=["charuco", "circles", "acircles"],
)
def test_simulate_other_targets_and_their_detect_command(tmp_path, capsys, extra):
    """`--target` simulates a ChArUco board or a circle grid (its points, the default pitch
    fitted to its span), and the `detect` command printed for its images names the same
    target: `detect`'s parser and `make_target` read it back as the simulated board."""
    from scheimflux.cli._main import build_parser
    from scheimflux.cli._simulate import _detect_command
    from scheimflux.targets._target import make_target

    out = tmp_path / "sim"
    assert main(["simulate", "--out", str(out), *extra, "--views", "3", "--frames", "0",
                 "--no-refine", "--seed", "1"]) == 0  # fmt: skip
    text = capsys.readouterr().out
    obs = read_observations(out / "observations.json")
    a = build_parser("detect").parse_args(["detect", "x", "--board", "1x1", "--square-mm", "1",
                                           "--out", "o", *extra])  # fmt: skip
    kw = dict(marker_mm=a.marker_mm, dictionary=a.dictionary, diameter_mm=a.circle_diameter_mm)
    unit = make_target(a.target, a.board, 1.0, **kw)
    n = len(unit.points_mm)
    _, mask = obs.corners()
    assert mask.shape == (3, n) and f"of {3 * n} corners seen" in text
    k = int(np.argmax(np.abs(np.asarray(unit.points_mm)[:, 0])))
    pitch = obs.board_points_mm[k][0] / unit.points_mm[k][0]
    assert f"{pitch:.3f} mm" in text or f"{pitch:g} mm" in text  # the fitted default pitch
    board = make_target(a.target, a.board, pitch, **kw)
    np.testing.assert_allclose(obs.board_points_mm, board.points_mm, rtol=1e-12, atol=1e-12)

    words = shlex.split(_detect_command(obs, board, "img"))
    back = build_parser("detect").parse_args(words[1:])
    assert back.target == a.target and back.board == a.board
    kw = dict(marker_mm=back.marker_mm, dictionary=back.dictionary,
              diameter_mm=back.circle_diameter_mm)  # fmt: skip
    again = make_target(back.target, back.board, back.square_mm, **kw)
    assert type(again) is type(board) and str(again) == str(board)
    np.testing.assert_allclose(again.points_mm, board.points_mm, rtol=1e-9)
