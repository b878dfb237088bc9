"""The parts of a curved line too steep for the scan direction (`extract_stripe`).

A scan finds at most one centre per scan line, where the line crosses it; where a curved
line turns towards the scan lines' own direction (a ring gauge's arc near its ends, a
parabola's arms), the profile along a scan line widens as 1 / cos of the angle and the
centres are refused (steeper than ~68 degrees on the ring-gauge arcs of a rotary-table
scan: 11-13 % of the arc was lost without a word). Here each linked piece's ends are
read: an end steeper than `STEEP_END_DEG` to the scan-perpendicular, or turning towards
it (`TURN_DEG`, `BEND_DEG`: a scan can lose a bending line short of 45 degrees), inside
the image, is followed by a pass with the other scan direction over the scan lines
beyond the point where the piece turned past 45 degrees (a band; a second pass only
where a steep end exists). A piece of the other pass that meets the end (a centre within
`JOIN_PX` of its centres from that point on) continues the line: the two are cut at one
point, the first centre past 45 degrees that the other pass also covers, and each keeps
its own side (the scan more perpendicular to the line there), so no point of the line is
counted twice; an end that stopped short of where the other pass's centres begin is
continued by a piece starting within `GAP_WIDTHS` line widths ahead of it. The new
piece's far end is followed the same way (a U-shaped line: one arm, its bottom, the
other arm), at most `MAX_PASSES` passes per image.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

from . import _fast
from ._result import StripeResult

# A piece's end is steep where the straight line through its last `_END_FIT` centres
# makes more than this angle with the scan-perpendicular (the scan chosen by "auto" is
# within 45 degrees of a straight line everywhere, so a straight line never has one).
STEEP_END_DEG = 50.0
# ... or steeper than TURN_FROM_DEG and turned by more than TURN_DEG since the window
# _BACK centres before (a bend: the scan's centres are refused from ~45-50 degrees on
# where the profile along the scan line passes the width test's 1.4 x the median
# width). A straight line's two windows agree within ~0.5 degrees (centre noise
# 0.05 px); 3 degrees over 16 centres is a radius of curvature under ~300 px. None of
# `tests/test_stripe_capture.py`'s board scenes (lines at 4-135 degrees, clipped or
# not, with and without a laser-off frame) has such an end.
TURN_FROM_DEG = 35.0
TURN_DEG = 3.0
_END_FIT = 8
_BACK = 16
# ... or steeper than BEND_FROM_DEG and bending: the angle of the end window taken 0, 1,
# ..., K centres further in (K = the piece's length less _END_FIT, at most _BEND_SPAN, at
# least _BEND_MIN), fitted by a straight line against K, turns by more than BEND_DEG
# over min(K, _BACK) centres towards the end. The fit over up to 25 windows reads a
# steady bend that the two-window turn above misses where the scan stops early (a U
# whose arms every scan line meets: its centres stop at ~35 degrees, 2.8 degrees turned
# over 16) or the piece is short (8-23 centres), and averages out a wavy line's noise
# (a dim line on a print: windows 1.5 degrees apart). Measured on every board scene of
# tests/test_stripe_capture.py and tests/test_capture.py: at most 1.7 degrees per 16
# centres (a line of curvature 0.002 / px at 33 degrees), 1.5 over 10 on a short
# piece; the ends this rule is for: 2.8-3.2 (the U), 2.4-8.8 (arcs seen by the scan
# that meets both their sides).
BEND_FROM_DEG = 25.0
BEND_DEG = 2.25
_BEND_SPAN = 24
_BEND_MIN = 8
# Largest distance (px) between centres of the two scans that see the same stretch of
# line (their spacing along the line is at most 1.41 px at 45 degrees, each within
# ~0.1 px of the line).
JOIN_PX = 1.5
# Largest angle between the two pieces' directions where they meet (deg).
JOIN_DEG = 20.0
# Centres of two pieces closer than this (px) are the same point of the line.
_SAME_PX = 0.7
# An end that stops short of 45 degrees (the bend rule) is not reached by the other
# scan's centres either (they stop at ~50-56 degrees to its own scan-perpendicular on a
# bend): a piece of the other pass that starts within this many line widths ahead of
# the end, along its tangent, continues it across the gap.
GAP_WIDTHS = 3.0
# Passes of the other scan direction per image, at most.
MAX_PASSES = 6
# Consecutive centres farther apart than this (px) are a gap in the line's length.
_GAP_PX = 4.0

_OTHER = {"vertical-scan": "horizontal-scan", "horizontal-scan": "vertical-scan"}


@dataclasses.dataclass
class _Piece:
    """One linked segment of one pass: `src` its result, `idx` its entries there (in
    scan order), `alive` which of them the merge keeps; `children` the pieces that
    continue it at its first (-1) or last (+1) end."""

    src: StripeResult
    idx: np.ndarray
    alive: np.ndarray
    primary: bool
    children: list = dataclasses.field(default_factory=list)

    @property
    def orientation(self) -> str:
        return self.src.orientation

    @property
    def uv(self) -> np.ndarray:
        return self.src.uv[self.idx]

    def xy(self) -> tuple[np.ndarray, np.ndarray]:
        """Scan index and position along the scan line of each entry."""
        uv = self.uv
        return (uv[:, 0], uv[:, 1]) if self.orientation == "vertical-scan" else (uv[:, 1], uv[:, 0])


def _pieces(res: StripeResult, primary: bool) -> list[_Piece]:
    out = []
    for label in np.unique(res.segment[res.valid & (res.segment >= 0)]):
        idx = np.flatnonzero(res.valid & (res.segment == label))
        out.append(_Piece(res, idx, np.ones(idx.size, bool), primary))
    return out


def _local_slope(x: np.ndarray, y: np.ndarray, half: int = 4) -> np.ndarray:
    """dy/dx of the straight line through each entry's +- `half` neighbours."""
    n = x.size
    c = np.zeros((5, n + 1))
    np.cumsum(np.stack([np.ones(n), x, x * x, y, x * y]), axis=1, out=c[:, 1:])
    lo = np.clip(np.arange(n) - half, 0, n)
    hi = np.clip(np.arange(n) + half + 1, 0, n)
    s0, s1, s2, t0, t1 = c[:, hi] - c[:, lo]
    det = s0 * s2 - s1 * s1
    return np.where(det > 1e-9, (s0 * t1 - s1 * t0) / np.where(det > 1e-9, det, 1.0), np.inf)


