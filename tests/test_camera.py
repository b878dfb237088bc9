"""Camera models against independent derivations of the paper's equations."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_difference, tree_allclose

import scheimflux as sf
from scheimflux._presets import SYSTEMS


def _cam(**kw):
    p = dict(
        f=97.0,
        e=-2.4,
        z0=249.5,
        phi=math.radians(2.9),
        theta=math.radians(13.3),
        x0=796.2,
        y0=594.0,
        dx=0.0044,
        dy=0.0044,
    )
    p.update(kw)
    return sf.ThickLensScheimpflug(**p)


def _independent_object_point(p, u, v):
    """Eqs. (5)–(11) composed step by step in plain Python floats."""
    x_im, y_im = p["dx"] * (u - p["x0"]), p["dy"] * (v - p["y0"])  # eq. 5
    cf, sf_, ct, st = (
        math.cos(p["phi"]),
        math.sin(p["phi"]),
        math.cos(p["theta"]),
        math.sin(p["theta"]),
    )
    Rx = np.array([[1, 0, 0], [0, cf, -sf_], [0, sf_, cf]])
    Ry = np.array([[ct, 0, st], [0, 1, 0], [-st, 0, ct]])
    S = np.array([0.0, 0.0, -p["z0"]])  # eq. 6: untilted point is S + [x_im, y_im, 0]
    xp, yp, zp = S + Ry @ Rx @ np.array([x_im, y_im, 0.0])  # eq. 7, rotation about S
    f, e = p["f"], p["e"]
    # Newton, with distances measured along the light (towards -z here) from the focal
    # points F = e + f and F' = -f: x = -(z - e - f), x' = -(z' + f), x x' = -f^2,
    # lateral magnification beta = x'/x_lateral = -x'/f.
    x_img = -(zp + f)
    x_obj = -f * f / x_img
    beta = -x_img / f
    return np.array([xp / beta, yp / beta, e + f - x_obj])


PARAMS = dict(
    f=97.0,
    e=-2.4,
    z0=249.5,
    phi=math.radians(2.9),
    theta=math.radians(13.3),
    x0=796.2,
    y0=594.0,
    dx=0.0044,
    dy=0.0048,
)


@pytest.mark.parametrize("uv", [(0.0, 0.0), (1599.0, 1199.0), (796.2, 594.0), (120.5, 1003.25)])
def test_object_point_matches_independent_composition(uv):
    cam = sf.ThickLensScheimpflug(**PARAMS)
    got = cam.object_point(jnp.array(uv))
    want = _independent_object_point(PARAMS, *uv)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-10)
    # K_f p̃ is parallel to the conjugate point (eq. 12 drops the homogeneous scale)
    kp = cam.K_f @ jnp.array([*uv, 1.0])
    np.testing.assert_allclose(
        np.cross(kp, want) / (np.linalg.norm(kp) * np.linalg.norm(want)), 0.0, atol=1e-13
    )


def test_K_f_matches_paper_eq12_entries():
    p = PARAMS
    cam = sf.ThickLensScheimpflug(**p)
    f, e, z0 = p["f"], p["e"], p["z0"]
    cf, sf_, ct, st = (
        math.cos(p["phi"]),
        math.sin(p["phi"]),
        math.cos(p["theta"]),
        math.sin(p["theta"]),
    )
    dx, dy, x0, y0 = p["dx"], p["dy"], p["x0"], p["y0"]
    want = np.array(
        [
            [f * ct * dx, f * sf_ * st * dy, -f * (ct * dx * x0 + sf_ * st * dy * y0)],
            [0.0, f * cf * dy, -f * cf * dy * y0],
            [
                -(e + f) * st * dx,
                (e + f) * sf_ * ct * dy,
                (e + f) * (st * dx * x0 - sf_ * ct * dy * y0 - z0) + e * f,
            ],
        ]
    )
    np.testing.assert_allclose(cam.K_f, want, rtol=1e-13)


def test_newton_formula_and_unit_magnification_of_principal_planes():
    cam = _cam()
    f, e = float(cam.f), float(cam.e)
    for zp in (-150.0, -249.5, -400.0):
        P = cam.conjugate(jnp.array([1.3, -0.7, zp]))
        assert (float(P[2]) - (e + f)) * (zp + f) == pytest.approx(-f * f, rel=1e-12)
    P = cam.conjugate(jnp.array([1.3, -0.7, 0.0]))  # H' ↦ H with unit magnification
    np.testing.assert_allclose(P, [1.3, -0.7, e], atol=1e-12)


def test_untilted_zero_e_is_textbook_pinhole():
    cam = _cam(e=0.0, phi=0.0, theta=0.0)
    # image distance z0 behind the lens, inverted image: α = -z0/dx
    pin = sf.Pinhole(-cam.z0 / cam.dx, -cam.z0 / cam.dy, 0.0, cam.x0, cam.y0)
    X = jnp.array([[3.0, -2.0, 150.0], [-10.0, 4.0, 180.0], [0.0, 0.0, 120.0]])
    np.testing.assert_allclose(cam.project(X), pin.project(X), rtol=1e-12)
    uv = jnp.array([[10.0, 20.0], [1500.0, 900.0]])
    r1, r2 = cam.backproject(uv), pin.backproject(uv)
    np.testing.assert_allclose(r1.direction, r2.direction, atol=1e-14)


def test_pinhole_backproject_inverts_project():
    pin = sf.paper_pinhole("regular-1.5")
    X = jnp.array([[3.0, -2.0, 150.0], [-10.0, 4.0, 180.0]])
    uv = pin.project(X)
    d = pin.backproject(uv).direction
    np.testing.assert_allclose(d, X / jnp.linalg.norm(X, axis=-1, keepdims=True), atol=1e-14)


@pytest.mark.parametrize("system", SYSTEMS)
def test_paper_tables_round_trip(system):
    grid = jnp.stack(jnp.meshgrid(jnp.linspace(0, 1599, 9), jnp.linspace(0, 1199, 7)), -1)
    for cam in (sf.paper_thick_lens(system), sf.paper_pinhole(system)):
        plane = sf.LaserPlane.from_normal_distance([0.1, -0.05, 1.0], 160.0)
        rec = sf.stripe_to_camera(cam, plane, grid)
        assert bool(jnp.all(rec.valid))
        np.testing.assert_allclose(cam.project(rec.points), grid, atol=1e-8)
        np.testing.assert_allclose(plane.signed_distance(rec.points), 0.0, atol=1e-10)
    tl = sf.paper_thick_lens(system)
    # the plane of sharp focus is the set of conjugate points: reconstructing on it
    # gives the conjugate points themselves
    rec = sf.stripe_to_camera(tl, tl.focus_plane(), grid)
    P = jax.vmap(jax.vmap(tl.object_point))(grid)
    np.testing.assert_allclose(rec.points, P, rtol=1e-10)
    assert 1.2 < float(-tl.magnification(jnp.array([tl.x0, tl.y0]))) < 2.0


def test_scheimpflug_line_lies_in_sensor_and_focus_planes():
    cam = _cam()
    point, d = cam.scheimpflug_line()
    for s in (-50.0, 0.0, 80.0):
        Q = point + s * d
        np.testing.assert_allclose(cam.focus_plane().signed_distance(Q), 0.0, atol=1e-9)
        Qi = Q.at[2].set(0.0)  # image side: same x, y on z = 0
        n = cam.R_s[:, 2]
        np.testing.assert_allclose(jnp.dot(n, Qi - jnp.array([0, 0, -cam.z0])), 0.0, atol=1e-9)


def test_projection_marks_points_behind_camera():
    cam = _cam()
    X = jnp.array([[1.0, 2.0, 150.0], [1.0, 2.0, -150.0]])
    uv, valid = cam.project_with_mask(X)
    assert valid.tolist() == [True, False]
    assert bool(jnp.all(jnp.isnan(cam.project(X)[1])))
    assert not bool(jnp.any(jnp.isnan(cam.project(X)[0])))


@pytest.mark.parametrize("shape", [(), (1,), (3, 1, 2)])
def test_batch_shapes_jit_and_vmap(shape, getkey):
    cam = _cam()
    X = jax.random.uniform(getkey(), shape + (3,), minval=-5, maxval=5) + jnp.array([0, 0, 155.0])
    uv = cam.project(X)
    assert uv.shape == shape + (2,)
    np.testing.assert_allclose(eqx.filter_jit(lambda c, x: c.project(x))(cam, X), uv, rtol=1e-13)
    flat = X.reshape(-1, 3)
    loop = jnp.stack([cam.project_one(x)[0] for x in flat]).reshape(uv.shape)
    np.testing.assert_allclose(uv, loop, rtol=1e-13)
    ray = cam.backproject(uv)
    assert ray.direction.shape == shape + (3,)


def test_shape_errors_are_clear():
    cam = _cam()
    with pytest.raises(ValueError, match=r"X must have shape \(\.\.\., 3\)"):
        cam.project(jnp.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"uv must have shape \(\.\.\., 2\)"):
        cam.backproject(jnp.zeros((4, 3)))
    with pytest.raises(ValueError, match="scalar"):
        sf.ThickLensScheimpflug(f=jnp.ones(2), e=0, z0=1, phi=0, theta=0, x0=0, y0=0, dx=1, dy=1)


def _param_vector_fn(cam, fn):
    """Wrap `fn(camera)` as a function of the camera's parameters stacked in a vector."""
    leaves, treedef = jax.tree.flatten(cam)

    def g(vec):
        return fn(jax.tree.unflatten(treedef, list(vec)))

    return jnp.stack(leaves), g


