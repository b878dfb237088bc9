"""Quality gates: when a calibration is a success, and which observations it left out.

A solve that "converged" is not yet a calibration to measure with. Levenberg–Marquardt
converges just as happily from a bad start into a wrong camera (a nominal tilt that is
off, held fixed: 3.46 px reprojection RMS with the axis point 1,500 px below a 1,200 px
sensor). The gates below compare what the solve reached with what the data promise:

- **reprojection**: the corners' RMS reprojection error (px per coordinate) at most
  `RMS_FACTOR` × the stated corner σ; likewise the board **stripe** points' distance
  from their boards and the **gauge** points' distance from the gauge, against the
  stated stripe σ (in mm at the boards' distance).
- **axis point**: where the optical axis meets the sensor, `(x0, y0)` of the thick-lens
  model, lies on the sensor. (The paper's pinhole, eq. 14, absorbs a sensor tilt into
  its skew and principal point, which then lies far off the sensor — the paper's own
  Table 2 — so for it this is a warning, not a gate.)
- **tails**: the residuals left after the rejection pass are not heavy-tailed: their
  excess kurtosis is at most `KURTOSIS_LIMIT` (0 for Gaussian noise, 3 for Laplace).

Observations are screened before the solve (pixels outside the declared sensor are not
used, and counted) and after it (a rejection pass at `REJECT_SIGMA` robust standard
deviations; see [`outlier_masks`][]).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..io._observations import Observations, StageScan, near_centre, within_radius

# Reprojection / stripe / gauge RMS above this many stated σ fail the gate.
RMS_FACTOR = 3.0
# Residuals beyond this many robust standard deviations are rejected after the solve.
# For Gaussian noise a corner (2-D) is beyond 5 σ with probability exp(−12.5) ≈ 4e-6, a
# stripe point (1-D) with 6e-7: with 10⁴ observations, no good one is lost.
REJECT_SIGMA = 5.0
# Excess kurtosis of the residuals (0 for Gaussian, 3 for Laplace) above this fails.
KURTOSIS_LIMIT = 2.0
# More than this fraction of the corners or stripe points rejected fails the gate.
REJECT_FRACTION_LIMIT = 0.1
# Half a pixel beyond the outermost pixel centres: the sensor's edge.
_EDGE = 0.5


@dataclasses.dataclass(frozen=True)
class Gate:
    """One quality check: `value` against `limit` (`unit`); `message` says what to do if
    it failed, or why it passed where `value` is beyond `limit` (else it is empty)."""

    name: str
    passed: bool
    value: float
    limit: float
    unit: str
    message: str

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "passed": bool(self.passed),
            "value": _num(self.value),
            "limit": _num(self.limit),
            "unit": self.unit,
            "message": self.message,
        }


@dataclasses.dataclass(frozen=True)
class Quality:
    """The gates of a calibration, the observations it left out, and its warnings.

    **Fields:**
    - `gates`: every [`Gate`][] checked.
    - `rejected`: counts of left-out observations: `corners_outside_sensor`,
      `stripe_outside_sensor`, `gauge_outside_sensor` (before the solve), with a field
      radius also `field_radius_px`, `corners_beyond_radius`, `stripe_beyond_radius`,
      `gauge_beyond_radius` ([`screen_field`][]),
      `corner_outliers`, `stripe_outliers`, `gauge_outliers` (rejection pass; with a
      table target also `table_corner_outliers`, `table_stripe_outliers`), and the
      pass's `threshold_sigma`.
    - `warnings`: one-line notes that do not fail the calibration.
    - `plane`: the laser plane's conditioning ([`plane_conditioning`][]), or None.
    - `hint`: where a gate failed, what to check first (also among the warnings), or
      None.
    """

    gates: tuple[Gate, ...]
    rejected: dict
    warnings: tuple[str, ...] = ()
    plane: dict | None = None
    hint: str | None = None

    @property
    def passed(self) -> bool:
        return all(g.passed for g in self.gates)

    @property
    def failures(self) -> tuple[Gate, ...]:
        return tuple(g for g in self.gates if not g.passed)

    def to_dict(self) -> dict:
        return {
            "passed": self.passed,
            "gates": [g.to_dict() for g in self.gates],
            "rejected": dict(self.rejected),
            "warnings": list(self.warnings),
            "laser_plane": self.plane,
        }

    def summary(self) -> str:
        r = self.rejected
        k = r.get("threshold_sigma")
        beyond = f"beyond {k:g} robust σ" if k is not None else "no rejection pass:"
        lines = [
            "quality gates: " + ("passed" if self.passed else "FAILED"),
            *(
                f"  {'ok  ' if g.passed else 'FAIL'} {g.name:<13} {g.value:.4g} "
                f"(limit {g.limit:.4g} {g.unit})"
                + (f"; {g.message}" if g.passed and g.message else "")
                for g in self.gates
            ),
            "  left out: outside the sensor "
            f"{r.get('corners_outside_sensor', 0)} corners, "
            f"{r.get('stripe_outside_sensor', 0)} stripe and "
            f"{r.get('gauge_outside_sensor', 0)} gauge pixels; "
            + (
                f"beyond {r['field_radius_px']:g} px from the sensor's centre "
                f"{r.get('corners_beyond_radius', 0)} corners, "
                f"{r.get('stripe_beyond_radius', 0)} stripe and "
                f"{r.get('gauge_beyond_radius', 0)} gauge pixels; "
                if r.get("field_radius_px") is not None
                else ""
            )
            + f"{beyond} "
            f"{r.get('corner_outliers', 0)} corners, {r.get('stripe_outliers', 0)} stripe "
            f"and {r.get('gauge_outliers', 0)} gauge points"
            + (
                f"; on the table target {r['table_corner_outliers']} corners and "
                f"{r.get('table_stripe_outliers', 0)} laser-line points"
                if "table_corner_outliers" in r
                else ""
            ),
        ]
        lines.extend(f"  warning: {w}" for w in self.warnings)
        return "\n".join(lines)


class QualityError(ValueError):
    """The calibration failed a quality gate; `.calibration` holds it for inspection."""

    def __init__(self, message: str, calibration):
        super().__init__(message)
        self.calibration = calibration


def _num(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


# ----------------------------------------------------------------------------- screening


def _inside(px: np.ndarray, width: int, height: int) -> np.ndarray:
    """Rows of `px` `(N, 2)` that are finite and on the sensor."""
    u, v = px[:, 0], px[:, 1]
    with np.errstate(invalid="ignore"):
        return (
            np.isfinite(u)
            & np.isfinite(v)
            & (u >= -_EDGE)
            & (u <= width - _EDGE)
            & (v >= -_EDGE)
            & (v <= height - _EDGE)
        )


def screen_observations(obs: Observations) -> tuple[Observations, dict]:
    """Leave out every pixel outside the declared sensor, and count them.

    A pixel that is not on the sensor cannot have been observed by it: a stripe from a
    frame of another size, swapped `(v, u)` columns, or a detector's wild guess. Corners
    outside become "not detected" (NaN), stripe and gauge pixels are dropped.

    **Returns:** `(screened observations, counts)`; counts has `corners_outside_sensor`,
    `stripe_outside_sensor` and `gauge_outside_sensor`.
    """
    W, H = int(obs.width), int(obs.height)
    n_corner = n_stripe = n_gauge = 0
    views = []
    for view in obs.views:
        c = np.array(view.corners_px, dtype=np.float64).reshape(-1, 2)
        seen = np.all(np.isfinite(c), axis=1)
        bad_c = seen & ~_inside(c, W, H)
        c[bad_c] = np.nan
        s = np.asarray(view.stripe_px, dtype=np.float64).reshape(-1, 2)
        finite = np.all(np.isfinite(s), axis=1)
        keep = _inside(s, W, H)
        n_corner += int(bad_c.sum())
        n_stripe += int((finite & ~keep).sum())
        views.append(dataclasses.replace(view, corners_px=c, stripe_px=s[keep]))
    stage = obs.stage
    if stage is not None:
        frames = []
        for f in stage.frames:
            f = np.asarray(f, dtype=np.float64).reshape(-1, 2)
            keep = _inside(f, W, H)
            n_gauge += int((np.all(np.isfinite(f), axis=1) & ~keep).sum())
            frames.append(f[keep])
        stage = StageScan(stage.delta_omega_deg, stage.gauge_radius_mm, frames)
    counts = {
        "corners_outside_sensor": n_corner,
        "stripe_outside_sensor": n_stripe,
        "gauge_outside_sensor": n_gauge,
    }
    return dataclasses.replace(obs, views=views, stage=stage), counts


def screen_field(obs: Observations, radius_px: float) -> tuple[Observations, dict]:
    """Leave out every pixel farther than `radius_px` from the sensor's centre, and count
    them: a calibration inside the part of the field the user trusts (e.g. where the lens
    does not vignette: there a clipped ray bundle's centroid is not the image of one ray,
    docs/noncentral.md).

    The centre is the middle of the sensor, `((width − 1) / 2, (height − 1) / 2)`.
    Corners beyond the radius become "not detected" (NaN); stripe, gauge and table-target
    laser-line pixels are dropped; table-target corners become NaN.

    **Returns:** `(screened observations, counts)`; counts has `field_radius_px` and
    `corners_beyond_radius`, `stripe_beyond_radius`, `gauge_beyond_radius` (table-target
    corners and line pixels are counted with the corners and the stripe).

    **Raises:** `ValueError` for a radius that is not a positive finite number.
    """
    try:
        radius = float(radius_px)
    except (TypeError, ValueError):
        raise ValueError(
            f"the field radius must be a number of pixels, got {radius_px!r}"
        ) from None
    if not (math.isfinite(radius) and radius > 0):
        raise ValueError(f"the field radius must be a positive number of pixels, got {radius_px!r}")
    def near(px):
        return near_centre(obs, np.asarray(px, dtype=np.float64).reshape(-1, 2), radius)

    def n_corners(views_px):
        return sum(int(np.all(np.isfinite(c), axis=-1).sum()) for c in views_px)

    cut = within_radius(obs, radius)
    n_corner = n_corners(v.corners_px for v in obs.views) - n_corners(
        v.corners_px for v in cut.views
    )
    n_stripe = sum(len(v.stripe_px) for v in obs.views) - sum(len(v.stripe_px) for v in cut.views)
    n_gauge = 0
    stage = obs.stage
    if stage is not None:
        frames = [np.asarray(f, dtype=np.float64).reshape(-1, 2) for f in stage.frames]
        kept = [f[near(f)] for f in frames]
        n_gauge = sum(len(f) for f in frames) - sum(len(f) for f in kept)
        stage = StageScan(stage.delta_omega_deg, stage.gauge_radius_mm, kept)
    table = obs.stage_target
    if table is not None:
        c = np.array(table.corners_px, dtype=np.float64)
        seen = np.all(np.isfinite(c), axis=-1)
        far = seen & ~near(c).reshape(seen.shape)
        c[far] = np.nan
        lines = [np.asarray(s, dtype=np.float64).reshape(-1, 2) for s in table.stripe_px]
        kept = tuple(s[near(s)] for s in lines)
        n_corner += int(far.sum())
        n_stripe += sum(len(s) for s in lines) - sum(len(s) for s in kept)
        table = dataclasses.replace(table, corners_px=c, stripe_px=kept)
    counts = {
        "field_radius_px": radius,
        "corners_beyond_radius": n_corner,
        "stripe_beyond_radius": n_stripe,
        "gauge_beyond_radius": n_gauge,
    }
    return dataclasses.replace(cut, stage=stage, stage_target=table), counts


# ----------------------------------------------------------------------------- outliers


def robust_sigma(r: np.ndarray) -> float:
    """1.4826 × the median absolute residual: σ of Gaussian noise, blind to outliers."""
    r = np.asarray(r, dtype=np.float64)
    return float(1.4826 * np.median(np.abs(r))) if r.size else math.nan


def outlier_masks(
    corner_err_px: np.ndarray,
    corner_w: np.ndarray,
    stripe_r: np.ndarray,
    stripe_w: np.ndarray,
    gauge_r: np.ndarray | None = None,
    gauge_w: np.ndarray | None = None,
    *,
    threshold: float = REJECT_SIGMA,
    corner_sigma: float = 0.0,
    sigma: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Which observations lie beyond `threshold` robust standard deviations.

    Corners: the length `e` of the reprojection error; for 2-D Gaussian noise of σ per
    coordinate `e` is Rayleigh-distributed with median σ √(2 ln 2), so σ̂ =
    median(e) / 1.1774 and a corner is out when `e > threshold · σ̂`. Stripe and gauge
    points: a signed distance, σ̂ = 1.4826 · median |r| ([`robust_sigma`][]). The scale
    is the larger of σ̂ and the stated σ (`corner_sigma` px; `sigma` in the units of the
    stripe and gauge residuals): a stated σ that is too small does not reject good data,
    and nearly noise-free data (σ̂ ≪ σ) do not lose their largest model residuals.

    **Arguments:** the corner errors `(V, M, 2)` px with weights `(V, M)`; the stripe
    residuals and weights `(V, K)`; optionally the gauge residuals and weights `(F, L)`.

    **Returns:** boolean masks (True: reject) of the corner, stripe and gauge shapes.
    """
    used = corner_w > 0
    e = np.linalg.norm(corner_err_px, axis=-1)
    s = float(np.median(e[used])) / math.sqrt(2 * math.log(2)) if used.any() else math.inf
    corner_out = used & (e > threshold * max(s, corner_sigma))

    def scalar(r, w):
        u = w > 0
        if not u.any():
            return np.zeros(r.shape, bool)
        return u & (np.abs(r) > threshold * max(robust_sigma(r[u]), sigma))

    gauge_out = None if gauge_r is None else scalar(gauge_r, gauge_w)
    return corner_out, scalar(stripe_r, stripe_w), gauge_out