@dataclasses.dataclass(frozen=True)
class _End:
    piece: _Piece
    side: int  # -1: the piece's first centre, +1: its last
    stretch: np.ndarray  # entries of the piece from where it turned past 45 deg to the end
    scan_cut: float  # scan index where it turned past 45 deg
    whole: bool = False  # the whole piece is steeper than 45 deg


def _steep_end(
    p: _Piece, side: int, shape: tuple[int, int], border: float, force: bool = False
) -> _End | None:
    """The piece's end on `side` if it runs steep there (`_turns_steep`; any end with
    `force`), away from the image's border (a line leaving the image is not followed)."""
    a = np.flatnonzero(p.alive)
    if a.size < 6:
        return None
    x, y = p.xy()
    x, y = x[a], y[a]
    if not force and not _turns_steep(x[::side], y[::side]):
        return None
    u, v = p.uv[a[-1] if side > 0 else a[0]]
    h, w = shape
    if not (border <= u <= w - 1 - border and border <= v <= h - 1 - border):
        return None
    s = np.abs(_local_slope(x, y))
    order = np.arange(a.size)[::-1] if side > 0 else np.arange(a.size)  # from the end in
    shallow = np.flatnonzero(s[order] <= 1.0)
    pos = int(shallow[0]) if shallow.size else a.size - 1
    stretch = a[order[: pos + 1][::-1]]  # from the cut towards the end
    return _End(p, side, stretch, float(x[order[pos]]), whole=not shallow.size)


def _tangent(p: _Piece, j: int, side: int) -> np.ndarray:
    """Unit tangent (u, v) of the piece at its entry `j`, pointing out of its `side`."""
    x, y = p.xy()
    a = np.flatnonzero(p.alive)
    s = _local_slope(x[a], y[a])[np.searchsorted(a, j)]
    d = np.array([1.0, s]) if np.isfinite(s) else np.array([0.0, 1.0])
    d = side * d / np.linalg.norm(d)
    return d if p.orientation == "vertical-scan" else d[::-1]


