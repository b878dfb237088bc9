"""Centres of clipped scan lines from the flanks beside the plateau (with a laser-off
image): where a checker edge under the plateau or near one rim makes its profile
asymmetric (`extract_stripe` step 4b, docs/stripe.md).

Brightness is albedo x (ambient + laser): outside the clipped plateau the laser-on
minus laser-off difference over the laser-off level, `R = (on - off) / off`, is the
laser over the ambient light, free of the albedo. For a Gaussian line (blurred by a
Gaussian lens and the pixel, still a Gaussian) `ln R = k - (y - c)^2 / (2 s^2)` on
either flank, whatever albedo each flank lies on. `k` and `s` change slowly along the
line (laser power, room light, blur); they are fitted on the neighbouring scan lines
whose plateau centre was accepted, and each unclipped flank pixel of a refused scan
line then gives its distance to the centre. Pixels within reach of an albedo edge (the
blur mixes the two albedos there) are not used.
"""

from __future__ import annotations

import cv2
import numpy as np

from ._clipped import RIM_RATIO_MAX

# Unclipped pixels read on each flank, from the plateau's rim outward.
FLANK = 4
# Pixels either side of a flank pixel over which the laser-off level must stay within
# `RIM_RATIO_MAX` (in log): the reach of the blur (lens and pixel, ~1 px) and one more.
EDGE_REACH = 2
# Lowest laser light over the ambient light (`R`) of a flank pixel used: an error of the
# laser-off level moves ln R by its relative size over R.
R_MIN = 0.5
# Scan lines on either side whose accepted plateau centres fit `k` and `s`.
CALIB_HALF = 60
# Fewest flank pixels of accepted scan lines in that fit.
CALIB_MIN = 24
# Rounds of that fit: the first against the accepted plateau centres, each next one
# against the accepted scan lines' centres from their own two flanks.
CALIB_ROUNDS = 3
# Largest difference (px) of the centres read from the two flanks; see `rim_centres`.
SIDES_AGREE = 0.25
# A centre read from one flank needs a centre from both (or an accepted plateau centre)
# within this many scan lines on either side along the line (`bracketed`): near the
# line's end, where the target's border cuts the plateau, one flank stays clean.
ONE_SIDE_REACH = 20
# ... and must lie within this many px of the straight line through those within
# `ONE_SIDE_REACH` (at least 6): on a ChArUco print, whose marker bits put albedo edges
# near the flanks everywhere, one-flank centres were up to 0.19 px off the exact line
# (0.16 px with a bound of 0.1 px here); the one-flank centres of a checkerboard are
# 0.04 px RMS off.
ONE_SIDE_LINE = 0.05


def edge_spread(off: np.ndarray, floor: float) -> np.ndarray:
    """(H, W) max - min of `log(max(off, floor))` over the (2 `EDGE_REACH` + 1)² square
    about each pixel (float32)."""
    k = np.ones((2 * EDGE_REACH + 1,) * 2, np.uint8)
    lg = np.log(np.maximum(off.astype(np.float32), np.float32(floor)))
    return cv2.dilate(lg, k) - cv2.erode(lg, k)


def _flank_pixels(on, off, clip, lo, hi, reach, step):
    """Per scan line (columns), up to `FLANK` unclipped pixel offsets beyond the clipped
    run's end in direction `step` (-1: towards lower rows), the run being the one
    through the window's middle row `reach`. Returns (FLANK, W) row offsets into the
    window and a mask of usable ones."""
    n_win, n = on.shape
    idx = np.arange(n_win)[:, None]
    if step < 0:
        beyond = ~clip & (idx < reach)
        first = np.where(beyond.any(0), n_win - 1 - np.argmax(beyond[::-1], 0), -1)
    else:
        beyond = ~clip & (idx > reach)
        first = np.where(beyond.any(0), np.argmax(beyond, 0), n_win)
    k = np.arange(FLANK)[:, None]
    at = first[None, :] + step * k
    inside = (at >= 0) & (at < n_win)
    atc = np.clip(at, 0, n_win - 1)
    cols = np.arange(n)[None, :]
    # contiguous unclipped run from the rim outward
    ok = inside & ~clip[atc, cols] & (first >= 0)[None, :] & (first < n_win)[None, :]
    ok = np.cumprod(ok, axis=0).astype(bool)
    return atc, ok


