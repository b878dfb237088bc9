"""Measured values with their GUM uncertainty: calibration, stripe noise and fit residual.

A measured value `v` (a radius, a step, a flatness) is a function of the fitted shape,
which is a function of the reconstructed points, which are functions of the calibration
parameters `θ` and the stripe pixels `p`:

    v = V(fit(X(θ, p_1), …, X(θ, p_N)))

Linear propagation (GUM, first order) with Jacobians by autodiff — through the
reconstruction and, by the implicit function theorem, through the fit:

- **calibration**: `C_cal = G_θ Σ_θ G_θᵀ`, `G_θ = ∂v/∂θ` — one Jacobian of the whole
  chain, so the covariance between all points (what moves every point alike, like the
  camera datum, cancels) is exact, without forming the `3N × 3N` point covariance.
  `Σ_θ` is the marginal covariance of the free camera, laser-plane (and stage)
  parameters of the joint calibration (board poses marginalised).
- **stripe noise**: `C_px = σ_px² G_p G_pᵀ`, `G_p = ∂v/∂p`, each pixel coordinate
  independent with σ_px.
- **fit residual**: the scatter of the orthogonal residuals beyond what the stripe noise
  explains (form deviation, unmodelled effects):
  `C_fit = max(0, s² − s²_px) Σ_i (N_i g_i)(N_i g_i)ᵀ` with `s² = |r|² / (M − p)`,
  `s²_px` the residual variance the stripe noise predicts, `N_i = ∂r_i/∂x_i` and
  `g_i = ∂v/∂x_i`. For a fitted parameter this is the classical `s² ∇v (JᵀJ)⁻¹ ∇vᵀ`.
  Without σ_px (points without pixels, or σ_px not given) the stripe noise is in the
  residuals, and this term carries it.

Both sums count the points as independent. Points reconstructed from extracted stripe
centres are not: one centre per scan line, each from a filter several pixels wide, so
neighbours along a line share their errors (rendered captures: lag-1 correlation
0.67–0.88, integrated autocorrelation τ = 3.7–7.5), and a value that averages many
neighbours varies τ times more than the independent sums say. So the residuals' lag
correlations `ρ_k` are estimated along the lines the points come in (consecutive
points, broken where the frame or face label changes or where a step is more than 4 ×
the median step: a gap, the next frame), lags kept while `ρ_k > max(0.05, 3/√n)` as in
the calibration (`_calcov.residual_lag_correlation`), and both sums become banded,
`Σ_i Σ_{j on i's line, |i−j| ≤ K} ρ_|i−j| P_i P_jᵀ`. Independent noise keeps no lag:
the sums are then the independent ones exactly. The stripe term takes the residuals'
correlation as the pixels' (where a smooth form error dominates the residuals this
overstates it: the conservative side).

`U = k u` with k = 2 (≈ 95 % for a normal distribution with many degrees of freedom).
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..calibration.trust._calcov import MAX_LAG, lag_correlations
from ._lsq import fit_shape, parameter_jacobian, residual_normals
from ._shapes import AbstractShape

__all__ = ["Measurement", "measure_points"]

COVERAGE_FACTOR = 2.0
# Relative eigenvalue of the fit's scaled JᵀJ below which the geometry is degenerate (the
# implicit derivative and the fit's covariance do not exist).
FIT_RANK_RTOL = 1e-12
SOURCES = ("calibration", "frozen_parameters", "stripe_noise", "fit_residual")


@dataclasses.dataclass(frozen=True)
class Measurement:
    """Measured values with uncertainty and budget.

    **Fields:**
    - `kind`: the shape (`"cylinder"`, `"plane"`, …); `names`: the values' names.
    - `values` `(K,)` (mm); `covariance` `(K, K)` (mm², all sources; off-diagonal terms
      are what ratios and differences of the values need).
    - `budget`: per source in `SOURCES`, the standard uncertainty of each value `(K,)`,
      or None where the source was not evaluated (see `notes`).
    - `coverage_factor`: k (2).
    - `residuals` `(N, m)`: the fit's orthogonal residuals (mm); `residual_stats`: RMS,
      peak-to-valley, max |r|, the variance factor s² and the stripe-noise prediction.
    - `n_points`, `n_params`; `geometry`: the fitted shape as numbers (axis, normal, …).
    - `sensitivity`: `{"labels": [...], "d_values": (K, q)}`: `∂v/∂θ` for the calibration
      parameters (None without a calibration).
    - `notes`: what the budget includes and what it does not.
    """

    kind: str
    names: tuple
    values: np.ndarray
    covariance: np.ndarray
    budget: dict
    coverage_factor: float
    residuals: np.ndarray
    residual_stats: dict
    n_points: int
    n_params: int
    geometry: dict
    sensitivity: dict | None
    notes: tuple

    @property
    def std(self) -> np.ndarray:
        """Combined standard uncertainty u of each value (mm)."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    @property
    def U(self) -> np.ndarray:
        """Expanded uncertainty `k u` (mm)."""
        return self.coverage_factor * self.std

    def _within(self) -> bool:
        """Whether the fit's residual variance is no more than the stated stripe noise
        explains (the fit-residual term is then 0: nothing left to attribute)."""
        st = self.residual_stats
        s2, s2_px = st.get("variance_factor"), st.get("stripe_noise_variance", 0.0)
        return bool(s2_px and s2 is not None and s2 <= s2_px)

    def summary(self) -> str:
        """A few lines: each value ± U (k = 2) with its budget, and the residuals.

        The headline names the sources the U leaves out (a U of the fit residual alone
        is not the measurement's), and values under 0.001 µm keep two significant digits
        rather than printing as 0.000."""
        lines = [f"{self.kind} fit: {self.n_points} points, {self.n_params} parameters"]
        left = [src.replace("_", " ") for src in SOURCES if self.budget.get(src) is None]
        which = f", without {', '.join(left)}" if left else ""
        for k, name in enumerate(self.names):
            lines.append(
                f"  {name:<12} {self.values[k]:.6f} mm ± {_um(self.U[k])} µm "
                f"(U, k = {self.coverage_factor:g}{which})"
            )
            for src in SOURCES:
                b = self.budget.get(src)
                text = "not included" if b is None else f"u = {_um(b[k])} µm"
                if src == "fit_residual" and b is not None and b[k] == 0 and self._within():
                    text = "u = 0 µm (the residuals are within the stated stripe noise)"
                lines.append(f"    {src.replace('_', ' '):<17} {text}")
        st = self.residual_stats
        if self.n_params:
            lines.append(
                f"  residuals: RMS {st['rms'] * 1e3:.3f} µm, peak-to-valley "
                f"{st['peak_to_valley'] * 1e3:.3f} µm, max |r| {st['max_abs'] * 1e3:.3f} µm"
            )
        lines.extend(f"  note: {n}" for n in self.notes)
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """JSON-ready dict (`"format": "scheimflux.measurement/1"`, lengths in mm)."""

        def num(v):
            v = float(v)
            return v if math.isfinite(v) else None

        out = {
            "format": "scheimflux.measurement/1",
            "kind": self.kind,
            "unit": "mm",
            "coverage_factor": self.coverage_factor,
            "values": {
                name: {
                    "value": num(self.values[k]),
                    "standard_uncertainty": num(self.std[k]),
                    "U": num(self.U[k]),
                    "budget": {
                        src: None if self.budget.get(src) is None else num(self.budget[src][k])
                        for src in SOURCES
                    },
                }
                for k, name in enumerate(self.names)
            },
            "covariance": [[num(v) for v in row] for row in self.covariance],
            "residuals": {key: num(v) for key, v in self.residual_stats.items()},
            "n_points": self.n_points,
            "n_params": self.n_params,
            "geometry": {k: [num(x) for x in np.ravel(v)] for k, v in self.geometry.items()},
            "notes": list(self.notes),
        }
        if self.sensitivity is not None:
            out["sensitivity"] = {
                "labels": list(self.sensitivity["labels"]),
                "d_values": [[num(v) for v in row] for row in self.sensitivity["d_values"]],
            }
        return out


