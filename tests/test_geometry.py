"""Rigid transforms, laser plane and rotary stage."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_difference

import scheimflux as sf
from scheimflux.geometry import Pose, rot_x, rot_y, rot_z, rotation_matrix


def test_elementary_rotations_are_right_handed():
    a = 0.3
    ez = jnp.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(rot_x(a) @ jnp.array([0.0, 1.0, 0.0]), [0, math.cos(a), math.sin(a)])
    np.testing.assert_allclose(rot_y(a) @ ez, [math.sin(a), 0, math.cos(a)])
    np.testing.assert_allclose(rot_z(a) @ jnp.array([1.0, 0, 0]), [math.cos(a), math.sin(a), 0])
    np.testing.assert_allclose(rotation_matrix(jnp.array([0.0, 0.0, a])), rot_z(a), atol=1e-15)


def test_pose_inverse_and_compose(getkey):
    T_ab = Pose(jax.random.normal(getkey(), (3,)), jax.random.normal(getkey(), (3,)))
    T_bc = Pose(jax.random.normal(getkey(), (3,)), jax.random.normal(getkey(), (3,)))
    X = jax.random.normal(getkey(), (5, 3))
    np.testing.assert_allclose(T_ab.inverse().apply(T_ab.apply(X)), X, atol=1e-12)
    np.testing.assert_allclose(T_ab.compose(T_bc).apply(X), T_ab.apply(T_bc.apply(X)), atol=1e-12)
    M = T_ab.as_matrix()
    np.testing.assert_allclose(M[:3, :3] @ X.T + M[:3, 3:], T_ab.apply(X).T, atol=1e-12)
    back = Pose.from_matrix(T_ab.R, T_ab.translation)
    np.testing.assert_allclose(back.R, T_ab.R, atol=1e-12)


def test_rotation_gradient_is_finite_at_identity():
    f = lambda v: Pose(v, jnp.zeros(3)).apply(jnp.array([1.0, 2.0, 3.0]))  # noqa: E731
    J = jax.jacfwd(f)(jnp.zeros(3))
    assert bool(jnp.all(jnp.isfinite(J)))
    np.testing.assert_allclose(J, central_difference(f, np.zeros(3)), atol=1e-8)


def test_plane_conversions():
    plane = sf.LaserPlane.from_normal_distance([1.0, 2.0, 10.0], 150.0)
    assert float(plane.distance) == pytest.approx(150.0)
    np.testing.assert_allclose(jnp.linalg.norm(plane.normal), 1.0)
    X = plane.normal * 150.0
    assert float(plane.signed_distance(X)) == pytest.approx(0.0, abs=1e-12)
    assert float(plane.signed_distance(X + 2.0 * plane.normal)) == pytest.approx(2.0)
    p3 = sf.LaserPlane.from_points(
        X,
        X + jnp.cross(plane.normal, jnp.array([1.0, 0, 0])),
        X + jnp.cross(plane.normal, jnp.array([0, 1.0, 0])),
    )
    np.testing.assert_allclose(p3.n, plane.n, rtol=1e-12)
    with pytest.raises(ValueError, match="shape"):
        sf.LaserPlane(jnp.ones(4))


def test_paper_stage_is_a_rotation():
    st = sf.paper_stage()
    R = np.asarray(st.R_m_c)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    # differs from the printed table only in the two chosen signs, by < 2e-5
    from scheimflux._presets import _R_C2M_PRINTED, R_C2M_SIGNS

    np.testing.assert_allclose(R, _R_C2M_PRINTED * R_C2M_SIGNS, atol=2e-5)


def test_stage_frame_rotation():
    st = sf.RotaryStage(np.eye(3), np.zeros(3), math.radians(90.0))
    np.testing.assert_allclose(
        st.to_measurement(jnp.array([1.0, 0, 5.0]), 1), [0, 1.0, 5.0], atol=1e-12
    )
    with pytest.raises(ValueError, match="R_m_c and t_m_c"):
        sf.RotaryStage()
