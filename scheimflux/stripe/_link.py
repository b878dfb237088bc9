"""Continuity: link per-scan-line centres into line segments and drop the stray ones.

The centres come one per scan line. Neighbouring scan lines belong to the same segment
when both are valid (allowing gaps of up to `max_gap` scan lines) and the centre moves
by at most `max_jump_px` per scan line. A segment is kept when it has at least
`min_points` centres and, hysteresis on contrast, at least one centre with the strength
`high` (its other centres need only the lower acceptance threshold already applied).
"""

from __future__ import annotations

import numpy as np

from . import _fast
from ._image import _median


def link_segments(
    y: np.ndarray,
    valid: np.ndarray,
    strength: np.ndarray,
    *,
    max_jump_px: float,
    max_gap: int,
    min_points: int,
    high: float,
    trim: int = 0,
    min_line: int = 0,
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
    - `trim`: centres dropped at each end of a segment (scan lines from its ends).
    - `min_line`: if no segment spans this many scan lines, the frame holds no line
      (glints and short reflections alone): nothing is kept.
    """
    if _fast.enabled and y.ndim == 1 and y.dtype == strength.dtype == np.float64:
        return _fast.link_segments(
            np.ascontiguousarray(y, np.float64), np.ascontiguousarray(valid, np.bool_),
            np.ascontiguousarray(strength, np.float64), float(max_jump_px), int(max_gap),
            int(min_points), float(high), int(trim), int(min_line),
        )  # fmt: skip
    idx = np.flatnonzero(valid)
    labels = np.full(y.shape, -1, np.intp)
    if idx.size == 0:
        return labels, np.zeros(y.shape, bool)
    step = np.diff(idx)
    jump = np.abs(np.diff(y[idx]))
    new = np.ones(idx.size, bool)
    new[1:] = (step > max_gap + 1) | (jump > max_jump_px * step)
    seg = np.cumsum(new) - 1
    first = np.flatnonzero(new)  # segments are runs: first/last member of each
    last = np.r_[first[1:], idx.size] - 1
    count = last - first + 1
    peak = np.maximum.reduceat(strength[idx], first)
    keep_seg = (count >= min_points) & (peak >= high)
    # The smoothing kernels reach past the end of a line: its last `trim` centres come
    # from the fading tail of the filters, not from the line. Drop them.
    # Only ends that face a long gap (or the frame's first/last centre) are line ends;
    # a short gap is a few refused centres inside the line.
    if trim > 0:
        # before the first and after the last centre: the scan lines to the frame edge
        # (a line that runs out of the image has no end to trim)
        gap_before = np.r_[idx[0], idx[first[1:]] - idx[last[:-1]] - 1]
        gap_after = np.r_[gap_before[1:], y.size - 1 - idx[-1]]
        long_gap = max(2 * min_points, 3)
        dist_first = np.where(gap_before[seg] >= long_gap, idx - idx[first[seg]], trim)
        dist_last = np.where(gap_after[seg] >= long_gap, idx[last[seg]] - idx, trim)
        keep_seg_pt = np.minimum(dist_first, dist_last) >= trim
    else:
        keep_seg_pt = np.ones(idx.size, bool)
    kept = keep_seg[seg] & keep_seg_pt
    if not np.any(keep_seg & (idx[last] - idx[first] + 1 >= min_line)):
        return labels, np.zeros(y.shape, bool)
    labels[idx[kept]] = seg[kept]
    keep = np.zeros(y.shape, bool)
    keep[idx[kept]] = True
    return labels, keep


def _local_fit(y: np.ndarray, w: np.ndarray, half: int) -> tuple[np.ndarray, np.ndarray]:
    """Leave-one-out prediction of `y` at each scan line from a weighted quadratic fit
    over the scan lines within ± `half`, and the number of points it used.

    `w` is (N,) or (M, N): M weightings of the same `y` at once (one set of array
    operations for all of them). Windowed power sums come from prefix sums (O(N)) read
    with two slices of an edge-padded cumulative sum; the local coordinate
    `t = (x - i) / half` is expanded binomially from sums in `x / half`.
    """
    n = y.size
    single = w.ndim == 1
    w = np.atleast_2d(w)
    if _fast.enabled and n > 0 and half > 0:
        pred, count = _fast.local_fit(
            np.ascontiguousarray(y, np.float64), np.ascontiguousarray(w, np.float64), int(half)
        )
        return (pred[0], count[0]) if single else (pred, count)
    u = np.arange(n, dtype=np.float64) / half
    yw = np.where(w > 0, y, 0.0) * w
    # windowed sums of w u^k (k <= 4) and w y u^k (k <= 2) from one cumulative sum
    u2 = u * u
    cols = np.stack([w, w * u, w * u2, w * u2 * u, w * u2 * u2, yw, yw * u, yw * u2], 1)
    # c[..., j] = sum over scan lines < j - half - 1 (zeros before, the total after), so
    # that the window [i - half, i + half] is c[i + 2 half + 1] - c[i]
    c = np.zeros(cols.shape[:2] + (n + 2 * half + 1,))
    np.cumsum(cols, axis=2, out=c[:, :, half + 1 : n + half + 1])
    c[:, :, n + half + 1 :] = c[:, :, n + half : n + half + 1]
    win = c[:, :, 2 * half + 1 :] - c[:, :, :n]
    S0, S1, S2, S3, S4, T0, T1, T2 = (win[:, k] for k in range(8))
    # the same sums in the local coordinate t = u_j - u_i (binomial expansion)
    a = u
    a2 = a * a
    St = [
        S0,
        S1 - a * S0,
        S2 - 2 * a * S1 + a2 * S0,
        S3 - 3 * a * S2 + 3 * a2 * S1 - a2 * a * S0,
        S4 - 4 * a * S3 + 6 * a2 * S2 - 4 * a2 * a * S1 + a2 * a2 * S0,
    ]
    Tt = [T0, T1 - a * T0, T2 - 2 * a * T1 + a2 * T0]
    # leave the point itself out (it sits at t = 0: only the zeroth sums hold it)
    St[0] = St[0] - w
    Tt[0] = Tt[0] - yw
    # Prediction at t = 0: the first unknown of the 3 x 3 normal equations (Cramer).
    s0, s1, s2, s3, s4 = St
    t0, t1, t2 = Tt
    c00 = s2 * s4 - s3 * s3
    c01 = s1 * s4 - s2 * s3
    c02 = s1 * s3 - s2 * s2
    det = s0 * c00 - s1 * c01 + s2 * c02
    num = t0 * c00 - s1 * (t1 * s4 - s3 * t2) + s2 * (t1 * s3 - s2 * t2)
    count = St[0]
    good = (count >= 6) & (np.abs(det) > 1e-9 * np.maximum(s0, 1.0) ** 3)
    pred = np.where(good, num / np.where(good, det, 1.0), np.nan)
    count = np.where(good, count, 0.0)
    return (pred[0], count[0]) if single else (pred, count)


def consistent(
    y: np.ndarray, valid: np.ndarray, *, half: int = 40, floor_px: float = 0.25
) -> np.ndarray:
    """Which valid centres agree with a smooth line through their neighbours.

    A robust local quadratic (± `half` scan lines, leave-one-out, two passes with
    shrinking thresholds `max(1, 3 s)`, then `max(floor_px, 5 s)` where `s`
    is the robust spread of the residuals) predicts each centre from the others; a
    centre farther from it is refused. This removes runs that leave the line to follow
    a checker edge (the laser's tail on a bright square makes a one-sided ridge along
    the edge) and centres pulled by an albedo step under the line. Centres with fewer
    than 6 neighbours in their window are kept (too few to judge) unless they also lie
    off the robust global cubic of all centres (isolated glints, stray reflections).
    """
    keep = valid.copy()
    if valid.sum() < 12:
        return keep
    yv = np.where(valid, y, 0.0)
    if _fast.enabled and y.dtype == np.float64:
        off_curve = _fast.cubic_seed(y, np.ascontiguousarray(valid, np.bool_))
        keep &= ~off_curve
        return _fast.consistent_passes(yv, valid, keep, off_curve, int(half), float(floor_px))
    # Seed: a global cubic, fitted robustly, down-weights gross runs off the line for
    # the first local fit only (every centre is judged by the local fits).
    x = np.flatnonzero(valid)
    xs = (x - x.mean()) / max(float(np.ptp(x)), 1.0)
    yx = y[x]
    # start from a robust straight line (median of the slopes between the two halves,
    # median intercept), so that a cluster of stray points cannot bend the cubic
    half_n = x.size // 2
    slope = float(_median((yx[half_n:2 * half_n] - yx[:half_n]) / (
        xs[half_n:2 * half_n] - xs[:half_n])))
    r0 = yx - slope * xs
    r0 = np.abs(r0 - _median(r0))
    seed = r0 <= max(20.0, 5.0 * 1.4826 * float(_median(r0)))
    V = np.stack([np.ones_like(xs), xs, xs * xs, xs * xs * xs], 1)
    for _ in range(2):
        Vs = V[seed]
        coef = np.linalg.solve(Vs.T @ Vs + 1e-12 * np.eye(4), Vs.T @ yx[seed])
        r = np.abs(yx - V @ coef)
        seed = r <= max(1.0, 4.0 * 1.4826 * float(_median(r[seed])))
        if seed.sum() < 12:
            seed[:] = True
            break
    off_curve = np.zeros(valid.shape, bool)
    off_curve[x[~seed]] = True
    keep &= ~off_curve
    if _fast.enabled and yv.dtype == np.float64:
        return _fast.consistent_passes(yv, valid, keep, off_curve, int(half), float(floor_px))
    fits: list[tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]] = []

    def fit(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`_local_fit` with these weights (a fit already made with equal ones is reused)."""
        for done, result in fits:
            if np.array_equal(done, weights):
                return result
        result = _local_fit(yv, weights.astype(np.float64), half)
        fits.append((weights, result))
        return result

    for step, (factor, floor) in enumerate(((3.0, 1.0), (5.0, floor_px))):
        if step == 0 and off_curve.any():
            # both fits of the first pass in one call (two weightings of the same y)
            both = np.stack([keep, valid]).astype(np.float64)
            (pred, pred_all), (count, count_all) = _local_fit(yv, both, half)
            fits += [(keep, (pred, count)), (valid, (pred_all, count_all))]
            # A piece of line the global cubic does not follow (a strongly curved line,
            # a piece beyond a gap) is judged by its own points when it has enough
            # of them to be a line on its own (at least 30 in the window).
            own = (count < 6) & (count_all >= 30)
            pred = np.where(own, pred_all, pred)
            count = np.where(own, count_all, count)
        else:
            pred, count = fit(keep)
        r = np.abs(yv - pred)
        judged = valid & (count >= 6) & np.isfinite(r)
        if not judged.any():
            return keep & ~off_curve
        spread = 1.4826 * float(_median(r[judged & keep])) if (judged & keep).any() else 0.0
        thr = max(floor, factor * spread)
        # off the global curve and without neighbours to vouch for it: refused
        keep = valid & ~(judged & (r > thr)) & ~(off_curve & ~judged)
    return keep
