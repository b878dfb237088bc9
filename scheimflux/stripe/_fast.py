"""Compiled (Numba) loops for the per-scan-line stages of the band extractor.

The NumPy code in `_steger.py` and `_link.py` is the reference: it does each step as a
few dozen whole-array operations on arrays of one value per scan line (1600 for a
1600 x 1200 frame), so at this size the calls' own overhead, not the arithmetic,
costs most of its time. The loops here do the same arithmetic per scan line in one
compiled call, **in the same order and in the same precision** (float32 where the
reference is float32: NumPy keeps float32 when a float32 array meets a Python float,
so every such constant is cast here to float32 first), which gives the same results
to the last bit apart from the transcendental functions (`arctan2`, `sin`, `cos` of
the normal's angle), where NumPy's vectorised versions and the C library may differ
by a unit in the last place. `tests/test_stripe.py` holds both paths equal.

Numba is optional: without it (or with `SCHEIMFLUX_NUMBA=0` in the environment) the
NumPy reference runs. The compiled code is cached on disk (`cache=True`): the first
call on a machine compiles it (seconds), later processes load it.

(One module, longer than most: each loop here sits beside the others it shares helpers
with, and each names the reference function it repeats, which is where to read why.)
"""

from __future__ import annotations

import inspect
import math
import os

import numpy as np

try:
    if os.environ.get("SCHEIMFLUX_NUMBA", "1") == "0":
        raise ImportError("disabled by SCHEIMFLUX_NUMBA=0")
    import numba

    AVAILABLE = True
except ImportError:  # pragma: no cover - depends on the installation
    numba = None
    AVAILABLE = False

#: Whether the extractor uses the compiled loops (tests switch it off to compare).
enabled = AVAILABLE


def _jit(fn):
    if numba is None:  # pragma: no cover
        return fn
    # the plain function: a run-time type-checking import hook (the test suite's
    # jaxtyping hook) wraps every function of the package, and Numba compiles Python
    return numba.njit(cache=True, nogil=True)(inspect.unwrap(fn))


_F32 = np.float32


@_jit
def _sign(x):
    if x > 0:
        return 1.0
    if x < 0:
        return -1.0
    if x == 0:
        return 0.0
    return x  # NaN


@_jit
def _clip01(x):
    if x < 0.0:
        return 0.0
    if x > 1.0:
        return 1.0
    return x  # NaN stays NaN, as np.clip


@_jit
def _line_point(rx, ry, rxx, rxy, ryy, inside):
    """`_steger._line_points` on one pixel (float32 throughout)."""
    half = _F32(0.5)
    half_diff = half * (rxx - ryy)
    root = np.sqrt(half_diff * half_diff + rxy * rxy)
    lam = half * (rxx + ryy) - root
    ax, ay = rxy, lam - rxx
    bx, by = lam - ryy, rxy
    if ax * ax + ay * ay >= bx * bx + by * by:
        vx, vy = ax, ay
    else:
        vx, vy = bx, by
    norm = np.sqrt(vx * vx + vy * vy)
    flip = _F32(-1.0) if vy < 0 else _F32(1.0)
    if norm > 0:
        inv = flip / norm
        ny = vy * inv
    else:
        inv = _F32(0.0)
        ny = _F32(1.0)
    nx = vx * inv
    g = nx * rx + ny * ry
    safe = lam if lam < 0 else _F32(-1.0)
    t = -g / safe
    ok = (lam < 0) and (abs(t * nx) <= inside) and (abs(t * ny) <= inside)
    return nx, ny, lam, t, ok


@_jit
def _sorted_window(padded, window):
    """The first `window` entries of `padded` sorted by insertion, and how many of them
    are finite (missing entries are +inf)."""
    buf = np.empty(window)
    finite = 0
    for m in range(window):
        v = padded[m]
        finite += v < np.inf
        p = m
        while p > 0 and buf[p - 1] > v:
            buf[p] = buf[p - 1]
            p -= 1
        buf[p] = v
    return buf, finite


