"""The calibration parameters' covariance with one noise level per kind of observation.

`diagnostics(cal)` states `Σ = s² (JᵀJ)⁺` with a single variance factor `s²` pooled over
all residuals. That is right when every residual's assumed σ is off by the same factor.
It is not for this calibration: the board-stripe residual is the distance of a stripe
point from its board, which only the pixel noise *across* the stripe moves (noise along
the stripe slides the point along the line laser plane ∩ board), so with the assumed
σ_stripe those residuals scatter less than 1 — and, being the most numerous, they pull
the pooled s² below 1 and shrink the variance of what the corners determine (measured:
s² ≈ 0.7 with exactly the simulated noise; docs/metrology.md, "Monte Carlo").

Here each kind of residual `g` (corners, board stripes, gauge scan) gets its own variance
factor from its own residuals, with the redundancy it actually has (Förstner's variance
components, one step):

    s²_g = |r_g|² / (n_g − tr H_gg),    H = J (JᵀJ)⁺ Jᵀ,

and the covariance of the weighted least-squares estimate with those noise levels is the
sandwich

    Σ = (JᵀJ)⁺ (Σ_g s²_g J_gᵀ J_g) (JᵀJ)⁺,

which reduces to `s² (JᵀJ)⁺` when all `s²_g` are equal. The pseudo-inverse uses the same
column normalisation and cut-off as `diagnostics` (the gauge freedoms the solve fixes by
holding parameters are not in `J`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["GroupCovariance", "group_covariance", "sandwich_covariance"]

# Residual blocks of the joint problems, in the order `joint_residuals` concatenates them.
GROUPS = ("corners", "stripes", "gauge", "table target", "table stripes")
# A group with fewer redundant observations than this gets no variance factor of its own
# (it keeps the pooled one).
MIN_REDUNDANCY = 10.0


@dataclasses.dataclass(frozen=True)
class GroupCovariance:
    """Covariance of the joint calibration's free parameters, one σ² factor per group.

    **Fields:**
    - `covariance` `(p, p)`: the sandwich covariance (labels of `diagnostics(cal,
      block="joint")`).
    - `variance_factors`: `{group: s²_g}`; `redundancy`: `{group: n_g − tr H_gg}`;
      `n_residuals`: `{group: n_g}`.
    - `pooled`: the single s² of `diagnostics`.
    """

    covariance: np.ndarray
    variance_factors: dict
    redundancy: dict
    n_residuals: dict
    pooled: float


def _group_sizes(cal, params) -> list[int]:
    """Residuals per group, from the blocks' shapes (`jax.eval_shape`: traced, not run)."""
    import jax

    from ..calibrate._model import corner_residuals, gauge_residuals, stripe_residuals

    def size(fn):
        return int(np.prod(jax.eval_shape(fn, params, cal.data).shape))

    sizes = [size(corner_residuals), size(stripe_residuals)]
    if params.stage is not None:
        sizes.append(size(gauge_residuals))
    if getattr(params, "table_pose", None) is not None:
        from ..calibrate._stage_table import table_stripe_residuals, table_target_residuals

        n_s = size(table_stripe_residuals)
        sizes += [size(table_target_residuals) - n_s, n_s]
    return sizes


def group_covariance(cal, *, rtol: float | None = None) -> GroupCovariance:
    """The joint calibration's parameter covariance with a variance factor per residual
    group (corners, board stripes, gauge scan): see the module text.

    **Arguments:**
    - `cal`: a `Calibration` with a laser plane (its data are kept in it).
    - `rtol`: singular-value cut-off of the pseudo-inverse (default: `diagnostics`').

    **Returns:** a [`GroupCovariance`][]. **Raises:** `ValueError` (one line) for a
    calibration without laser plane or without redundancy.
    """
    from ..calibrate import residual_function
    from ..calibrate._covariance import NULL_RTOL
    from ..calibrate._solve import jacobian

    rtol = NULL_RTOL if rtol is None else rtol
    if cal.params.plane is None:
        raise ValueError("the calibration has no laser plane: no joint covariance")
    fn, params, spec = residual_function(cal, "joint")
    J = np.asarray(jacobian(fn, params, cal.data, spec), dtype=np.float64)
    r = np.asarray(fn(params, cal.data), dtype=np.float64)
    sizes = _group_sizes(cal, params)
    if sum(sizes) != len(r):
        raise ValueError("the residual groups do not add up to the joint residual vector")
    cov, factors, redund, counts, pooled = sandwich_covariance(J, r, sizes, rtol=rtol)
    names = GROUPS[: len(sizes)]
    return GroupCovariance(
        cov, dict(zip(names, factors)), dict(zip(names, redund)), dict(zip(names, counts)),
        pooled,
    )


def sandwich_covariance(J, r, sizes, *, rtol: float = 1e-8):
    """`(Σ, s²_g list, redundancies, counts, pooled s²)` of a weighted least-squares
    optimum with Jacobian `J` `(n, p)` and residuals `r` `(n,)` whose rows come in
    consecutive groups of `sizes`, each group with its own variance factor (module text).
    Rows that are identically zero (padding) are not observations.

    **Raises:** `ValueError` when there are no more observations than parameters.
    """
    J = np.asarray(J, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    used = np.any(J != 0, axis=1) | (r != 0)
    col = np.linalg.norm(J, axis=0)
    d = np.where(col > 0, 1.0 / np.where(col > 0, col, 1.0), 1.0)
    U, s, Vt = np.linalg.svd(J * d, full_matrices=False)
    keep = s > rtol * s[0]
    U, s, Vt = U[:, keep], s[keep], Vt[keep]
    p, n = int(keep.sum()), int(used.sum())
    if n <= p:
        raise ValueError("the calibration has no redundancy (residuals <= parameters)")
    pooled = float(np.sum(r[used] ** 2) / (n - p))
    h = np.sum(U * U, axis=1)  # diagonal of the hat matrix: each row's share of p
    bounds = np.cumsum([0] + list(sizes))
    US = U * s  # J d = U S Vᵀ, so group g's rows of J d are (U S)_g Vᵀ
    B = np.zeros((len(s), len(s)))
    factors, redund, counts = [], [], []
    for a, b in zip(bounds[:-1], bounds[1:]):
        m = used[a:b]
        red = float(m.sum() - np.sum(h[a:b][m]))
        s2 = float(np.sum(r[a:b][m] ** 2) / red) if red >= MIN_REDUNDANCY else pooled
        factors.append(s2)
        redund.append(red)
        counts.append(int(m.sum()))
        A = US[a:b][m]
        B += s2 * (A.T @ A)
    # (JᵀJ)⁺ = d V S⁻² Vᵀ d, so the sandwich is d V S⁻² B S⁻² Vᵀ d
    inv2 = 1.0 / s**2
    cov = d[:, None] * (Vt.T @ ((inv2[:, None] * B) * inv2[None, :]) @ Vt) * d[None, :]
    return cov, factors, redund, counts, pooled
