"""OpenCVCamera against cv2 itself, and OpenCV's calibration YAML."""

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_difference, tree_allclose

from scheimflux.camera._distortion import NoDistortion, OpenCVDistortion, RadialTangential
from scheimflux.camera._opencv import OpenCVCamera, opencv_tilt_matrices
from scheimflux.io._opencv_yaml import read_opencv_yaml, write_opencv_yaml

W, H = 1600, 1200
K = np.array([[3000.0, 0.0, 805.3], [0.0, 3012.5, 597.1], [0.0, 0.0, 1.0]])
# all 14 non-zero, realistic magnitudes; τx, τy ≈ 1.7°, −1.1°
DIST = np.array(
    [-0.12, 0.35, 1.2e-3, -8e-4, -0.9, 0.05, -0.02, 0.3, 2e-3, -1e-3, 1.5e-3, -5e-4, 0.03, -0.02]
)
ZERO3 = np.zeros(3)


def _cv_project(X, K, dist):
    out, _ = cv2.projectPoints(np.asarray(X).reshape(-1, 1, 3), ZERO3, ZERO3, K, dist)
    return out[:, 0]


def _sensor_grid(n=21):
    """n × n pixels spanning the whole sensor, corners included."""
    u, v = np.meshgrid(np.linspace(0, W - 1, n), np.linspace(0, H - 1, n))
    return np.stack([u.ravel(), v.ravel()], -1)


@pytest.fixture(scope="module")
def cam():
    return OpenCVCamera.from_opencv(K, DIST)


@pytest.fixture(scope="module")
def scene(cam):
    """441 object points (100–900 mm deep) whose images cover the whole sensor."""
    uv = _sensor_grid()
    ray = eqx.filter_jit(lambda c, p: c.backproject(p))(cam, uv)
    depth = np.random.default_rng(1).uniform(100.0, 900.0, (uv.shape[0], 1))
    return uv, np.asarray(ray.direction) * depth


_project = eqx.filter_jit(lambda c, X: c.project_with_mask(X))
_backproject = eqx.filter_jit(lambda c, uv: c.backproject(uv))


def test_project_matches_cv2(cam, scene):
    uv, X = scene
    ours, valid = _project(cam, X)
    want = _cv_project(X, K, DIST)
    assert bool(jnp.all(valid))
    err = np.abs(np.asarray(ours) - want).max()
    assert err < 1e-9, err  # measured ≈ 2e-13 px
    # the points really span the sensor
    assert want[:, 0].min() < 1 and want[:, 0].max() > W - 2
    assert want[:, 1].min() < 1 and want[:, 1].max() > H - 2


def test_tilt_matrix_is_not_transposed(cam, scene):
    """The tilt is large enough that the transposed matrix misses cv2 by many pixels."""
    _, X = scene
    xy = X[:, :2] / X[:, 2:]
    xy_d = np.asarray(eqx.filter_jit(lambda m, p: jax.vmap(m.distort)(p))(cam.distortion, xy))
    m, m_inv = (np.asarray(a) for a in opencv_tilt_matrices(0.03, -0.02))
    np.testing.assert_allclose(m @ m_inv, np.eye(3), atol=1e-15)
    h = np.concatenate([xy_d, np.ones((len(xy_d), 1))], 1) @ m  # m.T applied: wrong
    wrong = h[:, :2] / h[:, 2:] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    assert np.abs(wrong - _cv_project(X, K, DIST)).max() > 10.0


def test_tilt_alone_matches_cv2():
    dist = np.zeros(14)
    dist[12:] = [0.1, 0.07]  # strong tilt, no distortion
    cam = OpenCVCamera.from_opencv(K, dist)
    X = np.stack(np.meshgrid(np.linspace(-0.3, 0.3, 7), np.linspace(-0.2, 0.2, 5)), -1)
    X = np.concatenate([X.reshape(-1, 2), np.ones((35, 1))], 1) * 500.0
    np.testing.assert_allclose(_project(cam, X)[0], _cv_project(X, K, dist), atol=1e-9)