def _join(end: _End, q: _Piece) -> bool:
    """Cut `end`'s piece and `q` at the first centre of the end's stretch that `q`
    covers (within `JOIN_PX`): the piece keeps its centres up to it, `q` those beyond
    it along the line. False (and nothing cut) where `q` does not meet the stretch,
    runs another way there, or holds fewer than 3 centres beyond it."""
    p = end.piece
    live = np.flatnonzero(q.alive)
    if live.size < 3:
        return False
    dist, near = cKDTree(q.uv[live]).query(p.uv[end.stretch])
    hit = np.flatnonzero(dist <= JOIN_PX)
    if hit.size == 0:
        return False
    k = int(hit[0])
    j = int(end.stretch[k])
    t = _tangent(p, j, end.side)
    # one line continued, not another one crossing it: the same direction there
    if abs(float(t @ _tangent(q, int(live[near[k]]), 1))) < math.cos(math.radians(JOIN_DEG)):
        return False
    ahead = q.alive & ((q.uv - p.uv[j]) @ t > 0.75)
    if ahead.sum() < 3:  # nothing beyond the piece: it keeps its own centres
        return False
    p.alive[end.stretch[k + 1 :]] = False
    q.alive = ahead
    return True


def _across_gap(end: _End, found: list[_Piece], gap: float) -> _Piece | None:
    """The piece of `found` that continues `end` across a gap: its centre nearest the
    end's last one within `gap` px, ahead of it along the end's tangent (within
    `JOIN_DEG` of it) and running the same way there (within `JOIN_DEG`); it keeps its
    centres more than 0.75 px ahead of the end (3 at least). None where there is none."""
    p = end.piece
    j = int(end.stretch[-1])
    e = p.uv[j]
    t = _tangent(p, j, end.side)
    best = None
    for q in found:
        live = np.flatnonzero(q.alive)
        if live.size < 3:
            continue
        d = q.uv[live] - e
        r = np.hypot(d[:, 0], d[:, 1])
        k = int(np.argmin(r))
        if r[k] > gap or (best is not None and r[k] >= best[0]):
            continue
        cos = math.cos(math.radians(JOIN_DEG))
        if float(d[k] @ t) < cos * r[k] or abs(float(t @ _tangent(q, int(live[k]), 1))) < cos:
            continue
        best = (float(r[k]), q)
    if best is None:
        return None
    q = best[1]
    ahead = q.alive & ((q.uv - e) @ t > 0.75)
    if ahead.sum() < 3:
        return None
    q.alive = ahead
    return q


def _band(end: _End, shape: tuple[int, int], pad: int) -> np.ndarray:
    """The image beyond the end's cut, in its piece's scan lines (a band of columns
    for a vertical scan)."""
    h, w = shape
    n = w if end.piece.orientation == "vertical-scan" else h
    if end.side > 0:
        lo, hi = max(int(math.floor(end.scan_cut)) - pad, 0), n
    else:
        lo, hi = 0, min(int(math.ceil(end.scan_cut)) + pad + 1, n)
    band = np.zeros((h, w), bool)
    if end.piece.orientation == "vertical-scan":
        band[:, lo:hi] = True
    else:
        band[lo:hi, :] = True
    return band


def _near_end(q: _Piece, point: np.ndarray) -> int:
    """The side of `q` whose end lies nearer `point`."""
    a = np.flatnonzero(q.alive)
    first, last = q.uv[a[0]], q.uv[a[-1]]
    return -1 if np.linalg.norm(first - point) <= np.linalg.norm(last - point) else 1


def _sequence(p: _Piece) -> list[tuple[_Piece, int]]:
    """The piece's kept entries in its scan order with its children's sequences
    before its first and after its last entry, each oriented along the line."""
    seq = [(p, int(j)) for j in p.idx[p.alive]]
    for side, child, child_side in p.children:
        sub = _sequence(child)
        if child_side > 0:  # the child meets this piece at its last entry: reverse
            sub = sub[::-1]
        seq = seq + sub if side > 0 else sub[::-1] + seq
    return seq


def _length(uv: np.ndarray) -> float:
    if len(uv) < 2:
        return 0.0
    d = np.hypot(*np.diff(uv, axis=0).T)
    return float(d[d <= _GAP_PX].sum())


def _angle(x: np.ndarray, y: np.ndarray) -> np.ndarray | np.floating:
    """Angle (deg, 0-90) of the straight line through each row of (K, n) samples to the
    x axis."""
    xm = x - x.mean(axis=-1, keepdims=True)
    den = np.einsum("...j,...j->...", xm, xm)
    num = np.abs(np.einsum("...j,...j->...", xm, y - y.mean(axis=-1, keepdims=True)))
    return np.degrees(np.arctan2(num, den))


