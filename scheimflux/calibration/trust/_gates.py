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

from ..core._screen import _EDGE, excess_kurtosis

# Reprojection / stripe / gauge RMS above this many stated σ fail the gate.
RMS_FACTOR = 3.0
# Excess kurtosis of the residuals (0 for Gaussian, 3 for Laplace) above this fails.
KURTOSIS_LIMIT = 2.0
# More than this fraction of the corners or stripe points rejected fails the gate.
REJECT_FRACTION_LIMIT = 0.1
# Physical sanity. A focal length (px) below this fraction of the sensor's larger side
# is a field of view over 2 atan(1 / (2 · 0.1)) = 157° across it: wider than any lens
# the central camera models describe (a fisheye's equidistant f is ~0.3 of the side).
MIN_FOCAL_FRACTION = 0.1
# Pixels more than this far from square (fx / fy, either way): a 16:9 stream resized to
# 4:3 gives 0.75; no sensor or resize comes near 4.
MAX_ASPECT = 4.0
# A principal point more than this many sensor sizes beyond the sensor's edge (a model
# with its own sensor tilt, OpenCV's: the tilt does not move it there).
MAX_PRINCIPAL_OUTSIDE = 1.0
# Noise no real detector reaches on a sharp, in-focus image: corners scattering more
# than this (px per coordinate) or laser-line centres (px across the line) mean the
# model does not fit (or the wrong points were found), whatever the stated σ.
CORNER_SIGMA_LIMIT_PX = 1.0
STRIPE_SIGMA_LIMIT_PX = 2.0


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
    - `noise`: each residual group's σ as the calibration used it and as it was stated
      (`calibrate(noise="estimate")` estimates them from the data: `trust._variance`),
      and how far the joint solve moved the camera from its corners-only solve
      (`camera_shift`); `{}` where not recorded.
    """

    gates: tuple[Gate, ...]
    rejected: dict
    warnings: tuple[str, ...] = ()
    plane: dict | None = None
    hint: str | None = None
    noise: dict = dataclasses.field(default_factory=dict)

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
            **({"noise": dict(self.noise)} if self.noise else {}),
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
        if self.noise:
            lines.append("  " + _noise_line(self.noise))
        lines.extend(f"  warning: {w}" for w in self.warnings)
        return "\n".join(lines)


def _noise_line(noise: dict) -> str:
    """One line: the σ the calibration used per group, and the stated."""
    how = "estimated from the data" if noise.get("mode") == "estimate" else "as stated"
    text = (
        f"noise ({how}): corners {noise['corner_px']:.3g} px "
        f"(stated {noise['stated_corner_px']:g})"
    )
    px = [x for x in noise.get("stripe_px") or () if x is not None]
    if px:
        text += (
            f"; laser line {min(px):.3g}-{max(px):.3g} px across it per view "
            f"(stated {noise['stated_stripe_px']:g})"
        )
    if noise.get("gauge_px") is not None:
        text += f"; gauge scan {noise['gauge_px']:.3g} px"
    shift = noise.get("camera_shift")
    if shift:
        held = noise.get("held_corners_geometry", shift["moved"])
        how = "held at the corners' camera and poses" if held else "within the corners' σ"
        text += (
            f"; joint camera {how} (moved: chi-square {shift['d2']:.3g}, limit "
            f"{shift['limit']:.3g})"
        )
    return text


class QualityError(ValueError):
    """The calibration failed a quality gate; `.calibration` holds it for inspection."""

    def __init__(self, message: str, calibration):
        super().__init__(message)
        self.calibration = calibration


def _num(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


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


def focal_length_gate(fx_px: float, fy_px: float, width: int, height: int) -> Gate:
    """The focal lengths in pixels must be physical: at least `MIN_FOCAL_FRACTION` of the
    sensor's larger side, and within `MAX_ASPECT` of each other; value: the smaller
    focal length as a fraction of that side."""
    side = float(max(width, height))
    f_min = min(fx_px, fy_px)
    value = f_min / side if side > 0 and math.isfinite(f_min) else -math.inf
    aspect = max(fx_px, fy_px) / f_min if f_min > 0 else math.inf
    ok = bool(value >= MIN_FOCAL_FRACTION and aspect <= MAX_ASPECT)
    if ok:
        msg = ""
    elif not value >= MIN_FOCAL_FRACTION:
        fov = 2.0 * math.degrees(math.atan(side / (2.0 * f_min))) if f_min > 0 else 180.0
        msg = (
            f"focal length {fx_px:.4g} x {fy_px:.4g} px on a {width} x {height} px sensor "
            f"(a {fov:.0f}° field of view): no real lens; the solve collapsed (boards "
            "placed next to the lens): a wrong start or wrong points"
        )
    else:
        msg = (
            f"focal lengths {fx_px:.4g} and {fy_px:.4g} px differ {aspect:.2g}x: pixels this "
            "far from square exist on no sensor; the solve reached a wrong camera"
        )
    return Gate("focal length", ok, value, MIN_FOCAL_FRACTION, "of the sensor side", msg)


def principal_point_gate(cx: float, cy: float, width: int, height: int) -> Gate:
    """The principal point of a model with its own sensor tilt must lie within
    `MAX_PRINCIPAL_OUTSIDE` sensor sizes of the sensor; value: its distance outside the
    sensor in sensor sizes."""
    du = max(-cx, cx - width, 0.0) / max(width, 1)
    dv = max(-cy, cy - height, 0.0) / max(height, 1)
    out = math.hypot(du, dv) if math.isfinite(cx + cy) else math.inf
    ok = bool(out <= MAX_PRINCIPAL_OUTSIDE)
    msg = (
        ""
        if ok
        else f"principal point ({cx:.1f}, {cy:.1f}) px lies {out:.2g} sensor sizes off the "
        f"{width} x {height} px sensor: no real camera; the solve reached a wrong camera"
    )
    return Gate("principal point", ok, out, MAX_PRINCIPAL_OUTSIDE, "sensor sizes", msg)


def noise_gate(name: str, sigma: float, limit: float, unit: str, advice: str) -> Gate:
    """An estimated noise σ must stay below what real data reach (`limit`)."""
    ok = bool(math.isfinite(sigma) and sigma <= limit)
    msg = "" if ok else f"the {name} scatter {sigma:.3g} {unit} (at most {limit:g}): {advice}"
    return Gate(f"{name} noise", ok, sigma, limit, unit, msg)


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
