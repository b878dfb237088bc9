"""The calibration covariance with one variance factor per residual group (`_calcov.py`).

A linear least-squares problem stands in for the calibration (its Jacobian is the
calibration's at the optimum, to first order): two groups of observations, each weighted
with an assumed σ of 1, while the data carry σ = 1 in one group and 0.3 in the other (as
the board-stripe residuals scatter less than their assumed σ). The sandwich covariance must
match the spread of the estimates over fresh noise; the pooled `s² (JᵀJ)⁻¹` must not.
"""

import numpy as np
import pytest

from scheimflux.calibration.trust._calcov import sandwich_covariance
from scheimflux.calibration.trust._covariance import covariance_from_jacobian

DRAWS = 3000


def _problem():
    rng = np.random.default_rng(3)
    # group 0 (σ 1) determines all three parameters, group 1 (σ 0.3, more rows) mostly
    # the first one: pooling its small scatter into one s² understates the other two
    A0 = rng.standard_normal((120, 3))
    A1 = np.c_[rng.standard_normal(400), 0.05 * rng.standard_normal((400, 2))]
    return np.vstack([A0, A1]), np.r_[np.ones(120), np.full(400, 0.3)], (120, 400)


def test_sandwich_matches_the_spread_of_least_squares_estimates():
    J, sig, sizes = _problem()
    rng = np.random.default_rng(4)
    noise = sig[None, :] * rng.standard_normal((DRAWS, len(sig)))
    est = np.linalg.lstsq(J, noise.T, rcond=None)[0].T  # truth 0: x̂ per draw
    resid = noise - est @ J.T  # r = y − J x̂ (sign does not matter)
    emp = np.cov(est.T)
    mean_sw = np.mean([sandwich_covariance(J, r, sizes)[0] for r in resid[:400]], axis=0)
    pooled = np.mean([covariance_from_jacobian(J, r)[0] for r in resid[:400]], axis=0)
    # the empirical variance of 3000 normal draws is known to √(2/3000) = 2.6 %, the mean
    # of 400 sandwich estimates (each s²_g from > 100 residuals) to < 1 %: 10 % is > 3 σ
    np.testing.assert_allclose(np.diag(mean_sw), np.diag(emp), rtol=0.10)
    # the pooled factor misses parameters 1 and 2 by far more than that
    assert np.all(np.diag(pooled)[1:] < 0.6 * np.diag(emp)[1:])
    factors = np.mean([sandwich_covariance(J, r, sizes)[1] for r in resid[:400]], axis=0)
    np.testing.assert_allclose(factors, [1.0, 0.09], rtol=0.05)


def test_equal_noise_gives_the_pooled_covariance():
    J, _, sizes = _problem()
    r = np.random.default_rng(5).standard_normal(len(J))
    cov, factors, redund, counts, pooled = sandwich_covariance(J, r, sizes)
    ref, s2, *_ = covariance_from_jacobian(J, r)
    # with s²_g replaced by the pooled s², the sandwich is s² (JᵀJ)⁻¹ exactly; with its
    # own s²_g (equal only statistically) it is within their scatter (≈ 15 % per group)
    assert abs(pooled - s2) < 1e-12 * s2
    np.testing.assert_allclose(sum(redund), len(J) - 3, rtol=1e-10)
    assert counts == [120, 400]
    np.testing.assert_allclose(np.diag(cov), np.diag(ref), rtol=0.3)
    padded = np.vstack([J, np.zeros((7, 3))])  # padding rows are not observations
    cov2, f2, _, c2, p2 = sandwich_covariance(padded, np.r_[r, np.zeros(7)], (120, 407))
    np.testing.assert_allclose(cov2, cov, rtol=1e-10)
    assert c2 == [120, 400] and abs(p2 - pooled) < 1e-12


