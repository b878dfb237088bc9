"""What the calibration data determine: covariance, correlations and singular values of
the parameters at the optimum (residual maps: `_plots`; point and length uncertainty:
`_uncertainty`; cross-validation: `_cross_validate`).

Everything here is computed from the Jacobian of the (noise-weighted, unitless) residual
vector at the optimum. With `J` that Jacobian, `r` the residuals, `n` the number of
observations and `p` the number of free parameters, the covariance of the parameters is

    Σ = s² (JᵀJ)⁺,    s² = |r|² / (n − p)

(`s²`, the a-posteriori variance factor, is ≈ 1 when the noise σ given to `calibrate`
is right and the model fits; it scales Σ so the standard deviations follow the actual
residuals). The pseudo-inverse is taken on the column-normalised Jacobian, whose
singular values also reveal the directions the data cannot determine.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np

from ..core._camera import CameraCalibration
from ..core._model import camera_plane_residuals, camera_residuals, joint_residuals
from ..core._result import Calibration
from ..core._solve import free_spec

# A singular value of the column-normalised Jacobian below this fraction of the largest
# marks a direction the data do not determine.
NULL_RTOL = 1e-8
# |correlation| above this between two camera parameters is reported.
CORRELATION_WARN = 0.99

_UNITS = {
    "camera.f": "mm",
    "camera.e": "mm",
    "camera.z0": "mm",
    "camera.phi": "rad",
    "camera.theta": "rad",
    "camera.x0": "px",
    "camera.y0": "px",
    "camera.dx": "mm",
    "camera.dy": "mm",
    "camera.pupil": "mm",
    "camera.lateral": "mm",
    "camera.pivot": "mm",
    "camera.alpha": "px",
    "camera.beta": "px",
    "camera.gamma": "px",
    "camera.fx": "px",
    "camera.fy": "px",
    "camera.cx": "px",
    "camera.cy": "px",
    "camera.tau_x": "rad",
    "camera.tau_y": "rad",
    "plane.n": "1/mm",
    "stage.T_m_c.rotvec": "rad",
    "stage.T_m_c.translation": "mm",
    "eccentricity": "mm",
}


def _unit(label: str) -> str:
    base = label.split("[")[0]
    if base.startswith("camera.distortion"):
        return "-"
    return _UNITS.get(base, "")


def _is_system(label: str) -> bool:
    """Camera, plane, stage and gauge parameters (everything but the board poses)."""
    return not label.startswith("board_poses")


# ----------------------------------------------------------------------------- problem


def residual_function(
    cal: Calibration | CameraCalibration, block: str = "auto"
) -> tuple[Callable, object, object]:
    """The residual function, parameters and filter spec of a calibration's solve.

    A `CameraCalibration` (from `calibrate_camera`) has only the `"camera"` block.

    **Arguments:**
    - `block`: `"auto"` (the final solve: `"joint"` when `cal.fits` has one, else
      `"camera"`), `"joint"` or `"camera"`.
      `"camera"`: `camera_residuals` (corners only) at the camera fit's optimum.
      `"joint"`: `joint_residuals` (with a stage) or `camera_plane_residuals` with the
      joint fit's free parameters. For a sequential calibration (`joint=False`), `"joint"`
      is that same problem linearised at the sequential estimate — the covariance the
      data would support if all blocks were solved together; it gives the plane and
      stage an uncertainty that includes the camera's; `diagnostics` then takes the
      variance factor s² from the camera solve (the sequential estimate is not the
      joint optimum, so its joint misfit is no noise estimate).

    **Returns:** `(fn, params, spec)`; `fn(params, cal.data)` is the residual vector.
    """
    if isinstance(cal, CameraCalibration):
        if block not in ("auto", "camera"):
            raise ValueError("a CameraCalibration has only the 'camera' block")
        return camera_residuals, cal.fit.params, cal.fit.free_mask
    if block == "auto":
        block = "joint" if "joint" in cal.fits else "camera"
    if block == "camera":
        fit = cal.fits["camera"]
        return camera_residuals, fit.params, fit.free_mask
    if block != "joint":
        raise ValueError(f"block must be 'auto', 'joint' or 'camera', got {block!r}")
    params = cal.params
    if params.plane is None:
        raise ValueError("the calibration has no laser plane: no joint residuals")
    fn = joint_residuals if params.stage is not None else camera_plane_residuals
    if "joint" in cal.fits:
        fit = cal.fits["joint"]
        return fn, fit.params, fit.free_mask
    extra = ("stage.delta_omega",) if params.stage is not None else ()
    return fn, params, free_spec(params, tuple(cal.freeze) + extra)


# ----------------------------------------------------------------------------- diagnostics


@dataclasses.dataclass(frozen=True)
class Diagnostics:
    """First-order statistics of a calibration at its optimum.

    **Fields:**
    - `block`: which solve (`"joint"` or `"camera"`).
    - `labels`, `values`: the free parameters (physical units: mm, rad, px).
    - `std`: standard deviations; `covariance` `(p, p)`; `correlation` `(p, p)`.
    - `variance_factor`: s² = |r|² / (n − p) of the unitless residuals (≈ 1 when the
      assumed noise σ is right); `n_residuals` (n, observations with non-zero weight),
      `n_params` (p).
    - `singular_values`: of the Jacobian with unit-norm columns, descending;
      `condition_number` their ratio max / min.
    - `null_directions`: per non-identifiable direction, `(relative singular value,
      [(label, component), ...])`.
    - `warnings`: human-readable strings (non-identifiable directions, camera
      parameter pairs correlated beyond |ρ| > 0.99).
    - `frozen`: the parameter paths held fixed.
    - `coverage`: fraction of the sensor covered by the calibration data
      (`Calibration.coverage`), None when unknown.
    - `correlation_time`: `{group: τ}`, `τ = 1 + 2 Σ_k ρ_k`, of the residual groups
      whose neighbouring stripe centres share their errors, where the covariance counts
      that correlation ([`fit_diagnostics`][]); empty: counted as independent.
    """

    block: str
    labels: list[str]
    values: np.ndarray
    std: np.ndarray
    covariance: np.ndarray
    correlation: np.ndarray
    variance_factor: float
    n_residuals: int
    n_params: int
    singular_values: np.ndarray
    condition_number: float
    null_directions: list
    warnings: list[str]
    frozen: tuple = ()
    coverage: float | None = None
    correlation_time: dict = dataclasses.field(default_factory=dict)

    def index(self, label: str) -> int:
        """Position of a parameter label (e.g. `"camera.z0"`, `"plane.n[2]"`)."""
        try:
            return self.labels.index(label)
        except ValueError:
            raise KeyError(f"no free parameter {label!r}") from None

    def std_of(self, label: str) -> float:
        return float(self.std[self.index(label)])

    def select(self, prefix: str | tuple[str, ...]) -> np.ndarray:
        """Indices of the labels starting with `prefix` (a string or a tuple)."""
        return np.array([i for i, lab in enumerate(self.labels) if lab.startswith(prefix)], int)

    def summary(self) -> str:
        """A text table of the camera, plane and stage parameters with ± σ."""
        lines = [
            f"calibration diagnostics ({self.block} solve): {self.n_params} free parameters, "
            f"{self.n_residuals} residuals",
            f"  variance factor s² = {self.variance_factor:.4g}   "
            f"condition number (column-normalised J) = {self.condition_number:.3g}",
            "",
            f"  {'parameter':<32} {'value':>16} {'± σ':>12}  unit",
        ]
        for i, lab in enumerate(self.labels):
            if not _is_system(lab):
                continue
            lines.append(f"  {lab:<32} {self.values[i]:>16.9g} {self.std[i]:>12.3g}  {_unit(lab)}")
        note = self._undetermined_terms_note()
        if note:
            lines.append(note)
        rot = self.select("board_poses.rotvec")
        tra = self.select("board_poses.translation")
        if len(rot) or len(tra):
            n_views = max(len(rot), len(tra)) // 3
            parts = [f"  board_poses: {n_views} views"]
            if len(rot):
                parts.append(f"σ(rotvec) median {np.median(self.std[rot]) * 1e6:.3g} µrad")
            if len(tra):
                parts.append(f"σ(translation) median {np.median(self.std[tra]) * 1e3:.3g} µm")
            lines.append(", ".join(parts))
        if self.correlation_time:
            taus = ", ".join(
                f"{'board stripes' if g == 'stripes' else g} tau = {t:.3g}"
                for g, t in self.correlation_time.items()
            )
            lines.append(
                f"  σ count the correlation of neighbouring stripe centres ({taus}; banded "
                "residual covariance, as measure and verify)"
            )
        if self.frozen:
            lines.append("  fixed: " + ", ".join(self.frozen))
        cov = "unknown" if self.coverage is None else f"{100 * self.coverage:.0f} %"
        lines.append(f"  sensor covered by calibration data: {cov}")
        if self.warnings:
            lines.append("")
            lines.extend(f"  warning: {w}" for w in self.warnings)
        return "\n".join(lines)

    def _undetermined_terms_note(self) -> str:
        """A line naming the distortion terms whose σ exceed their value (with a high
        radial order the terms trade against each other: each is undetermined alone while
        the distortion they make together may be well fixed), or ""."""
        dist = self.select("camera.distortion.")
        weak = [int(i) for i in dist if self.std[i] > abs(self.values[i])]
        if not weak:
            return ""
        rho = max(
            (abs(float(self.correlation[i, j])) for i in weak for j in dist if j != i),
            default=0.0,
        )
        # the terms' joint significance, x' S⁺ x over all distortion terms (about their
        # count where the data cannot tell the distortion from none at all), in units of
        # each σ (the terms' scales span 1e-4 to 1e6)
        sd = np.asarray(self.std, dtype=np.float64)[dist]
        joint = ""
        if np.all(np.isfinite(sd) & (sd > 0)):
            z = np.asarray(self.values, dtype=np.float64)[dist] / sd
            R = np.asarray(self.correlation, dtype=np.float64)[np.ix_(dist, dist)]
            chi2 = float(z @ np.linalg.pinv(R, hermitian=True) @ z)
            joint = (
                f"; all {len(dist)} distortion terms together: chi² = {chi2:.3g} (about "
                f"{len(dist)} where the data cannot tell the distortion from none)"
            )
        names = ", ".join(self.labels[i].rsplit(".", 1)[-1] for i in weak)
        return (
            f"  {names}: σ larger than the value, not determined one by one (|ρ| with the "
            f"other distortion terms up to {rho:.3g}){joint}. Their effect on what is "
            "measured is in the σ of lengths and points (length_uncertainty, measure), "
            "which carry the full covariance"
        )

    def to_dict(self) -> dict:
        """JSON-ready dict for the calibration file (no board poses' covariance)."""
        cam = self.select("camera.")
        sys_ = [i for i, lab in enumerate(self.labels) if _is_system(lab)]
        return {
            "block": self.block,
            "variance_factor": _num(self.variance_factor),
            "n_residuals": int(self.n_residuals),
            "n_params": int(self.n_params),
            "condition_number": _num(self.condition_number),
            "std": {self.labels[i]: _num(self.std[i]) for i in sys_},
            "units": {self.labels[i]: _unit(self.labels[i]) for i in sys_},
            "camera_correlation": {
                "labels": [self.labels[i] for i in cam],
                "matrix": [[_num(v) for v in row] for row in self.correlation[np.ix_(cam, cam)]],
            },
            "singular_values": [_num(v) for v in self.singular_values],
            "coverage_fraction": None if self.coverage is None else _num(self.coverage),
            "correlation_time": {g: _num(t) for g, t in self.correlation_time.items()},
            "warnings": list(self.warnings),
        }


def _num(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def std_and_correlation(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Standard deviations and the correlation matrix of a covariance `(p, p)` (ρ = 0
    where a σ is 0, ρ = 1 on the diagonal)."""
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    with np.errstate(divide="ignore", invalid="ignore"):
        corr = cov / np.outer(std, std)
    corr = np.where(np.outer(std, std) > 0, corr, 0.0)
    np.fill_diagonal(corr, 1.0)
    return std, corr


def dominant_parameters(labels: list[str], v: np.ndarray, top: int) -> list:
    """The `top` largest components (above 0.05) of a unit direction `v` in parameter
    space, as `[(label, component), ...]`."""
    order = np.argsort(-np.abs(v))[:top]
    return [(labels[i], float(v[i])) for i in order if abs(v[i]) > 0.05]


def correlation_warnings(labels: list[str], corr: np.ndarray) -> list[str]:
    """One warning per pair of camera parameters correlated beyond `CORRELATION_WARN`."""
    out = []
    cam = [i for i, lab in enumerate(labels) if lab.startswith("camera.")]
    for a_i, a in enumerate(cam):
        for b in cam[a_i + 1 :]:
            if abs(corr[a, b]) > CORRELATION_WARN:
                out.append(
                    f"strongly correlated: {labels[a]} and {labels[b]} (ρ = {corr[a, b]:+.4f})"
                )
    return out


def covariance_from_jacobian(J, r, *, rtol: float = NULL_RTOL):
    """`(Σ, s², n, singular values, V)` from a residual Jacobian `J` and residuals `r`.

    Rows that are identically zero (padding, zero weight) are not observations. The
    pseudo-inverse drops singular values of the column-normalised `J` below
    `rtol · max`; `V` holds the right singular vectors (columns, normalised space).
    """
    J = np.asarray(J, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    used = np.any(J != 0, axis=1) | (r != 0)
    n, p = int(used.sum()), J.shape[1]
    col = np.linalg.norm(J, axis=0)
    d = np.where(col > 0, 1.0 / np.where(col > 0, col, 1.0), 1.0)
    _, s, Vt = np.linalg.svd(J * d, full_matrices=False)
    keep = s > rtol * s[0] if s.size else s > 0
    inv = np.where(keep, 1.0 / np.where(keep, s, 1.0) ** 2, 0.0)
    cov_n = (Vt.T * inv) @ Vt
    dof = n - p
    s2 = float(np.sum(r**2) / dof) if dof > 0 else math.nan
    cov = s2 * (d[:, None] * cov_n * d[None, :])
    return cov, s2, n, s, Vt.T
