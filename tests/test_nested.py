"""The F-test that decides whether the non-central thick lens keeps its pupil terms."""

import numpy as np
import pytest

from scheimflux.calibration.core._nested import nested_f_test


def _rss_pairs(rng, n_trials, n=60, p_reduced=4, extra_coef=(0.0, 0.0)):
    """Residual sums of squares of nested linear least squares (a reduced model and the
    same with len(extra_coef) more regressors) on `n_trials` data sets: exact
    projections, no solver."""
    X = rng.standard_normal((n, p_reduced + len(extra_coef)))
    beta = np.concatenate([rng.standard_normal(p_reduced), extra_coef])
    y = X @ beta + rng.standard_normal((n_trials, n))
    def rss(A):
        Q, _ = np.linalg.qr(A)
        r = y - (y @ Q) @ Q.T
        return np.sum(r**2, axis=1)
    return rss(X[:, :p_reduced]), rss(X), n, p_reduced + len(extra_coef)


def test_p_values_are_uniform_when_the_extra_terms_are_zero():
    # Under the reduced model the p-value is uniform on [0, 1]: the fraction below any
    # level a is a, within binomial noise (20 000 trials: σ = sqrt(a(1-a)/20000) <= 0.0036;
    # the bound is 4σ).
    rng = np.random.default_rng(0)
    r0, r1, n, p = _rss_pairs(rng, 20_000)
    pv = np.array([nested_f_test(a, b, n, p, 2).p_value for a, b in zip(r0, r1)])
    for a in (0.01, 0.05, 0.1, 0.3, 0.5, 0.9):
        sigma = np.sqrt(a * (1 - a) / len(pv))
        assert abs(np.mean(pv < a) - a) < 4 * sigma, (a, np.mean(pv < a))


def test_real_extra_terms_are_significant():
    # Two extra regressors with coefficients of 1 (noise σ = 1, 60 observations): the
    # F statistic is ~ 1 + n/2 ≈ 30, far beyond the 1e-3 level's critical value (~7.7).
    rng = np.random.default_rng(1)
    r0, r1, n, p = _rss_pairs(rng, 200, extra_coef=(1.0, 1.0))
    tests = [nested_f_test(a, b, n, p, 2) for a, b in zip(r0, r1)]
    assert np.mean([t.significant for t in tests]) > 0.99


def test_closed_form_tail_matches_the_chi2_limit():
    # For d → ∞, q F → χ²_q, whose tail for q = 2 is exp(-x/2) = exp(-F).
    for f in (0.5, 2.0, 5.0):
        assert nested_f_test(1.0 + 2 * f * 1e-7, 1.0, 10**7 + 10, 10, 2).p_value == \
            pytest.approx(np.exp(-f), rel=1e-5)  # fmt: skip


def test_edge_cases():
    # a full fit worse than the reduced one (stopped early) is not significant
    t = nested_f_test(1.0, 1.5, 100, 10, 2)
    assert (t.f, t.p_value, t.significant) == (0.0, 1.0, False)
    assert nested_f_test(1.0, 0.0, 100, 10, 2).significant  # exact data
    with pytest.raises(ValueError, match="degrees of freedom"):
        nested_f_test(2.0, 1.0, 10, 10, 2)
    with pytest.raises(ValueError, match="even q"):
        nested_f_test(2.0, 1.0, 100, 10, 3)
    with pytest.raises(ValueError, match="finite"):
        nested_f_test(float("nan"), 1.0, 100, 10, 2)


def test_four_extra_terms_p_values_are_uniform_under_the_null():
    # q = 4 (the axial pupil terms and the lateral offset tested together): uniform
    # p-values under the reduced model, as for q = 2 (same binomial bound).
    rng = np.random.default_rng(2)
    r0, r1, n, p = _rss_pairs(rng, 20_000, extra_coef=(0.0,) * 4)
    pv = np.array([nested_f_test(a, b, n, p, 4).p_value for a, b in zip(r0, r1)])
    for a in (0.01, 0.05, 0.1, 0.3, 0.5, 0.9):
        sigma = np.sqrt(a * (1 - a) / len(pv))
        assert abs(np.mean(pv < a) - a) < 4 * sigma, (a, np.mean(pv < a))


@pytest.mark.parametrize("q", [2, 4, 6])
def test_even_q_tail_matches_scipy(q):
    # The closed form against SciPy's F survival function (an independent
    # implementation: the regularised incomplete beta function), relative 1e-10.
    from scipy.stats import f as f_dist

    for dof, stat in ((5, 0.3), (40, 2.0), (2000, 7.5), (10**5, 1.2)):
        rss1 = float(dof)
        rss0 = rss1 + q * stat  # F = ((rss0 − rss1)/q) / (rss1/dof) = stat
        t = nested_f_test(rss0, rss1, dof + 10, 10, q)
        assert t.f == pytest.approx(stat, rel=1e-9)  # rss0 − rss1 cancels ~5 digits
        assert t.p_value == pytest.approx(f_dist.sf(t.f, q, dof), rel=1e-10, abs=1e-300)