def _um(mm: float) -> str:
    """A length in mm as µm: 3 decimals, or 2 significant digits below 0.001 µm."""
    um = float(mm) * 1e3
    return f"{um:.3f}" if abs(um) >= 1e-3 or um == 0 else f"{um:.2g}"


@eqx.filter_jit
def _point_terms(shape, X, labels):
    """The fit, `∂v/∂X` `(K, N, 3)`, the residual normals and `∂r/∂y`."""
    fit = fit_shape(shape, X, labels)
    gX = jax.jacrev(lambda X: fit_shape(shape, X, labels).values)(X)
    if shape.n_params() == 0:  # static: no fit, no residuals
        return fit, gX, jnp.zeros((X.shape[0], 0, 3), X.dtype), jnp.zeros((0, 0), X.dtype)
    normals = residual_normals(fit, X, labels)
    J = parameter_jacobian(fit, X, labels)
    return fit, gX, normals, J


def _check_labels(shape, n, labels):
    if labels is None:
        return np.zeros(n, np.int32)
    lab = np.asarray(labels)
    if lab.shape != (n,):
        raise ValueError(f"labels must have shape ({n},), got {lab.shape}")
    if not np.issubdtype(lab.dtype, np.integer) and lab.dtype != bool:
        raise ValueError(f"labels must be integers, got dtype {lab.dtype}")
    return lab.astype(np.int32)