def excess_kurtosis(r: np.ndarray) -> float:
    """`mean(r⁴) / mean(r²)² − 3` about zero (0 for Gaussian noise)."""
    r = np.asarray(r, dtype=np.float64)
    m2 = float(np.mean(r**2)) if r.size else 0.0
    if m2 == 0.0:
        return 0.0
    return float(np.mean(r**4) / m2**2 - 3.0)


# ----------------------------------------------------------------------------- the plane


def plane_conditioning(
    points: np.ndarray, view: np.ndarray, sigma_mm: float, *, min_spread: float = 20.0
) -> dict:
    """How well the board stripe points determine the laser plane; raises if they do not.

    The points of one board pose lie on one line (the board ∩ the laser plane), and a
    line leaves the plane free to turn about it. With `s₀ ≥ s₁ ≥ s₂` the singular values
    of the centred points `(N, 3)`, `s₁ / √N` is their RMS spread across the best line
    within the plane. A total-least-squares plane through N points with noise σ normal
    to it has its normal tilted by σ / s_k (rad) about the k-th in-plane axis, and its
    offset uncertain by σ / √N: these are the predicted σ reported.

    **Arguments:**
    - `points` `(N, 3)` mm and the board view of each, `view` `(N,)`.
    - `sigma_mm`: the stripe points' noise (mm).
    - `min_spread`: the spread across the line must be at least this many σ.

    **Returns:** a JSON-ready dict: `n_points`, `n_views`, `singular_values`,
    `spread_across_line_mm`, `normal_sigma_rad` (about the weak and the strong in-plane
    axis), `offset_sigma_mm`.
    """
    points = np.asarray(points, dtype=np.float64)
    views = np.unique(np.asarray(view))
    if len(views) < 2:
        raise ValueError(
            f"the laser line was seen on {len(views)} board pose(s): a plane needs the line "
            "on at least 2 board poses at different depths or tilts (one line leaves the "
            "plane free to turn about it); add views with the laser on the board"
        )
    n = len(points)
    s = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    spread = float(s[1] / math.sqrt(n))
    info = {
        "n_points": int(n),
        "n_views": int(len(views)),
        "singular_values": [float(x) for x in s],
        "spread_across_line_mm": spread,
        "normal_sigma_rad": [float(sigma_mm / s[1]), float(sigma_mm / s[0])],
        "offset_sigma_mm": float(sigma_mm / math.sqrt(n)),
    }
    if not spread >= min_spread * sigma_mm:
        raise ValueError(
            f"the stripe points of the {len(views)} board poses lie on one line (spread "
            f"across it {spread * 1e3:.3g} µm, {spread / sigma_mm:.2g} × the stripe σ "
            f"{sigma_mm * 1e3:.3g} µm; need {min_spread:g} ×): the laser plane is not "
            "determined; use board poses at different depths or tilts"
        )
    return info


