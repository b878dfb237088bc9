"""Stripe → 3-D reconstruction (paper eqs. 3 and 13)."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_difference
from jax.flatten_util import ravel_pytree

import scheimflux as sf


@pytest.fixture
def system():
    cam = sf.paper_thick_lens("scheimpflug-1.5")
    plane = sf.LaserPlane.from_normal_distance([-0.15, 0.03, 0.99], 155.0)
    return cam, plane


def _grid(n=6):
    u, v = jnp.meshgrid(jnp.linspace(0, 1599, n), jnp.linspace(0, 1199, n))
    return jnp.stack([u, v], -1)


def test_rational_map_equals_paper_eq3(system):
    cam, plane = system
    uv = _grid().reshape(-1, 2)
    rec = sf.stripe_to_camera(cam, plane, uv)
    ph = jnp.concatenate([uv, jnp.ones((uv.shape[0], 1))], 1)
    kp = ph @ cam.K_f.T
    want = kp / (kp @ plane.n)[:, None]  # X = K_f p / ([A B C] K_f p)
    np.testing.assert_allclose(rec.points, want, rtol=1e-12)


def test_round_trip_and_points_on_plane(system):
    cam, plane = system
    uv = _grid()
    rec = sf.stripe_to_camera(cam, plane, uv)
    assert bool(jnp.all(rec.valid))
    np.testing.assert_allclose(cam.project(rec.points), uv, atol=1e-9)
    np.testing.assert_allclose(plane.signed_distance(rec.points), 0.0, atol=1e-11)


def test_status_codes(system):
    cam, plane = system
    # a plane containing the ray of pixel (800, 600): ray parallel to the plane
    d = cam.backproject(jnp.array([800.0, 600.0])).direction
    normal = jnp.cross(d, jnp.array([0.0, 1.0, 0.0]))
    parallel_plane = sf.LaserPlane.from_normal_distance(normal, 50.0)
    behind_plane = sf.LaserPlane.from_normal_distance(-d, 100.0)  # plane behind the camera
    uv = jnp.array([[800.0, 600.0], [jnp.nan, 3.0]])
    r1 = sf.stripe_to_camera(cam, parallel_plane, uv)
    r2 = sf.stripe_to_camera(cam, behind_plane, uv)
    assert r1.status.tolist() == [sf.Status.PARALLEL, sf.Status.INVALID_PIXEL]
    assert r2.status.tolist() == [sf.Status.BEHIND_CAMERA, sf.Status.INVALID_PIXEL]
    for r in (r1, r2):
        assert bool(jnp.all(jnp.isnan(r.points)))
        assert not bool(jnp.any(r.valid))


@pytest.mark.parametrize("shape", [(), (1,), (3, 1, 2)])
def test_batch_shapes_jit_eager_vmap(system, shape, getkey):
    cam, plane = system
    uv = jax.random.uniform(getkey(), shape + (2,), minval=0.0, maxval=1200.0)
    rec = sf.stripe_to_camera(cam, plane, uv)
    assert rec.points.shape == shape + (3,) and rec.status.shape == shape
    with jax.disable_jit():
        eager = sf.stripe_to_camera(cam, plane, uv)
    np.testing.assert_allclose(rec.points, eager.points, rtol=1e-13)
    flat = uv.reshape(-1, 2)
    loop = jnp.stack([sf.stripe_to_camera(cam, plane, p).points for p in flat])
    np.testing.assert_allclose(rec.points.reshape(-1, 3), loop, rtol=1e-13)


def test_float32_and_float64(system):
    cam, plane = system
    uv64 = _grid()
    r64 = sf.stripe_to_camera(cam, plane, uv64)
    r32 = sf.stripe_to_camera(cam, plane, uv64.astype(jnp.float32))
    assert r32.points.dtype == jnp.float32 and r64.points.dtype == jnp.float64
    # float32 keeps the points to a few 1e-7 relative: ~50 nm at 155 mm
    np.testing.assert_allclose(r32.points, r64.points, rtol=3e-6, atol=1e-3)


def test_shape_errors(system):
    cam, plane = system
    with pytest.raises(ValueError, match=r"uv must have shape \(\.\.\., 2\)"):
        sf.stripe_to_camera(cam, plane, jnp.zeros((5, 3)))
    stage = sf.paper_stage()
    with pytest.raises(ValueError, match="frame_index"):
        sf.stripe_to_measurement(cam, plane, stage, jnp.zeros((4, 5, 2)), np.arange(3))
    # a per-frame index without its points axis is refused, never guessed
    with pytest.raises(ValueError, match=r"frame_index\[:, None\]"):
        sf.stripe_to_measurement(cam, plane, stage, jnp.zeros((4, 5, 2)), np.arange(4))


def test_measurement_frame(system):
    cam, plane = system
    stage = sf.RotaryStage(np.eye(3), [1.0, 2.0, 3.0], math.radians(10.0))
    uv = jnp.broadcast_to(jnp.array([[700.0, 500.0], [900.0, 650.0]]), (4, 2, 2))
    rec = sf.stripe_to_measurement(cam, plane, stage, uv, np.arange(4)[:, None])
    Xc = sf.stripe_to_camera(cam, plane, uv[0]).points + jnp.array([1.0, 2.0, 3.0])
    for i in range(4):
        a = math.radians(10.0 * i)
        Rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
        np.testing.assert_allclose(rec.points[i], Xc @ Rz.T, rtol=1e-12)
    # radius about z_m is invariant under the table rotation
    r = jnp.linalg.norm(rec.points[..., :2], axis=-1)
    np.testing.assert_allclose(r, jnp.broadcast_to(r[0], r.shape), rtol=1e-12)
    # a scalar frame index and an explicit full-shape index agree
    a = sf.stripe_to_measurement(cam, plane, stage, uv[2], 2).points
    np.testing.assert_allclose(a, rec.points[2], rtol=1e-13)


def test_reconstruction_gradients_match_finite_differences(system):
    cam, plane = system
    uv = jnp.array([[300.0, 200.0], [1300.0, 1000.0]])
    flat, unravel = ravel_pytree((cam, plane))

    def g(v):
        c, p = unravel(v)
        return sf.stripe_to_camera(c, p, uv).points

    J = jax.jacfwd(g)(flat)
    J_fd = central_difference(g, flat, step=1e-7)
    scale = np.abs(J_fd).max(axis=-1, keepdims=True)
    np.testing.assert_allclose(J / scale, J_fd / scale, atol=2e-6)
    # and w.r.t. the pixel
    Ju = jax.jacfwd(lambda p: sf.stripe_to_camera(cam, plane, p).points)(uv[0])
    np.testing.assert_allclose(
        Ju,
        central_difference(lambda p: sf.stripe_to_camera(cam, plane, p).points, uv[0]),
        rtol=1e-6,
    )


def test_frame_index_with_as_many_frames_as_points(system):
    # Issue 11 item 1: with F == N a 1-D per-frame index used to be applied along the
    # points axis by a shape heuristic, silently. The explicit (F, 1) index must turn
    # frame i by i * delta_omega; the expected points come from the camera frame and the
    # stage's closed form, one frame at a time.
    cam, plane = system
    stage = sf.RotaryStage(np.eye(3), [1.0, 2.0, 3.0], math.radians(10.0))
    F = 3
    uv = jnp.asarray(
        np.stack([[[700.0 + 50 * i + 10 * k, 500.0 + 40 * k] for k in range(F)] for i in range(F)])
    )
    rec = sf.stripe_to_measurement(cam, plane, stage, uv, np.arange(F)[:, None])
    for i in range(F):
        Xc = np.asarray(sf.stripe_to_camera(cam, plane, uv[i]).points) + [1.0, 2.0, 3.0]
        a = math.radians(10.0 * i)
        Rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
        np.testing.assert_allclose(rec.points[i], Xc @ Rz.T, rtol=1e-12)
    # the ambiguous 1-D index is refused (main applied it along the points)
    with pytest.raises(ValueError, match="frame_index"):
        sf.stripe_to_measurement(cam, plane, stage, uv, np.arange(F))
    # a full (F, N) index and the (F, 1) index agree
    full = sf.stripe_to_measurement(cam, plane, stage, uv, np.repeat(np.arange(F)[:, None], F, 1))
    np.testing.assert_array_equal(np.asarray(full.points), np.asarray(rec.points))


def test_degenerate_plane_status(system):
    cam, _ = system
    uv = _grid(3)
    # plane 0.15 µm from the camera centre (issue 11 item 4): every point would collapse
    # onto the centre; it must not be "valid"
    near = sf.LaserPlane.from_normal_distance([-0.15, 0.03, 0.99], 1.5e-4)
    rec = sf.stripe_to_camera(cam, near, uv)
    assert np.all(np.asarray(rec.status) == sf.Status.DEGENERATE_PLANE)
    assert np.all(np.isnan(np.asarray(rec.points)))
    # just beyond the threshold the plane works and the points lie on it
    ok = sf.LaserPlane.from_normal_distance([-0.15, 0.03, 0.99], 2e-3)
    rec = sf.stripe_to_camera(cam, ok, uv)
    assert bool(jnp.all(rec.valid))
    np.testing.assert_allclose(ok.signed_distance(rec.points), 0.0, atol=1e-15)
    # a traced non-finite plane (no construction check under jit) gets the status too
    bad = jax.jit(lambda s: sf.LaserPlane(jnp.array([s, 0.0, 1.0])))(jnp.nan)
    rec = sf.stripe_to_camera(cam, bad, uv)
    assert np.all(np.asarray(rec.status) == sf.Status.DEGENERATE_PLANE)


def test_outside_sensor_status(system):
    cam, plane = system
    uv = jnp.array([[-300.0, 500.0], [800.0, 600.0], [1599.4, 1199.4], [1599.6, 10.0]])
    rec = sf.stripe_to_camera(cam, plane, uv, sensor_size=(1600, 1200))
    O, K = sf.Status.OUTSIDE_SENSOR, sf.Status.OK
    assert rec.status.tolist() == [O, K, K, O]
    assert np.all(np.isnan(np.asarray(rec.points)[[0, 3]]))
    # without a sensor size the same pixels reconstruct (the old behaviour)
    assert bool(jnp.all(sf.stripe_to_camera(cam, plane, uv).valid))
    stage = sf.paper_stage()
    rm = sf.stripe_to_measurement(cam, plane, stage, uv, 0, sensor_size=(1600, 1200))
    assert rm.status.tolist() == [O, K, K, O]
    with pytest.raises(ValueError, match="sensor_size"):
        sf.stripe_to_camera(cam, plane, uv, sensor_size=(0, 1200))


def _masked_loss(cam, plane, px, w):
    rec = sf.stripe_to_camera(cam, plane, px)
    pts = jnp.where(rec.valid[:, None], rec.points, 0.0)
    return jnp.sum(w[:, None] * pts**2)


_masked_grad = eqx.filter_jit(jax.grad(_masked_loss, argnums=(0, 1)))


def _check_masked_gradient(cam, plane, px, bad):
    # The gradient with the bad pixel must equal the gradient with that pixel replaced by
    # a good one and weighted 0, i.e. the loss over the good pixels alone (same shapes:
    # one compilation), and be finite.
    w = jnp.where(jnp.arange(px.shape[0]) == bad, 0.0, 1.0)
    g = jax.tree.leaves(_masked_grad(cam, plane, px, w))
    g_ref = jax.tree.leaves(_masked_grad(cam, plane, px.at[bad].set(px[0]), w))
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in g)
    assert any(bool(jnp.any(x != 0)) for x in g)
    for a, b in zip(g, g_ref):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-300)


def test_masked_loss_gradient_finite_with_a_nan_pixel(system):
    # Issue 11 item 8: one NaN pixel in a batch must not make the gradient of a masked
    # loss NaN for the shared parameters (camera and plane).
    cam, plane = system
    px = jnp.array([[300.0, 200.0], [900.0, 700.0], [jnp.nan, 500.0]])
    assert sf.stripe_to_camera(cam, plane, px).status.tolist()[2] == sf.Status.INVALID_PIXEL
    _check_masked_gradient(cam, plane, px, 2)


def test_masked_loss_gradient_finite_with_a_failed_undistortion(system):
    # k1 = -2000 folds the radial map inside the sensor: the corner pixel's undistortion
    # fails (INVALID_PIXEL); the masked loss's gradient must stay finite and equal the
    # gradient over the other pixels alone.
    cam, plane = system
    cam = eqx.tree_at(lambda c: c.distortion, cam, sf.camera.RadialTangential(k1=-2000.0))
    px = jnp.array([[800.0, 600.0], [820.0, 640.0], [0.0, 0.0]])
    rec = sf.stripe_to_camera(cam, plane, px)
    assert rec.status.tolist() == [sf.Status.OK, sf.Status.OK, sf.Status.INVALID_PIXEL]
    _check_masked_gradient(cam, plane, px, 2)


def test_float16_pixels_refused(system):
    cam, plane = system
    with pytest.raises(ValueError, match="float16"):
        sf.stripe_to_camera(cam, plane, _grid().astype(jnp.float16))