@_jit
def _slide(buf, gone, v):
    """Replace the value `gone` of the sorted window `buf` by `v`, in place, keeping it
    sorted: `v` takes `gone`'s slot and moves down or up to its place."""
    window = buf.size
    p = 0
    while buf[p] != gone:
        p += 1
    while p > 0 and buf[p - 1] > v:
        buf[p] = buf[p - 1]
        p -= 1
    while p < window - 1 and buf[p + 1] < v:
        buf[p] = buf[p + 1]
        p += 1
    buf[p] = v


@_jit
def _median_normals(nx, ny, found, window):
    """`_steger._smooth_normal` (float64 out): a sorted sliding window (one removal and
    one insertion per scan line) over the angles, padded as the reference pads them."""
    n = nx.size
    half = window // 2
    flip = np.empty(n)
    padded = np.empty(n + 2 * half)
    all_found = True
    for i in range(n):
        all_found = all_found and found[i]
    for i in range(n):
        flip[i] = -1.0 if ny[i] < 0 else 1.0
        phi = np.arctan2(np.float64(nx[i]) * flip[i], np.float64(ny[i]) * flip[i])
        padded[half + i] = phi if (all_found or found[i]) else np.inf
    for i in range(half):
        padded[i] = padded[half] if all_found else np.inf
        padded[n + half + i] = padded[n + half - 1] if all_found else np.inf
    buf, finite = _sorted_window(padded, window)
    sx = np.empty(n)
    sy = np.empty(n)
    for i in range(n):
        if i > 0:  # slide: the value leaving the window is replaced by the new one
            gone, v = padded[i - 1], padded[i + window - 1]
            finite += (v < np.inf) - (gone < np.inf)
            _slide(buf, gone, v)
        if all_found:
            phi = buf[half]
        elif finite >= 3:
            phi = buf[max((finite - 1) // 2, 0)]
        else:
            phi = (
                padded[half + i]
                if found[i]
                else np.arctan2(np.float64(nx[i]) * flip[i], np.float64(ny[i]) * flip[i])
            )
        sx[i] = np.sin(phi) * flip[i]
        sy[i] = np.cos(phi) * flip[i]
    return sx, sy


@_jit
def _hermite(p0, p1, m0, m1):
    a2 = 3.0 * (p1 - p0) - 2.0 * m0 - m1
    a3 = 2.0 * (p0 - p1) + m0 + m1
    b3, b2 = 3.0 * a3, 2.0 * a2
    x = _clip01(p0 / (p0 - p1 if p0 != p1 else 1.0))
    for _ in range(3):
        h = ((a3 * x + a2) * x + m0) * x + p0
        dh = (b3 * x + b2) * x + m0
        x = _clip01(x - h / (dh if dh != 0 else 1.0))
    return x


@_jit
def _interp(flat, pos, top, ccol, h_s, n_cols):
    """The smoothed composite at scan coordinate `pos` (linear), rows clipped."""
    lo = np.floor(pos)
    f = pos - lo
    li = np.intp(lo)
    c0 = min(max(li - top, 0), h_s - 1)
    c1 = min(max(li + 1 - top, 0), h_s - 1)
    return (1 - f) * flat[c0 * n_cols + ccol] + f * flat[c1 * n_cols + ccol]


@_jit
def band_lines(
    r, rx, ry, rxx, rxy, ryy, rows, smooth, top, ccol, lo, hi, bg_off, sigma, s_total,
    reach, inside, fwhm_per_sigma, window,
):  # fmt: skip
    """`_select`, `_evaluate` and `_asymmetry` of `_steger.steger_band` in one pass.

    `r .. ryy`: the (K, W) float32 window derivatives; `rows`: (K, W) their image rows;
    `smooth`: the smoothed composite (flattened rows of `n_cols`), read at the image
    row `row` of scan line `j` at `(row - top[j]) * n_cols + ccol[j]`.

    **Returns:** `(y, strength, width, found, row, asym, ny, ok)`; `ok` is False when a
    background sample falls outside the composite (the caller then runs the reference,
    which raises).
    """
    k_rows, n = rx.shape
    h_s, n_cols = smooth.shape
    flat = smooth.reshape(-1)
    inside32 = _F32(inside)
    best = np.empty(n, np.intp)
    found = np.zeros(n, np.bool_)
    nx = np.empty(n, np.float32)
    ny = np.empty(n, np.float32)
    lam = np.empty(n, np.float32)
    tt = np.empty(n, np.float32)
    half = _F32(0.5)
    # the most negative eigenvalue among the rows lo..hi-1 per column (first one), row
    # by row (contiguous, vectorised)
    lbest = np.empty(n, np.float32)
    for k in range(lo, hi):
        for j in range(n):
            a, b, c = rxx[k, j], rxy[k, j], ryy[k, j]
            hd = half * (a - c)
            lk = half * (a + c) - np.sqrt(hd * hd + b * b)
            if k == lo or lk < lbest[j]:
                lbest[j] = lk
                best[j] = k
    for j in range(n):
        kb = best[j]
        nx_, ny_, lam_, t_, ok_ = _line_point(
            rx[kb, j], ry[kb, j], rxx[kb, j], rxy[kb, j], ryy[kb, j], inside32
        )
        if not ok_:
            # strongest line point of the column (first one), or row lo if none
            kb = lo
            ok_ = False
            sb = np.float32(-np.inf)
            for k in range(lo, hi):
                nk, yk, lk, tk, is_line = _line_point(
                    rx[k, j], ry[k, j], rxx[k, j], rxy[k, j], ryy[k, j], inside32
                )
                if is_line and -lk > sb:
                    sb, kb, ok_ = -lk, k, True
            nx_, ny_, lam_, t_, _ = _line_point(
                rx[kb, j], ry[kb, j], rxx[kb, j], rxy[kb, j], ryy[kb, j], inside32
            )
        best[j], found[j], nx[j], ny[j], lam[j], tt[j] = kb, ok_, nx_, ny_, lam_, t_

    # background level and slopes beside the chosen pixel
    bg = np.empty(n, np.float32)
    grad_y = np.empty(n, np.float32)
    two_off = _F32(2.0 * bg_off)
    for j in range(n):
        row = rows[best[j], j]
        i0 = (row - bg_off - top[j]) * n_cols + ccol[j]
        i1 = (row + bg_off - top[j]) * n_cols + ccol[j]
        if i0 < 0 or i1 < 0 or i0 >= flat.size or i1 >= flat.size:
            return (np.empty(0), np.empty(0), np.empty(0), found, np.empty(0), np.empty(0),
                    np.empty(0), False)  # fmt: skip
        b0, b1 = flat[i0], flat[i1]
        bg[j] = half * (b0 + b1)
        grad_y[j] = (b1 - b0) / two_off
    grad_x = np.zeros(n, np.float32)
    if n > 1:
        grad_x[0] = bg[1] - bg[0]
        grad_x[n - 1] = bg[n - 1] - bg[n - 2]
        for j in range(1, n - 1):
            grad_x[j] = (bg[j + 1] - bg[j - 1]) / _F32(2.0)
    nxs, nys = _median_normals(nx, ny, found, window)

    y = np.empty(n)
    strength = np.empty(n)
    width = np.empty(n)
    rowk = np.empty(n)
    asym = np.empty(n)
    s32 = _F32(sigma)
    ss32 = _F32(sigma * sigma)
    fw32 = _F32(fwhm_per_sigma)
    for j in range(n):
        k = best[j]
        km, kp = max(k - 1, 0), min(k + 1, k_rows - 1)
        nxk, nyk = nxs[j], nys[j]
        g0 = nxk * (rx[k, j] - grad_x[j]) + nyk * (ry[k, j] - grad_y[j])
        gm = nxk * (rx[km, j] - grad_x[j]) + nyk * (ry[km, j] - grad_y[j])
        gp = nxk * (rx[kp, j] - grad_x[j]) + nyk * (ry[kp, j] - grad_y[j])
        d0 = nxk * rxy[k, j] + nyk * ryy[k, j]
        dm = nxk * rxy[km, j] + nyk * ryy[km, j]
        dp = nxk * rxy[kp, j] + nyk * ryy[kp, j]
        rk = np.float64(rows[k, j])
        if abs(nyk) > 0.2:
            ny_safe = nyk
        else:
            ny_safe = math.copysign(0.2, nyk + 1e-300)
        yj = rk + tt[j] / ny_safe
        up = (_sign(g0) != _sign(gp)) and (k + 1 < k_rows)
        down = (not up) and (_sign(gm) != _sign(g0)) and (k >= 1)
        if up:
            yj = rk + _hermite(g0, gp, d0, dp)
        elif down:
            yj = (rk - 1.0) + _hermite(gm, g0, dm, d0)
        if g0 == 0:
            yj = rk
        lk = lam[j]
        strength[j] = np.float64((-lk * s32) * s32) if found[j] else 0.0
        height = r[k, j] - bg[j]
        s2 = height / (-lk if lk < 0 else np.float32(np.inf))
        wv = s2 - ss32
        if wv < 0:
            wv = _F32(0.0)
        wj = fw32 * np.sqrt(wv)
        width[j] = np.float64(wj) if (found[j] and s2 > 0) else np.nan
        y[j] = yj if found[j] else np.nan
        rowk[j] = rk

        # asymmetry of the smoothed profile about the centre
        ok = found[j] and np.isfinite(y[j])
        yc = y[j] if ok else rk
        delta = min(s_total / max(abs(nyk), 0.2), np.float64(reach))
        tj, cj = top[j], ccol[j]
        centre = _interp(flat, yc, tj, cj, h_s, n_cols)
        plus = _interp(flat, yc + delta, tj, cj, h_s, n_cols)
        minus = _interp(flat, yc - delta, tj, cj, h_s, n_cols)
        hgt = centre - bg[j]
        if ok and hgt > 0:
            asym[j] = (plus - minus) / hgt
        else:
            asym[j] = np.nan
    return y, strength, width, found, rowk, asym, nys, True


@_jit
def local_fit(y, w, half):
    """`_link._local_fit` for (M, N) weights: predictions and counts, (M, N) each."""
    m_w, n = w.shape
    pred = np.empty((m_w, n))
    count = np.empty((m_w, n))
    u = np.empty(n)
    for i in range(n):
        u[i] = i / half
    prefix = np.zeros((8, n + 1))
    for m in range(m_w):
        for i in range(n):
            wi = w[m, i]
            ui = u[i]
            u2 = ui * ui
            yw = (y[i] if wi > 0 else 0.0) * wi
            wu2 = wi * u2
            cols = (wi, wi * ui, wu2, wu2 * ui, wu2 * u2, yw, yw * ui, yw * u2)
            for k in range(8):
                prefix[k, i + 1] = prefix[k, i] + cols[k]
        for i in range(n):
            a = min(i + half + 1, n)
            b = max(i - half, 0)
            S0 = prefix[0, a] - prefix[0, b]
            S1 = prefix[1, a] - prefix[1, b]
            S2 = prefix[2, a] - prefix[2, b]
            S3 = prefix[3, a] - prefix[3, b]
            S4 = prefix[4, a] - prefix[4, b]
            T0 = prefix[5, a] - prefix[5, b]
            T1 = prefix[6, a] - prefix[6, b]
            T2 = prefix[7, a] - prefix[7, b]
            ai = u[i]
            a2 = ai * ai
            wi = w[m, i]
            yw = (y[i] if wi > 0 else 0.0) * wi
            s0 = S0 - wi
            s1 = S1 - ai * S0
            s2 = S2 - 2 * ai * S1 + a2 * S0
            s3 = S3 - 3 * ai * S2 + 3 * a2 * S1 - a2 * ai * S0
            s4 = S4 - 4 * ai * S3 + 6 * a2 * S2 - 4 * a2 * ai * S1 + a2 * a2 * S0
            t0 = T0 - yw
            t1 = T1 - ai * T0
            t2 = T2 - 2 * ai * T1 + a2 * T0
            c00 = s2 * s4 - s3 * s3
            c01 = s1 * s4 - s2 * s3
            c02 = s1 * s3 - s2 * s2
            det = s0 * c00 - s1 * c01 + s2 * c02
            num = t0 * c00 - s1 * (t1 * s4 - s3 * t2) + s2 * (t1 * s3 - s2 * t2)
            good = (s0 >= 6) and (abs(det) > 1e-9 * max(s0, 1.0) ** 3)
            pred[m, i] = num / det if good else np.nan
            count[m, i] = s0 if good else 0.0
    return pred, count


@_jit
def windowed_median(values, ok, window):
    """`_coarse._windowed_median`: median of the `ok` entries in a centred window of
    `window` (odd) entries, NaN where there are none; a sorted sliding window."""
    n = values.size
    half = window // 2
    padded = np.full(n + 2 * half, np.inf)
    for i in range(n):
        if ok[i]:
            padded[half + i] = values[i]
    buf, finite = _sorted_window(padded, window)
    out = np.empty(n)
    for i in range(n):
        if i > 0:  # slide: the value leaving the window is replaced by the new one
            gone, v = padded[i - 1], padded[i + window - 1]
            finite += (v < np.inf) - (gone < np.inf)
            _slide(buf, gone, v)
        out[i] = buf[(finite - 1) // 2] if finite > 0 else np.nan
    return out


@_jit
def link_segments(y, valid, strength, max_jump_px, max_gap, min_points, high, trim, min_line):
    """`_link.link_segments` (labels, kept mask): one pass over the valid centres."""
    n = y.size
    labels = np.full(n, -1, np.intp)
    keep = np.zeros(n, np.bool_)
    idx = np.flatnonzero(valid)
    m = idx.size
    if m == 0:
        return labels, keep
    seg = np.empty(m, np.intp)
    first = np.empty(m, np.intp)  # per segment: its first and last member, its peak
    last = np.empty(m, np.intp)
    peak = np.empty(m)
    s = -1
    for i in range(m):
        new = i == 0
        if not new:
            step = idx[i] - idx[i - 1]
            jump = abs(y[idx[i]] - y[idx[i - 1]])
            new = (step > max_gap + 1) or (jump > max_jump_px * step)
        v = strength[idx[i]]
        if new:
            s += 1
            first[s] = i
            peak[s] = v
        elif not np.isnan(peak[s]) and (np.isnan(v) or v > peak[s]):
            peak[s] = v  # np.maximum: NaN propagates
        last[s] = i
        seg[i] = s
    n_seg = s + 1
    long_gap = max(2 * min_points, 3)
    any_line = False
    keep_seg = np.empty(n_seg, np.bool_)
    for s in range(n_seg):
        keep_seg[s] = (last[s] - first[s] + 1 >= min_points) and (peak[s] >= high)
        if keep_seg[s] and idx[last[s]] - idx[first[s]] + 1 >= min_line:
            any_line = True
    if not any_line:
        return labels, keep
    for i in range(m):
        s = seg[i]
        if not keep_seg[s]:
            continue
        if trim > 0:
            gap_before = idx[0] if s == 0 else idx[first[s]] - idx[last[s - 1]] - 1
            gap_after = (
                n - 1 - idx[m - 1] if s == n_seg - 1 else idx[first[s + 1]] - idx[last[s]] - 1
            )
            dist_first = idx[i] - idx[first[s]] if gap_before >= long_gap else trim
            dist_last = idx[last[s]] - idx[i] if gap_after >= long_gap else trim
            if min(dist_first, dist_last) < trim:
                continue
        labels[idx[i]] = s
        keep[idx[i]] = True
    return labels, keep


@_jit
def tile_rows(scan, rows, start, tile_w):
    """`_steger._tiles`' composite: `comp[i, t tile_w + c] = scan[rows[i, t], start[t] + c]`
    as float32 (the same values as the reference's fancy index and cast)."""
    height, n_tiles = rows.shape
    comp = np.empty((height, n_tiles * tile_w), np.float32)
    for i in range(height):
        for t in range(n_tiles):
            r = rows[i, t]
            s = start[t]
            base = t * tile_w
            for c in range(tile_w):
                comp[i, base + c] = np.float32(scan[r, s + c])
    return comp


@_jit
def gather_rows(src, row0, ccol, n_rows):
    """`out[q, j] = src[row0[j] + q, ccol[j]]` for q < n_rows, float32; `ok` False when a
    row falls outside `src` (the caller then runs the reference's indexing)."""
    h, w = src.shape
    n = row0.size
    out = np.empty((n_rows, n), np.float32)
    for j in range(n):
        if row0[j] < 0 or row0[j] + n_rows > h or ccol[j] < 0 or ccol[j] >= w:
            return out, False
    for q in range(n_rows):
        for j in range(n):
            out[q, j] = src[row0[j] + q, ccol[j]]
    return out, True


@_jit
def ridge_rows(small, d):
    """`_ridge.ridge_response(small, d, 0)` (float32): `min(c - up, c - down)` along the
    rows, 0 within `d` rows of the ends."""
    h, w = small.shape
    out = np.zeros((h, w), np.float32)
    for i in range(d, h - d):
        for j in range(w):
            c = small[i, j]
            out[i, j] = min(c - small[i - d, j], c - small[i + d, j])
    return out


@_jit
def column_argmax(a):
    """`np.argmax(a, axis=0)` of a 2-D array without NaN (first maximum per column)."""
    h, w = a.shape
    best = np.zeros(w, np.intp)
    top = a[0].copy()
    for i in range(1, h):
        for j in range(w):
            if a[i, j] > top[j]:
                top[j] = a[i, j]
                best[j] = i
    return best


@_jit
def _median(x):
    """`_image._median` (the mean of the two middle values for an even count)."""
    s = np.sort(x)
    m = s.size // 2
    if s.size % 2:
        return s[m]
    return (s[m - 1] + s[m]) / 2


@_jit
def consistent_passes(yv, valid, keep, off_curve, half, floor_px):
    """The two local-fit passes of `_link.consistent` (after its global cubic)."""
    n = yv.size
    any_off = False
    for i in range(n):
        any_off = any_off or off_curve[i]
    keep = keep.copy()
    for step in range(2):
        factor, floor = (3.0, 1.0) if step == 0 else (5.0, floor_px)
        if step == 0 and any_off:
            w = np.empty((2, n))
            for i in range(n):
                w[0, i] = 1.0 if keep[i] else 0.0
                w[1, i] = 1.0 if valid[i] else 0.0
            p, c = local_fit(yv, w, half)
            pred, count = p[0].copy(), c[0].copy()
            for i in range(n):
                # a piece of line the global cubic does not follow, judged by its own
                if count[i] < 6 and c[1, i] >= 30:
                    pred[i], count[i] = p[1, i], c[1, i]
        else:
            w = np.empty((1, n))
            for i in range(n):
                w[0, i] = 1.0 if keep[i] else 0.0
            p, c = local_fit(yv, w, half)
            pred, count = p[0], c[0]
        r = np.abs(yv - pred)
        judged = np.zeros(n, np.bool_)
        n_judged = 0
        n_kept = 0
        for i in range(n):
            judged[i] = valid[i] and count[i] >= 6 and np.isfinite(r[i])
            n_judged += judged[i]
            n_kept += judged[i] and keep[i]
        if n_judged == 0:
            for i in range(n):
                keep[i] = keep[i] and not off_curve[i]
            return keep
        spread = 0.0
        if n_kept > 0:
            vals = np.empty(n_kept)
            k = 0
            for i in range(n):
                if judged[i] and keep[i]:
                    vals[k] = r[i]
                    k += 1
            spread = 1.4826 * _median(vals)
        thr = max(floor, factor * spread)
        for i in range(n):
            keep[i] = (
                valid[i] and not (judged[i] and r[i] > thr) and not (off_curve[i] and not judged[i])
            )
    return keep
