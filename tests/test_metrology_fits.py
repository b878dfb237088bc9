"""Differentiable fits (scheimflux.metrology): exact recovery of constructed geometry,
gradients against finite differences of the independent NumPy fits, jit == eager,
vmap == loop, the fit uncertainty against Monte Carlo, and one-line refusals."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from scheimflux.metrology import (
    Circle,
    Cylinder,
    Distance,
    Plane,
    Sphere,
    Steps,
    fit_cylinder,
    fit_shape,
    label_steps,
    measure_points,
)

N = 120


def _basis(axis):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    helper = np.eye(3)[np.argmin(np.abs(axis))]
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    return axis, e1, np.cross(axis, e1)


AXIS, E1, E2 = _basis([0.2, -0.1, 1.0])
CENTRE = np.array([1.0, -2.0, 250.0])


def cylinder_points(rng, r=17.5, noise=0.0, n=N):
    a = rng.uniform(0.0, 2 * math.pi, n)
    z = rng.uniform(-3.0, 3.0, n)
    radial = np.cos(a)[:, None] * E1 + np.sin(a)[:, None] * E2
    return CENTRE + (r + noise * rng.standard_normal(n))[:, None] * radial + z[:, None] * AXIS


def sphere_points(rng, r=6.0, noise=0.0, n=N):
    v = rng.standard_normal((n, 3))
    v[:, 2] = np.abs(v[:, 2])  # a hemisphere, as a scan sees it
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return CENTRE + (r + noise * rng.standard_normal(n))[:, None] * v


def circle_points(rng, r=5.0, n=N):
    a = rng.uniform(0.0, 4.0, n)  # a partial arc
    return CENTRE + r * (np.cos(a)[:, None] * E1 + np.sin(a)[:, None] * E2)


def plane_points(rng, n=N):
    s = rng.uniform(-4.0, 4.0, (n, 2))
    return CENTRE + s[:, :1] * E1 + s[:, 1:] * E2


def step_profile(rng, gap=1.3, n=N):
    """Two parallel segments (one laser profile across a step) `gap` mm apart."""
    t = rng.uniform(-2.0, 2.0, n)
    lab = (t > 0).astype(np.int32)
    pts = CENTRE + t[:, None] * E1 + (lab * gap)[:, None] * E2
    return pts, lab


def step_planes(rng, h=0.75, n=N):
    s = rng.uniform(-2.0, 2.0, (n, 2))
    lab = (s[:, 0] > 0).astype(np.int32)
    return CENTRE + s[:, :1] * E1 + s[:, 1:] * E2 + (lab * h)[:, None] * AXIS, lab


CASES = {
    "cylinder": (Cylinder(), lambda rng: (cylinder_points(rng), None), 17.5),
    "sphere": (Sphere(), lambda rng: (sphere_points(rng), None), 6.0),
    "circle": (Circle(), lambda rng: (circle_points(rng), None), 5.0),
    "plane": (Plane(), lambda rng: (plane_points(rng), None), 0.0),
    "steps-lines": (Steps(), step_profile, 1.3),
    "steps-planes": (Steps(model="planes"), step_planes, 0.75),
}


@pytest.mark.parametrize("name", list(CASES))
def test_exact_geometry_is_recovered(name):
    shape, make, truth = CASES[name]
    X, lab = make(np.random.default_rng(1))
    fit = eqx.filter_jit(fit_shape)(shape, X, lab)
    assert bool(fit.result == optx.RESULTS.successful)
    # exact points: the optimum has zero residuals; LM stops at steps ~1e-13 mm, so the
    # value is good to ~1e-10 mm (points are ~250 mm from the origin: rounding 3e-14 mm)
    assert float(jnp.max(jnp.abs(fit.residuals))) < 1e-9
    assert abs(float(fit.values[0]) - truth) < 1e-9


def test_radius_gradient_matches_finite_differences_of_the_numpy_fit():
    # d radius / d points by implicit differentiation through the optimistix solve,
    # against central differences of the independent NumPy Levenberg–Marquardt fit.
    rng = np.random.default_rng(2)
    X = cylinder_points(rng, noise=2e-3)
    g = np.asarray(eqx.filter_jit(jax.grad(lambda X: fit_shape(Cylinder(), X).values[0]))(X))
    # h = 1e-4 mm: truncation O(h² · r''') ~ 1e-8 relative; the NumPy fit converges to
    # ~1e-13 mm, i.e. 1e-9 on a difference quotient of 2e-4: far below the gradient's
    # entries (~1/N ~ 1e-2)
    h = 1e-4
    for i, j in [(0, 0), (5, 1), (17, 2), (60, 0), (99, 2)]:
        Xp, Xm = X.copy(), X.copy()
        Xp[i, j] += h
        Xm[i, j] -= h
        fd = (fit_cylinder(Xp).radius - fit_cylinder(Xm).radius) / (2 * h)
        assert abs(g[i, j] - fd) < 1e-6 + 1e-4 * abs(fd), (i, j, g[i, j], fd)
    # a rigid translation of every point leaves the radius unchanged
    assert abs(float(np.sum(g[:, 0]))) < 1e-10


def test_jit_equals_eager_and_vmap_equals_loop():
    rng = np.random.default_rng(3)
    sets = np.stack([sphere_points(rng, noise=1e-3, n=40) for _ in range(3)])
    jitted = eqx.filter_jit(lambda X: fit_shape(Sphere(), X).values)
    with jax.disable_jit():
        eager = np.asarray(fit_shape(Sphere(), sets[0]).values)
    np.testing.assert_allclose(np.asarray(jitted(sets[0])), eager, rtol=1e-12)
    batched = np.asarray(eqx.filter_jit(jax.vmap(lambda X: fit_shape(Sphere(), X).values))(sets))
    loop = np.stack([np.asarray(jitted(s)) for s in sets])
    np.testing.assert_allclose(batched, loop, rtol=1e-12)


def test_fit_uncertainty_against_monte_carlo():
    # Radial noise σ on a hemisphere: the stated fit uncertainty (from the residuals) of
    # one data set against the spread of 300 independent fits. 300 samples know a σ to
    # ±4 % (1/sqrt(2·299)); the bounds below are > 4 such σ. Coverage of the truth by
    # ±U (k = 2): 95.4 % expected, σ of the fraction 1.2 %.
    rng = np.random.default_rng(4)
    sigma, truth = 2e-3, 6.0
    sets = np.stack([sphere_points(rng, truth, sigma) for _ in range(300)])
    r = np.asarray(eqx.filter_jit(jax.vmap(lambda X: fit_shape(Sphere(), X).values[0]))(sets))
    m = measure_points(sets[0], Sphere())
    u = float(m.budget["fit_residual"][0])
    assert m.budget["calibration"] is None and m.budget["stripe_noise"] is None
    assert 0.8 < np.std(r, ddof=1) / u < 1.25
    assert np.mean(np.abs(r - truth) <= m.U[0]) >= 0.92
    assert abs(m.residual_stats["rms"] / sigma - 1) < 0.2


def test_distance_value_and_gradient():
    X = np.array([[0.0, 0.0, 100.0], [3.0, 4.0, 100.0], [1.0, 1.0, 1.0]])
    m = measure_points(X, Distance(i=0, j=1))
    assert m.values[0] == pytest.approx(5.0, rel=1e-15)
    g = np.asarray(jax.grad(lambda X: fit_shape(Distance(i=0, j=1), X).values[0])(X))
    np.testing.assert_allclose(g, [[-0.6, -0.8, 0], [0.6, 0.8, 0], [0, 0, 0]], atol=1e-15)


def test_label_steps_finds_the_faces():
    rng = np.random.default_rng(5)
    # faces are numbered along the profile: compare up to the numbering
    X, lab = step_profile(rng)
    found = label_steps(X)
    assert np.array_equal(found, lab) or np.array_equal(found, 1 - lab)
    with pytest.raises(ValueError, match="give the labels of a scan"):
        label_steps(step_planes(rng)[0])
    flat = plane_points(rng)  # one plane, no step
    with pytest.raises(ValueError, match="not clearly separated"):
        label_steps(flat - ((flat - CENTRE) @ AXIS)[:, None] * AXIS)


@pytest.mark.parametrize(
    "shape, points, match",
    [
        (Cylinder(), lambda rng: plane_points(rng), "coplanar"),
        (Sphere(), lambda rng: plane_points(rng), "coplanar"),
        (Cylinder(), lambda rng: CENTRE + np.outer(rng.uniform(0, 1, 20), AXIS), "collinear"),
        (Plane(), lambda rng: plane_points(rng)[:3], "at least 4 points"),
        (Circle(), lambda rng: np.full((10, 3), np.nan), "NaN"),
    ],
)
def test_degenerate_or_too_few_points_are_refused(shape, points, match):
    X = points(np.random.default_rng(6))
    with pytest.raises(ValueError, match=match):
        measure_points(X, shape)


def test_steps_face_checks():
    X, lab = step_profile(np.random.default_rng(7))
    keep = (lab == 0) | (np.arange(len(lab)) == np.argmax(lab))  # one point on face 1
    with pytest.raises(ValueError, match="face 1 has 1 points"):
        measure_points(X[keep], Steps(), labels=lab[keep])
    with pytest.raises(ValueError, match="labels must have shape"):
        measure_points(X, Steps(), labels=lab[:-1])
    with pytest.raises(ValueError, match="one line"):
        measure_points(X[lab == 0], Steps(), labels=np.r_[np.zeros(10), np.ones(
            int(np.sum(lab == 0)) - 10)].astype(int))


@pytest.mark.parametrize("shape", [Cylinder(), Sphere(), Plane()])
def test_differentiated_fits_hold_no_host_callback(shape):
    """The fit's derivatives (implicit function theorem, `_lsq._implicit`) compile to
    programs without host callbacks: JAX never writes a program holding one to its
    persistent compilation cache, and with optimistix's adjoint (lineax's checked solve)
    every `measure` compiled its differentiated programs anew (~15 s of 49 s)."""
    rng = np.random.default_rng(0)
    X = jnp.asarray(rng.normal(size=(40, 3)))
    for f in (jax.jacrev, jax.jacfwd):
        program = jax.jit(f(lambda X: fit_shape(shape, X).values)).lower(X).as_text()
        assert "callback" not in program


def _arcs(rng, noise, r=17.5, lines=6, per_line=200):
    """Points along `lines` arcs of a cylinder (at heights −3 … 3 mm), in order along
    each arc, as a scan's stripes come; radial noise `noise(rng, lines, per_line)`."""
    a = np.linspace(0.0, 2.5, per_line)
    z = np.linspace(-3.0, 3.0, lines)
    radial = np.cos(a)[:, None] * E1 + np.sin(a)[:, None] * E2  # (per_line, 3)
    rr = r + noise(rng, lines, per_line)  # (lines, per_line)
    X = CENTRE + rr[..., None] * radial[None] + z[:, None, None] * AXIS
    return X.reshape(-1, 3)


