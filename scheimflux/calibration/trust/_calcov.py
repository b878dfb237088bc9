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

Within a group the residuals' noise is not equal either: a board-stripe pixel's noise
moves its residual by `|∂r_i/∂p_i|`, which depends on the angle between the laser plane
and that view's board. By default (`weighting="pixels"`) each residual's variance is
`σ²_g a_i`, `a_i = |∂r_i/∂p_i|²` from its own pixel ([`pixel_noise_gains`][]): `s²_g`
is then the group's pixel noise σ²_g in px² (estimated from the residuals standardised
by `a_i`), and the meat is `Σ_i σ²_g a_i J_iᵀJ_i`. On the Monte Carlo scene of
docs/metrology.md the estimated σ_g are the simulated 0.030 / 0.050 / 0.050 px (corners /
board stripes / gauge), and the measured values' calibration terms equal the equal-
within-group ones to 1e-4 relative there (the steps and the radius do not depend on the
views whose stripe residuals are noisier).

Stripe centres are not independent along a line: one centre per scan line, each from a
filter several pixels wide (and JPEG's 8 × 8 blocks), so neighbouring centres share their
errors. The sandwich's meat `Σ_i σ²_g a_i J_iᵀJ_i` then understates the variance of what
the centres determine by the integrated autocorrelation `τ = 1 + 2 Σ_k ρ_k`. For the
stripe and gauge groups (one residual per centre, in order along each line) the lag
correlations `ρ_k` of the standardised residuals are estimated
([`residual_lag_correlation`][]: lags while `ρ_k` exceeds `max(0.05, 3/√n)`) and the
meat becomes `σ²_g Σ_i Σ_j ρ_|i−j| √(a_i a_j) J_iᵀJ_j` (a banded residual covariance).
Measured on rendered colour-JPEG captures (tessar ×1, `detect --scan`, 36 frames, 56667
gauge centres): gauge residuals ρ₁ = 0.88, ρ₂ = 0.63; the error of a second ring's radius
from exact pixels was +0.086 µm against U = 0.057 µm (k = 2) with independent centres.
Simulated observations (independent noise) give `ρ_k` under the threshold: unchanged.
Where a group correlates, the calibration's own stated covariance (`calibrate.
fit_diagnostics`: the file, the summary, the report) is raised to this one wherever it
is larger ([`raise_covariance`][]).
"""

from __future__ import annotations

import dataclasses
import weakref

import numpy as np

from ..core._model import CalibrationData
from ..core._result import Calibration
from ..core._solve import linearised
from ._covariance import NULL_RTOL, residual_function

__all__ = [
    "GroupCovariance",
    "correlated_groups",
    "group_covariance",
    "joint_linearisation",
    "pixel_noise_gains",
    "raise_covariance",
    "residual_lag_correlation",
    "sandwich_covariance",
]

# Residual blocks of the joint problems, in the order `joint_residuals` concatenates them.
GROUPS = ("corners", "stripes", "gauge", "table target", "table stripes")
# A group with fewer redundant observations than this gets no variance factor of its own
# (it keeps the pooled one).
MIN_REDUNDANCY = 10.0
# Groups whose residuals are one per stripe centre, in order along each line.
ORDERED_GROUPS = ("stripes", "gauge", "table stripes")
MAX_LAG = 32


@dataclasses.dataclass(frozen=True)
class GroupCovariance:
    """Covariance of the joint calibration's free parameters, one σ² factor per group.

    **Fields:**
    - `covariance` `(p, p)`: the sandwich covariance (labels of `diagnostics(cal,
      block="joint")`).
    - `variance_factors`: `{group: s²_g}`; `redundancy`: `{group: n_g − tr H_gg}`;
      `n_residuals`: `{group: n_g}`.
    - `pooled`: the single s² of `diagnostics`.
    - `weighting`: `"pixels"` (`variance_factors` are pixel noise variances, px²) or
      `"groups"` (relative to the σ the calibration assumed).
    - `correlation_time`: `{group: τ_g}`, `τ = 1 + 2 Σ_k ρ_k` of the groups whose
      neighbouring residuals correlate (absent: taken as independent).
    """

    covariance: np.ndarray
    variance_factors: dict
    redundancy: dict
    n_residuals: dict
    pooled: float
    weighting: str = "groups"
    correlation_time: dict = dataclasses.field(default_factory=dict)


def _group_sizes(cal, params) -> list[int]:
    """Residuals per group, from the blocks' shapes (`jax.eval_shape`: traced, not run)."""
    import jax

    from ..core._model import corner_residuals, gauge_residuals, stripe_residuals

    def size(fn):
        return int(np.prod(jax.eval_shape(fn, params, cal.data).shape))

    sizes = [size(corner_residuals), size(stripe_residuals)]
    if params.stage is not None:
        sizes.append(size(gauge_residuals))
    if getattr(params, "table_pose", None) is not None:
        from ..core._table_block import table_stripe_residuals, table_target_residuals

        n_s = size(table_stripe_residuals)
        sizes += [size(table_target_residuals) - n_s, n_s]
    return sizes


def group_covariance(
    cal, *, rtol: float | None = None, weighting: str = "pixels"
) -> GroupCovariance:
    """The joint calibration's parameter covariance with a variance factor per residual
    group (corners, board stripes, gauge scan): see the module text.

    **Arguments:**
    - `cal`: a `Calibration` with a laser plane (its data are kept in it).
    - `rtol`: singular-value cut-off of the pseudo-inverse (default: `diagnostics`').
    - `weighting`: `"pixels"` (default): each residual's noise is its own pixel's noise
      through the residual, `Var r_i = σ²_g |∂r_i/∂p_i|²` ([`pixel_noise_gains`][]), and
      `variance_factors` are the groups' pixel noise variances σ²_g (px²); `"groups"`:
      equal within each group (the factors are then relative to the assumed σ).

    **Returns:** a [`GroupCovariance`][]. **Raises:** `ValueError` (one line) for a
    calibration without laser plane or without redundancy.
    """

    rtol = NULL_RTOL if rtol is None else rtol
    if cal.params.plane is None:
        raise ValueError("the calibration has no laser plane: no joint covariance")
    if weighting not in ("pixels", "groups"):
        raise ValueError(f"weighting must be 'pixels' or 'groups', got {weighting!r}")
    _, params, _ = residual_function(cal, "joint")
    r, J, gains = joint_linearisation(cal)
    if weighting != "pixels":
        gains = None
    sizes = _group_sizes(cal, params)
    if sum(sizes) != len(r):
        raise ValueError("the residual groups do not add up to the joint residual vector")
    names = GROUPS[: len(sizes)]
    bounds = np.cumsum([0] + list(sizes))
    a = np.ones(len(r)) if gains is None else gains
    rho = [
        residual_lag_correlation(r[lo:hi], a[lo:hi], J[lo:hi]) if name in ORDERED_GROUPS
        else np.zeros(0)
        for name, lo, hi in zip(names, bounds[:-1], bounds[1:])
    ]  # fmt: skip
    cov, factors, redund, counts, pooled = sandwich_covariance(
        J, r, sizes, rtol=rtol, gains=gains, correlations=rho
    )
    tau = {n: 1.0 + 2.0 * float(np.sum(c)) for n, c in zip(names, rho) if len(c)}
    return GroupCovariance(
        cov, dict(zip(names, factors)), dict(zip(names, redund)), dict(zip(names, counts)),
        pooled, weighting, tau,
    )


def residual_lag_correlation(r, gains=None, J=None, *, max_lag: int = MAX_LAG) -> np.ndarray:
    """Lag correlations `ρ_1, ρ_2, …` of residuals that come in order along lines.

    The residuals are standardised by their gains (`r_i / √a_i`); rows that are not
    observations (zero residual and zero Jacobian row, or zero gain: padding) break the
    lines, so pairs across them do not count. Lags are kept from 1 while `ρ_k` exceeds
    `max(0.05, 3/√n)` (n observations; for independent noise `ρ_k` scatters by `1/√n`),
    at most `max_lag`.

    **Returns:** `(K,)`, empty when neighbouring residuals do not correlate.
    """
    r = np.asarray(r, dtype=np.float64)
    a = np.ones(len(r)) if gains is None else np.asarray(gains, dtype=np.float64)
    used = (r != 0) if J is None else (np.any(np.asarray(J) != 0, axis=1) | (r != 0))
    used &= a > 0
    z = np.where(used, r / np.sqrt(np.where(used, a, 1.0)), 0.0)
    return lag_correlations(z, lambda k: used[:-k] & used[k:], int(used.sum()), max_lag)


def lag_correlations(z, pairs, n: int, max_lag: int = MAX_LAG) -> np.ndarray:
    """The lag correlations `ρ_1, ρ_2, …` of standardised residuals `z` `(N,)` or `(N, m)`
    (0 where not an observation) over the pairs `(i, i + k)` that `pairs(k)` marks (a
    boolean `(N − k,)`; the m columns pooled), kept from lag 1 while `ρ_k` exceeds
    `max(0.05, 3/√n)` for `n` observations (for independent noise `ρ_k` scatters by
    `1/√n`), at most `max_lag`. Empty for fewer than 10 observations or zero variance.
    The one estimator of [`residual_lag_correlation`][] (the calibration's residuals) and
    `metrology._gum.lag_correlation` (a fit's residuals along their lines)."""
    z = np.asarray(z, dtype=np.float64).reshape(len(z), -1)
    m = z.shape[1]
    if n < 10:
        return np.zeros(0)
    var = float(np.sum(z * z)) / (n * m)
    if not var > 0:
        return np.zeros(0)
    limit = max(0.05, 3.0 / np.sqrt(n))
    out = []
    for k in range(1, min(max_lag, n - 1) + 1):
        pair = pairs(k)
        if not pair.any():
            break
        rho = float(np.sum(np.sum(z[:-k] * z[k:], axis=1)[pair])) / (pair.sum() * m) / var
        if not rho > limit:
            break
        out.append(rho)
    return np.asarray(out)


def pixel_noise_gains(fn, params, data) -> np.ndarray:
    """`a_i = |∂r_i/∂p_i|²` `(n,)`: how much each residual moves per pixel of noise on the
    one observed pixel `p_i` it depends on (px⁻² × the residual's unit²).

    Every residual of the joint problems depends on the pixel of one observation only (a
    corner's u or v, one stripe or gauge pixel), so `∂r/∂u` of all pixels at once (one
    JVP with every u tangent set to 1) is each residual's own `∂r_i/∂u_i`, and likewise
    for v: two forward passes, no `n × 2n` Jacobian. ([`group_covariance`][] gets them
    in the same program as the residuals' Jacobian, `calibrate._solve.linearised`.)
    """
    import equinox as eqx

    from ..core._solve import own_pixel_gains

    return np.asarray(eqx.filter_jit(own_pixel_gains)(fn, params, data), dtype=np.float64)


def sandwich_covariance(J, r, sizes, *, rtol: float = 1e-8, gains=None, correlations=None):
    """`(Σ, s²_g list, redundancies, counts, pooled s²)` of a weighted least-squares
    optimum with Jacobian `J` `(n, p)` and residuals `r` `(n,)` whose rows come in
    consecutive groups of `sizes`, each group with its own variance factor (module text).
    Rows that are identically zero (padding) are not observations.

    `gains` `(n,)` (optional): each residual's noise variance relative to the others of
    its group, `Var r_i = s²_g a_i` (e.g. [`pixel_noise_gains`][]: then `s²_g` is the
    group's pixel noise variance, px²). Default: equal within each group. `s²_g` is
    estimated from the standardised residuals, `Σ_g r_i²/a_i / (Σ_g (1 − 2 h_ii) +
    Σ_{i∈g, j} h_ij² a_j/a_i)` (one step, the other groups' factors taken equal; with
    `a ≡ 1` the denominator is `n_g − tr H_gg`), and the meat is `Σ_i s²_g a_i J_iᵀJ_i`.
    Rows with `a_i = 0` carry no noise and count in neither.

    `correlations` (optional): per group the lag correlations `ρ_1 … ρ_K` of its
    standardised noise along its rows ([`residual_lag_correlation`][]; empty: independent);
    the meat of that group is then `s²_g Σ_{|i−j|≤K} ρ_|i−j| √(a_i a_j) J_iᵀJ_j`.

    **Raises:** `ValueError` when there are no more observations than parameters.
    """
    J = np.asarray(J, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    used = np.any(J != 0, axis=1) | (r != 0)
    a = np.ones(len(r)) if gains is None else np.asarray(gains, dtype=np.float64)
    if a.shape != r.shape or not np.all(np.isfinite(a)) or np.any(a < 0):
        raise ValueError("gains must be finite, >= 0 and one per residual")
    used &= a > 0
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
    inv_a = np.where(used, 1.0 / np.where(used, a, 1.0), 0.0)
    a_used = np.where(used, a, 0.0)
    # Σ_{i∈g} Σ_j h_ij² a_j / a_i = tr(U_gᵀ diag(1/a) U_g · Uᵀ diag(a) U)
    UaU = (U * a_used[:, None]).T @ U
    bounds = np.cumsum([0] + list(sizes))
    US = U * s  # J d = U S Vᵀ, so group g's rows of J d are (U S)_g Vᵀ
    B = np.zeros((len(s), len(s)))
    factors, redund, counts = [], [], []
    if correlations is None:
        correlations = [()] * len(sizes)
    if len(correlations) != len(sizes):
        raise ValueError("correlations must give one sequence per group")
    for (lo, hi), rho in zip(zip(bounds[:-1], bounds[1:]), correlations):
        m = used[lo:hi]
        Ug = U[lo:hi] * np.sqrt(inv_a[lo:hi])[:, None]
        red = float(np.sum(1.0 - 2.0 * h[lo:hi][m]) + np.sum((Ug.T @ Ug) * UaU))
        q = float(np.sum(r[lo:hi][m] ** 2 * inv_a[lo:hi][m]))
        s2 = q / red if red >= MIN_REDUNDANCY else pooled
        factors.append(s2)
        redund.append(red)
        counts.append(int(m.sum()))
        A = US[lo:hi] * np.where(m, np.sqrt(a_used[lo:hi]), 0.0)[:, None]
        meat = A.T @ A
        for k, rho_k in enumerate(np.asarray(rho, dtype=np.float64), start=1):
            if k >= len(A):
                break
            cross = A[:-k].T @ A[k:]
            meat += rho_k * (cross + cross.T)
        B += s2 * meat
    # (JᵀJ)⁺ = d V S⁻² Vᵀ d, so the sandwich is d V S⁻² B S⁻² Vᵀ d
    inv2 = 1.0 / s**2
    cov = d[:, None] * (Vt.T @ ((inv2[:, None] * B) * inv2[None, :]) @ Vt) * d[None, :]
    return cov, factors, redund, counts, pooled


# ----------------------------------------------------------------------------- correlated centres


def raise_covariance(T: np.ndarray, B: np.ndarray) -> np.ndarray:
    """`A = T Tᵀ` raised to `B` wherever `B` is larger: `T U max(m, 1) Uᵀ Tᵀ`, with
    `U m Uᵀ` the eigen-decomposition of `T⁺ B T⁺ᵀ` (the generalised eigenproblem of `B`
    against `A`, on the range of `A`).

    In each of the common principal directions the larger variance of the two is kept, so
    the variance of every linear function of the parameters is at least its variance
    under `A` and under `B` (restricted to the range of `A`: what `A` leaves out, the
    non-identifiable directions, stays out). The result does not depend on the
    parameters' units. Where `B ≤ A` it is `A` (to rounding), where `B ≥ A` it is `B`.

    **Arguments:** `T` `(p, k)` of full column rank; `B` `(p, p)` symmetric.
    """
    T = np.asarray(T, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    # in units of A's σ (rows) and with unit columns: the parameters' units (px, rad, mm,
    # a gauge freedom held to 1e-7) span far more than the float64 pseudo-inverse keeps
    s = np.linalg.norm(T, axis=1)
    s = np.where(s > 0, s, 1.0)
    c = np.linalg.norm(T, axis=0)
    c = np.where(c > 0, c, 1.0)
    Ti = np.linalg.pinv(T / s[:, None] / c[None, :]) / c[:, None]  # T⁺ in units of σ
    M = Ti @ (B / np.outer(s, s)) @ Ti.T
    m, U = np.linalg.eigh(0.5 * (M + M.T))
    TU = T @ U
    return (TU * np.maximum(m, 1.0)) @ TU.T


# The joint residuals linearised at a joint solve's optimum, per solve and data:
# `{id(fit): (weakref to fit, data, (r, J, gains))}`. A calibration read back from its
# file keeps no normal matrix: its `fit_diagnostics` (every call), the correlated-centres
# covariance and `measure`'s budget each needed this Jacobian (49026 x 68: ~1-3 s).
_LINEARISED: dict[int, tuple] = {}


def joint_linearisation(cal: Calibration):
    """`(r, J, gains)` of the joint residuals at the calibration's joint optimum
    (`_solve.linearised` with the pixel gains), computed once per joint solve and data."""
    fn, params, spec = residual_function(cal, "joint")
    fit = cal.fits.get("joint")
    if fit is None:
        return linearised(fn, params, cal.data, spec, pixel_gains=True)
    hit = _LINEARISED.get(id(fit))
    if hit is not None and hit[0]() is fit and hit[1] is cal.data:
        return hit[2]
    out = linearised(fn, params, cal.data, spec, pixel_gains=True)
    for a in out:
        a.setflags(write=False)  # shared by every caller
    key = id(fit)
    _LINEARISED[key] = (weakref.ref(fit, lambda _, k=key: _LINEARISED.pop(k, None)), cal.data, out)
    return out


# Correlation of the stripe centres along their lines, per joint solve (a calibration
# with its quality gates added is a new object sharing the solve and its data):
# `{id(fit): (weakref to fit, data, GroupCovariance or None)}`, so that the calibrate
# command's gates, file and summary (each asks for it) build the Jacobian once.
_CORRELATED: dict[int, tuple] = {}


def correlated_groups(cal: Calibration):
    """The joint solve's [`metrology.GroupCovariance`][] when the stripe centres along a
    laser line share their errors, else None.

    Screened first on the final residuals alone, as [`correlated_centres_warning`][]
    does: the lag correlations ([`metrology.residual_lag_correlation`][], lags kept while
    `ρ_k > max(0.05, 3/√n)`) of each group whose residuals come in order along the lines
    (board stripes, gauge scan, table-target stripes). Independent noise (simulated
    observations) keeps none there and costs no Jacobian. Where one does, the group
    covariance (full Jacobian, each group's own pixel noise, the lags re-estimated from
    the residuals standardised by their pixel gains) decides; None again if it finds no
    lag. Calibrations without a joint solve or a laser plane: None.
    """
    fit = (getattr(cal, "fits", None) or {}).get("joint")
    if (
        fit is None
        or not isinstance(getattr(cal, "data", None), CalibrationData)
        or getattr(cal.params, "plane", None) is None
    ):
        return None
    hit = _CORRELATED.get(id(fit))
    if hit is not None and hit[0]() is fit and hit[1] is cal.data:
        return hit[2]
    out = None
    r = np.asarray(fit.residuals, dtype=np.float64).reshape(-1)
    bounds = np.cumsum([0] + list(_group_sizes(cal, fit.params)))
    if bounds[-1] == len(r) and any(
        len(residual_lag_correlation(r[lo:hi]))
        for name, lo, hi in zip(GROUPS, bounds[:-1], bounds[1:])
        if name in ORDERED_GROUPS
    ):
        gc = group_covariance(cal)
        out = gc if gc.correlation_time else None
    key = id(fit)
    _CORRELATED[key] = (weakref.ref(fit, lambda _, k=key: _CORRELATED.pop(k, None)), cal.data, out)
    return out
