"""Stripe → 3-D reconstruction (paper eqs. 3 and 13)."""

import math

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


def test_measurement_frame(system):
    cam, plane = system
    stage = sf.RotaryStage(np.eye(3), [1.0, 2.0, 3.0], math.radians(10.0))
    uv = jnp.broadcast_to(jnp.array([[700.0, 500.0], [900.0, 650.0]]), (4, 2, 2))
    rec = sf.stripe_to_measurement(cam, plane, stage, uv, np.arange(4))
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
