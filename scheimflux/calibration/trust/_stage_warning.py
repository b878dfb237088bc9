"""How well a calibration determines the rotary-table axis, and a warning when it does not.

A ring gauge nearly coaxial with the table fixes the axis only through its eccentricity;
a short arc or few frames fix it little better. The images are then reproduced well,
distances within one frame are right, and yet distances between points seen at
different table angles are off. The quantity that shows it is the predicted error of
such a length: the stage covariance (and the camera's and plane's, where the solve
freed them) propagated to

    L(θ) = |M(X(θ, p), 0) − M(X(θ, q), j)|,   j = round(π / |Δω|),

the distance between a field point `X(θ, p)` (pixel p on the laser plane) seen in
frame 0 and a field point `X(θ, q)` seen in the frame half a turn away (every pair of
five pixels spanning the field: the pairs across the field carry the axis direction's
error through their lever arm along the axis), `M(·, i)` the stage's map to the measurement
frame. `σ_L² = ∇L Σ_θ ∇Lᵀ` (first order; what moves both ends alike cancels).
[`axis_conditioning`][] computes it with the axis direction's and position's σ, and
[`axis_warning`][] turns it into one line naming the cause and the remedy.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..._export import exported_jit
from ...reconstruct._reconstruct import intersect_ray_plane
from ..core._model import CalibrationData
from ..core._solve import ONE_SHOT, split

__all__ = ["AxisConditioning", "axis_conditioning", "axis_warning"]

#: Predicted across-frame length error (µm, 1σ) above which the axis is called weak.
WEAK_AXIS_UM = 1.0
#: Arc, frame count and gauge eccentricity below which each is named as a cause.
SHORT_ARC_DEG = 180.0
FEW_FRAMES = 8
COAXIAL_MM = 0.2


@dataclasses.dataclass(frozen=True)
class AxisConditioning:
    """Predicted uncertainty of the table axis and of an across-frame length.

    **Fields:**
    - `sigma_across_um`: σ of the distance between a field point seen in frame 0 and one
      seen in the frame half a turn away (largest over the pairs of reference pixels), µm.
    - `sigma_direction_mrad`: σ of the axis direction (largest angle perpendicular to it).
    - `sigma_position_um`: σ of the axis position at the field (largest component
      perpendicular to the axis).
    - `opposite_frame`: the frame index j used (half a turn, or as near as Δω allows).
    - `n_frames`, `arc_deg`: the gauge frames used and the arc they span (None if unknown).
    - `eccentricity_mm`: |gauge offset from the table axis| (None without a gauge).
    """

    sigma_across_um: float
    sigma_direction_mrad: float
    sigma_position_um: float
    opposite_frame: int
    n_frames: int | None = None
    arc_deg: float | None = None
    eccentricity_mm: float | None = None

    @property
    def weak(self) -> bool:
        return not self.sigma_across_um <= WEAK_AXIS_UM  # NaN counts as weak

    def to_dict(self) -> dict:
        return {k: v for k, v in dataclasses.asdict(self).items()} | {"weak": self.weak}


def _perp_max(J: np.ndarray, cov: np.ndarray, d: np.ndarray) -> float:
    P = np.eye(3) - np.outer(d, d)
    c = P @ J @ cov @ J.T @ P
    return float(math.sqrt(max(float(np.linalg.eigvalsh(c).max()), 0.0)))


@exported_jit(compiler_options=ONE_SHOT)
def _gradients(params, spec, uv, j):
    """Per ordered pair of reference pixels: L and ∇L; the axis direction and its
    Jacobian; per pixel the Jacobian of the axis foot.

    Forward mode only, and the camera model traced once: the field points `X(p)` of the
    N pixels and their Jacobians `∂X/∂θ` come from one `jacfwd` (N × 3 × P), and every
    pair's ∇L is the chain rule `∂L/∂θ|_X + ∂L/∂X_a ∂X_a/∂θ + ∂L/∂X_b ∂X_b/∂θ`, the
    partial derivatives of the stage map alone (small). Reverse mode through the camera
    (`grad` of L per pair, as before) made this the slowest program of a calibration to
    compile (27 % of a cold `calibrate`) for the same numbers.
    """
    x0, unravel, static = split(params, spec)

    def build(x):
        return eqx.combine(unravel(x), static)

    def field(x, p):
        prm = build(x)
        X, _ = intersect_ray_plane(prm.camera.backproject_one(p), prm.plane)
        return X, X

    def across(x, Xa, Xb):
        st = build(x).stage
        return jnp.linalg.norm(st.to_measurement(Xa, 0.0) - st.to_measurement(Xb, j))

    def direction(x):
        return build(x).stage.R_m_c[2]

    def foot(x, X):
        st = build(x).stage
        d = st.R_m_c[2]
        C = -st.R_m_c.T @ st.t_m_c
        return C + jnp.dot(X - C, d) * d

    JX, X = jax.vmap(jax.jacfwd(field, has_aux=True), in_axes=(None, 0))(x0, uv)
    n = uv.shape[0]
    a, b = jnp.repeat(jnp.arange(n), n), jnp.tile(jnp.arange(n), n)  # every ordered pair
    L = jax.vmap(across, in_axes=(None, 0, 0))(x0, X[a], X[b])
    dx, dXa, dXb = jax.vmap(jax.jacfwd(across, argnums=(0, 1, 2)), in_axes=(None, 0, 0))(
        x0, X[a], X[b]
    )
    gL = dx + jnp.einsum("pk,pkq->pq", dXa, JX[a]) + jnp.einsum("pk,pkq->pq", dXb, JX[b])
    Jd = jax.jacfwd(direction)(x0)
    Jf = jax.vmap(jax.jacfwd(foot), in_axes=(None, 0))(x0, X)  # the field point held fixed
    return L, gL, direction(x0), Jd, Jf


def axis_conditioning(
    params, spec, covariance, uv, *, frame_index=None, gauge_weights=None
) -> AxisConditioning | None:
    """Predicted σ of the table axis and of a length across half a table turn.

    **Arguments:**
    - `params`, `spec`: a solve's parameters and free mask (`Fit.params`,
      `Fit.free_mask`); `params` must hold a camera, a laser plane and a stage.
    - `covariance`: the free parameters' covariance, in the order of `split(params, spec)`.
    - `uv`: `(N, 2)` reference pixels (field points on the laser plane); every ordered
      pair (p in frame 0, q half a turn later) is a length.
    - `frame_index`, `gauge_weights`: the gauge scan's `(F,)` frame indices and `(F, L)`
      weights, to report the frames used and their arc (optional).

    **Returns:** an [`AxisConditioning`][], or None when `params` has no stage or plane.
    """
    if getattr(params, "stage", None) is None or getattr(params, "plane", None) is None:
        return None
    dw = float(params.stage.delta_omega)
    if not math.isfinite(dw) or dw == 0.0:
        raise ValueError(f"the stage's delta_omega must be a non-zero angle, got {dw}")
    j = max(1, int(round(math.pi / abs(dw))))
    cov = np.asarray(covariance, dtype=np.float64)
    uv = jnp.asarray(np.asarray(uv, dtype=np.float64).reshape(-1, 2))
    L, gL, d, Jd, Jf = (np.asarray(a) for a in _gradients(params, spec, uv, float(j)))
    if cov.shape != (gL.shape[1],) * 2:
        raise ValueError(f"covariance {cov.shape} does not match {gL.shape[1]} free parameters")
    ok = L > 1e-6  # a point on the axis has no across-frame length
    var = np.einsum("nq,qr,nr->n", gL[ok], cov, gL[ok])
    s_across = float(np.sqrt(np.clip(var, 0.0, None)).max()) if ok.any() else math.nan
    s_dir = _perp_max(Jd, cov, d)
    s_pos = max(_perp_max(J, cov, d) for J in Jf)
    n_frames = arc = None
    if frame_index is not None:
        fi = np.asarray(frame_index, dtype=np.float64)
        if gauge_weights is not None:
            fi = fi[np.asarray(gauge_weights).sum(axis=1) > 0]
        n_frames = len(fi)
        arc = math.degrees(abs(dw) * (fi.max() - fi.min())) if n_frames else 0.0
    ecc = getattr(params, "eccentricity", None)
    return AxisConditioning(
        1e3 * s_across,
        1e3 * s_dir,
        1e3 * s_pos,
        j,
        n_frames,
        arc,
        None if ecc is None else float(np.linalg.norm(np.asarray(ecc))),
    )


def axis_warning(cond: AxisConditioning | None) -> str | None:
    """One line for a weakly determined axis (None when it is determined well enough)."""
    if cond is None or not cond.weak:
        return None
    causes = []
    if cond.eccentricity_mm is not None and cond.eccentricity_mm < COAXIAL_MM:
        causes.append(f"gauge nearly coaxial ({cond.eccentricity_mm:.3g} mm off the axis)")
    if cond.arc_deg is not None and cond.arc_deg < SHORT_ARC_DEG:
        causes.append(f"short arc ({cond.arc_deg:.0f}°)")
    if cond.n_frames is not None and cond.n_frames < FEW_FRAMES:
        causes.append(f"few frames ({cond.n_frames})")
    cause = f" ({'; '.join(causes)})" if causes else ""
    return (
        f"weak table axis{cause}: a length between points at opposite table angles has a "
        f"predicted error of {cond.sigma_across_um:.3g} µm (1σ; axis direction σ "
        f"{cond.sigma_direction_mrad:.3g} mrad, position σ {cond.sigma_position_um:.3g} µm); "
        "put a target on the table (docs/stage.md), scan a longer arc with more frames, "
        f"or mount the gauge eccentric (≥ {COAXIAL_MM:g} mm)"
    )


def reference_pixels(width: int, height: int) -> np.ndarray:
    """Five field pixels: the sensor's centre and four points 10 % in from its corners."""
    w, h = max(int(width), 1) - 1, max(int(height), 1) - 1
    f = np.array([[0.5, 0.5], [0.1, 0.1], [0.9, 0.1], [0.1, 0.9], [0.9, 0.9]])
    return f * np.array([w, h])


