"""Is a scan the calibration's own ring gauge, where it stood when the stage was calibrated?

The stage solve fits the table axis and the gauge's eccentricity so that the gauge scan's
points lie on a cylinder of the gauge's *nominal* radius. Measured again — the same
stripe files, the same images extracted with other options, or a fresh scan of the gauge
left where it stood — that radius comes back as its nominal value within the fit
residual, whatever the calibration's errors: a repeatability figure, not an accuracy.

A scan frame is taken as a frame of the calibration's gauge scan when most of its pixels
(`MATCH_FRACTION`) lie within `MATCH_PX` of the stripe of one gauge frame. Half a pixel is
10 stripe-noise σ (0.05 px) and, at the paper rig's ×1.5 and 4.4 µm pixels, ~1.5 µm on
the object: another artefact, or the gauge put back after it was lifted off, images
elsewhere. The stripe is the gauge frame's centres joined to their nearest neighbours
(gaps up to `GAP_FACTOR` × the frame's median spacing), not the centres alone: a
calibration whose gauge frames hold a centre every 8 px (the simulator's observations)
and a scan of the same gauge with one centre per scan line (`extract` of its images) lie
on one stripe, but most of the scan's centres are more than `MATCH_PX` from any of the
calibration's (the gauge was measured as 17.500000 mm, PASS).

A scan is the calibration's gauge scan when at least `OWN_SCAN_FRACTION` of its frames
are ([`is_own_gauge_scan`][]). Single frames of another scan can lie on a gauge frame's
stripe: where a gauge moved on the table slides along its own stripe (the paper rig,
12 frames, the gauge moved 10 µm: 2 frames within 0.32 px median, 0.69 px at most of
the unmoved gauge's stripe, the other 10 frames 2.5–5.5 px off), a frame of it is that
stripe to the pixels' precision, yet the scan as a whole measures the moved gauge.
"""

from __future__ import annotations

import itertools

import numpy as np

MATCH_PX = 0.5
MATCH_FRACTION = 0.8
GAP_FACTOR = 4.0
OWN_SCAN_FRACTION = 0.5
# The joined stripe is sampled every _STEP_PX; a pixel within MATCH_PX of the stripe is
# within _RADIUS_PX of a sample (half a step along it), and one matched at _RADIUS_PX is
# at most that far from the stripe.
_STEP_PX = 0.25
_RADIUS_PX = float(np.hypot(MATCH_PX, _STEP_PX / 2))


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
    lines = [_stripe_samples(g) for g in gauge]
    label = np.concatenate([np.full(len(s), j) for j, s in enumerate(lines)])
    near = cKDTree(np.concatenate(lines)).query_ball_point(uv, _RADIUS_PX)
    counts = np.fromiter(map(len, near), np.int64, len(near))
    sample = np.fromiter(itertools.chain.from_iterable(near), np.int64, int(counts.sum()))
    # each (pixel, gauge frame) pair once, however many of that frame's samples are near
    pair = np.unique(np.repeat(np.arange(len(uv)), counts) * len(gauge) + label[sample])
    pixel, frame_of = np.divmod(pair, len(gauge))
    frames = np.unique(fi)
    row = np.searchsorted(frames, fi)
    hits = np.zeros((len(frames), len(gauge)), np.int64)  # pixels near each gauge frame
    np.add.at(hits, (row[pixel], frame_of), 1)
    size = np.bincount(row, minlength=len(frames))
    best = hits.max(axis=1)
    return [int(f) for f, b, n in zip(frames, best, size) if b >= MATCH_FRACTION * n]


def is_own_gauge_scan(matched: list[int] | None, n_frames: int) -> bool:
    """Whether a scan of `n_frames` frames with stripe pixels, of which `matched` are
    frames of the calibration's gauge scan, is that gauge scan (at least
    `OWN_SCAN_FRACTION` of its frames)."""
    return bool(matched) and len(matched) >= OWN_SCAN_FRACTION * max(int(n_frames), 1)


def _stripe_samples(g: np.ndarray) -> np.ndarray:
    """A gauge frame's stripe as points `_STEP_PX` apart: each centre joined by straight
    segments to its two nearest centres, where they are at most `GAP_FACTOR` × the
    frame's median nearest-neighbour spacing away (a gap in the stripe stays a gap)."""
    from scipy.spatial import cKDTree

    g = g[np.isfinite(g).all(axis=1)]
    if len(g) < 2:
        return g
    k = min(3, len(g))
    dist, idx = cKDTree(g).query(g, k=k)
    limit = GAP_FACTOR * float(np.median(dist[:, 1]))
    i = np.repeat(np.arange(len(g)), k - 1)
    j, d = idx[:, 1:].ravel(), dist[:, 1:].ravel()
    keep = d <= limit
    pairs, first = np.unique(
        np.sort(np.stack([i[keep], j[keep]], axis=1), axis=1), axis=0, return_index=True
    )
    i, j, d = pairs[:, 0], pairs[:, 1], d[keep][first]
    n = np.maximum(np.ceil(d / _STEP_PX).astype(np.int64), 1)
    seg = np.repeat(np.arange(len(i)), n)
    t = (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)) / np.repeat(n, n)
    samples = g[i[seg]] + t[:, None] * (g[j[seg]] - g[i[seg]])
    return np.concatenate([g, samples])


def own_gauge_message(cal, matched: list[int], n_frames: int) -> str:
    """One line: which frames are the calibration's gauge scan, and what that means."""
    r = float(np.asarray(cal.data.gauge_radius))
    shown = _shown(matched)
    return (
        f"{len(matched)} of {n_frames} frame(s) ({shown}) are frames of the calibration's "
        f"own ring-gauge scan (within {MATCH_PX} px of its stripes): its radius "
        f"({r:g} mm) was an input of the calibration, so measuring it gives back its "
        "nominal value (repeatability, not accuracy)"
    )


def few_gauge_frames_message(matched: list[int], n_frames: int) -> str:
    """One line for a scan of which a few frames (not [`is_own_gauge_scan`][]) lie on the
    stripes of the calibration's gauge scan."""
    shown = _shown(matched)
    return (
        f"{len(matched)} of {n_frames} frame(s) ({shown}) lie within {MATCH_PX} px of "
        "stripes of the calibration's own ring-gauge scan; the other frames do not, so "
        "the scan is measured as another artefact"
    )


def _shown(matched: list[int]) -> str:
    """The first frame numbers of `matched`, for a message."""
    return ", ".join(str(i) for i in matched[:8]) + (", ..." if len(matched) > 8 else "")