def _bend(angles: np.ndarray, span: np.ndarray) -> np.ndarray:
    """Degrees turned towards the end over min(K, `_BACK`) centres, K = `span`: the
    slope of a straight line fitted to `angles[..., k]` (the end window's angle taken k
    centres further in) against k = 0..K, sign flipped (the angle grows towards the
    end). `angles` (..., `_BEND_SPAN` + 1), entries past K ignored; 0 where K <
    `_BEND_MIN`."""
    k = np.arange(_BEND_SPAN + 1, dtype=np.float64)
    kk = span[..., None].astype(np.float64)
    use = k <= kk
    kbar = kk / 2.0
    num = np.where(use, (k - kbar) * angles, 0.0).sum(axis=-1)
    den = np.maximum(span * (span + 1.0) * (span + 2.0) / 12.0, 1.0)
    turn = -num / den * np.minimum(span, _BACK)
    return np.where(span >= _BEND_MIN, turn, 0.0)


def _steep_angles(
    a0: np.ndarray | np.floating,
    a1: np.ndarray | np.floating,
    back: np.ndarray | np.bool_,
    bend: np.ndarray | np.floating,
) -> np.ndarray | np.bool_:
    """The steep-end rule on the end window's angle `a0`, where `back` the angle `a1` of
    the window `_BACK` centres before it, and the fitted turn `bend` (`_bend`)."""
    turn = back & (a0 > TURN_FROM_DEG) & (a0 - a1 > TURN_DEG)
    bends = (a0 > BEND_FROM_DEG) & (bend > BEND_DEG)
    return (a0 > STEEP_END_DEG) | turn | bends


def _turns_steep(x: np.ndarray, y: np.ndarray) -> bool:
    """Whether a piece whose centres `(x, y)` end at their last entry ends steep."""
    n = x.size
    if n < _END_FIT:
        return False
    end = np.arange(n - _END_FIT, n)
    back = n >= _END_FIT + _BACK
    span = min(n - _END_FIT, _BEND_SPAN)
    ends = end - np.minimum(np.arange(_BEND_SPAN + 1), span)[:, None]
    angles = _angle(x[ends], y[ends])
    a0 = angles[0]
    a1 = angles[_BACK] if back else a0
    bend = _bend(angles, np.asarray(span))
    return bool(_steep_angles(a0, a1, np.bool_(back), bend))


def _may_turn_steep(result: StripeResult) -> bool:
    """Whether any linked segment of `result` ends steep (`_steep_end`'s angle rule
    alone, on the valid centres of each run of one segment label; it runs on every
    frame: compiled, `_fast.steep_end`, or vectorised here)."""
    col = 0 if result.orientation == "vertical-scan" else 1
    if _fast.enabled:
        return bool(_fast.steep_end(
            result.uv, col, result.valid, result.segment, _END_FIT, _BACK,
            STEEP_END_DEG, TURN_FROM_DEG, TURN_DEG, _BEND_SPAN, _BEND_MIN,
            BEND_FROM_DEG, BEND_DEG,
        ))  # fmt: skip
    a = np.flatnonzero(result.valid)
    if a.size < _END_FIT:
        return False
    x, y = result.uv[a, col], result.uv[a, 1 - col]
    cut = np.flatnonzero(result.segment[a[1:]] != result.segment[a[:-1]]) + 1
    first = np.concatenate(([0], cut))
    stop = np.concatenate((cut, [a.size]))
    runs = stop - first
    keep = runs >= _END_FIT
    first, stop, runs = first[keep], stop[keep], runs[keep]
    # the windows at each run's start (read backwards) and end, and 0.._BEND_SPAN
    # centres further in (up to the run's other end)
    step = np.arange(_END_FIT)
    end = np.concatenate((first[:, None] + _END_FIT - 1 - step, stop[:, None] - _END_FIT + step))
    inward = np.concatenate((np.ones(first.size, np.intp), -np.ones(stop.size, np.intp)))
    n_run = np.concatenate((runs, runs))
    back = n_run >= _END_FIT + _BACK
    span = np.minimum(n_run - _END_FIT, _BEND_SPAN)
    k = np.minimum(np.arange(_BEND_SPAN + 1), span[:, None])  # (ends, _BEND_SPAN + 1)
    there = end[:, None, :] + (inward[:, None] * k)[:, :, None]
    angles = _angle(x[there], y[there])
    a0 = angles[:, 0]
    a1 = angles[:, _BACK]
    return bool(np.any(_steep_angles(a0, a1, back, _bend(angles, span))))


