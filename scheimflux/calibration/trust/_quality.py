"""The quality gates of a finished calibration (see `scheimflux.calibration.trust._gates`)."""

from __future__ import annotations

import dataclasses
import math

import jax
import numpy as np

from ...camera._noncentral import ThickLensNonCentral
from ...camera._opencv import OpenCVCamera
from ...camera._pinhole import Pinhole
from ...camera._thick_lens import ThickLensScheimpflug
from ...geometry._coverage import clip_to_radius, coverage_from_data
from ..core._plane import stripe_sigma_rms_mm
from ..core._rejection import _block_residuals
from ..core._result import Calibration
from ..core._screen import board_plane_angles_deg
from ._gates import (
    CORNER_SIGMA_LIMIT_PX,
    STRIPE_SIGMA_LIMIT_PX,
    Quality,
    QualityError,
    axis_point_gate,
    focal_length_gate,
    fraction_gate,
    noise_gate,
    principal_point_gate,
    rms_gate,
    sensor_side_gate,
    tails_gate,
)
from ._stage_warning import axis_warning, calibration_axis_conditioning


def _gated(
    cal: Calibration,
    rejected: dict,
    conditioning,
    throw: bool,
    notes: tuple[str, ...] = (),
    hint=None,
    noise: dict | None = None,
) -> Calibration:
    """`cal` with its quality gates assessed and its coverage of the sensor recorded;
    `QualityError` (with `throw`) if a gate fails. `notes`: the solves' decisions and
    findings (the pupil terms' test, the gauge profile's), added to the warnings.
    `hint`: what to check first, said (in the error and the warnings) only when a gate
    fails: a string, None, or a sequence of them and of functions that return one (run
    only then). `noise`: the σ used and stated (`Quality.noise`)."""
    quality = assess_quality(cal, rejected, conditioning, noise)
    hint = None if quality.passed else _hint_text(hint)
    if hint is not None:
        notes = (*notes, hint)
        quality = dataclasses.replace(quality, hint=hint)
    if notes:
        quality = dataclasses.replace(quality, warnings=quality.warnings + tuple(notes))
    coverage = coverage_from_data(cal.data, cal.sensor_size)
    radius = rejected.get("field_radius_px")
    if coverage is not None and radius is not None:
        coverage = clip_to_radius(coverage, radius)
    cal = dataclasses.replace(cal, quality=quality, coverage=coverage)
    if throw and not quality.passed:
        raise QualityError(
            "calibration failed its quality gates: "
            + "; ".join(g.message for g in quality.failures)
            + ("" if hint is None else f"; {hint}"),
            cal,
        )
    return cal


def _hint_text(hint) -> str | None:
    """`_gated`'s `hint` as one string (None when it says nothing)."""
    items = hint if isinstance(hint, (list, tuple)) else (hint,)
    texts = [h() if callable(h) else h for h in items]
    texts = [t for t in texts if t]
    return "; ".join(texts) if texts else None


# A board within this angle of the laser plane carries a poorly determined stripe line.
WEAK_BOARD_ANGLE_DEG = 5.0


# Neighbouring stripe centres whose errors correlate this much (τ = 1 + 2 Σ ρ_k, the
# factor by which the variance of a mean of many neighbours exceeds the independent one)
# are named: the calibration's σ assume independent centres.
CORRELATION_TAU_WARN = 2.0
# The residual groups of `metrology._calcov` (`Diagnostics.correlation_time`'s keys) by
# the names the warning gives them.
_GROUP = {"board stripes": "stripes"}


