"""When a Levenberg–Marquardt solve that reached its step limit counts as converged: the
Gauss–Newton step that remains, in units of each parameter's σ."""

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from scheimflux.calibration.core._solve import (
    AT_OPTIMUM_SIGMA,
    _dense,
    least_squares,
    remaining_step_sigma,
)


def _weak_design(rng):
    """A 200 × 5 design with columns of scales 1e-3 … 1e3 and two nearly collinear
    columns: the scaled normal matrix's eigenvalues span ~1e-9 (a weak valley)."""
    A = rng.normal(size=(200, 5))
    A[:, 4] = A[:, 3] + 3e-5 * rng.normal(size=200)
    return A * np.array([1e-3, 1.0, 1e3, 1.0, 1.0])


def test_remaining_step_is_the_linear_least_squares_offset_in_sigma():
    # For r = A x − b the Gauss–Newton step from x is exactly x* − x, and σ² = diag of
    # (AᵀA)⁻¹ (residuals in units of σ): both from NumPy's own lstsq and inverse here.
    rng = np.random.default_rng(3)
    A = _weak_design(rng)
    b = rng.normal(size=200)
    x_opt = np.linalg.lstsq(A, b, rcond=None)[0]
    sigma = np.sqrt(np.diag(np.linalg.inv(A.T @ A)))
    structure = _dense(5, 200)
    for frac in ([1e-4, 0, 0, 0, 0], [0, 0, 0, 0.3, -0.3], [2.0, -1.0, 0.5, 1e-3, 0]):
        d = np.asarray(frac) * sigma
        r = A @ (x_opt + d) - b
        got = remaining_step_sigma(structure, A, r, np.ones(5, bool))
        assert got == pytest.approx(np.max(np.abs(frac)), rel=1e-5), (frac, got)
    # a held parameter: the remaining step of the others with it fixed
    free = np.array([True, True, False, True, True])
    x = x_opt.copy()
    x[[0, 3]] += 0.01 * sigma[[0, 3]]
    r = A @ x - b
    Af = A[:, free]
    step = np.linalg.lstsq(Af, -r, rcond=None)[0]
    want = np.max(np.abs(step) / np.sqrt(np.diag(np.linalg.inv(Af.T @ Af))))
    got = remaining_step_sigma(structure, A, r, free)
    assert got == pytest.approx(want, rel=1e-5)
    # a column no residual depends on: no σ, no verdict
    A0 = A.copy()
    A0[:, 1] = 0.0
    assert remaining_step_sigma(structure, A0, r, np.ones(5, bool)) == math.inf


class _Point(eqx.Module):
    x: jnp.ndarray
    y: jnp.ndarray


def _rosenbrock(params, data):
    return jnp.stack([data * (1.0 - params.x), 10.0 * (params.y - params.x**2)])


@pytest.mark.parametrize("max_steps, converged", [(2, False), (60, True)])
def test_step_limit_is_converged_only_at_the_optimum(max_steps, converged):
    # With rtol = atol = 0 the state-change test can never pass: every solve ends at its
    # step limit. After 2 steps from (-1.2, 1) the solve is far from (1, 1) and stays
    # unconverged; after 60 it is at the optimum and counts as converged.
    p0 = _Point(jnp.asarray(-1.2), jnp.asarray(1.0))
    fit = least_squares(_rosenbrock, p0, jnp.asarray(1.0), blocks=None, rtol=0.0, atol=0.0,
                        throw=False, max_steps=max_steps)  # fmt: skip
    gap = fit.stats["remaining_step_sigma"]
    assert fit.steps == max_steps
    assert fit.converged is converged and (gap <= AT_OPTIMUM_SIGMA) is converged, gap
    if converged:
        assert fit.message == ""
        np.testing.assert_allclose([float(fit.params.x), float(fit.params.y)], 1.0,
                                   atol=1e-9)  # fmt: skip
    else:
        assert "maximum number of steps" in fit.message
