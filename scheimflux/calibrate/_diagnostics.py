"""What the calibration data determine: covariance, correlations, singular values,
residual maps, point uncertainty and cross-validation.

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
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..io._observations import Observations
from ..reconstruct._reconstruct import intersect_ray_plane, stripe_to_camera
from ._calibrate import Calibration, CameraCalibration, calibrate
from ._model import (
    camera_plane_residuals,
    camera_residuals,
    corner_errors_px,
    joint_residuals,
    make_data,
)
from ._solve import free_spec, jacobian, parameter_labels, split

__all__ = [
    "CrossValidation",
    "Diagnostics",
    "cross_validate",
    "diagnostics",
    "plot_residuals",
    "point_uncertainty",
    "residual_function",
    "residual_map",
]

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
        if self.frozen:
            lines.append("  fixed: " + ", ".join(self.frozen))
        if self.warnings:
            lines.append("")
            lines.extend(f"  warning: {w}" for w in self.warnings)
        return "\n".join(lines)

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
            "warnings": list(self.warnings),
        }


def _num(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


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


def diagnostics(
    cal: Calibration | CameraCalibration,
    obs: Observations | None = None,
    *,
    block: str = "auto",
    freeze: Sequence[str] | None = None,
    top: int = 4,
) -> Diagnostics:
    """Standard deviations, correlations and identifiability of a calibration.

    Uses the Jacobian of the final solve's residuals (see [`residual_function`][]) at
    its optimum. A direction whose singular value (column-normalised J) is below
    1e-8 × the largest is reported with the `top` parameters that dominate it.

    **Arguments:**
    - `cal`: a `Calibration`, or a `CameraCalibration` together with the `obs` it was
      computed from (the covariance does not depend on the σ assumed for the corners:
      s² rescales it; a Huber `robust` setting is not known here and is ignored).
    - `block`: see [`residual_function`][].
    - `freeze`: analyse the same optimum with these parameter paths held fixed instead
      of the solve's own (e.g. `("camera.dx", "camera.dy")` to see what freeing f and
      the tilt would cost); the paths are relative to `SystemParams`.
    """
    fn, params, spec = residual_function(cal, block)
    if freeze is not None:
        spec = free_spec(params, tuple(freeze))
    if isinstance(cal, CameraCalibration):
        if obs is None:
            raise ValueError("diagnostics of a CameraCalibration need its observations (obs)")
        data = make_data(obs)
        frozen = ()
    else:
        data, frozen = cal.data, tuple(cal.freeze)
    if freeze is not None:
        frozen = tuple(freeze)
    J = jacobian(fn, params, data, spec)
    r = fn(params, data)
    cov, s2, n, s, V = covariance_from_jacobian(J, r)
    if (
        isinstance(cal, Calibration)
        and fn is not camera_residuals
        and "joint" not in cal.fits
        and "camera" in cal.fits
    ):
        # A sequential calibration is not the optimum of the joint problem: its misfit
        # there is no noise estimate. Take the variance factor of the camera solve.
        _, s2_cam, *_ = covariance_from_jacobian(
            jacobian(
                camera_residuals, cal.fits["camera"].params, data, cal.fits["camera"].free_mask
            ),
            cal.fits["camera"].residuals,
        )
        cov, s2 = cov * (s2_cam / s2), s2_cam
    labels = parameter_labels(params, spec)
    x0, _, _ = split(params, spec)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    with np.errstate(divide="ignore", invalid="ignore"):
        corr = cov / np.outer(std, std)
    corr = np.where(np.outer(std, std) > 0, corr, 0.0)
    np.fill_diagonal(corr, 1.0)
    warnings, nulls = [], []
    smax = s[0] if s.size else 0.0
    for k in np.flatnonzero(s < NULL_RTOL * smax):
        v = V[:, k]
        order = np.argsort(-np.abs(v))[:top]
        comps = [(labels[i], float(v[i])) for i in order if abs(v[i]) > 0.05]
        nulls.append((float(s[k] / smax), comps))
        names = ", ".join(f"{lab} ({c:+.2f})" for lab, c in comps)
        warnings.append(
            f"non-identifiable direction (singular value {s[k] / smax:.1e} × max): {names}; "
            "freeze one of these parameters"
        )
    cam = [i for i, lab in enumerate(labels) if lab.startswith("camera.")]
    for a_i, a in enumerate(cam):
        for b in cam[a_i + 1 :]:
            if abs(corr[a, b]) > CORRELATION_WARN:
                warnings.append(
                    f"strongly correlated: {labels[a]} and {labels[b]} (ρ = {corr[a, b]:+.4f})"
                )
    cond = float(smax / s[-1]) if s.size and s[-1] > 0 else math.inf
    return Diagnostics(
        block="joint" if fn is not camera_residuals else "camera",
        labels=labels,
        values=np.asarray(x0),
        std=std,
        covariance=cov,
        correlation=corr,
        variance_factor=s2,
        n_residuals=n,
        n_params=len(labels),
        singular_values=s,
        condition_number=cond,
        null_directions=nulls,
        warnings=warnings,
        frozen=frozen,
    )


# ----------------------------------------------------------------------------- residual map


def _sensor_extent(cal: Calibration, size) -> tuple[float, float]:
    if size is not None:
        w, h = size
        return float(w), float(h)
    uv = np.asarray(cal.data.corners)[np.asarray(cal.data.corner_w) > 0]
    return float(np.ceil(uv[:, 0].max() + 1)), float(np.ceil(uv[:, 1].max() + 1))


def residual_map(cal: Calibration, *, bins: tuple[int, int] = (16, 12), size=None):
    """Corner reprojection residuals binned across the sensor.

    **Arguments:**
    - `bins`: `(nu, nv)` bins along u and v.
    - `size`: `(width, height)` of the sensor in px (e.g. `(obs.width, obs.height)`);
      by default the grid spans 0 … the largest detected corner coordinate.

    **Returns:** `(mean_u, mean_v, rms, counts)`, each of shape `(nv, nu)` (rows along
    v, like an image): the mean residual (projected − observed, px) per bin, the RMS of
    the residual vector length, and the number of detected corners per bin (NaN means
    and RMS where a bin is empty). Bins cover `[-0.5, width - 0.5)` × `[-0.5, height - 0.5)`.
    """
    nu, nv = (int(b) for b in bins)
    if nu < 1 or nv < 1:
        raise ValueError(f"bins must be positive, got {bins}")
    w, h = _sensor_extent(cal, size)
    mask = np.asarray(cal.data.corner_w) > 0
    uv = np.asarray(cal.data.corners)[mask]
    err = np.asarray(corner_errors_px(cal.params, cal.data))[mask]
    iu = np.clip(np.floor((uv[:, 0] + 0.5) / w * nu).astype(int), 0, nu - 1)
    iv = np.clip(np.floor((uv[:, 1] + 0.5) / h * nv).astype(int), 0, nv - 1)
    flat = iv * nu + iu
    counts = np.bincount(flat, minlength=nu * nv)
    su = np.bincount(flat, err[:, 0], minlength=nu * nv)
    sv = np.bincount(flat, err[:, 1], minlength=nu * nv)
    s2 = np.bincount(flat, np.sum(err**2, axis=1), minlength=nu * nv)
    safe = np.maximum(counts, 1)
    empty = counts == 0
    mean_u = np.where(empty, np.nan, su / safe).reshape(nv, nu)
    mean_v = np.where(empty, np.nan, sv / safe).reshape(nv, nu)
    rms = np.where(empty, np.nan, np.sqrt(s2 / safe)).reshape(nv, nu)
    return mean_u, mean_v, rms, counts.reshape(nv, nu)


def plot_residuals(
    cal: Calibration, path, *, bins: tuple[int, int] = (16, 12), size=None, dpi: int = 120
) -> None:
    """Write a PNG: binned mean corner residual vectors (quiver) and their RMS (heat map).

    Needs matplotlib (`pip install 'scheimflux[plot]'`); uses the Agg canvas directly,
    so it never touches pyplot's global state or the interactive backend.
    """
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:  # pragma: no cover - exercised only without matplotlib
        raise ImportError(
            "plot_residuals needs matplotlib: pip install 'scheimflux[plot]' (or 'matplotlib>=3.7')"
        ) from None
    mean_u, mean_v, rms, counts = residual_map(cal, bins=bins, size=size)
    w, h = _sensor_extent(cal, size)
    nv, nu = counts.shape
    cu = (np.arange(nu) + 0.5) * w / nu - 0.5
    cv = (np.arange(nv) + 0.5) * h / nv - 0.5
    U, V = np.meshgrid(cu, cv)
    fig = Figure(figsize=(12, 4.8))
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.subplots(1, 2)
    ok = counts > 0
    length = np.hypot(mean_u, mean_v)
    ref = float(np.nanmax(length)) if ok.any() and np.nanmax(length) > 0 else 1.0
    q = ax1.quiver(
        U[ok],
        V[ok],
        mean_u[ok],
        mean_v[ok],  # v grows downwards, as does the (inverted) y axis below
        angles="xy",
        scale_units="xy",
        scale=ref / (0.9 * w / nu),
        color="tab:blue",
    )
    ax1.quiverkey(q, 0.82, 1.03, ref, f"{ref:.3g} px", labelpos="E")
    ax1.set_xlim(-0.5, w - 0.5)
    ax1.set_ylim(h - 0.5, -0.5)
    ax1.set_aspect("equal")
    ax1.set_xlabel("u (px)")
    ax1.set_ylabel("v (px)")
    ax1.set_title("mean corner residual per bin")
    im = ax2.imshow(
        np.ma.masked_invalid(rms),
        extent=(-0.5, w - 0.5, h - 0.5, -0.5),
        origin="upper",
        cmap="viridis",
        interpolation="nearest",
    )
    fig.colorbar(im, ax=ax2, label="RMS residual (px)")
    ax2.set_xlabel("u (px)")
    ax2.set_title(f"RMS per bin (overall {cal.reprojection_rms_px:.3g} px per coordinate)")
    fig.tight_layout()
    fig.savefig(path, dpi=dpi, format="png")


# ----------------------------------------------------------------------------- points


def _point_fn(frame: str):
    def one(params, uv, i):
        X, _ = intersect_ray_plane(params.camera.backproject_one(uv), params.plane)
        if frame == "measurement":
            X = params.stage.to_measurement(X, i)
        return X

    return one


@eqx.filter_jit
def _points_and_jacobian(params, spec, idx, uv, fi, frame):
    one = _point_fn(frame)
    x0, unravel, static = split(params, spec)
    x_sub = x0[idx]

    def f(xs, p, i):
        params = eqx.combine(unravel(x0.at[idx].set(xs)), static)
        return one(params, p, i)

    X = jax.vmap(f, in_axes=(None, 0, 0))(x_sub, uv, fi)
    JX = jax.vmap(jax.jacfwd(f), in_axes=(None, 0, 0))(x_sub, uv, fi)
    return X, JX


def point_uncertainty(
    cal: Calibration,
    uv,
    *,
    frame: str = "camera",
    frame_index=None,
    diag: Diagnostics | None = None,
):
    """Propagate the calibration's covariance to reconstructed stripe points.

    The points are `X(θ, uv)` (ray of each pixel ∩ laser plane, then the stage for
    `frame="measurement"`); θ are the free camera and plane parameters (and the stage
    and eccentricity for the measurement frame). With `Σ_θ` their marginal covariance
    from the joint problem ([`residual_function`][] with `block="joint"`, so the board
    poses' uncertainty is included) and `J_X = ∂X/∂θ` (autodiff), `cov = J_X Σ_θ J_Xᵀ`.
    This is the calibration error of each point, common to every scan; pixel noise of
    the measured stripe itself adds on top.

    The σ is relative to the **camera frame** (its origin at the image-side principal
    point): it is dominated by the frame's poorly determined placement along the optical
    axis (the camera datum that e and z0 share), which moves every point alike and
    cancels in distances and lengths. For what users measure, use
    [`length_uncertainty`][] (covariance between points).

    **Arguments:**
    - `uv`: stripe pixels `(N, 2)`.
    - `frame`: `"camera"` or `"measurement"` (needs a stage and `frame_index`: an
      integer or `(N,)`).
    - `diag`: a precomputed `diagnostics(cal, block="joint")`.

    **Returns:** `(points (N, 3), sigma (N, 3), cov (N, 3, 3))` in mm.
    """
    if frame not in ("camera", "measurement"):
        raise ValueError(f"frame must be 'camera' or 'measurement', got {frame!r}")
    uv = jnp.asarray(np.asarray(uv, dtype=np.float64).reshape(-1, 2))
    fn, params, spec = residual_function(cal, "joint")
    if frame == "measurement":
        if params.stage is None:
            raise ValueError("frame='measurement' needs a calibrated rotary stage")
        if frame_index is None:
            raise ValueError("frame='measurement' needs frame_index")
        fi = jnp.broadcast_to(jnp.asarray(frame_index, dtype=jnp.float64), uv.shape[:1])
        prefixes = ("camera.", "plane.", "stage.", "eccentricity")
    else:
        fi = jnp.zeros(uv.shape[:1], dtype=jnp.float64)
        prefixes = ("camera.", "plane.")
    if diag is None:
        diag = diagnostics(cal, block="joint")
    elif diag.block != "joint":
        raise ValueError("point_uncertainty needs diagnostics(cal, block='joint')")
    idx = diag.select(prefixes)
    X, JX = _points_and_jacobian(params, spec, jnp.asarray(idx), uv, fi, frame)
    JX = np.asarray(JX)
    S = diag.covariance[np.ix_(idx, idx)]
    cov = np.einsum("nij,jk,nlk->nil", JX, S, JX)
    sigma = np.sqrt(np.clip(np.einsum("nii->ni", cov), 0.0, None))
    return np.asarray(X), sigma, cov


# ----------------------------------------------------------------------------- cross-validation


@dataclasses.dataclass(frozen=True)
class CrossValidation:
    """Two calibrations from disjoint halves of the views, compared where it matters.

    **Fields:**
    - `rms_um`, `max_um`: RMS and largest distance between the two reconstructions of
      the same stripe pixels (camera frame, µm).
    - `aligned_rms_um`, `aligned_max_um`: the same after the best rigid alignment of the
      two point sets (Kabsch): what remains is a difference of shape — the part that
      changes measured lengths — while the raw difference also holds the weakly
      determined placement of the camera frame itself (e.g. its depth: e and z0 trade
      off along the axis when the perspective is weak).
    - `n_points`: how many pixels both reconstruct.
    - `plane_angle_urad`: angle between the two laser planes (µrad).
    - `plane_distance_um`: distance of the first plane's point at the FOV centre (where
      the centre pixel's ray meets it) from the second plane (µm).
    - `views`: the view indices of each half; `calibrations`: the two `Calibration`s.
    """

    rms_um: float
    max_um: float
    aligned_rms_um: float
    aligned_max_um: float
    n_points: int
    plane_angle_urad: float
    plane_distance_um: float
    views: tuple[list[int], list[int]]
    calibrations: tuple[Calibration, Calibration]

    def summary(self) -> str:
        return (
            f"cross-validation (views {self.views[0]} vs {self.views[1]}): "
            f"{self.n_points} stripe points differ by {self.rms_um:.4g} µm RMS, "
            f"{self.max_um:.4g} µm max ({self.aligned_rms_um:.4g} / {self.aligned_max_um:.4g} µm "
            "after rigid alignment); laser planes differ by "
            f"{self.plane_angle_urad:.4g} µrad and {self.plane_distance_um:.4g} µm "
            "at the FOV centre"
        )


def _stripe_pixels(obs: Observations) -> np.ndarray:
    uv = [np.asarray(v.stripe_px, dtype=np.float64).reshape(-1, 2) for v in obs.views]
    uv = np.concatenate(uv) if uv else np.zeros((0, 2))
    return uv[np.all(np.isfinite(uv), axis=1)]


def _aligned_distances(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """|R A + t − B| per point after the least-squares rigid fit (Kabsch)."""
    if len(A) < 3:
        return np.linalg.norm(A - B, axis=1)
    ca, cb = A.mean(axis=0), B.mean(axis=0)
    U, _, Vt = np.linalg.svd((A - ca).T @ (B - cb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return np.linalg.norm((A - ca) @ R.T - (B - cb), axis=1)


def cross_validate(obs: Observations, **calibrate_kwargs) -> CrossValidation:
    """Calibrate on the even and on the odd views separately and compare.

    Both halves are calibrated with `calibrate(half, **calibrate_kwargs)`. The rotary
    stage scan is left out of both (it is one scan that cannot be split into
    independent halves, and sharing it would correlate the two calibrations); the
    comparison is made in the camera frame, which needs no stage. Every board stripe
    pixel of the full set is reconstructed with both calibrations: on noise-free data
    from the model itself the two agree to rounding; the spread on real (noisy) data
    measures how well the calibration generalises to views it was not fitted to.
    """
    n = len(obs.views)
    halves = (list(range(0, n, 2)), list(range(1, n, 2)))
    if min(len(h) for h in halves) < 3:
        raise ValueError(f"cross-validation needs at least 6 views (3 per half), got {n}")
    cals = tuple(
        calibrate(
            dataclasses.replace(obs, views=[obs.views[i] for i in h], stage=None),
            **calibrate_kwargs,
        )
        for h in halves
    )
    uv = _stripe_pixels(obs)
    Xa = np.asarray(stripe_to_camera(cals[0].camera, cals[0].plane, uv).points)
    Xb = np.asarray(stripe_to_camera(cals[1].camera, cals[1].plane, uv).points)
    ok = np.all(np.isfinite(Xa) & np.isfinite(Xb), axis=1)
    d = np.linalg.norm(Xa[ok] - Xb[ok], axis=1) * 1e3
    da = _aligned_distances(Xa[ok], Xb[ok]) * 1e3
    na = np.asarray(cals[0].plane.normal)
    nb = np.asarray(cals[1].plane.normal)
    angle = math.atan2(float(np.linalg.norm(np.cross(na, nb))), float(abs(na @ nb)))
    centre = np.array([[(obs.width - 1) / 2, (obs.height - 1) / 2]])
    Xc = np.asarray(stripe_to_camera(cals[0].camera, cals[0].plane, centre).points)
    dist = float(np.abs(np.asarray(cals[1].plane.signed_distance(jnp.asarray(Xc))))[0])
    return CrossValidation(
        rms_um=float(np.sqrt(np.mean(d**2))) if d.size else math.nan,
        max_um=float(d.max()) if d.size else math.nan,
        aligned_rms_um=float(np.sqrt(np.mean(da**2))) if da.size else math.nan,
        aligned_max_um=float(da.max()) if da.size else math.nan,
        n_points=int(ok.sum()),
        plane_angle_urad=angle * 1e6,
        plane_distance_um=dist * 1e3,
        views=halves,
        calibrations=cals,
    )
