"""The calibration covariance with one variance factor per residual group (`_calcov.py`).

A linear least-squares problem stands in for the calibration (its Jacobian is the
calibration's at the optimum, to first order): two groups of observations, each weighted
with an assumed σ of 1, while the data carry σ = 1 in one group and 0.3 in the other (as
the board-stripe residuals scatter less than their assumed σ). The sandwich covariance must
match the spread of the estimates over fresh noise; the pooled `s² (JᵀJ)⁻¹` must not.
"""

import numpy as np
import pytest

from scheimflux.calibrate._covariance import covariance_from_jacobian
from scheimflux.metrology._calcov import sandwich_covariance

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
    from scheimflux.calibrate import calibrate, diagnostics, residual_function
    from scheimflux.calibrate._model import corner_residuals, stripe_residuals
    from scheimflux.calibrate._solve import jacobian
    from scheimflux.metrology import group_covariance
    from scheimflux.simulate import paper_rig, simulate_observations
    from scheimflux.targets import Checkerboard

    obs, _ = simulate_observations(
        paper_rig(refine=False), Checkerboard(6, 5, 0.4), n_views=4, stage_scan=False, seed=0
    )
    cal = calibrate(obs, distortion="none")
    d = diagnostics(cal, block="joint")
    gc = group_covariance(cal)
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
    terms = {}
    for how in ("groups", "pooled", gc):
        m = measure_stripes(cal, prof.px_true, Steps(), labels=prof.labels, sigma_px=0.05,
                            diag=d, calibration_covariance=how, frozen_sigma=None)
        G = np.asarray(m.sensitivity["d_values"])[0]
        idx = [d.labels.index(lab) for lab in m.sensitivity["labels"]]
        S = (d.covariance if isinstance(how, str) and how == "pooled" else gc.covariance)
        np.testing.assert_allclose(m.budget["calibration"][0] ** 2,
                                   G @ S[np.ix_(idx, idx)] @ G, rtol=1e-9)
        terms[how if isinstance(how, str) else "given"] = m.budget["calibration"][0]
    assert terms["groups"] == terms["given"]