def _box_filtered(width):
    """Radial noise of σ 2 µm shared by `width` neighbours along each line (a moving
    average of white noise: ρ_k = (width − k)/width, τ = width), as stripe centres from a
    filter several pixels wide."""

    def noise(rng, lines, per_line):
        white = rng.standard_normal((lines, per_line + width - 1))
        k = np.ones(width) / np.sqrt(width)
        return 2e-3 * np.stack([np.convolve(w, k, mode="valid") for w in white])

    return noise


def test_fit_uncertainty_counts_neighbours_that_share_their_errors():
    """Errors shared by neighbouring points along each line (τ = 5): the fit-residual
    u counted the points as independent and understated the spread of the radius over
    repeated scans by ~√τ; estimated along the lines it matches it. 150 scans know the
    spread to ±6 % (1/√(2·149)); u (the median over 12 scans) carries the lag estimates'
    error (ρ_k from 1200 points of which ~240 independent, τ to ~10 %, the median of 12
    to ~4 %): bounds 0.8–1.25, ~3σ of the two together (seeds 1–3 and 11 gave 0.97–1.02).
    The scans are fitted one by one with one compiled fit: a vmapped LM runs every scan
    to the slowest one's step count (measured 18 s against 7 s)."""
    from scheimflux.metrology._gum import _fit_stats, _point_terms

    rng = np.random.default_rng(11)
    noise = _box_filtered(5)
    sets = np.stack([_arcs(rng, noise) for _ in range(150)])
    fit = eqx.filter_jit(lambda X: fit_shape(Cylinder(), X).values[0])
    spread = np.std([float(fit(jnp.asarray(X))) for X in sets], ddof=1)
    ms = [measure_points(X, Cylinder()) for X in sets[:12]]
    u = np.median([float(m.budget["fit_residual"][0]) for m in ms])
    assert 0.8 < spread / u < 1.25
    taus = [m.residual_stats["correlation_time"] for m in ms]
    assert 3.5 < np.median(taus) < 6.5 and any("tau" in n for n in ms[0].notes)
    # the independent sum (no lags) understates it by about √τ
    f, gX, normals, _ = _point_terms(Cylinder(), jnp.asarray(sets[0]), jnp.zeros(1200, jnp.int32))
    u_indep = np.sqrt(_fit_stats(Cylinder(), f, np.asarray(normals), np.asarray(gX), 0.0)[0])
    assert spread / u_indep[0, 0] > 1.7

    # independent noise along the same lines: no lag kept, the budget as before
    white = _arcs(rng, lambda g, n, m: 2e-3 * g.standard_normal((n, m)))
    m = measure_points(white, Cylinder())
    assert m.residual_stats["correlation_time"] == 1.0
    assert not any("tau" in n for n in m.notes)