@pytest.mark.parametrize("which", ["thick", "pinhole"])
def test_project_gradients_match_finite_differences(which):
    cam = _cam() if which == "thick" else sf.Pinhole(5.0e4, 5.1e4, 12.0, 800.0, 600.0)
    X = jnp.array([[2.0, -1.0, 156.0], [-3.0, 2.5, 150.0]])
    vec, g = _param_vector_fn(cam, lambda c: c.project(X))
    J = jax.jacfwd(g)(vec)
    J_fd = central_difference(g, vec, step=1e-7)
    np.testing.assert_allclose(J, J_fd, rtol=2e-5, atol=1e-6 * np.abs(J_fd).max())
    # w.r.t. the point as well
    J_X = jax.jacfwd(lambda x: cam.project_one(x)[0])(X[0])
    np.testing.assert_allclose(
        J_X, central_difference(lambda x: cam.project_one(x)[0], X[0]), rtol=1e-6, atol=1e-6
    )


def test_float32_camera_works():
    cam = jax.tree.map(lambda x: x.astype(jnp.float32), _cam())
    uv = cam.project(jnp.array([1.0, 2.0, 150.0], dtype=jnp.float32))
    assert uv.dtype == jnp.float32 and bool(jnp.all(jnp.isfinite(uv)))


