"""Snell's law, surface intersections, sequential tracing, chief-ray aiming, paraxial data."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_difference, tree_allclose

from scheimflux.simulate._lens import Lens, load_lens, paraxial
from scheimflux.simulate._trace import (
    Surfaces,
    aim_ray,
    intersect_surface,
    refract,
    sensor_normal,
    sensor_rotation,
    trace,
)


def _surfaces(radii, z, n_after, sd=None, stop=0):
    radii = np.asarray(radii, dtype=np.float64)
    n_after = np.asarray(n_after, dtype=np.float64)
    sd = np.full(len(radii), np.inf) if sd is None else np.asarray(sd, dtype=np.float64)
    return Surfaces(
        jnp.asarray(z, dtype=jnp.float64),
        jnp.asarray(1.0 / radii),
        jnp.asarray(np.concatenate([[1.0], n_after[:-1]])),
        jnp.asarray(n_after),
        jnp.asarray(sd),
        stop,
    )


def _chief(lens, x_obj, stop_xy=(0.0, 0.0)):
    par = paraxial(lens)
    surf = lens.surfaces()
    d, ok = aim_ray(
        surf,
        x_obj,
        jnp.asarray(stop_xy),
        par.z_entrance_pupil,
        par.entrance_pupil_magnification,
    )
    return trace(surf, x_obj, d), ok


# ------------------------------------------------------------------ Snell's law, surfaces


@pytest.mark.parametrize("angle_deg", [0.0, 10.0, 30.0, 60.0])
def test_refract_plane_air_to_glass(angle_deg):
    a = math.radians(angle_deg)
    d = jnp.asarray([math.sin(a), 0.0, math.cos(a)])
    out, ok = refract(d, jnp.asarray([0.0, 0.0, 1.0]), 1.0, 1.5)
    r = math.asin(math.sin(a) / 1.5)
    assert bool(ok)
    np.testing.assert_allclose(out, [math.sin(r), 0.0, math.cos(r)], atol=1e-15)
    # The normal's orientation does not matter.
    out2, _ = refract(d, jnp.asarray([0.0, 0.0, -1.0]), 1.0, 1.5)
    np.testing.assert_allclose(out2, out, atol=1e-15)


def test_refract_total_internal_reflection():
    critical = math.asin(1.0 / 1.5)
    for a, expect in [(critical - 1e-6, True), (critical + 1e-6, False), (1.2, False)]:
        d = jnp.asarray([0.0, math.sin(a), math.cos(a)])
        out, ok = refract(d, jnp.asarray([0.0, 0.0, 1.0]), 1.5, 1.0)
        assert bool(ok) == expect
        assert np.all(np.isfinite(out))
    # Just below the critical angle the ray leaves almost grazing.
    d = jnp.asarray([0.0, math.sin(critical - 1e-6), math.cos(critical - 1e-6)])
    out, _ = refract(d, jnp.asarray([0.0, 0.0, 1.0]), 1.5, 1.0)
    assert float(out[1]) > 1.0 - 1e-5


def test_refract_gradient_finite_at_tir():
    def f(a):
        d = jnp.stack([jnp.zeros(()), jnp.sin(a), jnp.cos(a)])
        return refract(d, jnp.asarray([0.0, 0.0, 1.0]), 1.5, 1.0)[0].sum()

    assert np.isfinite(jax.grad(f)(jnp.asarray(1.2)))


@pytest.mark.parametrize("radius", [20.0, -20.0])
def test_spherical_surface_hand_calculation(radius):
    """Ray parallel to the axis at height h onto a sphere: sag, normal, Snell."""
    h, z_v, n2 = 5.0, 3.0, 1.6
    q, nrm, t, ok = intersect_surface(
        jnp.asarray([0.0, h, -10.0]), jnp.asarray([0.0, 0.0, 1.0]), z_v, 1.0 / radius
    )
    sag = radius - math.copysign(math.sqrt(radius**2 - h**2), radius)
    assert bool(ok)
    np.testing.assert_allclose(q, [0.0, h, z_v + sag], atol=1e-13)
    np.testing.assert_allclose(t, 10.0 + z_v + sag, atol=1e-13)
    # Refraction: incidence angle asin(h/R) against the normal, Snell, back to the axis.
    i = math.asin(h / radius)
    r = math.asin(math.sin(i) / n2)
    out, ok = refract(jnp.asarray([0.0, 0.0, 1.0]), nrm, 1.0, n2)
    slope = -(i - r)  # convex (R > 0): bent towards the axis
    np.testing.assert_allclose(out, [0.0, math.sin(slope), math.cos(slope)], atol=1e-14)


def test_spherical_surface_miss_and_tir():
    # A ray above a sphere of radius 4 misses it.
    _, _, _, ok = intersect_surface(
        jnp.asarray([0.0, 5.0, -1.0]), jnp.asarray([0.0, 0.0, 1.0]), 0.0, 0.25
    )
    assert not bool(ok)
    # Inside glass towards a convex back surface R = -10: TIR when 1.5 h / 10 > 1.
    surf = _surfaces([np.inf, -10.0], [0.0, 5.0], [1.5, 1.0])
    for h, expect in [(6.0, True), (6.7, False)]:
        tr = trace(surf, jnp.asarray([0.0, h, -1.0]), jnp.asarray([0.0, 0.0, 1.0]))
        assert bool(tr.ok) == expect
        assert np.all(np.isfinite(tr.points))


def test_clear_aperture_vignettes():
    surf = _surfaces([50.0, -50.0], [0.0, 5.0], [1.5, 1.0], sd=[10.0, 10.0])
    inside = trace(surf, jnp.asarray([0.0, 9.0, -1.0]), jnp.asarray([0.0, 0.0, 1.0]))
    outside = trace(surf, jnp.asarray([0.0, 11.0, -1.0]), jnp.asarray([0.0, 0.0, 1.0]))
    unclipped = trace(
        surf, jnp.asarray([0.0, 11.0, -1.0]), jnp.asarray([0.0, 0.0, 1.0]), clip=False
    )
    assert bool(inside.ok) and not bool(outside.ok) and bool(unclipped.ok)


def test_sensor_rotation():
    phi, theta = 0.3, -0.7
    r = sensor_rotation(phi, theta)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-15)
    np.testing.assert_allclose(r[:, 2], sensor_normal(phi, theta), atol=1e-15)
    c, s = math.cos, math.sin
    r_y = np.array([[c(theta), 0, s(theta)], [0, 1, 0], [-s(theta), 0, c(theta)]])
    r_x = np.array([[1, 0, 0], [0, c(phi), -s(phi)], [0, s(phi), c(phi)]])
    np.testing.assert_allclose(r, r_y @ r_x, atol=1e-15)


# ------------------------------------------------------------------ paraxial data


def test_singlet_thick_lens_formulas():
    lens = load_lens("singlet")
    r1, r2 = float(lens.radii[0]), float(lens.radii[1])
    d, n = float(lens.thicknesses[0]), float(lens.indices[0])
    f = 1.0 / ((n - 1) * (1 / r1 - 1 / r2 + (n - 1) * d / (n * r1 * r2)))
    h = -f * (n - 1) * d / (n * r2)  # H from the first vertex
    hp = -f * (n - 1) * d / (n * r1)  # H' from the last vertex
    par = paraxial(lens)
    np.testing.assert_allclose(par.efl, f, rtol=1e-13)
    np.testing.assert_allclose(par.z_principal_object, h, atol=1e-12)
    np.testing.assert_allclose(par.z_principal_image, d + hp, atol=1e-12)
    np.testing.assert_allclose(par.z_focal_object, h - f, atol=1e-12)
    np.testing.assert_allclose(par.z_focal_image, d + hp + f, atol=1e-12)
    np.testing.assert_allclose(par.e, (d + hp) - h, atol=1e-12)


@pytest.mark.parametrize("name", ["singlet", "achromat", "double-gauss"])
def test_paraxial_against_real_rays_at_small_aperture(name):
    """Focal points, principal planes and pupils agree with real rays near the axis."""
    lens = load_lens(name)
    par = paraxial(lens)
    surf = lens.surfaces()
    h = 1e-4
    # Parallel ray: crosses the axis at F', and its extension reaches height h at H'.
    tr = trace(surf, jnp.asarray([0.0, h, -5.0]), jnp.asarray([0.0, 0.0, 1.0]))
    p, d = tr.point, tr.direction
    z_cross = p[2] - p[1] * d[2] / d[1]
    z_h = p[2] + (h - p[1]) * d[2] / d[1]
    np.testing.assert_allclose(z_cross, par.z_focal_image, atol=1e-5)
    np.testing.assert_allclose(z_h, par.z_principal_image, atol=1e-5)
    # Chief ray at a tiny field angle: its object-space line crosses the axis at the
    # entrance pupil and its image-space line at the exit pupil.
    u = 1e-5
    x_obj = jnp.asarray([0.0, -u * 1e3, float(par.z_entrance_pupil) - 1e3])
    tr, ok = _chief(lens, x_obj)
    assert bool(ok) and bool(tr.ok)
    d0 = tr.points[0] - x_obj
    z_ep = x_obj[2] - x_obj[1] * d0[2] / d0[1]
    np.testing.assert_allclose(z_ep, par.z_entrance_pupil, atol=1e-3)
    p, d = tr.point, tr.direction
    np.testing.assert_allclose(p[2] - p[1] * d[2] / d[1], par.z_exit_pupil, atol=1e-3)
    # Pupil magnification: ratio of slopes in object and image space (Lagrange invariant).
    slope_in = d0[1] / d0[2]
    slope_out = d[1] / d[2]
    np.testing.assert_allclose(
        slope_in / slope_out,
        par.exit_pupil_magnification / par.entrance_pupil_magnification,
        rtol=1e-5,
    )


def test_tracer_matches_paraxial_imaging_in_small_angle_limit():
    """Image height and focus position of a finite conjugate (|β| = 1.5)."""
    lens = load_lens("double-gauss")
    par = paraxial(lens)
    beta = 1.5
    z_obj = par.object_distance(beta)
    z_img = par.image_distance(beta)
    h = 1e-4
    tr, ok = _chief(lens, jnp.stack([0.0, h, z_obj]))
    p, d = tr.point, tr.direction
    y_img = p[1] + (z_img - p[2]) * d[1] / d[2]
    np.testing.assert_allclose(y_img, -beta * h, rtol=1e-6)
    # A thin on-axis bundle focuses at the paraxial image distance.
    sd = float(lens.semi_diameters[lens.stop])
    tr, ok = _chief(lens, jnp.stack([0.0, 0.0, z_obj]), (0.0, 1e-4 * sd))
    p, d = tr.point, tr.direction
    np.testing.assert_allclose(p[2] - p[1] * d[2] / d[1], z_img, atol=1e-5)


# ------------------------------------------------------------------ aiming, autodiff


@pytest.mark.parametrize(
    "x_obj", [(0.0, 0.0, -100.0), (3.0, -2.0, -100.0), (15.0, 20.0, -150.0), (-30.0, 5.0, -400.0)]
)
def test_chief_ray_passes_through_stop_centre(x_obj):
    lens = load_lens("double-gauss")
    tr, ok = _chief(lens, jnp.asarray(x_obj))
    assert bool(ok) and bool(tr.ok)
    np.testing.assert_allclose(tr.points[lens.stop][:2], [0.0, 0.0], atol=1e-9)


def test_aimed_rim_ray_hits_requested_stop_point():
    lens = load_lens("double-gauss")
    target = (3.0, -6.0)
    tr, ok = _chief(lens, jnp.asarray([10.0, 5.0, -120.0]), target)
    np.testing.assert_allclose(tr.points[lens.stop][:2], target, atol=1e-9)


_DG = load_lens("double-gauss")


def _image_point(x):
    """Image-plane point of an aimed chief ray as a function of (R1, R3, t5, object point)."""
    base = _DG
    lens = eqx.tree_at(
        lambda ln: (ln.radii, ln.thicknesses),
        base,
        (base.radii.at[0].set(x[0]).at[2].set(x[1]), base.thicknesses.at[5].set(x[2])),
    )
    tr, _ = _chief(lens, x[3:])
    p, d = tr.point, tr.direction
    return p[:2] + (180.0 - p[2]) * d[:2] / d[2]


def test_gradients_match_central_differences():
    x = jnp.asarray([54.153, 35.951, 12.428, 8.0, -5.0, -120.0])
    both = jax.jit(lambda x: (_image_point(x), jax.jacfwd(_image_point)(x)))  # one compile
    jac = both(x)[1]
    fd = central_difference(lambda x: both(x)[0], x, step=1e-5)
    np.testing.assert_allclose(jac, fd, rtol=1e-6, atol=1e-8)


def test_reverse_mode_matches_forward_mode():
    lens = load_lens("achromat")

    def fn(x):
        ln = eqx.tree_at(lambda ln: ln.radii, lens, lens.radii.at[1].set(x[0]))
        tr, _ = _chief(ln, x[1:])
        return tr.point[:2] + 90.0 * tr.direction[:2] / tr.direction[2]

    x = jnp.asarray([-45.71, 2.0, -3.0, -150.0])
    rev, fwd = jax.jit(lambda x: (jax.jacrev(fn)(x), jax.jacfwd(fn)(x)))(x)
    np.testing.assert_allclose(rev, fwd, rtol=1e-10, atol=1e-13)


def test_paraxial_gradients_match_central_differences():
    def fn(radii):
        lens = eqx.tree_at(lambda ln: ln.radii, load_lens("double-gauss"), radii)
        par = paraxial(lens)
        return jnp.stack([par.efl, par.e, par.z_entrance_pupil, par.z_exit_pupil])

    radii = load_lens("double-gauss").radii
    finite = np.isfinite(np.asarray(radii))
    jac = np.asarray(jax.jit(jax.jacfwd(fn))(radii))
    assert np.all(np.isfinite(jac))
    assert np.all(jac[:, ~finite] == 0.0)
    sub = np.flatnonzero(finite)

    def fn_sub(r):
        return fn(radii.at[sub].set(r))

    fd = central_difference(jax.jit(fn_sub), radii[sub])
    np.testing.assert_allclose(jac[:, sub], fd, rtol=1e-6, atol=1e-9)


def test_jit_equals_eager_and_vmap_equals_loop():
    lens = load_lens("singlet")
    pts = jnp.asarray([[0.0, 0.0, -100.0], [4.0, -3.0, -110.0], [-8.0, 12.0, -90.0]])
    with jax.disable_jit():  # op by op: the traced functions inside are jitted too
        eager = [_chief(lens, p) for p in pts]
    jitted = jax.jit(_chief)
    for p, e in zip(pts, eager):
        assert tree_allclose(jitted(lens, p), e, rtol=1e-12, atol=1e-12)
    batched = jax.jit(jax.vmap(_chief, in_axes=(None, 0)))(lens, pts)
    stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *eager)
    assert tree_allclose(batched, stacked, rtol=1e-12, atol=1e-12)
    # the rays are real: each chief ray reached the image and the three differ
    (ray, ok) = batched
    assert bool(jnp.all(ok))
    assert not tree_allclose(jax.tree.map(lambda x: x[0], ray), jax.tree.map(lambda x: x[1], ray))


def test_lens_is_a_pytree_for_jit():
    lens = load_lens("singlet")
    efl = jax.jit(lambda ln: paraxial(ln).efl)
    assert isinstance(lens, Lens)
    np.testing.assert_allclose(efl(lens.scaled(2.0)), 2.0 * efl(lens), rtol=1e-14)