def _checked_fit(shape, X, labels):
    """Run the fit terms eagerly and refuse a fit that did not converge or is singular."""
    fit, gX, normals, J = _point_terms(shape, jnp.asarray(X), jnp.asarray(labels))
    if shape.n_params():
        if not bool(fit.result == optx.RESULTS.successful):
            raise ValueError(
                f"{shape.kind} fit did not converge in {int(fit.steps)} steps: "
                "no value reported"
            )
        J = np.asarray(J)
        d = np.sqrt(np.sum(J * J, axis=0))
        lam = np.linalg.eigvalsh((J / np.where(d > 0, d, 1.0)).T @ (J / np.where(d > 0, d, 1.0)))
        if np.any(d == 0) or lam[0] <= FIT_RANK_RTOL * lam[-1]:
            raise ValueError(
                f"{shape.kind} fit: degenerate geometry (the points do not determine the "
                "shape's parameters): no value reported"
            )
    values = np.asarray(fit.values)
    if not np.all(np.isfinite(values)):
        raise ValueError(f"{shape.kind} fit gave a non-finite value: no value reported")
    return fit, np.asarray(gX), np.asarray(normals)


STEP_BREAK = 4.0  # a step longer than this × the median step ends a line


def point_lines(X, frame_index=None, labels=None) -> np.ndarray:
    """`(N,)` line number of each point, lines being runs of consecutive points: a new
    line where the frame or the label changes, or after a step longer than
    `STEP_BREAK` × the median step between consecutive points (a gap, another frame)."""
    X = np.asarray(X, dtype=np.float64)
    n = len(X)
    if n < 2:
        return np.zeros(n, np.int64)
    step = np.linalg.norm(np.diff(X, axis=0), axis=1)
    same = step <= STEP_BREAK * np.median(step)
    for a in (frame_index, labels):
        if a is not None:
            a = np.asarray(a)
            same &= a[1:] == a[:-1]
    return np.concatenate([[0], np.cumsum(~same)])


def lag_correlation(r, lines, max_lag: int = MAX_LAG) -> np.ndarray:
    """Lag correlations `ρ_1, ρ_2, …` of residuals `r` `(N, m)` along `lines` (pairs on
    one line only, the m columns pooled), kept from lag 1 while `ρ_k > max(0.05, 3/√N)`
    (the calibration's estimator, `_calcov.lag_correlations`); empty when neighbours do
    not correlate."""
    lines = np.asarray(lines)
    return lag_correlations(r, lambda k: lines[:-k] == lines[k:], len(lines), max_lag)


def banded_sum(P, rho, lines) -> np.ndarray:
    """`Σ_i Σ_j c_ij P_i P_jᵀ` `(K, K)` for per-point terms `P` `(K, N, d)`, with
    `c_ii = 1`, `c_ij = ρ_|i−j|` for points of one line within `len(rho)` of each other,
    0 otherwise (the banded correlation of the points' noise)."""
    P = np.asarray(P, dtype=np.float64)
    out = np.einsum("kni,lni->kl", P, P)
    for k, rho_k in enumerate(np.asarray(rho, dtype=np.float64), start=1):
        if k >= P.shape[1]:
            break
        pair = (lines[:-k] == lines[k:]).astype(np.float64)
        cross = np.einsum("kni,lni,n->kl", P[:, :-k], P[:, k:], pair)
        out += rho_k * (cross + cross.T)
    return out