def follow_steep(
    result: StripeResult,
    shape: tuple[int, int],
    extract_other: Callable[[str, np.ndarray], StripeResult],
    merge: bool,
) -> StripeResult:
    """`result` with the parts of its line too steep for its scan direction found by
    the other one (`extract_other(orientation, band_mask)`) and merged in line order
    (`merge`), or, without `merge`, `result` itself with the length (px) and fraction of
    the line that those parts hold and it lacks (`steep_left_out_px`)."""
    if not _may_turn_steep(result):
        return result
    widths = result.width[result.valid & np.isfinite(result.width)]
    width = float(np.median(widths)) if widths.size else 5.0
    border = width + 3.0
    pad = int(math.ceil(3.0 * width)) + 4
    gap = GAP_WIDTHS * width
    # (the longest first: a fragment of the steep part is judged after the line's
    # steep parts are found from its main pieces)
    primary = sorted(_pieces(result, primary=True), key=lambda p: -p.idx.size)
    pieces: list[_Piece] = list(primary)
    queue = [(p, side, False) for p in primary for side in (-1, 1)]
    done: set[tuple[int, int]] = set()
    passes = 0
    while queue:
        p, side, force = queue.pop(0)
        if (id(p), side) in done or not p.alive.any():
            continue
        done.add((id(p), side))
        end = _steep_end(p, side, shape, border, force)
        if end is None:
            continue
        if end.whole:
            # a fragment of the steep part (the scan's centres thin out there): where
            # another scan's piece covers it, that one holds the stretch alone
            others = [q.uv[q.alive] for q in pieces[len(primary) :] if q.alive.any()]
            if others:
                dist, _ = cKDTree(np.concatenate(others)).query(p.uv[p.alive])
                if np.mean(dist <= JOIN_PX) >= 0.5:
                    p.alive[:] = False
                    continue
        # another piece covers the stretch already (a line steep in its middle is
        # reached from both sides): cut the two there, once
        met = False
        for q in pieces:
            if q is not p and q.alive.any() and q.orientation != p.orientation:
                a = np.flatnonzero(q.alive)
                ends = {-1: q.uv[a[0]], 1: q.uv[a[-1]]}
                if _join(end, q):
                    j = end.stretch[np.flatnonzero(p.alive[end.stretch])[-1]]
                    near = -1 if np.linalg.norm(ends[-1] - p.uv[j]) <= np.linalg.norm(
                        ends[1] - p.uv[j]) else 1  # fmt: skip
                    done.add((id(q), near))
                    met = True
                    break
        if met or passes >= MAX_PASSES:
            continue
        passes += 1
        band = _band(end, shape, pad)
        other = extract_other(_OTHER[p.orientation], band)
        # the pieces that meet the end's stretch, the one meeting it first tried first
        # (a fragment that meets it but runs off it gives way to the next)
        found = _pieces(other, primary=False)
        meets = []
        for i, q in enumerate(found):
            dist, _ = cKDTree(q.uv[q.alive]).query(p.uv[end.stretch])
            hit = np.flatnonzero(dist <= JOIN_PX)
            if hit.size:
                meets.append((int(hit[0]), i))
        joined = [found[i] for _, i in sorted(meets)]
        q = next((q for q in joined if _join(end, q)), None)
        if q is None:
            # none continues the end there (it stopped short of 45 degrees, where the
            # other scan's centres do not reach yet): one that starts just ahead of it
            q = _across_gap(end, found, gap)
            if q is None:
                continue
        j = end.stretch[np.flatnonzero(p.alive[end.stretch])[-1]]
        q_side = _near_end(q, p.uv[j])
        p.children.append((side, q, q_side))
        pieces.append(q)
        done.add((id(q), q_side))
        # its far end: followed where it turns steep, and where it stops at the band's
        # edge (the line goes on beyond it: a U's bottom found from one arm meets the
        # other arm there)
        a = np.flatnonzero(q.alive)
        far = q.uv[a[0] if q_side > 0 else a[-1]]
        iu, iv = np.clip(np.rint(far).astype(int), 0, [shape[1] - 1, shape[0] - 1])
        window = band[max(iv - pad, 0) : iv + pad + 1, max(iu - pad, 0) : iu + pad + 1]
        queue.append((q, -q_side, bool(not window.all())))
    if len(pieces) == len(primary):
        return result
    # a fragment of the steep part that the first scan kept (its centres thin out
    # there), steeper than 45 degrees and covered by another scan's piece, gives way
    # to that piece
    others = np.concatenate([q.uv[q.alive] for q in pieces[len(primary) :]])
    for p in primary:
        if p.children or p.alive.sum() < 2 or not others.size:
            continue
        x, y = p.xy()
        a = np.flatnonzero(p.alive)
        steep = np.median(np.abs(_local_slope(x[a], y[a]))) > 1.0
        if steep and np.mean(cKDTree(others).query(p.uv[a])[0] <= JOIN_PX) >= 0.5:
            p.alive[:] = False
    # a piece that runs over another one whose end was not steep (and so not cut)
    # keeps none of its centres there: no point of the line twice
    kept = np.concatenate([p.uv[p.alive] for p in primary])
    for q in pieces[len(primary) :]:
        if kept.size and q.alive.any():
            dist, _ = cKDTree(kept).query(q.uv)
            q.alive &= dist > _SAME_PX
        kept = np.concatenate([kept, q.uv[q.alive]])
    # the merged line: the primary entries in scan order (those cut off invalid), each
    # piece's continuations inserted at its ends
    n = len(result)
    keys = [np.arange(n, dtype=np.float64)]
    rows = []  # (key, piece, entry) of the other scans' centres
    valid = np.zeros(n, bool)
    for p in primary:
        valid[p.idx[p.alive]] = True
        if not p.children:
            continue
        kept = p.idx[p.alive]
        for side, child, child_side in p.children:
            sub = _sequence(child)
            if child_side > 0:
                sub = sub[::-1]  # from the junction outwards
            m = len(sub)
            if side > 0:
                ks = kept[-1] + (np.arange(m) + 1.0) / (m + 1.0)
            else:
                sub = sub[::-1]
                ks = kept[0] - 1.0 + (np.arange(m) + 1.0) / (m + 1.0)
            rows += [(k, q, j) for k, (q, j) in zip(ks, sub)]
    extra_uv = np.array([q.src.uv[j] for _, q, j in rows]).reshape(-1, 2)
    merged_valid = np.concatenate([valid, np.ones(len(rows), bool)])
    order = np.argsort(np.concatenate([keys[0], [k for k, _, _ in rows]]), kind="stable")
    uv_all = np.concatenate([result.uv, extra_uv])
    line_merged = _length(uv_all[order][merged_valid[order]])
    if not merge:
        line_own = _length(result.uv[result.valid])
        left = max(line_merged - line_own, 0.0)
        return dataclasses.replace(
            result,
            steep_left_out_px=left,
            steep_left_out_fraction=left / line_merged if line_merged > 0 else 0.0,
        )

    def column(name: str, invalid) -> np.ndarray:
        own = np.where(valid, getattr(result, name), invalid)
        extra = np.array([getattr(q.src, name)[j] for _, q, j in rows], own.dtype)
        return np.concatenate([own, extra])[order]

    # segment labels: the other scans' pieces after the primary's
    labels = {id(q): i for i, q in enumerate({id(q): q for _, q, _ in rows}.values())}
    base = int(result.segment.max()) + 1 if len(result) else 0
    segment = np.concatenate([
        np.where(valid, result.segment, -1),
        np.array([base + labels[id(q)] for _, q, _ in rows], np.intp),
    ])[order]  # fmt: skip
    uv = np.where(merged_valid[:, None], uv_all, np.nan)[order]
    return dataclasses.replace(
        result,
        uv=uv,
        strength=column("strength", 0.0),
        width=column("width", np.nan),
        valid=merged_valid[order],
        saturated=column("saturated", False),
        confidence=column("confidence", 0.0),
        segment=segment,
        steep=np.concatenate([np.zeros(n, bool), np.ones(len(rows), bool)])[order],
    )


def steep_note(name: str, result: StripeResult) -> str:
    """One line naming the part of `name`'s line left out because it runs too steep for
    the scan direction asked for (`StripeResult.steep_left_out_px`)."""
    return (
        f"{name}: {result.steep_left_out_px:.0f} px ({result.steep_left_out_fraction:.0%}) of "
        f"the line runs too steep for {result.orientation} and is left out (orientation "
        "auto takes it from the other scan direction)"
    )
