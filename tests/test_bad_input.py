"""Bad input as a new user gives it: each case checks the one-line message and the exit code
(the table in docs/bad-input.md lists the same cases, in the same order)."""

import json
import math
import os
import signal

import jax.numpy as jnp
import numpy as np
import pytest

import scheimflux as sf
from scheimflux.cli._main import main
from scheimflux.io._calibration import FORMAT, camera_to_dict, plane_to_dict, stage_to_dict
from scheimflux.io._files import atomic_output, write_atomic, write_json
from scheimflux.io._stripes import write_stripes

# ----------------------------------------------------------------------------- fixtures


def _cal_file(path, plane=None, stage=True):
    """A calibration file of the paper's x1.5 rig, written by hand (no solve needed)."""
    cam = sf.paper_thick_lens("scheimpflug-1.5")
    plane = sf.paper_laser_plane() if plane is None else plane
    doc = {
        "format": FORMAT,
        "model": "thick-lens",
        "camera": camera_to_dict(cam),
        "laser_plane": plane_to_dict(plane),
    }
    if stage:
        doc["stage"] = stage_to_dict(sf.paper_stage(10.0), [0.0, 0.0])
    path.write_text(json.dumps(doc))
    return str(path)


def _stripe_pixels(cam, plane, n):
    """`n` pixels on the stripe of `plane` (projections of points of the plane)."""
    X = sf.stripe_to_camera(cam, plane, jnp.array([[800.0, 600.0]])).points[0]
    d1 = jnp.cross(plane.normal, jnp.array([1.0, 0.0, 0.0]))
    pts = X + jnp.linspace(-2.0, 2.0, n)[:, None] * d1 / jnp.linalg.norm(d1)
    return np.asarray(cam.project(pts))


def _run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def _one_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def _no_tmp(folder) -> None:
    left = [n for n in os.listdir(folder) if n.startswith(".tmp-")]
    assert left == [], left


# ---------------------------------------------------------------------- reconstruct CLI


def test_reconstruct_output_folder_missing_is_found_first(tmp_path, capsys):
    # the output is checked before anything is read or computed: the calibration named
    # here does not even exist
    out = tmp_path / "no" / "pts.ply"
    code, _, err = _run(capsys, "reconstruct", "missing.json", "s.json", "--out", str(out))
    assert code == 1
    assert "output folder does not exist" in _one_line(err)


@pytest.mark.parametrize(
    "argv",
    [
        ("extract", "{frames}", "--out", "{out}"),
        ("detect", "{frames}", "--board", "11x8", "--square-mm", "0.3", "--out", "{out}"),
    ],
)
def test_detect_and_extract_output_folder_missing_is_found_first(tmp_path, capsys, argv):
    # before any image is read: the one frame here would otherwise be processed first
    import cv2

    frames = tmp_path / "frames"
    frames.mkdir()
    cv2.imwrite(str(frames / "view_0.png"), np.zeros((40, 50), np.uint8))
    out = tmp_path / "no" / "out.json"
    argv = [a.format(frames=frames, out=out) for a in argv]
    code, _, err = _run(capsys, *argv)
    assert code == 1
    assert "output folder does not exist" in _one_line(err)


def test_reconstruct_output_is_a_folder(tmp_path, capsys):
    (tmp_path / "pts.ply").mkdir()
    code, _, err = _run(
        capsys, "reconstruct", "c.json", "s.json", "--out", str(tmp_path / "pts.ply")
    )
    assert code == 1 and "is a folder" in _one_line(err)


def test_reconstruct_output_exists(tmp_path, capsys):
    (tmp_path / "pts.ply").write_text("keep")
    code, _, err = _run(
        capsys, "reconstruct", "c.json", "s.json", "--out", str(tmp_path / "pts.ply")
    )
    assert code == 1 and "pts.ply exists; pass overwrite=True (--overwrite)" in _one_line(err)
    assert (tmp_path / "pts.ply").read_text() == "keep"


