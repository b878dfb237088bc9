"""Differentiable orthogonal least-squares fits of a shape to points.

[`fit_shape`][] solves `min_y Σ_i |residual(y, x_i)|²` with optimistix's
Levenberg–Marquardt from the shape's closed-form start. Its derivatives with respect to the
points (and anything upstream of them: pixels, calibration parameters) come from the
implicit function theorem applied to the optimality condition at the optimum (as
optimistix's implicit adjoint forms them), not from unrolling the iterations. It is a
pure function of arrays: `jax.jit`, `jax.vmap`, `jax.grad` and `jax.jacrev` apply.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx

from ._shapes import AbstractShape

__all__ = ["ShapeFit", "fit_shape", "residual_normals"]

# Cauchy termination of the Levenberg–Marquardt solve: steps below 1e-13 mm (or rad) and
# relative cost changes below 1e-10 — far below any measurement noise (µm), above float64
# rounding of the cost of ~1e4 residuals.
RTOL, ATOL = 1e-10, 1e-13
MAX_STEPS = 256


class ShapeFit(eqx.Module):
    """A fitted shape.

    **Fields:**
    - `shape`: the [`AbstractShape`][] fitted.
    - `params`: the local parameters at the optimum, `(p,)`; `frame`: the start they are
      relative to (see the shape's `describe` for the geometry as plain numbers).
    - `values`: the measured values `(K,)` (`shape.names`).
    - `residuals`: the orthogonal residuals `(N, m)` (mm; `m = shape.n_residuals`).
    - `result`: the optimistix result (`optx.RESULTS.successful` when converged);
      `steps`: Levenberg–Marquardt steps taken.
    """

    shape: AbstractShape
    params: jax.Array
    frame: tuple
    values: jax.Array
    residuals: jax.Array
    result: optx.RESULTS
    steps: jax.Array


def _residuals(shape, y, frame, X, labels):
    r = jax.vmap(shape.residual, in_axes=(None, None, 0, 0))(y, frame, X, labels)
    return r.reshape(X.shape[0], shape.n_residuals)


def _default_labels(X, labels):
    if labels is None:
        return jnp.zeros(X.shape[0], jnp.int32)
    return jnp.asarray(labels, jnp.int32)


def _implicit(residuals, y):
    """`y` (the optimum of `½|residuals(y)|²`, its value unchanged) with the derivative
    the implicit function theorem gives it through whatever `residuals` closes over:
    `dy = −H⁻¹ d(Jᵀr)` at fixed y, H the cost's Hessian (`Jᵀr` and `H` as optimistix's
    implicit adjoint forms them for a least-squares solve).

    Written out rather than left to optimistix because its adjoint solves with lineax's
    checked linear solve, whose failure branch is a host callback: programs that hold a
    callback are never written to JAX's persistent compilation cache, so every `measure`
    compiled its three differentiated programs again (~15 s). Degenerate fits are
    refused before their derivatives are used (`shape.check`, the rank check of the
    fit's parameter Jacobian)."""

    def gradient(y):
        return jax.grad(lambda y: 0.5 * jnp.sum(residuals(y) ** 2))(y)

    H = jax.lax.stop_gradient(jax.jacfwd(gradient)(y))
    step = -jnp.linalg.solve(H, gradient(y))
    return y + (step - jax.lax.stop_gradient(step))


# Compiled as one program, also when called eagerly: op by op, the solve's loop closes
# over a new residual function at every call, so each call traced and compiled it again
# (a 1000-point cylinder: 20 s the first call, 2 s every later one; compiled: 5 s once,
# then 0.04 s). Inside a caller's `jit` it is inlined as before.
@eqx.filter_jit
def fit_shape(shape: AbstractShape, points, labels=None, *, max_steps: int = MAX_STEPS):
    """Fit `shape` to `points` by orthogonal least squares (differentiable).

    **Arguments:**
    - `shape`: a [`Plane`][], [`Sphere`][], [`Circle`][], [`Cylinder`][], [`Steps`][] or
      [`Distance`][].
    - `points`: `(N, 3)` float64, finite (call `shape.check(points, labels)` first for a
      clear error on too few or degenerate points; traced code cannot raise).
    - `labels`: `(N,)` integers (the face of each point, for [`Steps`][]); default zeros.

    **Returns:** a [`ShapeFit`][]. Check `result` (eagerly:
    `result == optx.RESULTS.successful`) before trusting `values`.
    """
    X = jnp.asarray(points)
    labels = _default_labels(X, labels)
    y0, frame = shape.start(X, labels)
    if shape.n_params() == 0:
        values = shape.values(y0, frame, X, labels)
        return ShapeFit(
            shape, y0, frame, values, jnp.zeros((X.shape[0], 0), X.dtype),
            optx.RESULTS.successful, jnp.asarray(0),
        )

    def fn(y, args):
        frame, X, labels = args
        return _residuals(shape, y, frame, X, labels).reshape(-1)

    # The solve sees no tangents; the derivatives come from `_implicit` below
    sol = optx.least_squares(
        fn,
        optx.LevenbergMarquardt(rtol=RTOL, atol=ATOL),
        jax.lax.stop_gradient(y0),
        args=jax.lax.stop_gradient((frame, X, labels)),
        max_steps=max_steps,
        throw=False,
    )
    y = _implicit(lambda y: fn(y, (frame, X, labels)), jax.lax.stop_gradient(sol.value))
    r = _residuals(shape, y, frame, X, labels)
    return ShapeFit(
        shape, y, frame, shape.values(y, frame, X, labels), r, sol.result,
        sol.stats["num_steps"],
    )


def residual_normals(fit: ShapeFit, points, labels=None):
    """`∂r_i/∂x_i` per point, `(N, m, 3)` (unit normals for orthogonal distances)."""
    X = jnp.asarray(points)
    labels = _default_labels(X, labels)
    jac = jax.jacfwd(fit.shape.residual, argnums=2)
    return jax.vmap(jac, in_axes=(None, None, 0, 0))(fit.params, fit.frame, X, labels)


def parameter_jacobian(fit: ShapeFit, points, labels=None):
    """`∂r/∂y` of all residuals, `(N·m, p)` (for the rank check at the optimum)."""
    X = jnp.asarray(points)
    labels = _default_labels(X, labels)
    return jax.jacfwd(lambda y: _residuals(fit.shape, y, fit.frame, X, labels).reshape(-1))(
        fit.params
    )
