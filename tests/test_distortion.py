"""Distortion models: closed forms, their inverses, convergence flags and derivatives."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_difference

from scheimflux.camera._distortion import (
    Division,
    NoDistortion,
    OpenCVDistortion,
    RadialTangential,
)

MODELS = {
    "none": NoDistortion(),
    "radtan": RadialTangential(k1=-0.21, k2=0.12, k3=-0.03, p1=1.1e-3, p2=-7e-4),
    "opencv": OpenCVDistortion(
        k1=-0.12,
        k2=0.35,
        p1=1.2e-3,
        p2=-8e-4,
        k3=-0.9,
        k4=0.05,
        k5=-0.02,
        k6=0.3,
        s1=2e-3,
        s2=-1e-3,
        s3=1.5e-3,
        s4=-5e-4,
    ),
    "division-barrel": Division(kappa=-0.15),
    "division-pincushion": Division(kappa=0.15),
}


def _points(n=40, radius=0.45, seed=0):
    rng = np.random.default_rng(seed)
    r = radius * np.sqrt(rng.uniform(0, 1, n))
    a = rng.uniform(0, 2 * np.pi, n)
    return jnp.asarray(np.stack([r * np.cos(a), r * np.sin(a)], -1))


@eqx.filter_jit
def _round_trips(model, xy):
    xy_d = jax.vmap(model.distort)(xy)
    back, ok = jax.vmap(model.undistort)(xy_d)
    xy2, ok2 = jax.vmap(model.undistort)(xy)
    return xy_d, back, ok, jax.vmap(model.distort)(xy2), ok2


@pytest.mark.parametrize("name", MODELS)
def test_round_trip(name):
    xy = _points()
    xy_d, back, ok, again, ok2 = _round_trips(MODELS[name], xy)
    moved = float(jnp.max(jnp.abs(xy_d - xy)))
    assert moved == 0.0 if name == "none" else moved > 1e-3
    assert bool(jnp.all(ok)) and bool(jnp.all(ok2))
    np.testing.assert_allclose(back, xy, rtol=0, atol=1e-13)  # undistort ∘ distort
    np.testing.assert_allclose(again, xy, rtol=0, atol=1e-13)  # distort ∘ undistort


def test_radtan_formula_and_opencv_special_case():
    m = MODELS["radtan"]
    x, y = 0.31, -0.22
    r2 = x * x + y * y
    rad = 1 + 0.0 + float(m.k1) * r2 + float(m.k2) * r2**2 + float(m.k3) * r2**3
    p1, p2 = float(m.p1), float(m.p2)
    want = [x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * rad + p1 * (r2 + 2 * y * y)]
    want[1] += 2 * p2 * x * y
    np.testing.assert_allclose(m.distort(jnp.array([x, y])), want, rtol=1e-15, atol=1e-16)
    same = OpenCVDistortion(k1=m.k1, k2=m.k2, k3=m.k3, p1=m.p1, p2=m.p2)
    np.testing.assert_allclose(same.distort(jnp.array([x, y])), want, rtol=1e-15, atol=1e-16)


def test_division_closed_forms():
    m = Division(kappa=-0.2)
    xy_d = jnp.array([0.3, -0.4])
    xy, ok = m.undistort(xy_d)
    assert bool(ok)
    np.testing.assert_allclose(xy, np.array([0.3, -0.4]) / (1 - 0.2 * 0.25), rtol=1e-15)


@pytest.mark.parametrize("name", ["radtan"])
def test_undistort_derivative_wrt_point(name):
    model = MODELS[name]
    xy_d = jnp.array([0.27, -0.19])
    fn = jax.jit(lambda p: model.undistort(p)[0])
    got = jax.jit(jax.jacfwd(fn))(xy_d)
    np.testing.assert_allclose(got, central_difference(fn, xy_d), rtol=1e-6, atol=1e-8)
    # reverse mode agrees with forward mode
    rev = jax.jit(jax.jacrev(fn))(xy_d)
    np.testing.assert_allclose(rev, got, rtol=1e-12, atol=1e-14)


def test_undistort_derivative_wrt_coefficients():
    coeffs = MODELS["opencv"].coefficients
    xy_d = jnp.array([-0.33, 0.21])

    @jax.jit
    def fn(c):
        return OpenCVDistortion.from_coefficients(c).undistort(xy_d)[0]

    got = jax.jit(jax.jacfwd(fn))(coeffs)
    want = central_difference(fn, coeffs, step=1e-6)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-8)


@pytest.mark.parametrize("name", MODELS)
def test_jit_equals_eager(name):
    model = MODELS[name]
    xy = jnp.array([0.12, 0.37])
    # the eager side really runs op by op (newton_inverse is itself filter_jit-ed, so a
    # plain call would compile too); a few ulps of difference are allowed (XLA fuses)
    with jax.disable_jit():
        eager = model.undistort(xy)
        eager_d = model.distort(xy)
        assert not isinstance(eager[0], jax.core.Tracer)
    jitted = eqx.filter_jit(lambda m, p: m.undistort(p))(model, xy)
    np.testing.assert_array_equal(eager[1], jitted[1])
    assert bool(jitted[1])
    np.testing.assert_allclose(eager[0], jitted[0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(
        eager_d, eqx.filter_jit(lambda m, p: m.distort(p))(model, xy), rtol=0, atol=1e-15
    )
    np.testing.assert_allclose(model.distort(jitted[0]), xy, rtol=0, atol=1e-13)  # an inverse


def test_vmap_equals_loop():
    model = MODELS["opencv"]
    xy = _points(n=3)
    batched, ok = jax.vmap(model.undistort)(xy)
    for i in range(xy.shape[0]):
        one, ok1 = model.undistort(xy[i])
        np.testing.assert_allclose(batched[i], one, rtol=0, atol=1e-15)
        assert bool(ok[i]) == bool(ok1)


def test_convergence_flag_beyond_fold():
    # r_d = r (1 + k1 r²) with k1 = −0.5 folds at r = 1/√1.5 ≈ 0.816, where r_d ≈ 0.544.
    model = RadialTangential(k1=-0.5)
    r_fold = 1 / np.sqrt(1.5)
    r_d_max = r_fold * (1 - 0.5 * r_fold**2)
    # beyond the largest distorted radius: no preimage at all
    xy, ok = model.undistort(jnp.array([0.6, 0.0]))
    assert not bool(ok)
    assert bool(jnp.all(jnp.isnan(xy)))
    # a point beyond the fold distorts to a radius that also has a preimage on the main
    # sheet: undistort must return that one (inside the fold), never the far one
    far = jnp.array([0.0, 1.0])
    xy_d = model.distort(far)
    xy, ok = model.undistort(xy_d)
    assert bool(ok)
    assert float(jnp.linalg.norm(xy)) < r_fold
    np.testing.assert_allclose(model.distort(xy), xy_d, atol=1e-15)
    # just inside the largest distorted radius, still invertible
    xy, ok = model.undistort(jnp.array([0.0, 0.98 * r_d_max]))
    assert bool(ok)
    # derivatives at a rejected point are finite (zero), not NaN
    g = jax.jacfwd(lambda p: model.undistort(p)[0])(jnp.array([0.6, 0.0]))
    assert bool(jnp.all(jnp.isfinite(g)))


def test_division_flags():
    m = Division(kappa=0.5)
    xy, ok = m.undistort(jnp.array([1.2, 0.6]))  # κ r_d² = 0.9: fine
    assert bool(ok)
    xy, ok = m.undistort(jnp.array([1.5, 0.0]))  # κ r_d² > 1: beyond the fold
    assert not bool(ok) and bool(jnp.all(jnp.isnan(xy)))
    assert bool(jnp.all(jnp.isnan(m.distort(jnp.array([0.8, 0.0])))))  # 4 κ r² > 1
    assert bool(jnp.all(jnp.isfinite(m.distort(jnp.array([0.7, 0.0])))))
    # barrel: invertible while |κ| r_d² < 1
    xy, ok = Division(kappa=-0.5).undistort(jnp.array([1.5, 0.0]))
    assert not bool(ok)


def test_non_finite_input_is_flagged():
    for model in MODELS.values():
        xy, ok = model.undistort(jnp.array([jnp.nan, 0.1]))
        assert not bool(ok)


def test_checks():
    with pytest.raises(ValueError, match="k1 must be a scalar"):
        RadialTangential(k1=[0.1, 0.2])
    with pytest.raises(ValueError, match="kappa"):
        Division(kappa=np.zeros(2))
    with pytest.raises(ValueError, match="12 coefficients"):
        OpenCVDistortion.from_coefficients(np.zeros(5))
    with pytest.raises(ValueError, match=r"shape \(2,\)"):
        MODELS["opencv"].distort(jnp.zeros(3))
    with pytest.raises(ValueError, match=r"shape \(2,\)"):
        MODELS["radtan"].undistort(jnp.zeros((4, 2)))
