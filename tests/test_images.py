"""Rendered images of a simulated data set (`write_scene_images`) and the full chain
images → detect → calibrate → reconstruct."""

import json

import cv2
import numpy as np
import pytest

from scheimflux.calibration import read_calibration
from scheimflux.cli._main import main
from scheimflux.io import read_observations
from scheimflux.simulate import paper_rig, simulate_observations
from scheimflux.simulate._images import write_scene_images
from scheimflux.targets._board import Checkerboard


@pytest.fixture(scope="module")
def rig():
    return paper_rig(refine=False)


def test_write_scene_images_small(rig, tmp_path):
    board = Checkerboard.parse("5x4", 0.6)
    _, truth = simulate_observations(rig, board, n_views=1, n_frames=1, seed=1)
    out = tmp_path / "images"
    paths = write_scene_images(out, rig, board, truth, ambient="dark")
    names = sorted(p.relative_to(out).as_posix() for p in out.rglob("*.png"))
    assert names == ["scan/frame_0.png", "view_0_board.png", "view_0_stripe.png"]
    assert sorted(paths) == sorted(str(out / n) for n in names)
    w, h = rig.sensor_size
    for p in paths:
        img = cv2.imread(p, cv2.IMREAD_UNCHANGED)
        assert img is not None and img.shape == (h, w) and img.dtype == np.uint8
    board_img = cv2.imread(str(out / "view_0_board.png"), cv2.IMREAD_UNCHANGED)
    assert board_img.min() < 60 and board_img.max() > 180  # black and white squares
    stripe = cv2.imread(str(out / "view_0_stripe.png"), cv2.IMREAD_UNCHANGED)
    assert stripe.max() > 120 and np.median(stripe) < 30  # bright line on a dark field

    before = (out / "view_0_board.png").read_bytes()
    with pytest.raises(FileExistsError, match="overwrite"):
        write_scene_images(out, rig, board, truth)
    assert (out / "view_0_board.png").read_bytes() == before
    with pytest.raises(ValueError, match="jpg images hold 8 bits"):
        write_scene_images(out / "j", rig, board, truth, ext="jpg", bit_depth=16)
    with pytest.raises(ValueError, match="layout must be"):
        write_scene_images(out / "j", rig, board, truth, layout="triple")


@pytest.mark.slow
def test_images_detect_calibrate_reconstruct(rig, tmp_path, capsys):
    board = Checkerboard.parse("11x8", 0.3)
    d_omega = 60.0
    _, truth = simulate_observations(
        rig, board, n_views=6, n_frames=6, delta_omega_deg=d_omega, seed=3
    )
    images = tmp_path / "images"
    write_scene_images(images, rig, board, truth, ambient="low", seed=3)
    # views whose board is not wholly in the image: detect drops them (a checkerboard is
    # found whole or not at all) and names them; calibrate never sees them
    whole = np.isfinite(truth.corners_px).all(axis=(1, 2))
    assert whole.sum() >= 4

    obs_path, cal, pts = tmp_path / "obs.json", tmp_path / "cal.json", tmp_path / "pts.json"
    argv = [
        "detect",
        str(images),
        "--board",
        "11x8",
        "--square-mm",
        "0.3",
        "--scan",
        str(images / "scan"),
        "--delta-omega-deg",
        str(d_omega),
        "--gauge-radius-mm",
        "17.5",
        "--pixel-pitch-mm",
        "0.0044",
        "0.0044",
        "--out",
        str(obs_path),
    ]
    assert main(argv) == 0, capsys.readouterr().err
    obs = read_observations(obs_path)
    corners, mask = obs.corners()
    assert len(obs.views) == whole.sum() and mask.all()
    assert sorted(d.view for d in obs.dropped) == np.flatnonzero(~whole).tolist()
    err = np.linalg.norm(corners - truth.corners_px[whole], axis=-1)
    assert err.max() < 0.1, err.max()

    argv = ["calibrate", str(obs_path), "--distortion", "none", "--out", str(cal)]
    assert main(argv) == 0, capsys.readouterr().err
    loaded = read_calibration(cal)
    assert loaded.diagnostics["converged"] is True
    assert loaded.diagnostics["reprojection_rms_px"] < 0.1

    stripes = tmp_path / "scan.json"
    assert main(["extract", str(images / "scan"), "--out", str(stripes)]) == 0
    argv = ["reconstruct", str(cal), str(stripes), "--frame", "measurement", "--out", str(pts)]
    assert main(argv) == 0, capsys.readouterr().err
    m = np.concatenate(
        [np.asarray(f).reshape(-1, 3) for f in json.loads(pts.read_text())["frames"]]
    )
    assert len(m) > 500
    ecc = loaded.eccentricity_mm
    r = np.hypot(m[:, 0] - ecc[0], m[:, 1] - ecc[1])
    print(f"radius: mean {r.mean():.6f} mm, max |r - 17.5| {np.abs(r - 17.5).max() * 1e3:.3f} um")
    assert np.abs(r - 17.5).max() < 2e-3