def test_tree_structure_is_nine_scalars():
    cam = _cam()
    names = ("f", "e", "z0", "phi", "theta", "x0", "y0", "dx", "dy")
    leaves, treedef = jax.tree.flatten(cam)
    # the leaves are exactly the nine named parameters, scalars, in field order
    assert len(leaves) == 9 and all(jnp.shape(x) == () for x in leaves)
    assert [float(x) for x in leaves] == [float(getattr(cam, n)) for n in names]
    # each leaf drives its own field: perturbing leaf i changes field i and nothing else,
    # and the rebuilt camera projects like one constructed with that value
    X = jnp.array([3.0, -2.0, 150.0])
    for i, name in enumerate(names):
        bumped = list(leaves)
        bumped[i] = leaves[i] * 1.001 + 1e-4
        cam2 = jax.tree.unflatten(treedef, bumped)
        for j, other in enumerate(names):
            same = float(getattr(cam2, other)) == float(getattr(cam, other))
            assert same == (j != i), (name, other)
        ref = _cam(**{name: float(bumped[i])})
        np.testing.assert_array_equal(cam2.project(X), ref.project(X))
        assert not np.allclose(cam2.project(X), cam.project(X), rtol=0, atol=1e-12)
    assert tree_allclose(jax.tree.unflatten(treedef, leaves), cam, rtol=0, atol=0)


@pytest.mark.parametrize(
    "distortion",
    [
        sf.camera.RadialTangential(k1=-50.0, k2=2e4, p1=0.02, p2=-0.01),
        sf.camera.Division(kappa=-50.0),
    ],
)
def test_distortion_in_untilted_plane_round_trip_and_geometry(distortion):
    cam = _cam(distortion=distortion)
    ideal = _cam()
    uv = jnp.stack(jnp.meshgrid(jnp.linspace(0, 1599, 7), jnp.linspace(0, 1199, 5)), -1)
    plane = ideal.focus_plane()
    X = sf.stripe_to_camera(cam, plane, uv).points
    np.testing.assert_allclose(cam.project(X), uv, atol=1e-8)
    # independent check of the forward model: the distorted pixel's sensor point, seen
    # from H', meets z = -z0 at z0 * distort(ξ) where ξ is the ideal point's
    uv_ideal = ideal.project(X)
    P_ideal = jax.vmap(jax.vmap(ideal.sensor_point))(uv_ideal)
    P_dist = jax.vmap(jax.vmap(ideal.sensor_point))(uv)
    xi = -P_ideal[..., :2] / P_ideal[..., 2:]
    xi_d = -P_dist[..., :2] / P_dist[..., 2:]
    np.testing.assert_allclose(xi_d, jax.vmap(jax.vmap(distortion.distort))(xi), atol=1e-13)
    assert float(jnp.max(jnp.abs(uv_ideal - uv))) > 1.0  # the distortion is not negligible


def test_distortion_gradients_match_finite_differences():
    cam = _cam(distortion=sf.camera.RadialTangential(k1=-30.0, k2=1e4, p1=0.01, p2=0.02))
    X = jnp.array([[0.5, -0.3, 156.0], [-1.5, 1.0, 155.0]])
    vec, g = _param_vector_fn(cam, lambda c: c.project(X))
    J = jax.jacfwd(g)(vec)
    J_fd = central_difference(g, vec, step=1e-7)
    np.testing.assert_allclose(J, J_fd, rtol=2e-5, atol=1e-6 * np.abs(J_fd).max())
