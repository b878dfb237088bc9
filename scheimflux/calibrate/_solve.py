"""Levenberg–Marquardt on a parameter pytree: freezing, scaling, status and timing.

The free leaves of the pytree are flattened into one vector, scaled so that every column
of the initial Jacobian has unit norm (a unitless state), and solved with optimistix's
Levenberg–Marquardt using autodiff Jacobians. Everything that changes between solves of
the same shape travels as array arguments, so a second calibration with the same number
of views and points reuses the compiled solver.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree


class NotConvergedError(RuntimeError):
    """Levenberg–Marquardt did not converge; `.fit` holds the last iterate."""

    def __init__(self, message: str, fit: Fit):
        super().__init__(message)
        self.fit = fit


@dataclasses.dataclass(frozen=True)
class Fit:
    """The outcome of one least-squares solve.

    **Fields:**
    - `params`: the solved pytree (frozen leaves untouched).
    - `converged`: whether optimistix reported success.
    - `message`: optimistix's result message ("" when converged).
    - `steps`: number of solver steps (dogleg pre-solve + Levenberg–Marquardt).
    - `residuals`: the final (weighted, unitless) residual vector.
    - `initial_cost`, `cost`: 0.5 · sum of squared residuals before and after.
    - `time_s`: wall time of the solve (including compilation on first use).
    - `free_mask`: the filter spec used (True on free leaves).
    - `scale`: the per-parameter column scale D of the initial Jacobian.
    """

    params: eqx.Module
    converged: bool
    message: str
    steps: int
    residuals: jax.Array
    initial_cost: float
    cost: float
    time_s: float
    free_mask: object
    scale: jax.Array

    @property
    def rms(self) -> float:
        r = np.asarray(self.residuals)
        return float(np.sqrt(np.mean(r**2))) if r.size else 0.0


def free_spec(params, freeze: Sequence[str] = ()):
    """Filter spec with True on inexact-array leaves, False under each frozen path.

    Paths are attribute names joined by dots, e.g. `"camera.dx"`, `"board_poses"`,
    `"stage.T_m_c.translation"`. Unknown paths raise `ValueError`.
    """
    spec = jax.tree.map(eqx.is_inexact_array, params)
    for path in freeze:
        node = params
        for name in path.split("."):
            if not hasattr(node, name):
                raise ValueError(f"cannot freeze {path!r}: no parameter {name!r} there")
            node = getattr(node, name)
        if node is None:
            continue

        def where(tree, _path=path):
            n = tree
            for name in _path.split("."):
                n = getattr(n, name)
            return n

        spec = eqx.tree_at(where, spec, replace=jax.tree.map(lambda _: False, node))
    return spec


def parameter_labels(params, spec) -> list[str]:
    """Names of the free scalars, in the order of the flattened state vector."""
    free, _ = eqx.partition(params, spec)
    labels = []
    for path, leaf in jax.tree_util.tree_flatten_with_path(free)[0]:
        name = "".join(
            f".{p.name}" if hasattr(p, "name") else f"[{getattr(p, 'idx', getattr(p, 'key', p))}]"
            for p in path
        ).lstrip(".")
        if np.ndim(leaf) == 0:
            labels.append(name)
        else:
            labels.extend(f"{name}{list(ix)}" for ix in np.ndindex(np.shape(leaf)))
    return labels


def _unscaled(x, args):
    fn, unravel, static, data = args
    return fn(eqx.combine(unravel(x), static), data)


def _scaled(y, args):
    fn, unravel, static, data, x0, scale = args
    return fn(eqx.combine(unravel(x0 + y * scale), static), data)


@eqx.filter_jit
def _jacobian(x, args):
    return jax.jacfwd(_unscaled)(x, args)


class _Unravel:
    """Rebuild the free pytree from the flat vector; equal (and hashing equal) for equal
    structures, so jitted solvers are reused across solves of the same shape."""

    def __init__(self, tree):
        leaves, self.treedef = jax.tree.flatten(tree)
        self.shapes = tuple(tuple(np.shape(x)) for x in leaves)
        self.dtypes = tuple(str(jnp.result_type(x)) for x in leaves)
        self._key = (self.treedef, self.shapes, self.dtypes)

    def __eq__(self, other):
        return isinstance(other, _Unravel) and self._key == other._key

    def __hash__(self):
        return hash(self._key)

    def __call__(self, flat):
        out, i = [], 0
        for shape in self.shapes:
            n = int(np.prod(shape, dtype=int))
            out.append(flat[i : i + n].reshape(shape))
            i += n
        return jax.tree.unflatten(self.treedef, out)


def split(params, spec):
    """`(x0, unravel, static)`: the free leaves as a flat vector and how to rebuild."""
    free, static = eqx.partition(params, spec)
    x0, _ = ravel_pytree(free)
    return x0, _Unravel(free), static


def jacobian(fn: Callable, params, data, spec):
    """Jacobian of `fn(params, data)` w.r.t. the free parameters (physical units)."""
    x0, unravel, static = split(params, spec)
    return _jacobian(x0, (fn, unravel, static, data))


def least_squares(
    fn: Callable,
    params,
    data,
    *,
    freeze: Sequence[str] = (),
    spec=None,
    max_steps: int = 200,
    rtol: float = 1e-8,
    atol: float = 1e-8,
    throw: bool = True,
) -> Fit:
    """Minimise `0.5 |fn(params, data)|²` over the free leaves of `params`.

    **Arguments:**
    - `fn`: a module-level (hashable) function `(params, data) -> residual vector`.
    - `params`: initial parameter pytree (`eqx.Module`).
    - `data`: pytree of arrays passed to `fn`.
    - `freeze`: dotted paths of leaves or sub-trees to hold fixed (or give `spec`).
    - `throw`: raise `NotConvergedError` when LM fails (the error carries the `Fit`).

    **Returns:** a `Fit`.
    """
    if spec is None:
        spec = free_spec(params, freeze)
    x0, unravel, static = split(params, spec)
    t0 = time.perf_counter()
    J = _jacobian(x0, (fn, unravel, static, data))
    if not bool(jnp.all(jnp.isfinite(J))):
        raise ValueError("the Jacobian is not finite at the initial parameters")
    col = jnp.linalg.norm(J, axis=0)
    scale = jnp.where(col > 0, 1.0 / jnp.where(col > 0, col, 1.0), 1.0)
    args = (fn, unravel, static, data, x0, scale)
    y0 = jnp.zeros_like(x0)
    r0 = _scaled(y0, args)
    if not bool(jnp.all(jnp.isfinite(r0))):
        bad = int(jnp.sum(~jnp.isfinite(r0)))
        raise ValueError(f"{bad} residuals are not finite at the initial parameters")
    # A trust-region dogleg pass first: on these problems (a narrow field of view leaves
    # the boards' common depth weakly determined) optimistix's LM damping creeps along
    # the weak valley for hundreds of steps, where dogleg's Gauss–Newton steps reach the
    # optimum in a handful. Levenberg–Marquardt then finishes and certifies convergence.
    pre = optx.least_squares(
        _scaled, optx.Dogleg(rtol=rtol, atol=atol), y0, args, max_steps=max_steps, throw=False
    )
    y_start = jnp.where(jnp.all(jnp.isfinite(pre.value)), pre.value, y0)
    if float(jnp.sum(_scaled(y_start, args) ** 2)) > float(jnp.sum(r0**2)):
        y_start = y0
    sol = optx.least_squares(
        _scaled,
        optx.LevenbergMarquardt(rtol=rtol, atol=atol),
        y_start,
        args,
        max_steps=max_steps,
        throw=False,
    )
    y = sol.value
    r = _scaled(y, args)
    r.block_until_ready()
    elapsed = time.perf_counter() - t0
    ok = sol.result == optx.RESULTS.successful and bool(jnp.all(jnp.isfinite(r)))
    message = "" if ok else _result_message(sol.result, r)
    fit = Fit(
        params=eqx.combine(unravel(x0 + y * scale), static),
        converged=bool(ok),
        message=message,
        steps=int(pre.stats["num_steps"]) + int(sol.stats["num_steps"]),
        residuals=r,
        initial_cost=float(0.5 * jnp.sum(r0**2)),
        cost=float(0.5 * jnp.sum(r**2)),
        time_s=elapsed,
        free_mask=spec,
        scale=scale,
    )
    if throw and not ok:
        raise NotConvergedError(f"Levenberg–Marquardt did not converge: {message}", fit)
    return fit


def _result_message(result, r) -> str:
    if not bool(jnp.all(jnp.isfinite(r))):
        return "residuals became non-finite"
    for name in ("max_steps_reached", "nonlinear_divergence", "nonlinear_max_steps_reached"):
        member = getattr(optx.RESULTS, name, None)
        if member is not None and result == member:
            return name.replace("_", " ")
    return "optimistix reported failure"


def refine(
    fn: Callable,
    params,
    data,
    *,
    freeze: Sequence[str] = (),
    spec=None,
    max_steps: int = 50,
    rtol: float = 1e-10,
    atol: float = 1e-10,
):
    """Pure, differentiable re-solve of `fn` from `params` (typically an optimum).

    Unlike `least_squares` this has no Python-side checks, so it can be traced: the
    derivative of the solution w.r.t. `data` (e.g. an observed corner) comes from
    optimistix's implicit adjoint, i.e. the implicit function theorem at the optimum.
    """
    if spec is None:
        spec = free_spec(params, freeze)
    x0, unravel, static = split(params, spec)
    sol = optx.least_squares(
        _unscaled,
        optx.LevenbergMarquardt(rtol=rtol, atol=atol),
        x0,
        (fn, unravel, static, data),
        max_steps=max_steps,
    )
    return eqx.combine(unravel(sol.value), static)