def correlated_centres_warning(
    blocks, *, counted: bool = False, taus: dict | None = None
) -> str | None:
    """A warning when neighbouring centres along the laser lines share their errors.

    `blocks`: `(name, residuals (rows, L), used (rows, L))`, each row one line's centres
    in order (a view's board stripe, a gauge frame). Centres extracted from images are one
    per scan line, each from a filter several pixels wide (and JPEG's 8 × 8 blocks): on
    rendered colour-JPEG captures (tessar ×1) the gauge residuals had ρ₁ = 0.88, ρ₂ = 0.63,
    and a second ring measured 3 σ off with independent centres. With `counted` (a joint
    solve) the calibration's σ count the correlation ([`fit_diagnostics`][] raises its
    covariance to the sandwich with a banded residual covariance, as the budgets of
    `measure` and `verify`, `metrology._calcov`), and the warning says so, with the τ
    those σ use where `taus` gives them (`{group: τ}` of the group covariance, its
    residuals standardised by their pixel gains: the plain lag correlations here read a
    different τ, 9.03 for its 9.30 on a colour-JPEG capture); without it (a
    sequential calibration, or where the joint solve's group covariance finds no lag)
    they count the centres as independent and it says by how much they can be too
    small. Lag correlations as there (`residual_lag_correlation`);
    simulated independent noise stays below them."""
    from ._calcov import residual_lag_correlation

    parts, worst = [], 1.0
    for name, r, used in blocks:
        used = np.asarray(used, bool)
        if not used.any():
            continue
        z = np.where(used, np.asarray(r, np.float64), 0.0)
        rho = residual_lag_correlation(np.pad(z, ((0, 0), (0, 1))).reshape(-1))
        tau = 1.0 + 2.0 * float(np.sum(rho))
        if tau >= CORRELATION_TAU_WARN:
            if counted and taus:
                tau = float(taus.get(_GROUP.get(name, name), tau))
            parts.append(f"{name} rho1 = {rho[0]:.2f}, tau = {tau:.3g}")
            worst = max(worst, tau)
    if not parts:
        return None
    said = f"neighbouring stripe centres share their errors ({'; '.join(parts)})"
    if counted:
        return (
            f"{said}: counted in the σ of this calibration (laser plane, table axis, every "
            "parameter the lines determine; banded residual covariance, "
            "diagnostics.uncertainty.correlation_time) and in the uncertainty budgets of "
            "measure and verify"
        )
    return (
        f"{said}: the σ of this calibration (laser plane, table axis, every parameter the "
        f"lines determine) count them as independent and can be up to {np.sqrt(worst):.2g}x "
        "(sqrt tau) too small; the uncertainty budgets of measure and verify include the "
        "correlation"
    )


def _other_start(init: str) -> str:
    """The other camera start to suggest after a failure from `init`."""
    return "the nominal tilt (--init nominal)" if init == "closed-form" else "--init closed-form"