def test_backproject_project_round_trip(cam, scene):
    uv, X = scene
    ray = _backproject(cam, uv)
    np.testing.assert_allclose(jnp.linalg.norm(ray.direction, axis=-1), 1.0, atol=1e-15)
    np.testing.assert_array_equal(ray.origin, 0.0)
    back = _cv_project(np.asarray(ray.direction), K, DIST)  # cv2 as the referee
    assert np.abs(back - uv).max() < 1e-9
    # the rays pass through the scene points
    d = X / np.linalg.norm(X, axis=-1, keepdims=True)
    np.testing.assert_allclose(ray.direction, d, atol=1e-12)


def test_behind_camera_is_invalid(cam):
    X = jnp.array([[10.0, -5.0, 300.0], [10.0, -5.0, -300.0], [1.0, 1.0, 0.0]])
    uv, valid = _project(cam, X)
    np.testing.assert_array_equal(valid, [True, False, False])
    assert bool(jnp.all(jnp.isnan(eqx.filter_jit(lambda c, X: c.project(X))(cam, X)[1:])))


def test_jit_equals_eager_and_vmap_equals_loop(cam, scene):
    uv, X = scene
    X, uv = X[::150], uv[::150]
    batched = _project(cam, X)[0]
    rays = _backproject(cam, uv).direction
    for i in range(X.shape[0]):
        one, _ = cam.project_with_mask(X[i])  # eager, one point
        np.testing.assert_allclose(batched[i], one, rtol=0, atol=1e-10)
        r = cam.backproject(uv[i])
        np.testing.assert_allclose(rays[i], r.direction, rtol=0, atol=1e-15)
    # leading batch shapes are kept
    assert _project(cam, np.stack([X[:2]] * 4).reshape(2, 4, 3))[0].shape == (2, 4, 2)


def test_gradients_match_central_differences(cam):
    X0 = jnp.array([120.0, -80.0, 450.0])
    fn = jax.jit(lambda p: OpenCVCamera.from_opencv(K, p).project_one(X0)[0])
    got = jax.jacfwd(fn)(jnp.asarray(DIST))
    want = central_difference(fn, DIST, step=1e-7)
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)
    bp = jax.jit(lambda p: cam.backproject_one(p).direction)
    uv0 = jnp.array([1510.0, 90.0])
    np.testing.assert_allclose(
        jax.jacfwd(bp)(uv0), central_difference(bp, uv0, step=1e-3), rtol=1e-6, atol=1e-11
    )


@pytest.mark.parametrize("n", [4, 5, 8, 12, 14])
def test_from_to_opencv_short_vectors(n):
    dist = DIST[:n]
    cam = OpenCVCamera.from_opencv(K, dist)
    K2, d14 = cam.to_opencv()
    np.testing.assert_array_equal(K2, K)
    np.testing.assert_array_equal(d14[:n], dist)
    np.testing.assert_array_equal(d14[n:], 0.0)
    assert d14.shape == (14,)
    X = np.array([[100.0, 80.0, 400.0], [-150.0, 90.0, 500.0], [-60.0, -100.0, 350.0]])
    np.testing.assert_allclose(_project(cam, X)[0], _cv_project(X, K, dist), atol=1e-9)
    # OpenCV's (1, N) and (N, 1) shapes are accepted too
    assert tree_allclose(OpenCVCamera.from_opencv(K, dist[None]), cam, rtol=0, atol=0)
    assert tree_allclose(OpenCVCamera.from_opencv(K, dist[:, None]), cam, rtol=0, atol=0)


def test_to_opencv_other_distortions():
    cam = OpenCVCamera(3000.0, 3000.0, 800.0, 600.0, RadialTangential(0.1, 0.2, 0.3, 0.4, 0.5))
    np.testing.assert_array_equal(cam.to_opencv()[1][:5], [0.1, 0.2, 0.4, 0.5, 0.3])
    cam = OpenCVCamera(3000.0, 3000.0, 800.0, 600.0, NoDistortion(), tau_x=0.01)
    np.testing.assert_array_equal(cam.to_opencv()[1], [0.0] * 12 + [0.01, 0.0])