@pytest.mark.slow  # a calibration compile: 513 s alone under load 18 on 2 cores
def test_groups_of_a_real_calibration_add_up_and_reduce_to_diagnostics():
    """On a ray-traced calibration (the 4-view scene other tests calibrate too, so its
    compiled programs are shared): the corner and board-stripe groups cover the joint
    residual vector, their redundancies add up to n − p, the pooled s² is their
    redundancy-weighted mean, and with each group's residuals rescaled to the pooled s²
    the sandwich is `diagnostics`' covariance (same labels, same order)."""
    from scheimflux.calibration import calibrate, diagnostics, residual_function
    from scheimflux.calibration.core._model import corner_residuals, stripe_residuals
    from scheimflux.calibration.core._solve import jacobian
    from scheimflux.metrology import group_covariance
    from scheimflux.simulate import paper_rig, simulate_observations
    from scheimflux.targets import Checkerboard

    obs, _ = simulate_observations(
        paper_rig(refine=False), Checkerboard(6, 5, 0.4), n_views=4, stage_scan=False, seed=0
    )
    cal = calibrate(obs, distortion="none")
    d = diagnostics(cal, block="joint")
    gc = group_covariance(cal, weighting="groups")
    assert list(gc.variance_factors) == ["corners", "stripes"]
    assert sum(gc.n_residuals.values()) == d.n_residuals
    red = np.array(list(gc.redundancy.values()))
    f = np.array(list(gc.variance_factors.values()))
    np.testing.assert_allclose(red.sum(), d.n_residuals - d.n_params, rtol=1e-9)
    np.testing.assert_allclose(f @ red / red.sum(), d.variance_factor, rtol=1e-9)
    fn, params, spec = residual_function(cal, "joint")
    J = np.asarray(jacobian(fn, params, cal.data, spec))
    r = np.asarray(fn(params, cal.data))
    sizes = [np.size(corner_residuals(params, cal.data)),
             np.size(stripe_residuals(params, cal.data))]
    scale = np.repeat(np.sqrt(d.variance_factor / f), sizes)
    cov = sandwich_covariance(J, r * scale, sizes)[0]
    # compared as correlation-scaled entries: SVD rounding on a condition number of ~1e6
    norm = np.sqrt(np.outer(d.std, d.std))
    assert np.max(np.abs(cov - d.covariance) / norm) < 1e-6
    # the groups differ: the board stripes scatter far less than their assumed σ
    assert gc.variance_factors["stripes"] < 0.5 * gc.variance_factors["corners"]
    # measure_stripes' calibration term is G Σ Gᵀ with the chosen covariance
    from scheimflux.metrology import Steps, measure_stripes
    from scheimflux.simulate import step_gauge

    prof = step_gauge(paper_rig(refine=False), (1.5,), step_px=6.0)[0]
    gp = group_covariance(cal)  # the default: each residual's noise from its pixel
    assert gp.weighting == "pixels" and list(gp.variance_factors) == ["corners", "stripes"]
    # the corners' pixel noise estimate is the simulated one (0.03 px; a few hundred
    # residuals know it to < 10 %; the undistorted model adds 0.007 px RMS, docs)
    assert 0.8 < np.sqrt(gp.variance_factors["corners"]) / 0.03 < 1.25
    terms = {}
    for how in ("groups", "pooled", gp):
        m = measure_stripes(cal, prof.px_true, Steps(), labels=prof.labels, sigma_px=0.05,
                            diag=d, calibration_covariance=how, frozen_sigma=None)
        G = np.asarray(m.sensitivity["d_values"])[0]
        idx = [d.labels.index(lab) for lab in m.sensitivity["labels"]]
        S = (d.covariance if isinstance(how, str) and how == "pooled" else gp.covariance)
        np.testing.assert_allclose(m.budget["calibration"][0] ** 2,
                                   G @ S[np.ix_(idx, idx)] @ G, rtol=1e-9)
        terms[how if isinstance(how, str) else "given"] = m.budget["calibration"][0]
    assert terms["groups"] == terms["given"]
    # noise-free pixels: the residuals are within the stated stripe noise, nothing is left
    # to the fit-residual term, and the summary says why it is 0 (not "u = 0.000 µm")
    assert m.budget["fit_residual"][0] == 0
    assert "fit residual      u = 0 µm (the residuals are within the stated" in m.summary()


def _heteroscedastic_problem():
    """One group whose rows carry different noise (as board-stripe residuals do: a stripe
    pixel's noise moves its point off the board by σ_px × sin of the angle between laser
    plane and board, which differs from view to view), equally weighted by the solve.
    Parameter 1 is determined by the noisier rows."""
    rng = np.random.default_rng(6)
    A0 = rng.standard_normal((150, 3))
    quiet = np.c_[rng.standard_normal(300), 0.02 * rng.standard_normal((300, 2))]
    loud = np.c_[0.02 * rng.standard_normal(100), rng.standard_normal((100, 2))]
    J = np.vstack([A0, quiet, loud])
    gain = np.r_[np.ones(150), np.full(300, 0.04), np.full(100, 1.0)]  # Var r_i = σ² a_i
    return J, gain, (150, 400)


