"""Is a scan the calibration's own ring gauge, where it stood when the stage was calibrated?

The stage solve fits the table axis and the gauge's eccentricity so that the gauge scan's
points lie on a cylinder of the gauge's *nominal* radius. Measured again — the same
stripe files, the same images extracted with other options, or a fresh scan of the gauge
left where it stood — that radius comes back as its nominal value within the fit
residual, whatever the calibration's errors: a repeatability figure, not an accuracy.

A scan frame is taken as a frame of the calibration's gauge scan when most of its pixels
(`MATCH_FRACTION`) lie within `MATCH_PX` of the pixels of one gauge frame. Half a pixel is
10 stripe-noise σ (0.05 px) and, at the paper rig's ×1.5 and 4.4 µm pixels, ~1.5 µm on
the object: another artefact, or the gauge put back after it was lifted off, images
elsewhere.
"""

from __future__ import annotations

import numpy as np

MATCH_PX = 0.5
MATCH_FRACTION = 0.8


def gauge_scan_pixels(cal) -> list[np.ndarray] | None:
    """The calibration's gauge-scan pixels per frame, or None (no gauge scan, or a
    calibration read without its observations)."""
    try:
        gauge = np.asarray(cal.data.gauge, dtype=np.float64)
        w = np.asarray(cal.data.gauge_w) > 0
    except (ValueError, AttributeError):
        return None
    frames = [g[m] for g, m in zip(gauge, w) if m.any()]
    return frames or None


def frames_on_calibration_gauge(cal, uv, frame_index=None) -> list[int] | None:
    """Scan frames (their indices) that are frames of the calibration's own gauge scan.

    **Arguments:** `cal` (a `Calibration` with its data), `uv` `(N, 2)` stripe pixels,
    `frame_index` `(N,)` the frame of each pixel (None: all one frame, index 0).

    **Returns:** the sorted frame indices whose pixels lie, for at least `MATCH_FRACTION`
    of them, within `MATCH_PX` of one frame of the gauge scan; `[]` when none does;
    None when the calibration holds no gauge scan to compare with.
    """
    from scipy.spatial import cKDTree

    gauge = gauge_scan_pixels(cal)
    if gauge is None:
        return None
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    fi = np.zeros(len(uv), np.int64) if frame_index is None else (
        np.broadcast_to(np.asarray(frame_index), (len(uv),)).astype(np.int64))  # fmt: skip
    ok = np.isfinite(uv).all(axis=1)
    uv, fi = uv[ok], fi[ok]
    if not len(uv):
        return []
    label = np.concatenate([np.full(len(g), j) for j, g in enumerate(gauge)])
    near = cKDTree(np.concatenate(gauge)).query_ball_point(uv, MATCH_PX)
    frames = np.unique(fi)
    row = np.searchsorted(frames, fi)
    hits = np.zeros((len(frames), len(gauge)), np.int64)  # pixels near each gauge frame
    for r, idx in zip(row, near):
        if idx:
            hits[r, np.unique(label[idx])] += 1
    size = np.bincount(row, minlength=len(frames))
    best = hits.max(axis=1)
    return [int(f) for f, b, n in zip(frames, best, size) if b >= MATCH_FRACTION * n]


def own_gauge_message(cal, matched: list[int], n_frames: int) -> str:
    """One line: which frames are the calibration's gauge scan, and what that means."""
    r = float(np.asarray(cal.data.gauge_radius))
    shown = ", ".join(str(i) for i in matched[:8]) + (", ..." if len(matched) > 8 else "")
    return (
        f"{len(matched)} of {n_frames} frame(s) ({shown}) are frames of the calibration's "
        f"own ring-gauge scan (within {MATCH_PX} px of its pixels): its radius "
        f"({r:g} mm) was an input of the calibration, so measuring it gives back its "
        "nominal value (repeatability, not accuracy)"
    )