def test_banded_sum_is_the_dense_correlated_sum():
    """`banded_sum` against the dense `Σ_ij c_ij P_i P_jᵀ` with `c` written out: 1 on the
    diagonal, ρ_|i−j| within a line, 0 across lines and beyond the lags."""
    from scheimflux.metrology._gum import banded_sum, point_lines

    rng = np.random.default_rng(3)
    P = rng.standard_normal((2, 40, 2))
    X = np.cumsum(np.full((40, 3), 0.1), axis=0)
    X[17:] += 5.0  # a gap: a second line from point 17
    frames = np.r_[np.zeros(30), np.ones(10)]  # and a third from point 30
    lines = point_lines(X, frames)
    np.testing.assert_array_equal(lines, np.r_[[0] * 17, [1] * 13, [2] * 10])
    rho = np.array([0.7, 0.4, 0.1])
    i, j = np.indices((40, 40))
    lag = np.abs(i - j)
    c = np.where(lag == 0, 1.0, 0.0)
    for k, rk in enumerate(rho, start=1):
        c = np.where((lag == k) & (lines[i] == lines[j]), rk, c)
    dense = np.einsum("kid,ij,ljd->kl", P, c, P)
    np.testing.assert_allclose(banded_sum(P, rho, lines), dense, rtol=1e-12)