def test_reconstruct_unknown_output_format(tmp_path, capsys):
    code, _, err = _run(
        capsys, "reconstruct", "c.json", "s.json", "--out", str(tmp_path / "pts.xyz")
    )
    assert code == 1 and "unknown point-cloud format '.xyz'" in _one_line(err)


def test_reconstruct_zero_frames(tmp_path, capsys):
    cal = _cal_file(tmp_path / "cal.json")
    write_stripes(tmp_path / "s.json", [])
    code, _, err = _run(
        capsys, "reconstruct", cal, str(tmp_path / "s.json"), "--out", str(tmp_path / "p.ply")
    )
    assert code == 1 and "has no frames" in _one_line(err)
    assert not (tmp_path / "p.ply").exists()


def test_reconstruct_zero_valid_points(tmp_path, capsys):
    # a laser plane behind the camera: every ray meets it behind the centre
    plane = sf.paper_laser_plane()
    cal = _cal_file(tmp_path / "cal.json", sf.LaserPlane(-plane.n))
    write_stripes(tmp_path / "s.json", [np.array([[700.0, 500.0], [900.0, 650.0]])])
    code, _, err = _run(
        capsys, "reconstruct", cal, str(tmp_path / "s.json"), "--out", str(tmp_path / "p.ply")
    )
    line = _one_line(err)
    assert code == 1
    assert "no valid point from 2 stripe pixels in 1 frames" in line
    assert "2 intersection behind the camera" in line and "nothing written" in line
    assert not (tmp_path / "p.ply").exists()


def test_reconstruct_as_many_frames_as_points_in_the_measurement_frame(tmp_path, capsys):
    # issue 11 item 1 through the CLI: 3 frames of 3 pixels; frame i must be turned by
    # i x delta omega (main turned pixel k of every frame by k x delta omega)
    cam, plane, stage = sf.paper_thick_lens(), sf.paper_laser_plane(), sf.paper_stage(10.0)
    cal = _cal_file(tmp_path / "cal.json")
    px = _stripe_pixels(cam, plane, 9).reshape(3, 3, 2)
    write_stripes(tmp_path / "s.json", list(px))
    out = tmp_path / "p.json"
    code, text, _ = _run(
        capsys, "reconstruct", cal, str(tmp_path / "s.json"), "--out", str(out),
        "--frame", "measurement",
    )  # fmt: skip
    assert code == 0 and "valid points  : 9" in text
    got = np.asarray(json.loads(out.read_text())["frames"])
    for i in range(3):
        Xc = np.asarray(sf.stripe_to_camera(cam, plane, px[i]).points)
        Xm0 = Xc @ np.asarray(stage.R_m_c).T + np.asarray(stage.t_m_c)
        a = math.radians(10.0 * i)
        Rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
        np.testing.assert_allclose(got[i], Xm0 @ Rz.T, rtol=0, atol=1e-9)


def test_reconstruct_stripes_file_is_a_folder(tmp_path, capsys):
    # a folder is read as a folder of frame images (issue 14); one without images is
    # refused in one line naming it, and nothing is written
    cal = _cal_file(tmp_path / "cal.json")
    (tmp_path / "s.json").mkdir()
    code, _, err = _run(
        capsys, "reconstruct", cal, str(tmp_path / "s.json"), "--out", str(tmp_path / "p.ply")
    )
    assert code == 1 and "no image files" in _one_line(err) and "s.json" in err
    assert not (tmp_path / "p.ply").exists()


# ------------------------------------------------------------------------- simulate CLI


_SMALL = ["--views", "3", "--frames", "2", "--no-refine", "--seed", "2"]


def test_simulate_out_is_a_file(tmp_path, capsys):
    (tmp_path / "f").write_text("x")
    code, _, err = _run(capsys, "simulate", "--out", str(tmp_path / "f"), *_SMALL)
    assert code == 1 and "exists and is not a folder" in _one_line(err)


