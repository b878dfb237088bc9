"""Camera-only calibration (no laser line on the boards) and the calibration read back.

The corners are made by OpenCV itself (`cv2.projectPoints`, an independent implementation
of the model) from a known camera, so the truth and OpenCV's own calibration are both at
hand; the slow ray-traced comparison is in test_opencv_calibrate.py.
"""

import importlib
import json
import math

import cv2
import numpy as np
import pytest

import scheimflux as sf
from scheimflux.calibration import calibrate, diagnostics, read_calibration, write_calibration
from scheimflux.cli import main
from scheimflux.io import (
    Observations,
    View,
    write_observations,
)

W, H = 1600, 1200
K_TRUE = np.array([[2600.0, 0.0, 803.0], [0.0, 2604.0, 598.0], [0.0, 0.0, 1.0]])
DIST_TRUE = np.array([-0.21, 0.12, 1.0e-3, -5.0e-4, 0.0])
NOISE_PX = 0.05


def _board(nx=11, ny=8, square=20.0):
    return np.array([[x * square, y * square, 0.0] for y in range(ny) for x in range(nx)])


def cv2_observations(n_views=8, seed=0, stripes=False):
    """Noisy corners of `n_views` board poses projected by cv2 (about 550 mm away, boards
    tilted up to ±35°), all inside the sensor."""
    rng = np.random.default_rng(seed)
    board = _board()
    centre = board.mean(axis=0)
    views, poses = [], []
    while len(views) < n_views:
        rvec = rng.uniform(-0.6, 0.6, 3) * [1, 1, 0.3]
        R, _ = cv2.Rodrigues(rvec)
        t = np.array([rng.uniform(-60, 60), rng.uniform(-40, 40), rng.uniform(500, 650)])
        t = t - R @ centre
        uv, _ = cv2.projectPoints(board, rvec, t, K_TRUE, DIST_TRUE)
        uv = uv[:, 0]
        if not (np.all(uv > 5) and np.all(uv[:, 0] < W - 6) and np.all(uv[:, 1] < H - 6)):
            continue
        noisy = uv + rng.normal(0.0, NOISE_PX, uv.shape)
        views.append(View(noisy, np.zeros((0, 2))))
        poses.append((rvec, t))
    obs = Observations(W, H, (0.0044, 0.0044), board, views)
    return obs, poses


@pytest.fixture(scope="module")
def camera_only():
    obs, _ = cv2_observations()
    return obs, calibrate(obs, model="opencv")


def test_no_stripes_is_a_camera_only_calibration(camera_only):
    obs, cal = camera_only
    assert cal.camera_only and cal.plane is None and cal.stage is None
    assert list(cal.fits) == ["camera"] and cal.fits["camera"].converged
    assert cal.plane_rms_mm is None and cal.gauge_rms_mm is None
    # per-coordinate RMS of 8 × 88 corners with σ = 0.05 px: 0.05 √((n − p)/n) ≈ 0.0485,
    # sampling spread ≈ 0.05 / √(2n) ≈ 0.0013 → ±4 spreads
    assert 0.043 < cal.reprojection_rms_px < 0.053
    # the truth within 4 σ of the calibration's own uncertainty
    d = diagnostics(cal)
    K, dist = cal.camera.to_opencv()
    for label, got, want in (
        ("camera.fx", K[0, 0], K_TRUE[0, 0]),
        ("camera.fy", K[1, 1], K_TRUE[1, 1]),
        ("camera.cx", K[0, 2], K_TRUE[0, 2]),
        ("camera.cy", K[1, 2], K_TRUE[1, 2]),
        ("camera.distortion.k1", dist[0], DIST_TRUE[0]),
        ("camera.distortion.p1", dist[2], DIST_TRUE[2]),
    ):
        assert abs(got - want) < 4 * d.std_of(label), (label, got, want, d.std_of(label))
    # the terms the default model leaves out stay exactly zero and are listed as frozen
    assert np.all(dist[5:] == 0.0)
    assert "camera.distortion.k4" in cal.freeze and "camera.tau_x" in cal.freeze


def test_equals_cv2_calibrate_camera(camera_only):
    """Same corners, same model (cv2's default flags): the same K to 0.01 px, and every
    intrinsic within OpenCV's own reported σ."""
    obs, cal = camera_only
    obj = [obs.board_points_mm.astype(np.float32).reshape(-1, 1, 3)] * len(obs.views)
    img = [v.corners_px.astype(np.float32).reshape(-1, 1, 2) for v in obs.views]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    out = cv2.calibrateCameraExtended(obj, img, (W, H), None, None, criteria=crit)
    K_cv, dist_cv, std_cv = out[1], out[2].ravel(), out[5].ravel()
    K, dist = cal.camera.to_opencv()
    np.testing.assert_allclose(K, K_cv, rtol=0, atol=0.01)
    ours = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist[:5]])
    theirs = np.array([K_cv[0, 0], K_cv[1, 1], K_cv[0, 2], K_cv[1, 2], *dist_cv[:5]])
    assert np.all(np.abs(ours - theirs) < std_cv[:9]), (ours - theirs) / std_cv[:9]


