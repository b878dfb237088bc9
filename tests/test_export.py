"""`scheimflux export CAL.json --opencv CAM.yml`: the OpenCV equivalent of a calibration,
read back with `cv2.FileStorage` and checked against the camera's own pixel rays."""

import json

import cv2
import jax.numpy as jnp
import numpy as np
import pytest

import scheimflux as sf
from scheimflux.camera._distortion import RadialTangential
from scheimflux.cli._main import main
from scheimflux.io._calibration import FORMAT, camera_to_dict, plane_to_dict

SIZE = (1600, 1200)


def _write_cal(path, camera, model="thick-lens"):
    doc = {
        "format": FORMAT,
        "model": model,
        "camera": camera_to_dict(camera),
        "laser_plane": plane_to_dict(sf.paper_laser_plane()),
    }
    path.write_text(json.dumps(doc))
    return path


def _read_fs(path):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert fs.isOpened()
    K = fs.getNode("camera_matrix").mat()
    dist = fs.getNode("distortion_coefficients").mat().ravel()
    size = (int(fs.getNode("image_width").real()), int(fs.getNode("image_height").real()))
    fs.release()
    return K, dist, size


def _ray_residual_px(camera, K, dist, n=400, seed=0):
    """Independent check: the camera's rays through random pixels, turned into OpenCV's
    frame by the best rotation (Kabsch on the rays OpenCV's model gives the same pixels),
    projected by `cv2.projectPoints`; worst distance to the pixels."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform([0, 0], [SIZE[0] - 1, SIZE[1] - 1], (n, 2))
    d = np.asarray(camera.backproject(jnp.asarray(uv)).direction)
    d14 = np.zeros(14)
    d14[: len(dist)] = dist
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    src = uv.reshape(-1, 1, 2)
    xy = cv2.undistortPoints(src, K, d14, R=np.eye(3), P=np.eye(3), criteria=crit).reshape(-1, 2)
    d_cv = np.concatenate([xy, np.ones((n, 1))], axis=1)
    d_cv /= np.linalg.norm(d_cv, axis=1, keepdims=True)
    U, _, Vt = np.linalg.svd(d_cv.T @ d)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    p, _ = cv2.projectPoints((d @ R.T).reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, d14)
    return float(np.linalg.norm(p.reshape(-1, 2) - uv, axis=1).max())


def test_export_thick_lens(tmp_path, capsys):
    cal = _write_cal(tmp_path / "cal.json", sf.paper_thick_lens())
    out = tmp_path / "cam.yml"
    argv = ["export", str(cal), "--opencv", str(out), "--image-size", *map(str, SIZE)]
    assert main(argv) == 0, capsys.readouterr().err
    printed = capsys.readouterr().out
    assert "residual" in printed and "px RMS" in printed
    K, dist, size = _read_fs(out)
    assert size == SIZE and K.shape == (3, 3) and K[0, 1] == 0 and len(dist) == 14
    # the sensor tilt is carried by OpenCV's tau (13.3 deg about y in the paper's rig)
    assert abs(np.degrees(dist[13])) == pytest.approx(13.3, abs=0.5)
    # a tilt about two axes leaves a skew OpenCV cannot hold: the docstring's 0.03 px
    res = _ray_residual_px(sf.paper_thick_lens(), K, dist)
    assert res < 0.05, res
    rms = float(printed.split("residual ")[1].split(" px RMS")[0])
    assert rms < 0.02
    # nothing is overwritten without --overwrite; with it the same file comes back
    before = out.read_bytes()
    assert main(argv) == 1
    assert "exists; pass --overwrite" in capsys.readouterr().err
    assert out.read_bytes() == before


@pytest.mark.slow
def test_export_distorted(tmp_path, capsys):
    # a thick lens with radial distortion: OpenCV's polynomial (same k1 family) fits it
    cam = sf.paper_thick_lens()
    import equinox as eqx

    cam = eqx.tree_at(lambda c: c.distortion, cam, RadialTangential(k1=-0.4, k2=0.0, k3=0.0,
                                                                      p1=0.0, p2=0.0))  # fmt: skip
    cal = _write_cal(tmp_path / "cal.json", cam)
    out = tmp_path / "cam.yaml"
    assert main(["export", str(cal), "--opencv", str(out), "--image-size", "1600", "1200"]) == 0
    K, dist, _ = _read_fs(out)
    assert _ray_residual_px(cam, K, dist) < 0.1


def test_export_pinhole(tmp_path, capsys):
    # a pinhole without skew and without tilt is OpenCV's model exactly
    pin = sf.Pinhole(36000.0, 36100.0, 0.0, 810.0, 590.0)
    cal = _write_cal(tmp_path / "pin.json", pin, "pinhole")
    out = tmp_path / "pin.yml"
    assert main(["export", str(cal), "--opencv", str(out), "--image-size", "1600", "1200"]) == 0
    K, dist, _ = _read_fs(out)
    np.testing.assert_allclose(np.diag(K)[:2], [36000.0, 36100.0], rtol=1e-6)
    np.testing.assert_allclose(K[:2, 2], [810.0, 590.0], atol=1e-3)
    assert np.abs(dist).max() < 1e-9


def test_export_bad_inputs(tmp_path, capsys):
    cal = _write_cal(tmp_path / "cal.json", sf.paper_thick_lens())
    out = tmp_path / "cam.yml"
    assert main(["export", str(cal), "--opencv", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--image-size WIDTH HEIGHT" in err
    assert main(["export", str(cal), "--opencv", str(out), "--image-size", "0", "5"]) == 1
    assert "--image-size must be two positive integers" in capsys.readouterr().err
    assert main(["export", str(tmp_path / "nope.json"), "--opencv", str(out)]) == 1
    assert "not found" in capsys.readouterr().err
    (tmp_path / "bad.json").write_text("{}")
    assert main(["export", str(tmp_path / "bad.json"), "--opencv", str(out)]) == 1
    assert "format must be" in capsys.readouterr().err
    assert not out.exists()