def _fit_stats(shape, fit, normals, gX, s2_px, rho=(), lines=None):
    """`(C_fit (K, K), stats)` for the fit-residual term (`rho`, `lines`: the points'
    lag correlations along their lines, `lag_correlation`)."""
    r = np.asarray(fit.residuals)
    M, p = r.size, shape.n_params()
    K = len(shape.names)
    if p == 0:
        return np.zeros((K, K)), {}
    s2 = float(np.sum(r * r)) / (M - p) if M > p else math.inf
    P = np.einsum("nmj,knj->knm", normals, gX)  # (K, N, m): ∂v/∂r_i scaled by the normals
    if len(rho):
        raw = banded_sum(P, rho, lines)
    else:
        raw = np.einsum("knm,lnm->kl", P, P)
    excess = max(0.0, s2 - s2_px) if math.isfinite(s2) else math.inf
    stats = {
        "rms": float(np.sqrt(np.mean(r * r))),
        "peak_to_valley": float(np.max(r) - np.min(r)),
        "max_abs": float(np.max(np.abs(r))),
        "variance_factor": s2,
        "stripe_noise_variance": s2_px,
        "lag1_correlation": float(rho[0]) if len(rho) else 0.0,
        "correlation_time": 1.0 + 2.0 * float(np.sum(rho)),
    }
    return excess * raw, stats


def correlation_note(rho) -> str | None:
    """The note stating that neighbouring points' errors correlate, or None."""
    if not len(rho):
        return None
    tau = 1.0 + 2.0 * float(np.sum(rho))
    return (
        f"neighbouring points share their errors (residual lag-1 correlation "
        f"{rho[0]:.2f} over {len(rho)} lag(s), tau = {tau:.3g}): counted in the fit "
        "residual and stripe noise terms (banded covariance along each line)"
    )


def _sd(C):
    return np.sqrt(np.clip(np.diag(C), 0.0, None))


def measure_points(points, shape: AbstractShape, *, labels=None) -> Measurement:
    """Fit `shape` to reconstructed points and state the value with its fit uncertainty.

    Points alone carry no calibration or pixel information: the budget holds the fit
    residual only (which includes the points' own noise); calibration and stripe noise
    are reported as not included. Use [`measure_stripes`][] for the full budget.
    Give the points in the order they were reconstructed (frame by frame, along each
    line, as `reconstruct` writes them): neighbours' correlated errors are estimated
    along that order (module text).

    **Arguments:**
    - `points`: `(N, 3)` (mm), finite.
    - `shape`: the model ([`Cylinder`][], [`Plane`][], …).
    - `labels`: `(N,)` face of each point for [`Steps`][].

    **Returns:** a [`Measurement`][]. **Raises:** `ValueError` (one line) for too few
    points, degenerate geometry, a fit that did not converge.
    """
    X = np.asarray(points, dtype=np.float64)
    shape.check(X, _check_labels(shape, len(X) if X.ndim == 2 else 0, labels))
    lab = _check_labels(shape, len(X), labels)
    fit, gX, normals = _checked_fit(shape, X, lab)
    lines = point_lines(X, labels=lab)
    rho = lag_correlation(fit.residuals, lines) if shape.n_params() else np.zeros(0)
    C_fit, stats = _fit_stats(shape, fit, normals, gX, 0.0, rho, lines)
    notes = [
        "calibration and stripe noise not included (points only): measure from the "
        "calibration and the stripes for the full budget",
    ]
    if (note := correlation_note(rho)) is not None:
        notes.append(note)
    return _measurement(shape, fit, {"fit_residual": C_fit}, stats, None, notes)


def _measurement(shape, fit, terms, stats, sensitivity, notes) -> Measurement:
    K = len(shape.names)
    C = sum(terms.values(), np.zeros((K, K)))
    if shape.n_params() == 0:
        terms.pop("fit_residual", None)
    return Measurement(
        kind=shape.kind,
        names=tuple(shape.names),
        values=np.asarray(fit.values, dtype=np.float64),
        covariance=C,
        budget={src: (_sd(terms[src]) if src in terms else None) for src in SOURCES},
        coverage_factor=COVERAGE_FACTOR,
        residuals=np.asarray(fit.residuals),
        residual_stats=stats,
        n_points=int(np.shape(fit.residuals)[0]),
        n_params=shape.n_params(),
        geometry={k: np.asarray(v) for k, v in shape.describe(fit.params, fit.frame).items()},
        sensitivity=sensitivity,
        notes=tuple(notes),
    )
