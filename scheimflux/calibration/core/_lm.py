"""Levenberg–Marquardt for calibration on optimistix's public extension points.

`BlockLevenbergMarquardt` is an `optx.AbstractGaussNewton` (optimistix's own loop,
termination and `Solution`) made of

- the descent `optx.DampedNewtonDescent` (damping λ = 1 / step size), whose damped
  systems `[J; √λ I]` go through `BlockNormalCholesky` (block-assembled normal equations,
  `_linear.py`), and
- the search `CalibrationTrustRegion`, an `optx.AbstractSearch` of its own: the classical
  trust-region update with optimistix's constants, a chosen initial step size and a rule
  for cost changes at the float64 noise level.

No private optimistix state is touched, and no concrete optimistix class is subclassed.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Float

from ._linear import BlockNormalCholesky, BlockStructure


def _sum_squares(tree) -> Float[Array, ""]:
    return sum(jnp.sum(x**2) for x in jax.tree.leaves(tree))


class _TrustState(eqx.Module):
    step_size: Float[Array, ""]


class CalibrationTrustRegion(optx.AbstractSearch):
    """The classical trust region (accept when the cost falls by at least `low_cutoff` of
    the Gauss–Newton prediction; grow the step size `high_constant`× above
    `high_cutoff`; shrink it `low_constant`× on rejection: optimistix's
    `ClassicalTrustRegion` rule and constants), with two changes:

    - `initial_step_size`: optimistix starts at step size 1, i.e. λ = 1, which on a
      unit-column-scaled Jacobian equals the whole diagonal of `JᵀJ`: the first steps are
      gradient steps and λ falls by 3.5× per step only. Calibration problems are well
      initialised and have weak valleys (the boards' common depth against the
      magnification: eigenvalues ~1e-11 of the scaled `JᵀJ`), where heavy damping creeps
      for hundreds of steps; starting at Gauss–Newton (λ = 1e-12; a failed step still
      shrinks the region 4×) converges in a handful.
    - `cost_noise`: at the optimum the cost of ~10⁴ residuals is known only to a few
      1e-12 (float64 rounding), and every further step "increases" it by that noise. The
      classical rule rejects such steps and shrinks the region for dozens of steps before
      the solver may stop. A change below `cost_noise` (relative) carries no information:
      it is accepted at an unchanged step size, so the convergence test can see it.
    """

    initial_step_size: float = 1e12
    cost_noise: float = 1e-10
    high_cutoff: float = 0.99
    low_cutoff: float = 0.01
    high_constant: float = 3.5
    low_constant: float = 0.25

    def init(self, y, f_info_struct) -> _TrustState:
        del f_info_struct
        return _TrustState(jnp.asarray(self.initial_step_size))

    def step(self, first_step, y, y_eval, f_info, f_eval_info, state: _TrustState):
        y_diff = jax.tree.map(lambda a, b: a - b, y_eval, y)
        # Gauss–Newton model of the cost change: ½|J δ + r|² − ½|r|²
        model = jax.tree.map(lambda a, b: a + b, f_info.jac.mv(y_diff), f_info.residual)
        predicted = 0.5 * (_sum_squares(model) - _sum_squares(f_info.residual))
        f, f_eval = f_info.as_min(), f_eval_info.as_min()
        change = f_eval - f
        accept = (change <= self.low_cutoff * predicted) | first_step
        good = (change < self.high_cutoff * predicted) & (predicted < 0) & ~first_step
        mul = jnp.where(good, self.high_constant, 1.0)
        mul = jnp.where(accept, mul, self.low_constant)
        flat = (jnp.abs(change) <= self.cost_noise * jnp.abs(f)) & ~accept
        step_size = jnp.where(flat, state.step_size, mul * state.step_size)
        return step_size, accept | flat, optx.RESULTS.successful, _TrustState(step_size)


class MaskedRMSNorm(eqx.Module):
    """RMS norm over the free components of the state vector (mask 1); the plain RMS
    norm of anything else (the residual vector, told apart by its length).

    Held components of a step are exactly zero; counting them would dilute the RMS and
    make the convergence test depend on how many parameters are held.
    """

    mask: Float[Array, " n"]

    def __call__(self, x) -> Float[Array, ""]:
        leaves = jax.tree.leaves(x)
        if len(leaves) == 1 and leaves[0].shape == self.mask.shape:
            n = jnp.maximum(jnp.sum(self.mask), 1.0)
            return jnp.sqrt(jnp.sum(self.mask * leaves[0] ** 2) / n)
        return optx.rms_norm(x)


def _quiet(**kwargs) -> None:
    del kwargs


class BlockLevenbergMarquardt(optx.AbstractGaussNewton):
    """Levenberg–Marquardt with block normal equations (see the module docstring).

    **Arguments:**
    - `structure`: the Jacobian's block structure (`_linear.BlockStructure`).
    - `mask`: 1 on free, 0 on held components of the state vector (a held component's
      Jacobian column is zero, so its step is zero; the mask keeps it out of the
      convergence test).
    - `rtol`, `atol`: optimistix's Cauchy termination, on RMS norms (of the free
      state components, and of the residuals).
    """

    rtol: float
    atol: float
    norm: MaskedRMSNorm
    descent: optx.DampedNewtonDescent
    search: CalibrationTrustRegion
    verbose: Callable[..., None]

    def __init__(self, structure: BlockStructure, mask, rtol: float, atol: float):
        self.rtol = rtol
        self.atol = atol
        self.norm = MaskedRMSNorm(jnp.asarray(mask))
        self.descent = optx.DampedNewtonDescent(linear_solver=BlockNormalCholesky(structure))
        self.search = CalibrationTrustRegion()
        self.verbose = _quiet


def result_message(result, finite: bool = True) -> str:
    """The failure message of a solve ("" on success): optimistix's own message for its
    result (`optx.RESULTS[result]`), or that the residuals became non-finite."""
    if not finite:
        return "residuals became non-finite"
    if result == optx.RESULTS.successful:
        return ""
    return optx.RESULTS[result]