def rim_centres(on, off, spread, sat_level, row0, reach, y_ref, calib, todo, noise, floor):
    """Centres of the scan lines `todo` from their plateau's flanks.

    **Arguments:**
    - `on`, `off`: (2 reach + 1, W) windows of the laser-on image (its plain channel,
      whose clipping is the plateau) and the denoised laser-off image, rows `row0 - reach
      ... row0 + reach` of each scan line (scan frame); `spread`: the same window of
      the laser-off level's spread (max - min of its log, levels under `floor` as
      `floor`) over +- `EDGE_REACH` px in both directions (`edge_spread`).
    - `sat_level`: the clipping level; `row0`: (W,) int rows at the windows' middles.
    - `y_ref`: (W,) the accepted plateau centres (scan frame), valid at `calib`.
    - `todo`: (W,) bool, the clipped scan lines to measure.
    - `noise`: the pixel noise std (grey levels); `floor`: the lowest laser-off level
      read (a darker albedo shows too little light beside the line).

    **Returns:** (W,) centres (NaN where none) and (W,) bool, read from one flank only.

    A flank pixel is used where it is unclipped, the difference is at least 8 noise
    stds, its laser-off level is at least `floor` and within `RIM_RATIO_MAX` (log) over
    +- `EDGE_REACH` px in both directions (an edge along the scan line mixes the
    neighbouring scan line's albedo and line position in through the blur). `k` and
    `1 / (2 s^2)` are fitted (least squares on `ln R` against `(y - c)^2`) to the flank
    pixels of the accepted scan lines within +- `CALIB_HALF`; each flank pixel then
    gives a centre `y -+ sqrt((k - ln R) 2 s^2)`, and each flank the mean of its
    pixels' centres, weighted by their precision. Where both flanks give one, they must
    agree within `SIDES_AGREE`. One flank alone gives the centre (`one_side`) only
    where the other flank's first pixel is lit by the line too (refused for an albedo
    edge within reach, not for the line's end); the caller judges it against its
    neighbours.
    """
    n_win, n = on.shape
    clip = on >= sat_level
    diff = on - off
    offs = np.arange(n_win)[:, None] - reach
    usable = ~clip & (spread <= RIM_RATIO_MAX) & (off >= floor) & (diff >= 8.0 * noise)
    usable &= diff >= R_MIN * off
    cols = np.arange(n)[None, :]
    sides = []
    lit = []  # the flank's first pixel is lit by the line (the line is there)
    for step in (-1, 1):
        at, ok = _flank_pixels(on, off, clip, 0, n_win, reach, step)
        lit.append(ok[0] & (diff[at[0], cols[0]] >= 8.0 * noise))
        ok &= usable[at, cols]
        y = (row0[None, :] + offs[at, 0]).astype(np.float64)
        z = np.log(np.maximum(diff[at, cols], 1e-6) / np.maximum(off[at, cols], floor))
        # ln R's std from the difference's noise (shot noise of the laser-on level)
        sz = (
            noise
            * np.sqrt(np.maximum(on[at, cols], 1.0) / max(float(np.median(off)), 1.0))
            / np.maximum(diff[at, cols], 1e-6)
        )
        lv = np.log(np.maximum(off[at, cols], floor))
        sides.append((y, z, np.maximum(sz, 1e-3), ok, lv))
    # the laser-off level's log about its middle (the fit's albedo term, `_local_model`)
    lv_all = np.concatenate([sd[4][sd[3]] for sd in sides])
    mid = float(np.median(lv_all)) if lv_all.size else 0.0
    sides = [(y, z, sz, ok, lv - mid) for y, z, sz, ok, lv in sides]
    centre = np.full(n, np.nan)
    one_side = np.zeros(n, bool)
    ref = np.where(calib, y_ref, np.nan)
    for round_ in range(CALIB_ROUNDS):
        kq = _local_model(sides, ref, n, whole=round_ == 0)
        if kq is None:
            return centre, one_side
        both, one, est = _flank_centres(sides, *kq)
        # the accepted scan lines' references from their two flanks: on one albedo the
        # two flanks' errors from a wrong k or s are equal and opposite
        ref = np.where(both, est, np.nan)
    keep = todo & (both | (one & lit[0] & lit[1]))
    centre[keep] = est[keep]
    one_side[keep] = one[keep]
    return centre, one_side