def board_plane_angles_deg(board_normals: np.ndarray, plane_normal: np.ndarray) -> np.ndarray:
    """Angle (deg) between each board plane and the laser plane."""
    nb = board_normals / np.linalg.norm(board_normals, axis=-1, keepdims=True)
    nl = plane_normal / np.linalg.norm(plane_normal)
    c = np.clip(np.abs(nb @ nl), 0.0, 1.0)
    return np.degrees(np.arccos(c))


# ----------------------------------------------------------------------------- gates


def rms_gate(name: str, rms: float, sigma: float, unit: str, advice: str) -> Gate:
    limit = RMS_FACTOR * sigma
    ok = bool(math.isfinite(rms) and rms <= limit)
    msg = (
        ""
        if ok
        else f"{name} RMS {rms:.4g} {unit} is {rms / sigma:.3g}× the stated σ "
        f"{sigma:.3g} {unit} (limit {RMS_FACTOR:g}×): {advice}"
    )
    return Gate(name, ok, rms, limit, unit, msg)


def axis_point_gate(x0: float, y0: float, width: int, height: int) -> Gate:
    """The axis point `(x0, y0)` must lie on the sensor; value: its distance outside (px)."""
    du = max(-_EDGE - x0, x0 - (width - _EDGE), 0.0)
    dv = max(-_EDGE - y0, y0 - (height - _EDGE), 0.0)
    out = math.hypot(du, dv) if math.isfinite(x0 + y0) else math.inf
    ok = out == 0.0
    msg = (
        ""
        if ok
        else f"axis point (x0, y0) = ({x0:.1f}, {y0:.1f}) px lies outside the {width} × "
        f"{height} px sensor: the solve reached a wrong camera; try --init closed-form or "
        "check the nominal tilt and magnification"
    )
    return Gate("axis point", ok, out, 0.0, "px outside", msg)