def _fit_covariance(fit) -> np.ndarray | None:
    """`max(1, s²) (JᵀJ)⁺` of a solve that kept its normal matrix (as `fit_diagnostics`)."""
    H = getattr(fit, "normal_matrix", None)
    if H is None:
        return None
    H = np.asarray(H, dtype=np.float64)
    d = np.sqrt(np.clip(np.diag(H), 0.0, None))
    d = np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 1.0)
    n, p = int(fit.n_observations), H.shape[0]
    s2 = 2.0 * float(fit.cost) / (n - p) if n > p else 1.0
    return max(1.0, s2) * (d[:, None] * np.linalg.pinv(H * np.outer(d, d)) * d[None, :])


def _with_correlated_centres(cal, cov: np.ndarray) -> np.ndarray:
    """`cov` of the joint solve raised, as in `fit_diagnostics`, to the covariance that
    counts the correlation of neighbouring stripe centres (gauge, board or table stripes),
    wherever that is larger; `cov` itself where they are independent."""
    from ._calcov import correlated_groups, raise_covariance

    groups = correlated_groups(cal)
    if groups is None or groups.covariance.shape != cov.shape:
        return cov
    # cov = T Tᵀ on its range (eigenvectors of its correlation matrix: unit-free)
    s = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    s = np.where(s > 0, s, 1.0)
    w, V = np.linalg.eigh(cov / np.outer(s, s))
    keep = w > 1e-13 * max(float(w[-1]), 1e-300)
    return raise_covariance(s[:, None] * V[:, keep] * np.sqrt(w[keep]), groups.covariance)