def test_simulate_interrupted_with_overwrite_keeps_the_old_set(tmp_path, capsys, monkeypatch):
    # issue 11 item 10: a kill mid-way must not leave a new observations.json beside an
    # old truth.json. Interrupt the run after observations.json was written.
    out = tmp_path / "sim"
    out.mkdir()
    old = {}
    for name in ("observations.json", "truth.json", "scan_stripes.json"):
        (out / name).write_text(f"old {name}")
        old[name] = f"old {name}"
    import scheimflux.cli._simulate as simulate_cli
    import scheimflux.simulate._observe as observe
    from scheimflux.io import Observations, View

    # no ray tracing here (the interruption is what is tested): a one-view data set
    tiny = Observations(
        1600, 1200, (0.0044, 0.0044), np.zeros((4, 3)),
        [View(np.full((4, 2), 500.0), np.full((2, 2), 600.0))] * 3,
    )  # fmt: skip

    def killed(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(simulate_cli, "_build_rig", lambda args: None)
    monkeypatch.setattr(simulate_cli, "_default_square", lambda *args: 0.3)
    monkeypatch.setattr(observe, "simulate_observations", lambda *a, **k: (tiny, None))
    monkeypatch.setattr(observe, "write_truth", killed)
    code, _, err = _run(capsys, "simulate", "--out", str(out), *_SMALL, "--overwrite")
    assert code == 130 and "interrupted" in err
    for name, text in old.items():
        assert (out / name).read_text() == text
    _no_tmp(out)


def test_simulate_output_appearing_during_the_run_is_kept(tmp_path, capsys, monkeypatch):
    # without --overwrite: a truth.json created by someone else while simulate runs is
    # not replaced, and no new file of the set is moved in beside it
    out = tmp_path / "sim"
    import scheimflux.cli._simulate as simulate_cli
    import scheimflux.simulate._observe as observe
    from scheimflux.io import Observations, View

    tiny = Observations(
        1600, 1200, (0.0044, 0.0044), np.zeros((4, 3)),
        [View(np.full((4, 2), 500.0), np.full((2, 2), 600.0))] * 3,
    )  # fmt: skip

    def racing_write_truth(path, truth, overwrite=False):
        open(path, "w").close()
        (out / "truth.json").write_text("theirs")

    monkeypatch.setattr(simulate_cli, "_build_rig", lambda args: None)
    monkeypatch.setattr(simulate_cli, "_default_square", lambda *args: 0.3)
    monkeypatch.setattr(observe, "simulate_observations", lambda *a, **k: (tiny, None))
    monkeypatch.setattr(observe, "write_truth", racing_write_truth)
    code, _, err = _run(capsys, "simulate", "--out", str(out), *_SMALL)
    assert code == 1 and "truth.json exists; pass --overwrite" in _one_line(err)
    assert sorted(os.listdir(out)) == ["truth.json"]
    assert (out / "truth.json").read_text() == "theirs"


# ----------------------------------------------------------------------- file writing


def test_writer_never_clobbers_a_file_that_appears_during_the_write(tmp_path):
    # the check-then-replace race: another process creates the file after the check
    target = tmp_path / "out.json"
    with pytest.raises(FileExistsError, match="exists; pass overwrite=True"):
        with atomic_output(target) as tmp:
            with open(tmp, "w") as fh:
                fh.write("ours")
            target.write_text("theirs")  # appears between the check and the move
    assert target.read_text() == "theirs"
    _no_tmp(tmp_path)


def test_writer_without_hard_links_still_refuses(tmp_path, monkeypatch):
    import errno

    def no_links(src, dst):
        raise OSError(errno.EPERM, "no hard links")

    monkeypatch.setattr(os, "link", no_links)
    write_atomic(tmp_path / "a.txt", "one")
    assert (tmp_path / "a.txt").read_text() == "one"
    with pytest.raises(FileExistsError):
        with atomic_output(tmp_path / "b.txt") as tmp:
            open(tmp, "w").close()
            (tmp_path / "b.txt").write_text("theirs")
    assert (tmp_path / "b.txt").read_text() == "theirs"
    _no_tmp(tmp_path)


def test_writer_failure_or_sigterm_leaves_no_temporary_file(tmp_path):
    target = tmp_path / "out.bin"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError):
        with atomic_output(target, overwrite=True) as tmp:
            with open(tmp, "wb") as fh:
                fh.write(b"half")
            raise RuntimeError("disk full")
    with pytest.raises(KeyboardInterrupt):
        with atomic_output(target, overwrite=True) as tmp:
            with open(tmp, "wb") as fh:
                fh.write(b"half")
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(10**6):  # the handler runs between bytecodes
                pass
    assert target.read_bytes() == b"old"
    _no_tmp(tmp_path)
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # handler restored
    write_atomic(target, b"new", overwrite=True)
    assert target.read_bytes() == b"new"


