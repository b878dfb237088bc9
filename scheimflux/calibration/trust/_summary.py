"""The text summary of a calibration, as `scheimflux calibrate` prints it.

`scheimflux.calibration.calibration_summary` is the whole printout; [`format_summary`][]
formats the
calibration document (the dict written to CAL.json), [`format_trust`][] the σ of the free
parameters, the warnings, the quality gates and the left-out observations, and
[`trust_entries`][] the file's entries for those.
"""

from __future__ import annotations

from ._stage_warning import calibration_axis_conditioning
from ._uncertainty import fit_diagnostics

__all__ = ["CAMERA_ONLY_NOTE", "format_summary", "format_trust", "trust_entries"]

CAMERA_ONLY_NOTE = (
    "note: no stripe pixels on the board views: camera-only calibration (no laser "
    "plane; good for export --opencv, not for reconstruct)"
)


def _num(v, scale: float, spec: str) -> str:
    return "n/a" if v is None else format(v * scale, spec)


_UNIT_LABEL = {"mm": "mm", "deg": "deg", "px": "px", "1": ""}


def format_summary(doc: dict, *, frozen: tuple = ()) -> str:
    """Readable summary of a calibration document (as written to CAL.json).

    **Arguments:**
    - `doc`: the calibration as a JSON-ready dict
      (`scheimflux.calibration.calibration_to_dict`, or a calibration file read as JSON).
    - `frozen`: parameter paths to mark `(fixed)`; by default the document's own
      `diagnostics.frozen`.

    **Returns:** the text: model, camera parameters (with units), laser plane, stage,
    RMS figures, the solves and the frozen set, one item a line.
    """
    lines = []
    d = doc.get("diagnostics", {})
    cam = doc["camera"]
    dist = cam["distortion"]
    joint = "joint" if d.get("joint") else "separate steps"
    lines.append(
        f"model: {doc['model']}, distortion: {dist['model']}, init: {d.get('init')}, {joint}"
    )
    frozen = set(frozen or d.get("frozen", ()))

    def fmt(path, name, entry):
        unit = _UNIT_LABEL.get(entry["unit"], entry["unit"])
        mark = "  (fixed)" if path in frozen or path.rsplit(".", 1)[0] in frozen else ""
        return f"  {name:<6} = {entry['value']:>16.8g} {unit:<3}{mark}"

    lines.append("camera:")
    for name, entry in cam.items():
        if name != "distortion":
            lines.append(fmt(f"camera.{name}", name, entry))
    for name, entry in dist.items():
        if name != "model":
            lines.append(fmt(f"camera.distortion.{name}", name, entry))
    pl = doc.get("laser_plane")
    if pl is None:
        lines.append("laser plane: none (camera-only calibration)")
    else:
        n = ", ".join(f"{x:.6f}" for x in pl["unit_normal"])
        lines.append(
            f"laser plane: unit normal ({n}), distance {pl['distance_mm']:.4f} mm "
            f"(n = [{', '.join(f'{x:.6e}' for x in pl['n_per_mm'])}] 1/mm)"
        )
    st = doc.get("stage")
    if st is not None:
        lines.append("stage (camera -> measurement):")
        for i, row in enumerate(st["R_m_c"]):
            label = "R_m_c =" if i == 0 else ""
            lines.append(f"  {label:<8}[{', '.join(f'{x:+.8f}' for x in row)}]")
        t = ", ".join(f"{x:.5f}" for x in st["t_m_c_mm"])
        lines.append(f"  t_m_c = [{t}] mm, delta omega = {st['delta_omega_deg']:.6g} deg")
        if st.get("gauge_eccentricity_mm") is not None and d.get("gauge_rms_mm") is not None:
            ex, ey = st["gauge_eccentricity_mm"]
            lines.append(f"  gauge eccentricity = ({ex * 1e3:.2f}, {ey * 1e3:.2f}) um")
        tt = d.get("table_target")
        if isinstance(tt, dict):
            lines.append(
                f"  table target: {len(tt.get('steps', []))} table steps, reprojection RMS "
                f"{_num(tt.get('rms_px'), 1.0, '.4f')} px"
            )
    else:
        lines.append("stage: not calibrated (no rotary-stage scan in the observations)")
    lines.append(f"reprojection RMS: {_num(d.get('reprojection_rms_px'), 1.0, '.4f')} px")
    lines.append(f"laser-plane fit RMS: {_num(d.get('laser_plane_rms_mm'), 1e3, '.3f')} um")
    stripe_sigma = _stripe_sigma_line(d)
    if stripe_sigma:
        lines.append(stripe_sigma)
    if d.get("gauge_rms_mm") is not None:
        lines.append(f"gauge RMS: {_num(d['gauge_rms_mm'], 1e3, '.3f')} um")
    for name, s in d.get("solves", {}).items():
        ok = "converged" if s["converged"] else f"NOT converged ({s.get('message', '')})"
        if s.get("remaining_step_sigma") is not None:
            ok += (f" (step limit reached {s['remaining_step_sigma']:.1e} σ from the "
                   "optimum)")  # fmt: skip
        lines.append(f"solve {name:<7}: {s['steps']:>4} steps, {s['time_s']:7.2f} s, {ok}")
    lines.append(f"frozen: {', '.join(d.get('frozen', [])) or '(none)'}")
    return "\n".join(lines)


