"""Continuity: link per-scan-line centres into line segments and drop the stray ones.

The centres come one per scan line. Neighbouring scan lines belong to the same segment
when both are valid (allowing gaps of up to `max_gap` scan lines) and the centre moves
by at most `max_jump_px` per scan line. A segment is kept when it has at least
`min_points` centres and, hysteresis on contrast, at least one centre with the strength
`high` (its other centres need only the lower acceptance threshold already applied).
"""

from __future__ import annotations

import numpy as np


def link_segments(
    y: np.ndarray,
    valid: np.ndarray,
    strength: np.ndarray,
    *,
    max_jump_px: float,
    max_gap: int,
    min_points: int,
    high: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Segment label per scan line (-1 where invalid or dropped) and the kept mask.

    **Arguments:**
    - `y`: (N,) centre across the scan lines (NaN where invalid).
    - `valid`: (N,) bool, centres that passed the per-point tests.
    - `strength`: (N,) their strength.
    - `max_jump_px`: largest change of `y` per scan line within a segment.
    - `max_gap`: largest run of missing scan lines bridged within a segment.
    - `min_points`: fewest centres of a kept segment.
    - `high`: strength that at least one centre of a kept segment must reach.
    """
    idx = np.flatnonzero(valid)
    labels = np.full(y.shape, -1, np.intp)
    if idx.size == 0:
        return labels, np.zeros(y.shape, bool)
    step = np.diff(idx)
    jump = np.abs(np.diff(y[idx]))
    new = np.ones(idx.size, bool)
    new[1:] = (step > max_gap + 1) | (jump > max_jump_px * step)
    seg = np.cumsum(new) - 1
    n_seg = int(seg[-1]) + 1
    count = np.bincount(seg, minlength=n_seg)
    peak = np.full(n_seg, -np.inf)
    np.maximum.at(peak, seg, strength[idx])
    keep_seg = (count >= min_points) & (peak >= high)
    kept = keep_seg[seg]
    labels[idx[kept]] = seg[kept]
    keep = np.zeros(y.shape, bool)
    keep[idx[kept]] = True
    return labels, keep