def test_from_opencv_checks():
    with pytest.raises(ValueError, match="4, 5, 8, 12 or 14"):
        OpenCVCamera.from_opencv(K, np.zeros(6))
    skewed = K.copy()
    skewed[0, 1] = 0.5
    with pytest.raises(ValueError, match="no skew"):
        OpenCVCamera.from_opencv(skewed, np.zeros(5))
    with pytest.raises(ValueError, match="3×3"):
        OpenCVCamera.from_opencv(np.eye(4), np.zeros(5))
    with pytest.raises(ValueError, match="scalar"):
        OpenCVCamera([1.0, 2.0], 1.0, 0.0, 0.0)


# --- cv2.undistortPoints versus our convergence check ---------------------------------

K_WIDE = np.array([[900.0, 0.0, 800.0], [0.0, 900.0, 600.0], [0.0, 0.0, 1.0]])
BORDER = np.array(
    [[0, 0], [W - 1, 0], [0, H - 1], [W - 1, H - 1], [0, 600], [800, 0], [W - 1, 600]],
    dtype=float,
)


def _cv_undistort_error(uv, K, dist, criteria=None):
    """|projectPoints(undistortPoints(uv)) − uv| in px: how far cv2 misses its input."""
    src = uv.reshape(-1, 1, 2)
    if criteria is None:
        xy = cv2.undistortPoints(src, K, dist)[:, 0]
    else:
        xy = cv2.undistortPoints(src, K, dist, None, None, None, criteria)[:, 0]
    X = np.concatenate([xy, np.ones((len(xy), 1))], 1)
    return np.linalg.norm(_cv_project(X, K, dist) - uv, axis=1)


def test_cv2_undistort_points_fails_where_we_converge():
    """Strong pincushion: cv2's default 5 fixed-point steps miss by hundreds of px."""
    dist = np.array(
        [0.6, 0.3, 1e-3, -1e-3, 0.2, 0.1, -0.05, 0.02, 1e-3, -1e-3, 1e-3, -1e-3, 0.03, -0.02]
    )
    cam = OpenCVCamera.from_opencv(K_WIDE, dist)
    cv_err = _cv_undistort_error(BORDER, K_WIDE, dist)
    assert cv_err.max() > 200.0  # measured: 332 px at the top-left corner
    ray = _backproject(cam, BORDER)
    assert bool(jnp.all(jnp.isfinite(ray.direction)))
    ours = _cv_project(np.asarray(ray.direction), K_WIDE, dist)
    assert np.abs(ours - BORDER).max() < 1e-9


def test_cv2_undistort_points_wrong_beyond_fold_we_flag():
    """Strong barrel: the corners lie outside the image of the lens's main sheet.

    cv2 returns a point that reprojects hundreds of px away, even with 1000 steps;
    we return NaN with `converged = False`.
    """
    dist = np.array(
        [-0.35, 0.12, 1e-3, -1e-3, -0.02, 0.1, -0.05, 0.02, 1e-3, -1e-3, 1e-3, -1e-3, 0.03, -0.02]
    )
    cam = OpenCVCamera.from_opencv(K_WIDE, dist)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 1000, 1e-15)
    corners = BORDER[:4]
    assert _cv_undistort_error(corners, K_WIDE, dist, crit).min() > 100.0  # measured 326–357
    ray = _backproject(cam, corners)
    assert bool(jnp.all(jnp.isnan(ray.direction)))
    # the flag itself, on the untilted normalised point
    _, inv_tilt = cam.tilt_matrices
    xy_t = (corners - K_WIDE[:2, 2]) / np.diag(K_WIDE)[:2]
    h = np.concatenate([xy_t, np.ones((4, 1))], 1) @ np.asarray(inv_tilt).T
    undistort = eqx.filter_jit(lambda m, p: jax.vmap(m.undistort)(p))
    _, ok = undistort(cam.distortion, jnp.asarray(h[:, :2] / h[:, 2:]))
    assert not bool(jnp.any(ok))
    # no point of the main sheet (inside the fold radius) images near a corner
    g = np.linspace(-1.5, 1.5, 121)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    r_fold = 1.33  # first det J ≤ 0 along the rays from the centre (grid search)
    xy = xy[np.hypot(*xy.T) < r_fold]
    uv = _cv_project(np.concatenate([xy, np.ones((len(xy), 1))], 1), K_WIDE, dist)
    assert min(np.linalg.norm(uv - c, axis=1).min() for c in corners) > 100.0
    # where a main-sheet solution exists (top edge centre) we find it, cv2 too
    ray = _backproject(cam, BORDER[5:6])
    np.testing.assert_allclose(
        _cv_project(np.asarray(ray.direction), K_WIDE, dist), BORDER[5:6], atol=1e-9
    )