def test_writer_unwritable_folder(tmp_path, monkeypatch):
    import tempfile

    from scheimflux.cli._common import CLIError, check_output, check_output_folder

    def denied(*a, **k):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(tempfile, "mkstemp", denied)
    with pytest.raises(CLIError, match=r"cannot write into output folder .*Permission denied"):
        check_output(str(tmp_path / "p.ply"), overwrite=False)
    with pytest.raises(CLIError, match="cannot write into output folder"):
        check_output_folder(str(tmp_path))


def test_write_json_refuses_nan(tmp_path):
    with pytest.raises(ValueError, match=r"x\.json: refusing to write non-finite numbers"):
        write_json(tmp_path / "x.json", {"a": float("nan")})
    assert not (tmp_path / "x.json").exists()
    _no_tmp(tmp_path)


# ------------------------------------------------------------------------------ library


def test_laser_plane_impossible_values():
    with pytest.raises(ValueError, match=r"n = \[0, 0, 0\] describes no plane"):
        sf.LaserPlane([0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="is not finite"):
        sf.LaserPlane([math.nan, 0.0, 1.0])
    with pytest.raises(ValueError, match="is not finite"):
        sf.LaserPlane([0.0, math.inf, 1.0])
    with pytest.raises(ValueError, match="collinear"):
        sf.LaserPlane.from_points([0, 0, 1.0], [0, 0, 2.0], [0, 0, 3.0])
    with pytest.raises(ValueError, match="through the camera centre"):
        sf.LaserPlane.from_points([0, 0, 0.0], [1, 0, 2.0], [0, 1, 3.0])
    with pytest.raises(ValueError, match="distance must be finite and non-zero"):
        sf.LaserPlane.from_normal_distance([0, 0, 1.0], 0.0)


def test_float16_pixels_and_points_refused():
    cam, plane = sf.paper_thick_lens(), sf.paper_laser_plane()
    with pytest.raises(ValueError, match=r"uv is float16, too coarse for metrology"):
        sf.stripe_to_camera(cam, plane, np.zeros((3, 2), np.float16))
    with pytest.raises(ValueError, match=r"X is float16"):
        cam.project(np.ones((3, 3), np.float16))


def test_frame_index_without_its_points_axis_refused():
    cam, plane, stage = sf.paper_thick_lens(), sf.paper_laser_plane(), sf.paper_stage()
    uv = jnp.full((4, 4, 2), 800.0)
    with pytest.raises(ValueError, match=r"frame_index of shape \(4,\) does not match"):
        sf.stripe_to_measurement(cam, plane, stage, uv, np.arange(4))


# ------------------------------------------------------------------- observations file


def _obs_doc():
    return {
        "format": "scheimflux.observations/1",
        "sensor": {"width": 1600, "height": 1200, "pixel_pitch_mm": [0.0044, 0.0044]},
        "nominal": {"focal_length_mm": 97.0, "magnification": 1.5},
        "board_points_mm": [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]],
        "views": [{"corners_px": [[1, 2], [3, 4], [5, 6], [7, 8]], "stripe_px": []}],
    }