def test_file_round_trip_and_diagnostics_of_the_loaded_calibration(camera_only, tmp_path):
    obs, cal = camera_only
    path = tmp_path / "cal.json"
    write_calibration(path, cal)
    doc = json.loads(path.read_text())
    assert "laser_plane" not in doc and doc["model"] == "opencv"
    assert doc["sensor"] == {"width": W, "height": H}
    assert len(doc["board_poses"]["rotvec"]) == len(obs.views)

    bare = read_calibration(path)
    assert isinstance(bare, sf.Calibration) and bare.plane is None
    assert bare.sensor_size == (W, H)
    # a clear ValueError when the residuals are used (a TypeCheckError under the test
    # suite's runtime type checks, which stop it at the call: the same words)
    with pytest.raises((ValueError, TypeError), match="without its observations.*observations="):
        diagnostics(bare)

    loaded = read_calibration(path, observations=obs)
    assert isinstance(loaded, sf.Calibration)
    K, dist = cal.camera.to_opencv()
    K2, dist2 = loaded.camera.to_opencv()
    np.testing.assert_array_equal(K2, K)
    np.testing.assert_array_equal(dist2, dist)
    a, b = diagnostics(cal), diagnostics(loaded)
    assert a.labels == b.labels and a.block == b.block and a.frozen == b.frozen
    # same parameters (bit for bit through the file) and the same residual arrays: the
    # same Jacobian and covariance up to the solver's float64 rounding
    np.testing.assert_array_equal(b.values, a.values)
    np.testing.assert_allclose(b.std, a.std, rtol=1e-9, atol=0)
    np.testing.assert_allclose(b.covariance, a.covariance, rtol=1e-9, atol=1e-300)
    np.testing.assert_allclose(b.singular_values, a.singular_values, rtol=1e-9)
    assert b.variance_factor == pytest.approx(a.variance_factor, rel=1e-12)

    # written again from the loaded calibration: the same document (software aside)
    again = tmp_path / "again.json"
    write_calibration(again, loaded)
    assert json.loads(again.read_text()) == doc

    # observations that are not the calibration's are refused
    other, _ = cv2_observations(n_views=7, seed=1)
    with pytest.raises(ValueError, match="holds 8 board poses but the observations have 7"):
        read_calibration(path, observations=other)


def test_reconstruct_refuses_a_camera_only_calibration(camera_only, tmp_path, capsys):
    _, cal = camera_only
    path = tmp_path / "cal.json"
    write_calibration(path, cal)
    stripes = tmp_path / "s.json"
    stripes.write_text(json.dumps({"format": "scheimflux.stripes/1", "frames": [[[1, 2]]]}))
    out = tmp_path / "p.ply"
    assert main(["reconstruct", str(path), str(stripes), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert "camera-only calibration (no laser_plane)" in err and "\n" not in err
    assert not out.exists()


def test_stage_scan_without_board_stripes_is_refused():
    obs, _ = cv2_observations(n_views=3)
    from scheimflux.io import StageScan

    obs = Observations(
        W,
        H,
        (0.0044,) * 2,
        obs.board_points_mm,
        obs.views,
        stage=StageScan(10.0, 17.5, [np.ones((4, 2))]),
    )
    match = "rotary-stage scan or table target but no stripe pixels on any board view"
    with pytest.raises(ValueError, match=match):
        calibrate(obs, model="opencv")


def test_cli_camera_only_notes_it(camera_only, tmp_path, capsys, monkeypatch):
    obs, cal = camera_only
    # the subpackage (`sf.calibrate` is the function): the CLI looks `calibrate` up there
    calibrate_module = importlib.import_module("scheimflux.calibration")

    monkeypatch.setattr(calibrate_module, "calibrate", lambda o, **kw: cal)
    src = tmp_path / "obs.json"
    write_observations(src, obs)
    out = tmp_path / "cal.json"
    assert main(["calibrate", str(src), "--out", str(out), "--model", "opencv"]) == 0
    text = capsys.readouterr().out
    assert "laser plane: none (camera-only calibration)" in text
    assert "note: no stripe pixels on the board views: camera-only calibration" in text
    assert read_calibration(out).plane is None
    assert math.isfinite(read_calibration(out).reprojection_rms_px)
