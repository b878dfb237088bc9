"""Grey-gravity (centroid) centres, one per scan line: the classical baseline.

Per scan line (scan frame: rows = scan coordinate y): find the brightest pixel near the
coarse track, take a window of ± 1.5 FWHM around it, subtract a linear background
through the window's two ends, drop everything below `threshold` times the peak, and
take the intensity-weighted mean row.
"""

from __future__ import annotations

import math

import numpy as np

from ._steger import ScanLines

_SEARCH = 4


def centroid_band(
    gather, shape: tuple[int, int], track: np.ndarray, width_px: float, *, threshold: float = 0.2
) -> ScanLines:
    """Centroid per scan line near `track` (W,); `gather(rows, cols)` reads the image."""
    h, w = shape
    half = max(int(math.ceil(1.5 * width_px)), 2)
    reach = half + _SEARCH
    centre = np.rint(track).astype(np.intp)
    cols = np.arange(w)
    rows = centre[None, :] + np.arange(-reach, reach + 1)[:, None]
    vals = gather(np.clip(rows, 0, h - 1), cols[None, :]).astype(np.float64)
    inner = vals[half : half + 2 * _SEARCH + 1]
    peak_k = np.argmax(inner, axis=0) + half  # window index of the brightest pixel
    offs = np.arange(-half, half + 1)[:, None]
    idx = peak_k[None, :] + offs
    win = np.take_along_axis(vals, idx, axis=0)
    win_rows = np.take_along_axis(rows, idx, axis=0).astype(np.float64)
    left = win[:2].mean(axis=0)
    right = win[-2:].mean(axis=0)
    frac = (offs + half) / (2.0 * half)
    signal = win - (left + (right - left) * frac)
    peak = signal.max(axis=0)
    weights = np.clip(signal - threshold * peak, 0.0, None)
    total = weights.sum(axis=0)
    found = (total > 0) & (peak > 0)
    y = (weights * win_rows).sum(axis=0) / np.where(found, total, 1.0)
    above = signal >= 0.5 * peak
    width = above.sum(axis=0).astype(np.float64)
    # The window's rows must lie inside the image.
    inside = (win_rows[0] >= 0) & (win_rows[-1] <= h - 1)
    found &= inside
    return ScanLines(
        y=np.where(found, y, np.nan),
        strength=np.where(found, peak, 0.0),
        width=np.where(found, width, np.nan),
        found=found,
        row=np.rint(np.where(found, y, 0.0)),
    )