def test_per_residual_gains_match_the_spread_where_one_factor_per_group_does_not():
    J, gain, sizes = _heteroscedastic_problem()
    rng = np.random.default_rng(7)
    sig = 0.5  # the same pixel noise for both groups, unknown to the estimate
    noise = sig * np.sqrt(gain)[None, :] * rng.standard_normal((DRAWS, len(gain)))
    est = np.linalg.lstsq(J, noise.T, rcond=None)[0].T
    resid = noise - est @ J.T
    emp = np.diag(np.cov(est.T))
    with_gains = np.mean(
        [np.diag(sandwich_covariance(J, r, sizes, gains=gain)[0]) for r in resid[:300]], axis=0
    )
    per_group = np.mean(
        [np.diag(sandwich_covariance(J, r, sizes)[0]) for r in resid[:300]], axis=0
    )
    # 3000 draws know a variance to 2.6 %, the mean of 300 sandwiches (each from > 100
    # residuals per group) to < 1 %: 10 % is > 3 σ
    np.testing.assert_allclose(with_gains, emp, rtol=0.10)
    # one factor for the mixed group averages its quiet and loud rows: the parameters the
    # loud rows determine come out too certain (measured: 0.68 of the spread's variance)
    assert np.all(per_group[1:] < 0.8 * emp[1:])
    # with gains, each group's factor is its pixel noise variance, σ² for both
    f = np.mean([sandwich_covariance(J, r, sizes, gains=gain)[1] for r in resid[:300]], axis=0)
    np.testing.assert_allclose(f, [sig**2, sig**2], rtol=0.05)