def assess_quality(
    cal: Calibration, rejected: dict, plane_info: dict | None, noise: dict | None = None
) -> Quality:
    """The quality gates of a calibration (see `scheimflux.calibration.trust._gates`).

    `noise` (`Quality.noise`): with `mode` `"estimate"` the σ of the data are the
    estimated ones, so the RMS gates (residuals against σ) would pass by construction:
    the estimated σ are judged against what real data reach instead, and a σ far from
    the stated one is a warning."""
    params, data = cal.params, cal.data
    W, H = cal.sensor_size
    noise = dict(noise or {})
    estimated = noise.get("mode") == "estimate"
    sigma_c = float(data.sigma_corner_px)
    sigma_s = float(data.sigma_stripe_mm)
    fit_advice = (
        "the camera model does not fit the corners (a bad start converged to a wrong "
        "camera, a missing distortion model, or a wrong --sigma-corner-px); try "
        + _other_start(cal.init)
    )
    warnings = []
    if estimated:
        gates = [noise_gate("corner", sigma_c, CORNER_SIGMA_LIMIT_PX, "px", fit_advice)]
        note = _stated_note("corners", sigma_c, noise.get("stated_corner_px"), "--sigma-corner-px")
        if note:
            warnings.append(note)
    else:
        gates = [rms_gate("reprojection", cal.reprojection_rms_px, sigma_c, "px", fit_advice)]
    err, stripe, gauge = _block_residuals(params, data)
    cw, sw, gw = (np.asarray(w) > 0 for w in (data.corner_w, data.stripe_w, data.gauge_w))
    gates.append(tails_gate("corner", (err / sigma_c)[cw].reshape(-1)))
    n_out = int(rejected.get("corner_outliers", 0) or 0)
    gates.append(fraction_gate("corners", n_out, int(cw.sum()) + n_out))
    if params.plane is not None and sw.any():
        if estimated and noise.get("stripe_px") is not None:
            px = np.array([np.nan if x is None else x for x in noise["stripe_px"]])
            worst = int(np.nanargmax(px))
            gates.append(
                noise_gate(
                    "stripe",
                    float(px[worst]),
                    STRIPE_SIGMA_LIMIT_PX,
                    "px",
                    f"view {worst}'s laser-line points lie that far off its board's plane "
                    "(points off the board, a bent board, reflections, or the line of "
                    "another view)",
                )
            )
            med = float(np.nanmedian(px))
            note = _stated_note(
                "laser-line centres", med, noise.get("stated_stripe_px"), "--sigma-stripe-px"
            )
            if note:
                warnings.append(note + " (median over the views)")
        else:
            gates.append(
                rms_gate(
                    "stripe",
                    cal.plane_rms_mm,
                    stripe_sigma_rms_mm(data),
                    "mm",
                    "the board stripe points do not lie on one laser plane (stripes from the "
                    "wrong views, reflections, or a wrong --sigma-stripe-px; the σ is each "
                    "view's pixel σ as it moves the points off their boards, "
                    "diagnostics.stripe_gain)",
                )
            )
        gates.append(tails_gate("stripe", stripe[sw]))
        n_out = int(rejected.get("stripe_outliers", 0) or 0)
        gates.append(fraction_gate("stripe points", n_out, int(sw.sum()) + n_out))
        views = np.flatnonzero(sw.any(axis=1))
        R = np.asarray(jax.vmap(lambda p: p.R)(params.board_poses))
        angles = board_plane_angles_deg(R[views, :, 2], np.asarray(params.plane.n))
        weak = views[angles < WEAK_BOARD_ANGLE_DEG]
        if len(weak):
            warnings.append(
                f"weak geometry: boards of views {weak.tolist()} lie within "
                f"{WEAK_BOARD_ANGLE_DEG:g}° of the laser plane (smallest "
                f"{float(angles.min()):.2g}°): their stripe lines are poorly determined; "
                "tilt the boards against the laser plane"
            )
    if cal.gauge_rms_mm is not None and estimated and noise.get("gauge_px") is not None:
        gates.append(
            noise_gate(
                "gauge",
                float(noise["gauge_px"]),
                STRIPE_SIGMA_LIMIT_PX,
                "px",
                "the gauge scan does not fit a cylinder of the gauge radius about the table "
                "axis (wrong gauge radius, or Δω)",
            )
        )
    elif cal.gauge_rms_mm is not None:
        gates.append(
            rms_gate(
                "gauge",
                cal.gauge_rms_mm,
                sigma_s,
                "mm",
                "the gauge scan does not fit a cylinder of the gauge radius about the table "
                "axis (wrong gauge radius, or Δω)",
            )
        )
    lines = []
    if params.plane is not None:
        lines = [("board stripes", stripe, sw), ("gauge", gauge, gw)]
    note = correlated_centres_warning(lines)
    if note is not None:
        from ._calcov import correlated_groups

        # the joint solve's σ count the correlation where its group covariance finds it
        # (cached for fit_diagnostics, which states those σ)
        groups = correlated_groups(cal)
        if groups is not None:
            note = correlated_centres_warning(
                lines, counted=True, taus=dict(groups.correlation_time)
            )
        warnings.append(note)
    note = axis_warning(calibration_axis_conditioning(cal))
    if note is not None:
        warnings.append(note)
    cam = params.camera
    gates.extend(physical_gates(cam, W, H))
    if isinstance(cam, (ThickLensScheimpflug, ThickLensNonCentral)):
        gates.append(axis_point_gate(float(cam.x0), float(cam.y0), W, H))
        gates.append(sensor_side_gate(float(cam.z0)))
    elif isinstance(cam, Pinhole):
        g = axis_point_gate(float(cam.x0), float(cam.y0), W, H)
        if not g.passed:
            warnings.append(
                f"the pinhole's principal point ({float(cam.x0):.1f}, {float(cam.y0):.1f}) "
                "px lies off the sensor: expected for a tilted sensor, which the pinhole "
                "(paper eq. 14) absorbs into skew and principal point; the thick-lens "
                "model describes it"
            )
    for name, fit in cal.fits.items():
        if not fit.converged:
            warnings.append(f"the {name} solve did not converge ({fit.message})")
    if not cal.joint and rejected.get("threshold_sigma") is not None:
        warnings.append("outliers are counted but not left out without the joint solve")
    return Quality(tuple(gates), dict(rejected), tuple(warnings), plane_info, noise=noise)


def physical_gates(cam, width: int, height: int) -> list:
    """The gates no real camera fails: a focal length (px) of a physical lens and, for
    OpenCV's model (which has its own sensor tilt), a principal point near the sensor."""
    if width <= 0 or height <= 0:
        return []
    if isinstance(cam, OpenCVCamera):
        fx, fy = float(cam.fx), float(cam.fy)
        return [
            focal_length_gate(fx, fy, width, height),
            principal_point_gate(float(cam.cx), float(cam.cy), width, height),
        ]
    if isinstance(cam, Pinhole):
        return [focal_length_gate(float(cam.alpha), float(cam.beta), width, height)]
    if isinstance(cam, (ThickLensScheimpflug, ThickLensNonCentral)):
        return [focal_length_gate(float(cam.f / cam.dx), float(cam.f / cam.dy), width, height)]
    return []


# A stated σ this many times off the data's is said (the calibration uses the data's).
STATED_RATIO_NOTE = 3.0


def _stated_note(what: str, sigma: float, stated, option: str) -> str | None:
    """A note where the data's σ is far from the stated one."""
    if stated is None or not stated > 0 or not math.isfinite(sigma):
        return None
    ratio = sigma / float(stated)
    if 1.0 / STATED_RATIO_NOTE <= ratio <= STATED_RATIO_NOTE:
        return None
    return (
        f"the {what} scatter {sigma:.3g} px, {ratio:.2g}x the stated {float(stated):g} px "
        f"({option}): the calibration weights them by the scatter the data show"
    )