# --- OpenCV's calibration YAML -------------------------------------------------------


def test_yaml_round_trip(cam, tmp_path):
    path = tmp_path / "camera.yaml"
    write_opencv_yaml(path, cam, (W, H))
    back, size = read_opencv_yaml(path)
    assert size == (W, H)
    assert tree_allclose(back, cam, rtol=0, atol=0)
    # OpenCV reads it as its own calibration file
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    np.testing.assert_array_equal(fs.getNode("camera_matrix").mat(), K)
    np.testing.assert_array_equal(fs.getNode("distortion_coefficients").mat().ravel(), DIST)
    assert fs.getNode("image_width").real() == W and fs.getNode("image_height").real() == H
    fs.release()


def test_yaml_short_coefficients_and_overwrite(tmp_path):
    path = tmp_path / "camera.yml"
    cam5 = OpenCVCamera.from_opencv(K, DIST[:5])
    write_opencv_yaml(path, cam5, (W, H))
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert fs.getNode("distortion_coefficients").mat().shape == (5, 1)
    fs.release()
    cam8 = OpenCVCamera.from_opencv(K, DIST[:8])
    with pytest.raises(FileExistsError):
        write_opencv_yaml(path, cam8, (W, H))
    assert tree_allclose(read_opencv_yaml(path)[0], cam5, rtol=0, atol=0)  # untouched
    write_opencv_yaml(path, cam8, (640, 480), overwrite=True)
    back, size = read_opencv_yaml(path)
    assert size == (640, 480) and tree_allclose(back, cam8, rtol=0, atol=0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["camera.yml"]  # no temp files


def test_yaml_reads_opencv_sample_file(tmp_path):
    """A file laid out like OpenCV's calibration sample, extra nodes and all."""
    path = tmp_path / "out_camera_data.yml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("calibration_time", "Thu Jan 1 00:00:00 2026")
    fs.write("nframes", 20)
    fs.write("image_width", 1280)
    fs.write("image_height", 1024)
    fs.write("board_width", 9)
    fs.write("flags", 0)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", DIST[:5].reshape(5, 1))
    fs.write("avg_reprojection_error", 0.21)
    fs.release()
    cam, size = read_opencv_yaml(path)
    assert size == (1280, 1024)
    Kb, d = cam.to_opencv()
    np.testing.assert_array_equal(Kb, K)
    np.testing.assert_array_equal(d, np.concatenate([DIST[:5], np.zeros(9)]))


def test_yaml_errors(cam, tmp_path):
    path = tmp_path / "partial.yaml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", K)
    fs.write("image_width", W)
    fs.write("image_height", H)
    fs.release()
    with pytest.raises(ValueError, match="distortion_coefficients"):
        read_opencv_yaml(path)
    with pytest.raises(FileNotFoundError):
        read_opencv_yaml(tmp_path / "missing.yaml")
    with pytest.raises(ValueError, match="image_size"):
        write_opencv_yaml(tmp_path / "x.yaml", cam, (0, 480))
    with pytest.raises(TypeError, match="OpenCVCamera"):
        write_opencv_yaml(tmp_path / "x.yaml", OpenCVDistortion(), (W, H))