@pytest.mark.parametrize(
    "edit, message",
    [
        (
            lambda d: d["nominal"].update(focal_lenght_mm=50.0),
            r"unknown key 'nominal\.focal_lenght_mm' \(did you mean 'focal_length_mm'\?\)",
        ),
        (lambda d: d.update(veiws=[]), r"unknown key 'veiws' \(did you mean 'views'\?\)"),
        (
            lambda d: d["views"][0].update(stripes_px=[]),
            r"unknown key 'views\[0\]\.stripes_px' \(did you mean 'stripe_px'\?\)",
        ),
        (
            lambda d: d["sensor"].update(colour="grey"),
            r"unknown key 'sensor\.colour'; allowed here",
        ),
    ],
)
def test_observations_unknown_keys(tmp_path, capsys, edit, message):
    from scheimflux.io import read_observations

    doc = _obs_doc()
    read_observations_ok = tmp_path / "ok.json"
    read_observations_ok.write_text(json.dumps(doc))
    read_observations(read_observations_ok)  # the unedited file is fine
    edit(doc)
    path = tmp_path / "obs.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=message):
        read_observations(path)
    # and through the CLI: one line, exit 1, before any solve
    code, _, err = _run(capsys, "calibrate", str(path), "--out", str(tmp_path / "cal.json"))
    assert code == 1
    line = _one_line(err)
    assert "obs.json" in line and "unknown key" in line


def test_pose_from_matrix_refuses_non_rotations():
    from scheimflux.geometry import Pose

    with pytest.raises(ValueError, match=r"not a rotation matrix \(\|R Rᵀ − I\| = 3, det = 8"):
        Pose.from_matrix(2 * np.eye(3), np.zeros(3))
    with pytest.raises(ValueError, match=r"det = -1"):
        Pose.from_matrix(np.diag([1.0, 1.0, -1.0]), np.zeros(3))
    with pytest.raises(ValueError, match="not finite"):
        Pose.from_matrix(np.full((3, 3), np.nan), np.zeros(3))
    with pytest.raises(ValueError, match="not a rotation matrix"):
        sf.RotaryStage(np.ones((3, 3)), np.zeros(3), 0.1)
    R = np.asarray(sf.geometry.rotation_matrix(jnp.array([0.1, -0.2, 0.3])))
    np.testing.assert_allclose(Pose.from_matrix(R, np.zeros(3)).R, R, atol=1e-14)


def test_a_folder_of_frames_given_as_a_stripes_file_says_how_to_make_one(tmp_path, capsys):
    """`verify` and `measure` read a stripes file, `reconstruct` also a folder of frames:
    a folder of frame images given to the former names `scheimflux extract`."""
    import cv2

    from scheimflux.io import iter_stripes, read_stripes

    frames = tmp_path / "scan"
    frames.mkdir()
    cv2.imwrite(str(frames / "frame_0.png"), np.zeros((8, 8), np.uint8))
    for read in (read_stripes, lambda p: list(iter_stripes(p))):
        with pytest.raises(ValueError, match="is a folder") as err:
            read(str(frames))
        assert f"scheimflux extract {frames} --out STRIPES.json" in str(err.value)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ValueError, match="is a folder") as err:
        read_stripes(str(empty))
    assert "extract" not in str(err.value)


def test_a_truncated_image_is_unreadable_and_opencv_stays_quiet(tmp_path, capfd):
    """A TIFF cut short reads as None (the commands then name the file once, as
    unreadable), and the decoder's own complaint does not reach the terminal; a whole
    image reads back as stored, grey or BGR with the alpha dropped."""
    import cv2

    from scheimflux._image import read_grey, read_image

    grey = (np.arange(120 * 160) % 251).astype(np.uint8).reshape(120, 160)
    bgra = np.dstack([grey, grey // 2, grey // 3, np.full_like(grey, 255)])
    cv2.imwrite(str(tmp_path / "g.tif"), grey)
    cv2.imwrite(str(tmp_path / "c.png"), bgra)
    data = (tmp_path / "g.tif").read_bytes()
    (tmp_path / "cut.tif").write_bytes(data[: len(data) // 3])
    capfd.readouterr()
    assert read_image(tmp_path / "cut.tif") is None and read_grey(tmp_path / "cut.tif") is None
    out, err = capfd.readouterr()
    assert out == "" and err == ""
    np.testing.assert_array_equal(read_image(tmp_path / "g.tif"), grey)
    np.testing.assert_array_equal(read_image(tmp_path / "c.png"), bgra[:, :, :3])
    assert read_grey(tmp_path / "c.png").shape == (120, 160)