def calibration_axis_conditioning(cal) -> AxisConditioning | None:
    """[`axis_conditioning`][] of a calibration's final solve that holds the stage.

    The joint solve where there is one (camera, plane and stage uncertainty together;
    with the correlation of neighbouring stripe centres counted where they share their
    errors, as in `fit_diagnostics`), else the separate stage solve (camera and plane
    held fixed there, so their share is not included). None without a stage or a kept
    normal matrix.
    """
    fits = getattr(cal, "fits", {}) or {}
    fit = fits.get("joint", fits.get("stage"))
    if getattr(getattr(fit, "params", None), "stage", None) is None:
        return None
    data = getattr(cal, "data", None)
    cov = None
    if isinstance(data, CalibrationData) and data.table is not None:
        from ..core._stage_table import table_block_covariance

        # a table target: its own variance factor (a wobbling table's misfit would
        # otherwise scale the boards' share of the σ up with it)
        cov = table_block_covariance(fit, data)
    if cov is None:
        cov = _fit_covariance(fit)
    if cov is None:
        return None
    if fit is fits.get("joint"):
        cov = _with_correlated_centres(cal, cov)
    W, H = getattr(cal, "sensor_size", (0, 0))
    if not (W and H):
        return None
    fi = gw = None
    # not CalibrationData: a file read without its observations (no frame counts then)
    if isinstance(data, CalibrationData) and np.asarray(data.gauge_w).size:
        fi, gw = np.asarray(data.frame_index), np.asarray(data.gauge_w)
        table = getattr(data, "table", None)
        if not gw.any() and table is not None:  # no gauge scan: the table target's steps
            fi, gw = np.asarray(table.steps), np.asarray(table.w)
    return axis_conditioning(
        fit.params, fit.free_mask, cov, reference_pixels(W, H), frame_index=fi, gauge_weights=gw
    )