def test_equal_gains_are_one_factor_per_group():
    J, _, sizes = _problem()
    r = np.random.default_rng(8).standard_normal(len(J))
    ref = sandwich_covariance(J, r, sizes)
    # one gain for all rows rescales the factors and nothing else (gains that differ
    # between groups change the one-step factors slightly: the other groups' share of the
    # redundancy is counted in pixel units)
    got = sandwich_covariance(J, r, sizes, gains=np.full(len(J), 4.0))
    np.testing.assert_allclose(got[0], ref[0], rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(got[1], np.asarray(ref[1]) / 4.0, rtol=1e-10)
    np.testing.assert_allclose(got[2], ref[2], rtol=1e-10)
    with pytest.raises(ValueError, match="gains"):
        sandwich_covariance(J, r, sizes, gains=-np.ones(len(J)))


@pytest.mark.slow  # 120 s at load 16–17 on 2 cores (the residual function's compile)
def test_pixel_noise_gains_are_each_residuals_own_pixel_derivative():
    """On a ray-traced scene's corner and board-stripe residuals (no solve: the truth's
    parameters): the two-JVP gains equal the row norms² of the dense Jacobian with respect
    to every observed pixel, and no residual depends on more than one pixel. (The gauge
    residuals' gains are checked by the Monte Carlo of re-calibrations: the gauge group's
    estimated pixel noise is the simulated one, docs/metrology.md.)"""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from scheimflux.calibration.core._model import SystemParams, camera_plane_residuals, make_data
    from scheimflux.calibration.trust._calcov import pixel_noise_gains
    from scheimflux.camera import ThickLensScheimpflug
    from scheimflux.geometry import LaserPlane
    from scheimflux.geometry._transforms import Pose
    from scheimflux.simulate import paper_rig, simulate_observations
    from scheimflux.targets import Checkerboard

    rig = paper_rig(refine=False)
    obs, truth = simulate_observations(rig, Checkerboard(6, 5, 0.4), n_views=3,
                                       stage_scan=False, seed=0)
    data = make_data(obs, sigma_corner_px=0.03, sigma_stripe_mm=2e-3)
    poses = Pose(jnp.stack([p.rotvec for p in truth.board_poses]),
                 jnp.stack([p.translation for p in truth.board_poses]))
    params = SystemParams(ThickLensScheimpflug(**truth.nominal_params), poses,
                          LaserPlane(jnp.asarray(truth.laser_plane)))
    a = pixel_noise_gains(camera_plane_residuals, params, data)
    dense = np.zeros_like(a)
    for name in ("corners", "stripe"):
        Jp = jax.jacfwd(lambda x, name=name: camera_plane_residuals(
            params, eqx.tree_at(lambda d: getattr(d, name), data, x)))(getattr(data, name))
        Jp = np.asarray(Jp).reshape(len(a), -1, 2)
        assert np.all(np.sum(np.any(Jp != 0, axis=2), axis=1) <= 1), name  # one pixel
        dense += np.sum(Jp**2, axis=(1, 2))
    n_corner = 2 * int(np.sum(np.asarray(data.corner_w)))
    n_stripe = int(np.sum(np.asarray(data.stripe_w)))
    assert np.count_nonzero(dense) == n_corner + n_stripe
    # corners: r = (projection − pixel)/σ, so a = 1/σ² exactly
    np.testing.assert_allclose(a[dense > 0][:n_corner], 1 / 0.03**2, rtol=1e-12)
    # the same derivatives summed in another order: rounding only
    np.testing.assert_allclose(a, dense, rtol=1e-10, atol=1e-12 * dense.max())
    # group_covariance's one program (residuals, Jacobian, gains; compiled without the
    # expensive passes) against the residuals op by op, the Jacobian and the gains above
    from scheimflux.calibration.core._solve import free_spec, jacobian, linearised

    spec = free_spec(params, ("camera.dx", "camera.dy", "camera.f", "camera.x0", "camera.y0"))
    r, J, a2 = linearised(camera_plane_residuals, params, data, spec, pixel_gains=True)
    r0 = np.asarray(camera_plane_residuals(params, data))
    J0 = np.asarray(jacobian(camera_plane_residuals, params, data, spec))
    # compiled in another operation order: a projected pixel (~1e3 px, 1.1e-13 px per
    # ulp) may move by ~100 ulp, 4e-10 in a residual of σ = 0.03 px
    np.testing.assert_allclose(r, r0, rtol=0, atol=1e-9)
    np.testing.assert_allclose(J, J0, rtol=1e-8, atol=1e-10 * np.abs(J0).max())
    np.testing.assert_allclose(a2, a, rtol=1e-10, atol=1e-12 * a.max())
    assert linearised(camera_plane_residuals, params, data, spec)[2] is None


def test_correlated_centres_widen_the_covariance_to_the_spread():
    """Noise that neighbouring rows share (stripe centres one per scan line from a filter
    several pixels wide: rendered JPEG gauge centres had ρ₁ = 0.88, ρ₂ = 0.63): with the
    rows taken as independent the sandwich understates the spread of the estimates by
    about τ = 1 + 2 Σ ρ_k; with the lag correlations estimated from the residuals it
    matches it. Independent noise gives no correlation (the covariance unchanged)."""
    from scheimflux.calibration.trust._calcov import residual_lag_correlation

    rng = np.random.default_rng(7)
    n = 2000
    t = np.linspace(-1.0, 1.0, n)  # rows in order along a line: smooth Jacobian columns
    J = np.c_[np.ones(n), t, t * t - 1 / 3]
    # moving average of width 5 (a box filter): ρ_k = (5 − k)/5 for k < 5, τ = 5
    width = 5
    white = rng.standard_normal((DRAWS, n + width - 1))
    kernel = np.ones(width) / np.sqrt(width)
    noise = np.stack([np.convolve(w, kernel, mode="valid") for w in white])
    est = np.linalg.lstsq(J, noise.T, rcond=None)[0].T
    resid = noise - est @ J.T
    emp = np.diag(np.cov(est.T))
    rho = [residual_lag_correlation(r) for r in resid[:200]]
    np.testing.assert_allclose(np.mean([c[:4] for c in rho], axis=0), [0.8, 0.6, 0.4, 0.2],
                               atol=0.03)  # fmt: skip
    indep = np.mean([np.diag(sandwich_covariance(J, r, (n,))[0]) for r in resid[:200]], 0)
    corr = np.mean(
        [np.diag(sandwich_covariance(J, r, (n,), correlations=[c])[0])
         for r, c in zip(resid[:200], rho)], axis=0,
    )  # fmt: skip
    assert np.all(indep < 0.3 * emp)  # independent rows: ~1/τ = 0.2 of the spread
    # the empirical variance of 3000 draws is known to 2.6 %; ρ_k estimated from 2000
    # rows of which ~400 independent (σ(ρ) ~ 0.05, τ to ~10 %): 20 %
    np.testing.assert_allclose(corr, emp, rtol=0.2)
    # independent noise: no lag kept, the covariance as without correlations
    white_r = rng.standard_normal(n)
    r0 = white_r - J @ np.linalg.lstsq(J, white_r, rcond=None)[0]
    assert len(residual_lag_correlation(r0)) <= 1
    np.testing.assert_allclose(
        sandwich_covariance(J, r0, (n,), correlations=[np.zeros(0)])[0],
        sandwich_covariance(J, r0, (n,))[0], rtol=1e-12,
    )  # fmt: skip
