"""Property-based tests (hypothesis): round trips and invariants over random cameras,
laser planes, poses and pixels.

Each property runs through one compiled function (values vary, shapes do not), so a few
dozen examples cost a single compilation. Tolerances: float64 with condition numbers of
at most ~1e4 for these geometries (a 0.3 mm footprint seen from ~150 mm), so round trips
hold to ~1e-12 relative; the bounds below leave a factor of ~100 on that.
"""

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings, strategies as st

import scheimflux as sf
from scheimflux.geometry import Pose, rotation_matrix

SETTINGS = settings(max_examples=20, deadline=None, derandomize=True)


def _camera(f, e, m, phi_deg, theta_deg, x0, y0):
    """A thick-lens Scheimpflug camera around the paper's x1.5 system."""
    return sf.ThickLensScheimpflug(
        f, e, f * (1.0 + m), math.radians(phi_deg), math.radians(theta_deg), x0, y0, 0.0044, 0.0044
    )


cameras = st.builds(
    _camera,
    f=st.floats(60.0, 140.0),
    e=st.floats(-10.0, 10.0),
    m=st.floats(0.5, 2.0),
    phi_deg=st.floats(-5.0, 5.0),
    theta_deg=st.floats(-15.0, 15.0),
    x0=st.floats(700.0, 900.0),
    y0=st.floats(500.0, 700.0),
)
pixels = st.tuples(st.floats(0.0, 1599.0), st.floats(0.0, 1199.0))
unit = st.floats(-1.0, 1.0)
rotvecs = st.tuples(st.floats(-3.0, 3.0), st.floats(-3.0, 3.0), st.floats(-3.0, 3.0))
translations = st.tuples(st.floats(-200.0, 200.0), st.floats(-200.0, 200.0), st.floats(-200, 200))


@eqx.filter_jit
def _ray_round_trip(cam, uv, t):
    ray = cam.backproject(uv)
    X = ray.origin + t * ray.direction
    return cam.project(X), ray


@SETTINGS
@given(cam=cameras, uv=pixels, t=st.floats(20.0, 2000.0))
def test_project_backproject_round_trip(cam, uv, t):
    uv = jnp.asarray(uv)
    back, ray = _ray_round_trip(cam, uv, jnp.asarray(t))
    np.testing.assert_allclose(np.linalg.norm(ray.direction), 1.0, rtol=1e-14)
    # any point on the pixel's ray (in front of the camera) projects back onto the pixel
    np.testing.assert_allclose(back, uv, rtol=0, atol=1e-7)


@eqx.filter_jit
def _reconstruct(cam, plane, uv):
    rec = sf.stripe_to_camera(cam, plane, uv)
    return rec, cam.project(rec.points), plane.signed_distance(rec.points)


def _plane_through_focus(cam, tilt_x, tilt_y, shift):
    """A plane through the point of sharp focus on the axis, tilted by up to ~45°."""
    c = cam.object_point(jnp.stack([cam.x0, cam.y0]))
    normal = jnp.array([tilt_x, tilt_y, -1.0])
    c = c + shift * jnp.array([0.0, 0.0, 1.0])
    return sf.LaserPlane(normal / jnp.dot(normal, c))


@SETTINGS
@given(cam=cameras, uv=pixels, tx=unit, ty=unit, shift=st.floats(-5.0, 5.0))
def test_reconstruction_lies_on_the_plane_and_reprojects(cam, uv, tx, ty, shift):
    plane = _plane_through_focus(cam, tx, ty, shift)
    rec, back, dist = _reconstruct(cam, plane, jnp.asarray(uv)[None])
    if int(rec.status[0]) != sf.Status.OK:
        # only a grazing ray or an intersection behind the camera may be refused
        assert int(rec.status[0]) in (sf.Status.PARALLEL, sf.Status.BEHIND_CAMERA)
        return
    scale = float(jnp.linalg.norm(rec.points[0]))
    np.testing.assert_allclose(dist, 0.0, atol=1e-12 * scale)
    np.testing.assert_allclose(back[0], uv, rtol=0, atol=1e-7)


@SETTINGS
@given(
    cam=cameras,
    uv=pixels,
    normal=st.tuples(unit, unit, st.floats(0.3, 1.0)),
    d=st.floats(50.0, 400.0),
    k=st.floats(1e-3, 1e3),
)
def test_plane_from_normal_distance_is_scale_invariant(cam, uv, normal, d, k):
    # the same plane given by a scaled normal gives the same points
    normal = jnp.asarray(normal)
    p1 = sf.LaserPlane.from_normal_distance(normal, d)
    p2 = sf.LaserPlane.from_normal_distance(k * normal, d)
    np.testing.assert_allclose(p2.n, p1.n, rtol=1e-13)
    np.testing.assert_allclose(p1.distance, d, rtol=1e-13)
    r1, _, _ = _reconstruct(cam, p1, jnp.asarray(uv)[None])
    r2, _, _ = _reconstruct(cam, p2, jnp.asarray(uv)[None])
    np.testing.assert_array_equal(r1.status, r2.status)
    np.testing.assert_allclose(r1.points, r2.points, rtol=1e-12)