def _stripe_sigma_line(d: dict) -> str:
    """`"stripe σ off the boards: …"`: each view's σ of its stripe points' distances
    from its board, as the stripe gate took them (`stripe_gain`, `stripe_sigma_scale`
    and `sigma_stripe_mm` of the diagnostics); "" where the file has no gains."""
    gain, s_mm = d.get("stripe_gain"), d.get("sigma_stripe_mm")
    if not isinstance(gain, list) or not gain or not isinstance(s_mm, (int, float)):
        return ""
    scale = d.get("stripe_sigma_scale") or [1.0] * len(gain)
    sigma = [s_mm * a * b * 1e3 for a, b in zip(scale, gain)]
    own = (
        f" × {min(scale):.2g}-{max(scale):.2g} (views' own noise, stripe_sigma_px)"
        if max(scale) > 1.0
        else ""
    )
    return (
        f"stripe σ off the boards (the stripe gate's): {min(sigma):.3g}-{max(sigma):.3g} um "
        f"per view = {s_mm * 1e3:.3g} um (the stated pixel σ at a pixel's footprint){own} "
        f"× {min(gain):.2g}-{max(gain):.2g} (a pixel's error moved off its board)"
    )


def _uncertainty(cal):
    """The final solve's parameter diagnostics, or None where the solve kept no JᵀJ."""
    fits = getattr(cal, "fits", {}) or {}
    final = fits.get("joint", fits.get("camera"))
    if final is None or getattr(final, "normal_matrix", None) is None:
        return None
    return fit_diagnostics(cal)


def _joint_plane_sigma(diag) -> str:
    """`"; with them (this solve): sigma of the normal … urad, of the offset … um"` from the
    solve's covariance of `plane.n` (n = unit normal / distance), or `""` without it."""
    import math

    import numpy as np

    if diag is None:
        return ""
    idx = diag.select("plane.n")
    if len(idx) != 3:
        return ""
    n = np.asarray(diag.values, dtype=np.float64)[idx]
    C = np.asarray(diag.covariance, dtype=np.float64)[np.ix_(idx, idx)]
    norm = float(np.linalg.norm(n))
    if not (np.all(np.isfinite(C)) and norm > 0):
        return ""
    u = n / norm
    P = np.eye(3) - np.outer(u, u)  # a change of n across u turns the normal by dn / |n|
    turn = np.sqrt(np.clip(np.linalg.eigvalsh(P @ C @ P)[1:], 0.0, None)) / norm
    offset = math.sqrt(max(float(u @ C @ u), 0.0)) / norm**2  # distance 1 / |n|
    return (
        f"; with them (this solve's covariance): sigma of the normal "
        f"{turn[1] * 1e6:.3g} / {turn[0] * 1e6:.3g} urad, of the offset {offset * 1e3:.3g} um"
    )


def trust_entries(cal) -> dict:
    """The calibration file's `uncertainty` and `quality` entries (its diagnostics section).

    **Arguments:**
    - `cal`: a `Calibration` (or anything with its `fits` and `quality`).

    **Returns:** `{"uncertainty": Diagnostics.to_dict(), "quality": Quality.to_dict()}`,
    each present only where the calibration has it (the final solve kept its `JᵀJ`; the
    gates were assessed).
    """
    out = {}
    diag = _uncertainty(cal)
    if diag is not None:
        out["uncertainty"] = diag.to_dict()
    quality = getattr(cal, "quality", None)
    if quality is not None:
        out["quality"] = quality.to_dict()
    axis = calibration_axis_conditioning(cal)
    if axis is not None:
        out["stage_axis"] = axis.to_dict()
    return out


def format_trust(cal) -> str:
    """σ of the free parameters, warnings, quality gates and left-out observations.

    **Arguments:**
    - `cal`: a `Calibration`.

    **Returns:** the text, one item a line (empty where the calibration has neither
    parameter statistics nor gates).
    """
    parts = []
    diag = _uncertainty(cal)
    if diag is not None:
        parts.append(diag.summary())
    cov = getattr(cal, "coverage", None)
    parts.append(
        "coverage: unknown (no sensor size or an older calibration file)"
        if cov is None
        else f"coverage: {cov.summary()}; points outside it are extrapolated"
    )
    quality = getattr(cal, "quality", None)
    if quality is not None:
        parts.append(quality.summary())
        if quality.plane is not None:
            p = quality.plane
            w, s = p["normal_sigma_rad"]
            parts.append(
                f"laser plane from {p['n_points']} stripe points on {p['n_views']} boards: "
                f"spread across the line {p['spread_across_line_mm']:.3g} mm; their noise "
                f"alone (camera and board poses exact) would leave sigma of the normal "
                f"{w * 1e6:.3g} / {s * 1e6:.3g} urad, of the offset "
                f"{p['offset_sigma_mm'] * 1e3:.3g} um" + _joint_plane_sigma(diag)
            )
    axis = calibration_axis_conditioning(cal)
    if axis is not None:
        parts.append(
            f"table axis: predicted sigma of a length across half a turn "
            f"{axis.sigma_across_um:.3g} um; of the direction {axis.sigma_direction_mrad:.3g} "
            f"mrad, of the position {axis.sigma_position_um:.3g} um"
            + (" (WEAK: see the warning)" if axis.weak else "")
        )
    return "\n".join(parts)