def _local_model(sides, ref, n, whole=False):
    """`k0`, `k1` and `q = 1 / (2 s^2)` per scan line (NaN where fewer than `CALIB_MIN`
    pixels) from the weighted least-squares fit of `ln R = k0 + k1 L - q (y - ref)^2`
    (`L`: the log laser-off level about its middle) to the flank pixels of the scan lines
    within +- `CALIB_HALF` with a reference `ref`; None if there are none at all.

    `k1` takes up a laser-off level that is off by a power of itself (a drawn target's
    black level a few grey levels off: a fixed factor on `R` over the black squares,
    which would move one-flank centres by `s^2 ln(factor) / (y - c)`, ~0.2 px at 15 %);
    with a real laser-off image it fits ~0. It is held towards 0 (a ridge of 0.01 of the
    weights) where the flanks show one albedo only. `whole`: where there are too few
    pixels, the fit to all of them (the accepted plateau centres can be few: short
    pieces between checker edges)."""
    sums = np.zeros((10, n))
    for y, z, sz, ok, lv in sides:
        use = ok & np.isfinite(ref)[None, :]
        x = np.where(use, (y - np.nan_to_num(ref)[None, :]) ** 2, 0.0)
        w = np.where(use, 1.0 / sz**2, 0.0)
        zz = np.where(use, z, 0.0)
        ll = np.where(use, lv, 0.0)
        terms = [use, w, w * ll, w * x, w * ll * ll, w * ll * x, w * x * x, w * zz,
                 w * ll * zz, w * x * zz]  # fmt: skip
        sums += np.stack(terms).sum(axis=1)
    if sums[0].sum() < CALIB_MIN:
        return None
    c = np.zeros((10, n + 1))
    np.cumsum(sums, axis=1, out=c[:, 1:])
    lo = np.clip(np.arange(n) - CALIB_HALF, 0, n)
    hi = np.clip(np.arange(n) + CALIB_HALF + 1, 0, n)
    win = c[:, hi] - c[:, lo]
    if whole:
        win = np.where(win[:1] >= CALIB_MIN, win, c[:, -1:])
    cnt, sw, sl, sx, sll, slx, sxx, sz_, slz, sxz = win
    # normal equations for (k0, k1, -q) with rows (1, L, x)
    A = np.stack([np.stack([sw, sl, sx], -1), np.stack([sl, sll + 0.01 * sw, slx], -1),
                  np.stack([sx, slx, sxx], -1)], -2)  # fmt: skip
    rhs = np.stack([sz_, slz, sxz], -1)
    ok = cnt >= CALIB_MIN
    A = np.where(ok[:, None, None], A, np.eye(3))
    A = A + 1e-12 * np.trace(A, axis1=1, axis2=2)[:, None, None] * np.eye(3)
    sol = np.linalg.solve(A, np.where(ok[:, None], rhs, 0.0)[..., None])[..., 0]
    k0, k1, q = sol[:, 0], sol[:, 1], -sol[:, 2]
    ok &= np.isfinite(q) & (q > 0)
    nan = np.full(n, np.nan)
    return np.where(ok, k0, nan), np.where(ok, k1, nan), np.where(ok, q, nan)


def _flank_centres(sides, k0, k1, q):
    """Per scan line: both flanks give a centre and agree within `SIDES_AGREE`, one
    flank alone gives one, and the centre (their precision-weighted mean)."""
    per = []
    for step, (y, z, sz, ok, lv) in zip((-1, 1), sides, strict=True):
        k = k0[None, :] + k1[None, :] * lv
        d = np.sqrt(np.maximum(k - z, 0.0) / q[None, :])
        c = y - step * d  # the lower flank (step -1): c = y + d
        # each pixel's centre std: sz / |d ln R / dy| = sz / (2 q d)
        wc = np.where(ok & np.isfinite(c), (2.0 * q[None, :] * np.maximum(d, 1.0) / sz) ** 2, 0.0)
        sw = wc.sum(0)
        mean = np.where(sw > 0, (wc * np.nan_to_num(c)).sum(0) / np.where(sw > 0, sw, 1.0), np.nan)
        per.append((mean, sw))
    (c0, w0), (c1, w1) = per
    has0, has1 = w0 > 0, w1 > 0
    both = has0 & has1 & (np.abs(c0 - c1) <= SIDES_AGREE)
    one = has0 ^ has1
    two = (np.nan_to_num(c0) * w0 + np.nan_to_num(c1) * w1) / np.where(has0 | has1, w0 + w1, 1.0)
    est = np.where(both | one, two, np.nan)
    return both, one, est


def bracketed(one: np.ndarray, anchored: np.ndarray, reach: int = ONE_SIDE_REACH) -> np.ndarray:
    """Scan lines of `one` with a scan line of `anchored` within `reach` on each side."""
    n = one.size
    idx = np.arange(n)
    prev = np.maximum.accumulate(np.where(anchored, idx, -n - reach))
    nxt = np.minimum.accumulate(np.where(anchored, idx, 2 * n + reach)[::-1])[::-1]
    return one & (idx - prev <= reach) & (nxt - idx <= reach)
