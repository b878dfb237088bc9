"""The rejection pass after the joint solve: which observations lie beyond a robust
threshold, re-solving without them, and the record of what was left out.

Blocks screened: the board corners, the board stripes, the gauge scan and, with a target
on the rotary table, the table target's corners and the laser line on it. Each block is
screened on its own robust scale (never below its stated σ): a table that wobbles fits
its target worse than the boards fit theirs, and that misfit is not an outlier."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..._export import exported_jit
from ._camera import _corner_errors
from ._model import CalibrationData
from ._plane import _laser_residuals_jit
from ._screen import outlier_masks
from ._solve import ONE_SHOT, least_squares
from ._table_block import _errors_jit as _table_errors_jit, table_stripe_residuals

# run once per rejection pass: compiled as the other one-shot programs
_table_stripe_jit = exported_jit(table_stripe_residuals, compiler_options=ONE_SHOT)

LEFT_OUT_BLOCKS = ("corners", "stripe", "gauge", "table_corners", "table_stripe")


def _weights(data: CalibrationData) -> tuple:
    """The weight arrays of the blocks of `data`, in `LEFT_OUT_BLOCKS` order (the table
    target's two only when the data hold one)."""
    w = (data.corner_w, data.stripe_w, data.gauge_w)
    return w if data.table is None else w + (data.table.w, data.table.stripe_w)


def _left_out_indices(masks) -> dict:
    """The rejection masks as `{block: (n, 2) int array}` (row, index) per block."""
    return {k: np.argwhere(np.asarray(m)) for k, m in zip(LEFT_OUT_BLOCKS, masks)}


def apply_left_out(data: CalibrationData, left_out: dict) -> CalibrationData:
    """`data` with the observations of `left_out` (see `Calibration.left_out`) at weight
    0; `ValueError` when an index does not fit the data."""
    weights = _weights(data)
    for k in LEFT_OUT_BLOCKS[len(weights) :]:
        if len(np.asarray(left_out.get(k, ()))):
            raise ValueError(f"left-out {k} given but the observations hold no table target")
    masks = []
    for k, w in zip(LEFT_OUT_BLOCKS, weights):
        m = np.zeros(w.shape, bool)
        idx = np.asarray(left_out.get(k, ()), dtype=int).reshape(-1, 2)
        if len(idx) and (np.any(idx < 0) or np.any(idx >= np.array(w.shape))):
            raise ValueError(f"left-out {k} index out of range for these observations")
        m[idx[:, 0], idx[:, 1]] = True
        masks.append(m)
    return _without(data, masks)


# At most this many rejection passes (re-solves) after the joint solve.
MAX_REJECTION_PASSES = 3


def _without(data: CalibrationData, masks) -> CalibrationData:
    """`data` with the observations under `masks` (True: left out) at weight 0 (masks in
    `LEFT_OUT_BLOCKS` order; the table target's two apply where the data hold one)."""
    masks = tuple(masks)
    new = tuple(jnp.where(jnp.asarray(m), 0.0, w) for m, w in zip(masks, _weights(data)))
    out = eqx.tree_at(lambda d: (d.corner_w, d.stripe_w, d.gauge_w), data, new[:3])
    if len(new) > 3:
        out = eqx.tree_at(lambda d: (d.table.w, d.table.stripe_w), out, new[3:5])
    return out


def _rejection_passes(
    fn, start, params, data, freeze, reject, max_steps, throw, hold=(), *, release=None
):
    """The rejection pass: leave out what lies beyond `reject` robust σ, solve again.

    A few gross outliers pull a least-squares solution so far that good neighbours (the
    other corners of their view) look like outliers too. So the masks are recomputed from
    every observation at each new solution, and the joint problem is re-solved (from the
    separate steps' `start`: from the contaminated optimum LM crept along the weak
    depth valley without converging) until the masks stop changing, at most
    `MAX_REJECTION_PASSES` times. Same shapes (weights 0): the compiled solver is reused.
    With `fn` None (no joint solve) the outliers are only counted. `hold`: paths held
    at run time; `release`: those of them reported free (`least_squares`'s; default:
    all of `hold`, as the profiled axis point).

    **Returns:** `(fit or None, masks applied, number of passes)`.
    """
    masks = _outliers(params, data, reject)
    fit, applied, passes = None, tuple(np.zeros_like(m) for m in masks), 0
    if fn is not None:
        while passes < MAX_REJECTION_PASSES:
            same = all(np.array_equal(a, m) for a, m in zip(applied, masks))
            if same:
                break
            fit = least_squares(
                fn,
                start,
                _without(data, masks),
                freeze=freeze,
                hold=hold,
                release=hold if release is None else release,
                max_steps=max_steps,
                throw=throw,
            )
            applied, passes = masks, passes + 1
            masks = _outliers(fit.params, data, reject)
    else:
        applied = masks
    return fit, applied, passes


# ----------------------------------------------------------------------------- quality


def _unrobust(r: np.ndarray, k: float | None) -> np.ndarray:
    """Invert `_blocks._robustify` (Huber's square-root trick) to the plain residual."""
    if k is None:
        return r
    a = np.abs(r)
    return np.where(a <= k, r, np.sign(r) * (a**2 + k * k) / (2 * k))


def _block_residuals(params, data):
    """Corner errors `(V, M, 2)` px and the plain stripe `(V, K)` and gauge `(F, L)`
    residuals (units of their σ; zeros where the block is absent)."""
    err = _corner_errors(params, data)
    stripe, gauge = np.zeros(data.stripe_w.shape), np.zeros(data.gauge_w.shape)
    if params.plane is not None:
        r_s, r_g = _laser_residuals_jit(params, data)
        stripe = _unrobust(np.asarray(r_s).reshape(data.stripe_w.shape), data.robust)
        if r_g is not None:
            gauge = _unrobust(np.asarray(r_g)[:-2].reshape(data.gauge_w.shape), data.robust)
    return err, stripe, gauge


def _table_residuals(params, data):
    """The table target's corner errors `(F, M, 2)` px and the plain residuals `(F, K)`
    of the laser line on it (units of their σ)."""
    err = np.asarray(_table_errors_jit(params, data))
    stripe = np.asarray(_table_stripe_jit(params, data)).reshape(data.table.stripe_w.shape)
    return err, _unrobust(stripe, data.robust)


def _outliers(params, data, threshold: float):
    """Rejection masks (True: out) in `LEFT_OUT_BLOCKS` order: board corners, board
    stripes, gauge and, where the data hold a table target (and the parameters its pose),
    its corners and its laser line, each block on its own robust scale."""
    masks = _board_outliers(params, data, threshold)
    if data.table is None or params.table_pose is None:
        return masks
    err, stripe = _table_residuals(params, data)
    t_corners, t_stripe, _ = outlier_masks(
        err,
        np.asarray(data.table.w),
        stripe,
        np.asarray(data.table.stripe_w),
        threshold=threshold,
        corner_sigma=float(data.sigma_corner_px),
        sigma=1.0,
    )
    return masks + (t_corners, t_stripe)


def outlier_counts(masks) -> dict:
    """`{"corner_outliers": n, ...}` of rejection masks (the table target's where given)."""
    names = ("corner", "stripe", "gauge", "table_corner", "table_stripe")
    return {f"{k}_outliers": int(np.asarray(m).sum()) for k, m in zip(names, masks)}


def _board_outliers(params, data, threshold: float):
    err, stripe, gauge = _block_residuals(params, data)
    return outlier_masks(
        err,
        np.asarray(data.corner_w),
        stripe,
        np.asarray(data.stripe_w),
        gauge,
        np.asarray(data.gauge_w),
        threshold=threshold,
        corner_sigma=float(data.sigma_corner_px),
        sigma=1.0,  # stripe and gauge residuals are in units of their σ
    )