@SETTINGS
@given(
    a=st.tuples(st.floats(-50, 50), st.floats(-50, 50), st.floats(100, 200)),
    b=st.tuples(st.floats(-50, 50), st.floats(-50, 50), st.floats(100, 200)),
    c=st.tuples(st.floats(-50, 50), st.floats(-50, 50), st.floats(100, 200)),
)
def test_plane_from_points_contains_them_in_any_order(a, b, c):
    P = np.array([a, b, c])
    area = np.linalg.norm(np.cross(P[1] - P[0], P[2] - P[0]))
    normal = np.cross(P[1] - P[0], P[2] - P[0])
    if area < 1.0 or abs(normal @ P[0]) < 1e-3 * np.linalg.norm(normal) * 100:
        return  # (nearly) collinear or (nearly) through the origin: other tests cover these
    planes = [sf.LaserPlane.from_points(*P[list(o)]) for o in ((0, 1, 2), (2, 0, 1), (1, 0, 2))]
    for p in planes:
        np.testing.assert_allclose(p.signed_distance(jnp.asarray(P)), 0.0, atol=1e-9)
        np.testing.assert_allclose(p.n, planes[0].n, rtol=0, atol=1e-9 * float(np.linalg.norm(p.n)))


@eqx.filter_jit
def _compose(p, q, X):
    return p.compose(q).apply(X), p.apply(q.apply(X)), p.compose(p.inverse()).apply(X)


@SETTINGS
@given(r1=rotvecs, t1=translations, r2=rotvecs, t2=translations, X=translations)
def test_pose_composition_and_inverse(r1, t1, r2, t2, X):
    p, q = Pose(jnp.asarray(r1), jnp.asarray(t1)), Pose(jnp.asarray(r2), jnp.asarray(t2))
    X = jnp.asarray(X)
    composed, sequential, identity = _compose(p, q, X)
    np.testing.assert_allclose(composed, sequential, rtol=0, atol=1e-10)
    np.testing.assert_allclose(identity, X, rtol=0, atol=1e-10)
    # rotation matrices are orthonormal with det +1
    R = np.asarray(rotation_matrix(jnp.asarray(r1)))
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)


@eqx.filter_jit
def _measure(cam, plane, stage, uv, idx):
    return sf.stripe_to_measurement(cam, plane, stage, uv, idx).points


@SETTINGS
@given(
    uv=st.tuples(pixels, pixels),
    rv=rotvecs,
    t=translations,
    dw=st.floats(-math.pi, math.pi),
    i=st.integers(-36, 36),
)
def test_table_rotation_keeps_radius_and_height(uv, rv, t, dw, i):
    # frame i differs from frame 0 by a rotation about z_m: radius and z are kept, and
    # the distance between two points of one frame is the camera-frame distance
    cam, plane = sf.paper_thick_lens(), sf.paper_laser_plane()
    stage = sf.RotaryStage(pose=Pose(jnp.asarray(rv), jnp.asarray(t)), delta_omega=dw)
    px = jnp.asarray(uv)
    X0 = _measure(cam, plane, stage, px, jnp.zeros(2, jnp.int32))
    Xi = _measure(cam, plane, stage, px, jnp.full(2, i, jnp.int32))
    np.testing.assert_allclose(
        jnp.linalg.norm(Xi[:, :2], axis=1), jnp.linalg.norm(X0[:, :2], axis=1), rtol=1e-12
    )
    np.testing.assert_allclose(Xi[:, 2], X0[:, 2], rtol=0, atol=1e-10)
    Xc = sf.stripe_to_camera(cam, plane, px).points
    # a difference of two points ~300 mm from the origin carries their rounding error,
    # ~10 ulp of 300 mm = 7e-13 mm absolute, whatever the (possibly tiny) distance
    np.testing.assert_allclose(
        jnp.linalg.norm(Xi[0] - Xi[1]), jnp.linalg.norm(Xc[0] - Xc[1]), rtol=1e-12, atol=1e-12
    )
    # and the angle turned is i * delta_omega
    a0 = jnp.arctan2(X0[0, 1], X0[0, 0])
    ai = jnp.arctan2(Xi[0, 1], Xi[0, 0])
    turned = (float(ai - a0 - i * dw) + math.pi) % (2 * math.pi) - math.pi
    assert abs(turned) < 1e-9