def sensor_side_gate(z0: float) -> Gate:
    """The sensor must lie behind the lens (`z0 > 0`); value: `z0` (mm).

    Planar boards and a laser plane cannot tell the camera from its mirror image through
    the lens (sensor in front, e and the tilt negated, everything it sees behind it): the
    same pixel rays. A solve that reached the mirror is refused here, with what to do,
    rather than by the calibration file's schema."""
    ok = bool(math.isfinite(z0) and z0 > 0)
    msg = (
        ""
        if ok
        else f"the solve reached the mirror image of the camera (z0 = {z0:.4g} mm: the "
        "sensor in front of the lens, the boards behind it; planar targets cannot tell "
        "the two apart): a wrong start; give the nominal focal length, magnification and "
        "tilt (--focal-length-mm, --magnification, --tilt-deg)"
    )
    return Gate("sensor behind the lens", ok, z0, 0.0, "mm z0", msg)


def tails_gate(name: str, r: np.ndarray) -> Gate:
    """Heavy tails of residuals `r` in units of their stated σ.

    Fails when the excess kurtosis exceeds the limit while the residuals are not within
    the stated noise (RMS > 1): tails of residuals far below the noise (nearly
    noise-free data and a small model error) bias nothing that matters.
    """
    r = np.asarray(r, dtype=np.float64)
    k = excess_kurtosis(r)
    # the sampling σ of the excess kurtosis of n Gaussian values is √(24 / n): a limit
    # of 2 is > 10 such σ once n ≥ 600; below that, allow 5 of them
    limit = max(KURTOSIS_LIMIT, 5.0 * math.sqrt(24.0 / max(len(r), 1)))
    rms = float(np.sqrt(np.mean(r**2))) if r.size else 0.0
    ok = bool(k <= limit or rms <= 1.0)
    msg = (
        (
            ""
            if k <= limit
            else f"passed: heavy tails within the stated noise (residual RMS {rms:.2g} σ)"
        )
        if ok
        else f"{name} residuals are heavy-tailed after the rejection pass (excess kurtosis "
        f"{k:.3g} > {limit:.3g}): outliers or a model error remain; check the detections "
        "or use a distortion model"
    )
    return Gate(f"{name} tails", ok, k, limit, "excess kurtosis", msg)


def fraction_gate(name: str, rejected: int, total: int) -> Gate:
    frac = rejected / total if total else 0.0
    ok = frac <= REJECT_FRACTION_LIMIT
    msg = (
        ""
        if ok
        else f"{rejected} of {total} {name} ({100 * frac:.3g} %) were rejected as outliers "
        f"(limit {100 * REJECT_FRACTION_LIMIT:g} %): the model does not describe the data; "
        "check the detections, the sensor size and the camera model"
    )
    return Gate(f"{name} rejected", ok, frac, REJECT_FRACTION_LIMIT, "fraction", msg)
