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
    from numba import types as _nb_types
    from numba.extending import intrinsic as _intrinsic

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
    # jaxtyping hook) wraps every function of the package, and Numba compiles Python.
    # No C-callable wrapper (only for passing a kernel as a first-class function, which
    # nothing here does): less code to compile.
    return numba.njit(cache=True, nogil=True, no_cfunc_wrapper=True)(inspect.unwrap(fn))


def _jit_inner(fn):
    """`_jit` for the helpers that only compiled code calls: no Python-callable wrapper
    either (the unboxing of every argument is most of a small function's code)."""
    if numba is None:  # pragma: no cover
        return fn
    return numba.njit(cache=True, nogil=True, no_cfunc_wrapper=True, no_cpython_wrapper=True)(
        inspect.unwrap(fn)
    )


def _jit_inline(fn):
    """`_jit_inner`, inlined into its callers in Numba's IR (no call, no reference counts)."""
    if numba is None:  # pragma: no cover
        return fn
    return numba.njit(
        cache=True, nogil=True, no_cfunc_wrapper=True, no_cpython_wrapper=True, inline="always"
    )(inspect.unwrap(fn))


_F32 = np.float32

if numba is not None:

    @_intrinsic
    def _fma(typingctx, a, b, c):
        """Fused multiply-add of three float32 values (one rounding): `a b + c`."""
        f32 = _nb_types.float32
        sig = f32(f32, f32, f32)

        def codegen(context, builder, signature, args):
            return builder.fma(*args)

        return sig, codegen

    # LAPACK's `dgesv`, as `np.linalg.solve` calls it in compiled code (the same routine,
    # so the same values): called directly, its checks written out in `_solve4`, since
    # the generic wrapper (any shape and type, formatted messages) compiles for ~8 s.
    # (Numba's internal names: where a version lacks them, `np.linalg.solve` is used.)
    try:
        from numba.np import linalg as _nb_linalg

        _nb_linalg.ensure_lapack()
        _xgesv = _nb_linalg._LAPACK().numba_xgesv(_nb_types.float64)
        _F_INT = _nb_linalg.F_INT_nptype
        _keep_alive = _nb_linalg._dummy_liveness_func
    except (ImportError, AttributeError):  # pragma: no cover - other Numba versions
        _xgesv = None

else:  # pragma: no cover - the NumPy reference runs instead

    def _fma(a, b, c):
        return np.float32(np.float64(a) * np.float64(b) + np.float64(c))


@_jit_inner
def _sign(x):
    if x > 0:
        return 1.0
    if x < 0:
        return -1.0
    if x == 0:
        return 0.0
    return x  # NaN


@_jit_inner
def _clip01(x):
    if x < 0.0:
        return 0.0
    if x > 1.0:
        return 1.0
    return x  # NaN stays NaN, as np.clip


@_jit_inner
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


@_jit_inner
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


@_jit_inner
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


@_jit_inner
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


@_jit_inner
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


# --- the band's derivatives: OpenCV's separable filters repeated -------------------------
# `_steger.steger_band`'s reference filters a composite of tiles with `cv2.sepFilter2D`
# (float32). The loops below compute the same values only where they are read, with
# OpenCV's arithmetic on x86 (checked to the last bit by `tests/test_stripe.py`): the
# row pass `k[0] x[0]` then one fused multiply-add per tap in order; the column pass
# on symmetric (antisymmetric) kernels `k[r] x[0]` (0) then one fused multiply-add of
# `x[+t] + x[-t]` (`x[+t] - x[-t]`) per tap, except in the last `width % 8` columns of
# the filtered array, where OpenCV's remainder loop rounds the product and the sum
# apart. The composite's layout (which scan line sits in which column, its first row
# per scan line and its height) is the reference's, so that even its borders read the
# same data.

#: Columns OpenCV's float32 row (column) filter processes at a time with fused
#: multiply-adds; the remainder of the array's width is computed without (x86, AVX2).
ROW_LANES = 4
COL_LANES = 8


@_jit_inner
def _row_pass(buf, boff, k, out, ooff, count):
    """`out[ooff + m] = sum_t k[t] buf[boff + m + t]` for m < count (flat float32 arrays),
    as OpenCV's float32 row filter. (Views, so that every index is a sum of loop
    counters: Numba's check for negative indices would keep the loops from being
    vectorised.)"""
    src = buf[boff:]
    dst = out[ooff : ooff + count]
    k_first = k[0]
    for m in range(count):
        dst[m] = src[m] * k_first
    for t in range(1, k.size):
        kt = k[t]
        for m in range(count):
            dst[m] = _fma(src[m + t], kt, dst[m])


@_jit_inner
def _row_pass3(buf, boff, k0, k1, k2, out0, out1, out2, ooff, count):
    """`_row_pass` with three kernels of one size at once (each input read once)."""
    src = buf[boff:]
    d0 = out0[ooff : ooff + count]
    d1 = out1[ooff : ooff + count]
    d2 = out2[ooff : ooff + count]
    a0, a1, a2 = k0[0], k1[0], k2[0]
    for m in range(count):
        x = src[m]
        d0[m] = x * a0
        d1[m] = x * a1
        d2[m] = x * a2
    for t in range(1, k0.size):
        a0, a1, a2 = k0[t], k1[t], k2[t]
        for m in range(count):
            x = src[m + t]
            d0[m] = _fma(x, a0, d0[m])
            d1[m] = _fma(x, a1, d1[m])
            d2[m] = _fma(x, a2, d2[m])


@_jit_inner
def _col_pass2(src, first, stride, k_sym, k_anti, out_sym, out_anti, count):
    """`_col_pass` with a symmetric and an antisymmetric kernel of one size at once."""
    r = k_sym.size // 2
    ds = out_sym[:count]
    da = out_anti[:count]
    kc = k_sym[r]
    mid = src[first : first + count]
    for m in range(count):
        ds[m] = mid[m] * kc
        da[m] = _F32(0.0)
    for t in range(1, r + 1):
        ks, ka = k_sym[r + t], k_anti[r + t]
        up = src[first + t * stride : first + t * stride + count]
        down = src[first - t * stride : first - t * stride + count]
        for m in range(count):
            u, v = up[m], down[m]
            ds[m] = _fma(u + v, ks, ds[m])
            da[m] = _fma(u - v, ka, da[m])


@_jit_inner
def _row_fused(buf, k, i):
    """One output of `_row_pass`."""
    s = buf[i] * k[0]
    for t in range(1, k.size):
        s = _fma(buf[i + t], k[t], s)
    return s


@_jit_inner
def _row_value(buf, k, i):
    """One output of `_row_pass` as OpenCV's remainder columns compute it: product and
    sum rounded apart, except in the taps past the last multiple of 4 (its compiled
    loop, unrolled by 4, fuses them in its own remainder)."""
    s = buf[i] * k[0]
    fused_from = 4 * ((k.size - 1) // 4) + 1
    for t in range(1, k.size):
        if t >= fused_from:
            s = _fma(buf[i + t], k[t], s)
        else:
            s = s + buf[i + t] * k[t]
    return s


@_jit_inner
def _col_pass(src, first, stride, k, anti, out, count):
    """`out[m] = sum_t k[t] src[first + m + (t - r) stride]` for m < count (flat float32
    arrays of rows of `stride`), as OpenCV's float32 (anti)symmetric column filter."""
    r = k.size // 2
    dst = out[:count]
    if anti:
        for m in range(count):
            dst[m] = _F32(0.0)
    else:
        kc = k[r]
        mid = src[first : first + count]
        for m in range(count):
            dst[m] = mid[m] * kc
    for t in range(1, r + 1):
        kt = k[r + t]
        up = src[first + t * stride : first + t * stride + count]
        down = src[first - t * stride : first - t * stride + count]
        if anti:
            for m in range(count):
                dst[m] = _fma(up[m] - down[m], kt, dst[m])
        else:
            for m in range(count):
                dst[m] = _fma(up[m] + down[m], kt, dst[m])


@_jit_inner
def _col_value(src, c, stride, k, anti, fused):
    """One output of `_col_pass` at flat index `c`; `fused=False`: the product and the
    sum rounded apart (OpenCV's remainder columns)."""
    r = k.size // 2
    s = _F32(0.0) if anti else src[c] * k[r]
    for t in range(1, r + 1):
        up, down = src[c + t * stride], src[c - t * stride]
        x = up - down if anti else up + down
        s = _fma(x, k[r + t], s) if fused else s + x * k[r + t]
    return s


@_jit_inline
def _plain(ccol, n_comp, lanes):
    """Whether composite column `ccol` is in OpenCV's remainder of `n_comp` columns
    processed `lanes` at a time."""
    return ccol >= lanes * (n_comp // lanes)


@_jit
def _smooth_at(q, j, strip, strip_top, main_top, main_h, scan, colsrc, coltop, ccol, k0):
    """The reference's smoothed composite at its row `q` (in [0, main_h)) of scan line
    `j`: from `strip` where that row is an interior one held there, else computed here
    with the composite's replicated border rows."""
    r = k0.size // 2
    p = main_top[j] + q - strip_top[j]
    if q >= r and q < main_h - r and p >= 0 and p < strip.shape[0] and not np.isnan(strip[p, j]):
        return strip[p, j]
    h = scan.shape[0]
    n_comp = colsrc.size
    plain_rows = _plain(ccol[j], n_comp, ROW_LANES)
    col = np.empty(2 * r + 1, np.float32)
    buf = np.empty(2 * r + 1, np.float32)
    zero = np.intp(0)
    for t in range(2 * r + 1):
        qq = min(max(q - r + t, 0), main_h - 1)
        for b in range(2 * r + 1):
            cc = min(max(ccol[j] - r + b, 0), n_comp - 1)
            buf[b] = np.float32(scan[min(max(coltop[cc] + qq, 0), h - 1), colsrc[cc]])
        # (an intp 0, not the literal: one compiled specialisation of the callees)
        col[t] = _row_value(buf, k0, zero) if plain_rows else _row_fused(buf, k0, zero)
    return _col_value(col, r, 1, k0, False, not _plain(ccol[j], n_comp, COL_LANES))


@_jit
def band_window(scan, centre, k0, k1, k2, k_search, s_rows, colsrc, coltop, ccol, tile):
    """The window arrays of `_steger.steger_band` (smoothed image and the five
    derivatives at the `2 k_search + 1` rows around `centre` (W,) of each scan line)
    and a strip of the smoothed image at `± s_rows` around it, from the scan-frame
    image `scan` in tiles of `tile` scan lines (each within one of the reference's).

    `colsrc`, `coltop` (n_comp,): the scan line in each column of the reference's
    composite and the image row of its first row; `ccol` (W,): each scan line's column
    there.

    **Returns:** `(win, strip, strip_top)`: (6, K, W), (n_strip, W) float32 and the
    image row of each scan line's first strip row (rows past a tile's own: NaN).
    """
    h, w = scan.shape
    n_comp = colsrc.size
    r = k0.size // 2
    kk = 2 * k_search + 1
    kr = k_search + r
    sr = max(s_rows, k_search) + r
    n_tiles = (w + tile - 1) // tile
    spread = 0
    for t in range(n_tiles):
        lo, hi = centre[t * tile], centre[t * tile]
        for j in range(t * tile, min(t * tile + tile, w)):
            lo, hi = min(lo, centre[j]), max(hi, centre[j])
        spread = max(spread, hi - lo)
    win = np.empty((6, kk, w), np.float32)
    strip = np.empty((spread + 2 * s_rows + 1, w), np.float32)
    strip_top = np.empty(w, np.intp)
    # per tile, flat arrays of rows of `nb` (the tile's scan lines and r more on each
    # side; the filters' outputs past the tile's own columns are never read)
    nb = tile + 2 * r
    n0 = spread + 2 * sr + 1
    n1 = spread + 2 * kr + 1
    buf = np.empty(n0 * nb + 2 * r, np.float32)
    buf[n0 * nb :] = 0.0
    h0 = np.empty(n0 * nb, np.float32)
    h1 = np.empty(n1 * nb, np.float32)
    h2 = np.empty(n1 * nb, np.float32)
    sm = np.empty((spread + 2 * s_rows + 1) * nb, np.float32)
    dv = np.empty((5, (spread + kk) * nb), np.float32)
    at = np.empty(tile, np.intp)  # per scan line of a tile: its flat offset in `dv`
    for t in range(n_tiles):
        j0 = t * tile
        n = min(tile, w - j0)
        lo, hi = centre[j0], centre[j0]
        for j in range(j0, j0 + n):
            lo, hi = min(lo, centre[j]), max(hi, centre[j])
        # the composite's rows lo - sr .. hi + sr around the tile (h1, h2: the inner ones)
        m0 = hi - lo + 2 * sr + 1
        m1 = hi - lo + 2 * kr + 1
        c_first = ccol[j0] - r
        c_last = c_first + n + 2 * r - 1
        top0 = coltop[min(max(c_first, 0), n_comp - 1)]
        simple = (
            c_first >= 0 and c_last < n_comp and coltop[c_last] == top0
            and colsrc[c_last] - colsrc[c_first] == n + 2 * r - 1
        )  # fmt: skip
        row0 = lo - sr - coltop[ccol[j0]]  # the composite's row of the first one
        for q in range(m0):
            if simple:
                rho = min(max(top0 + row0 + q, 0), h - 1)
                src = scan[rho, colsrc[c_first] : colsrc[c_first] + n + 2 * r]
                dst = buf[q * nb : q * nb + n + 2 * r]
                for b in range(n + 2 * r):
                    dst[b] = np.float32(src[b])
            else:
                for b in range(n + 2 * r):
                    cc = min(max(c_first + b, 0), n_comp - 1)
                    rho = min(max(coltop[cc] + row0 + q, 0), h - 1)
                    buf[q * nb + b] = np.float32(scan[rho, colsrc[cc]])
        q_in = sr - kr  # h0's row of h1's first
        zero = np.intp(0)  # (not the literal: one compiled specialisation of `_row_pass`)
        _row_pass(buf, zero, k0, h0, zero, q_in * nb)
        _row_pass3(buf, q_in * nb, k0, k1, k2, h0[q_in * nb :], h1, h2, 0, m1 * nb)
        _row_pass(buf, (q_in + m1) * nb, k0, h0, (q_in + m1) * nb, (m0 - q_in - m1) * nb)
        for i in range(n):
            if _plain(ccol[j0 + i], n_comp, ROW_LANES):
                for q in range(m0):
                    h0[q * nb + i] = _row_value(buf, k0, q * nb + i)
                for q in range(m1):
                    h1[q * nb + i] = _row_value(buf, k1, (q + sr - kr) * nb + i)
                    h2[q * nb + i] = _row_value(buf, k2, (q + sr - kr) * nb + i)
        # column passes: the derivatives at the rows lo - k_search .. hi + k_search and
        # the smoothed image at lo - s_rows .. hi + s_rows
        n_d = hi - lo + kk
        n_s = hi - lo + 2 * s_rows + 1
        f0, f1 = r * nb, (sr - k_search) * nb
        _col_pass2(h1, f0, nb, k0, k1, dv[0], dv[3], n_d * nb)  # r_x, r_xy
        _col_pass2(h0, f1, nb, k2, k1, dv[4], dv[1], n_d * nb)  # r_yy, r_y
        _col_pass(h2, f0, nb, k0, False, dv[2], n_d * nb)  # r_xx
        fs = (sr - s_rows) * nb
        _col_pass(h0, fs, nb, k0, False, sm, n_s * nb)
        for i in range(n):
            j = j0 + i
            if _plain(j, w, COL_LANES):
                for p in range(n_d):
                    e = p * nb + i
                    dv[0, e] = _col_value(h1, f0 + e, nb, k0, False, False)
                    dv[1, e] = _col_value(h0, f1 + e, nb, k1, True, False)
                    dv[2, e] = _col_value(h2, f0 + e, nb, k0, False, False)
                    dv[3, e] = _col_value(h1, f0 + e, nb, k1, True, False)
                    dv[4, e] = _col_value(h0, f1 + e, nb, k2, False, False)
            if _plain(ccol[j], n_comp, COL_LANES):
                for p in range(n_s):
                    sm[p * nb + i] = _col_value(h0, fs + p * nb + i, nb, k0, False, False)
            strip_top[j] = lo - s_rows
        # each scan line's window rows, one window row of the tile at a time (stores
        # along the scan lines: contiguous)
        for i in range(n):
            at[i] = (centre[j0 + i] - lo) * nb + i
        for o in range(kk):
            dst = win[0, o, j0 : j0 + n]
            src = sm[(s_rows - k_search + o) * nb :]
            for i in range(n):
                dst[i] = src[at[i]]
            for d in range(5):
                dst = win[d + 1, o, j0 : j0 + n]
                src = dv[d, o * nb :]
                for i in range(n):
                    dst[i] = src[at[i]]
        for p in range(strip.shape[0]):
            dst = strip[p, j0 : j0 + n]
            if p < n_s:
                src = sm[p * nb : p * nb + n]
                for i in range(n):
                    dst[i] = src[i]
            else:
                for i in range(n):
                    dst[i] = np.nan
    return win, strip, strip_top


@_jit_inline
def _in_strip(q, p, main_h, r, n_strip):
    """Whether the smoothed composite's row `q` is an interior one that `band_window`'s
    strip holds, at its row `p` (its value there: NaN for rows past the tile's own, read
    through `_smooth_at` then). (Scalars only: an inlined helper taking the arrays would
    count references to each of them on every call.)"""
    return q >= r and q < main_h - r and p >= 0 and p < n_strip


@_jit
def band_lines(
    r, rx, ry, rxx, rxy, ryy, rows, strip, strip_top, main_top, main_h, scan, colsrc, coltop,
    ccol, k0, lo, hi, bg_off, sigma, s_total, reach, inside, fwhm_per_sigma, window,
):  # fmt: skip
    """`_select`, `_evaluate` and `_asymmetry` of `_steger.steger_band` in one pass.

    `r .. ryy`: the (K, W) float32 window derivatives; `rows`: (K, W) their image rows;
    the reference's smoothed composite (`main_h` rows, row `row - main_top[j]` of scan
    line `j` at image row `row`) is read through `_smooth_at` (`strip`, `strip_top`,
    `scan`, `colsrc`, `coltop`, `ccol`, `k0`: see `band_window`).

    **Returns:** `(y, strength, width, found, row, asym, ny, ok)`; `ok` is False when a
    background sample falls outside the composite (the caller then runs the reference,
    which raises).
    """
    k_rows, n = rx.shape
    r_k = k0.size // 2
    sampled = np.empty(3)
    pair = np.empty(2, np.float32)
    n_strip = strip.shape[0]
    nan32 = _F32(np.nan)
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
        q0 = row - bg_off - main_top[j]
        q1 = row + bg_off - main_top[j]
        if q0 < 0 or q1 < 0 or q0 >= main_h or q1 >= main_h:
            return (np.empty(0), np.empty(0), np.empty(0), found, np.empty(0), np.empty(0),
                    np.empty(0), False)  # fmt: skip
        for e in range(2):
            q = q0 if e == 0 else q1
            p = main_top[j] + q - strip_top[j]
            v = strip[p, j] if _in_strip(q, p, main_h, r_k, n_strip) else nan32
            if np.isnan(v):
                v = _smooth_at(q, j, strip, strip_top, main_top, main_h, scan, colsrc, coltop,
                               ccol, k0)  # fmt: skip
            pair[e] = v
        b0, b1 = pair[0], pair[1]
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
        # the smoothed composite at yc, yc + delta, yc - delta (linear), rows clipped
        for e in range(3):
            pos = yc if e == 0 else (yc + delta if e == 1 else yc - delta)
            lo_f = np.floor(pos)
            f = pos - lo_f
            li = np.intp(lo_f)
            for s in range(2):
                q = min(max(li + s - main_top[j], 0), main_h - 1)
                p = main_top[j] + q - strip_top[j]
                v = strip[p, j] if _in_strip(q, p, main_h, r_k, n_strip) else nan32
                if np.isnan(v):
                    v = _smooth_at(q, j, strip, strip_top, main_top, main_h, scan, colsrc,
                                   coltop, ccol, k0)  # fmt: skip
                pair[s] = v
            sampled[e] = (1 - f) * pair[0] + f * pair[1]
        centre, plus, minus = sampled[0], sampled[1], sampled[2]
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
    padded = np.empty(n + 2 * half)  # (np.full compiles its own helper)
    padded[:] = np.inf
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


@_jit_inner
def _flatnonzero(valid):
    """`np.flatnonzero(valid)` written out (its generic version compiles slowly)."""
    m = 0
    for i in range(valid.size):
        m += valid[i]
    idx = np.empty(m, np.intp)
    k = 0
    for i in range(valid.size):
        if valid[i]:
            idx[k] = i
            k += 1
    return idx


@_jit
def link_segments(y, valid, strength, max_jump_px, max_gap, min_points, high, trim, min_line):
    """`_link.link_segments` (labels, kept mask): one pass over the valid centres."""
    n = y.size
    labels = np.empty(n, np.intp)
    labels[:] = -1
    keep = np.zeros(n, np.bool_)
    idx = _flatnonzero(valid)
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


@_jit_inner
def _select(a, k):
    """The `k`-th smallest entry of `a` (reordered in place; no NaN): quickselect with
    a median-of-three pivot, leaving `a[:k]` <= `a[k]`."""
    lo, hi = 0, a.size - 1
    while hi > lo:
        mid = (lo + hi) // 2
        if a[mid] < a[lo]:
            a[mid], a[lo] = a[lo], a[mid]
        if a[hi] < a[lo]:
            a[hi], a[lo] = a[lo], a[hi]
        if a[hi] < a[mid]:
            a[hi], a[mid] = a[mid], a[hi]
        pivot = a[mid]
        i, j = lo, hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while a[j] > pivot:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    return a[k]


@_jit_inner
def _median(x):
    """`_image._median` (the mean of the two middle values for an even count)."""
    s = x.copy()
    m = s.size // 2
    upper = _select(s, m)
    if s.size % 2:
        return upper
    lower = s[0]
    for i in range(1, m):
        lower = max(lower, s[i])
    return (lower + upper) / 2


@_jit
def consistent_passes(yv, valid, keep, off_curve, half, floor_px):
    """The two local-fit passes of `_link.consistent` (after its global cubic)."""
    n = yv.size
    any_off = False
    for i in range(n):
        any_off = any_off or off_curve[i]
    keep = keep.copy()
    w = np.empty((2 if any_off else 1, n))
    for i in range(n):
        w[0, i] = 1.0 if keep[i] else 0.0
        if any_off:
            w[1, i] = 1.0 if valid[i] else 0.0
    p, c = local_fit(yv, w, half)  # the first pass's fits, kept for the second
    for step in range(2):
        factor, floor = (3.0, 1.0) if step == 0 else (5.0, floor_px)
        if step == 0 and any_off:
            pred, count = p[0].copy(), c[0].copy()
            for i in range(n):
                # a piece of line the global cubic does not follow, judged by its own
                if count[i] < 6 and c[1, i] >= 30:
                    pred[i], count[i] = p[1, i], c[1, i]
        elif step == 0:
            pred, count = p[0], c[0]
        else:
            # a fit already made with the same weights is reused (as the reference's
            # `fit` does): the first pass often keeps every valid centre
            same = -1
            for m in range(w.shape[0]):
                equal = True
                for i in range(n):
                    if (w[m, i] > 0) != keep[i]:
                        equal = False
                        break
                if equal:
                    same = m
                    break
            if same >= 0:
                pred, count = p[same], c[same]
            else:
                w1 = np.empty((1, n))
                for i in range(n):
                    w1[0, i] = 1.0 if keep[i] else 0.0
                p1, c1 = local_fit(yv, w1, half)
                pred, count = p1[0], c1[0]
        r = np.empty(n)  # np.abs(yv - pred), as a loop (an array expression compiles slowly)
        for i in range(n):
            r[i] = abs(yv[i] - pred[i])
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


@_jit
def clipped_lines(flat, stride_y, stride_x, n_rows, found, row, centre, level):
    """The test of `_extract`'s `clipped` (before its `valid &`): at least two of the
    three pixels at the rounded row (`row` where `found`, else `centre`; then `centre`)
    at or above `level`, per scan line; `flat` read at `y stride_y + x stride_x`."""
    n = centre.size
    out = np.zeros(n, np.bool_)
    for j in range(n):
        for pass_ in range(2):
            at = row[j] if (pass_ == 0 and found[j]) else centre[j]
            c = min(max(np.intp(np.rint(at)), 0), n_rows - 1)
            count = 0
            for d in range(-1, 2):
                y = min(max(c + d, 0), n_rows - 1)
                count += flat[y * stride_y + j * stride_x] >= level
            if count >= 2:
                out[j] = True
    return out


def _solve4(a, b):
    """`np.linalg.solve(a, b)` for a (4, 4) float64 `a` and (4,) `b`: the same LAPACK
    call (`dgesv` on column-major copies) and the same errors (LAPACK's code for an
    illegal argument, impossible here, raises too)."""
    for u in range(4):
        for v in range(4):
            if not np.isfinite(a[u, v]):
                raise np.linalg.LinAlgError("Array must not contain infs or NaNs.")
    for u in range(4):
        if not np.isfinite(b[u]):
            raise np.linalg.LinAlgError("Array must not contain infs or NaNs.")
    acpy = np.empty((4, 4))  # row v: column v of `a`
    for u in range(4):
        for v in range(4):
            acpy[v, u] = a[u, v]
    x = b.copy()
    ipiv = np.empty(4, _F_INT)
    r = _xgesv(100, 4, 1, acpy.ctypes, 4, ipiv.ctypes, x.ctypes, 4)  # 100: ord("d")
    _keep_alive([acpy.size, x.size, ipiv.size])
    if r != 0:
        raise np.linalg.LinAlgError("Matrix is singular to machine precision.")
    return x


if numba is not None and _xgesv is None:  # pragma: no cover - other Numba versions

    def _solve4(a, b):
        return np.linalg.solve(a, b)


_solve4 = _jit_inner(_solve4)


@_jit
def cubic_seed(y, valid):
    """The robust global cubic of `_link.consistent`: which valid centres it keeps
    (`off_curve`: the valid ones it refuses). The same steps; the normal equations are
    summed here in order (BLAS may order the sums otherwise: the coefficients can differ
    in the last bits, which moves a centre across a threshold only by that much)."""
    n = y.size
    x = _flatnonzero(valid)
    m = x.size
    mean = 0.0
    for i in range(m):
        mean += x[i]
    mean = mean / m
    span = max(float(x[m - 1] - x[0]), 1.0)
    xs = np.empty(m)
    yx = np.empty(m)
    for i in range(m):
        xs[i] = (x[i] - mean) / span
        yx[i] = y[x[i]]
    half_n = m // 2
    slopes = np.empty(half_n)
    for i in range(half_n):
        slopes[i] = (yx[half_n + i] - yx[i]) / (xs[half_n + i] - xs[i])
    slope = _median(slopes)
    r0 = np.empty(m)
    for i in range(m):
        r0[i] = yx[i] - slope * xs[i]
    mid = _median(r0)
    for i in range(m):
        r0[i] = abs(r0[i] - mid)
    lim = max(20.0, 5.0 * 1.4826 * _median(r0))
    seed = np.empty(m, np.bool_)
    for i in range(m):
        seed[i] = r0[i] <= lim
    r = np.empty(m)
    for _ in range(2):
        a = np.zeros((4, 4))
        b = np.zeros(4)
        for i in range(m):
            if seed[i]:
                p = (1.0, xs[i], xs[i] * xs[i], xs[i] * xs[i] * xs[i])
                for u in range(4):
                    for v in range(4):
                        a[u, v] += p[u] * p[v]
                    b[u] += p[u] * yx[i]
        for u in range(4):
            a[u, u] += 1e-12
        coef = _solve4(a, b)
        n_seed = 0
        for i in range(m):
            x1 = xs[i]
            r[i] = abs(yx[i] - (coef[0] + coef[1] * x1 + coef[2] * (x1 * x1)
                                + coef[3] * (x1 * x1 * x1)))  # fmt: skip
            n_seed += seed[i]
        kept = np.empty(n_seed)
        k = 0
        for i in range(m):
            if seed[i]:
                kept[k] = r[i]
                k += 1
        lim = max(1.0, 4.0 * 1.4826 * _median(kept))
        n_seed = 0
        for i in range(m):
            seed[i] = r[i] <= lim
            n_seed += seed[i]
        if n_seed < 12:
            seed[:] = True
            break
    off_curve = np.zeros(n, np.bool_)
    for i in range(m):
        if not seed[i]:
            off_curve[x[i]] = True
    return off_curve


@_jit
def band_layout(centre, tile, half, r, k_search):
    """`_steger._layout` and the arrays `_steger._band_compiled` derives from it, for
    the scan lines' rounded track `centre` (W,): `(main_top, height, ccol, colsrc,
    coltop, rows)`: each scan line's first composite row, the composite's height,
    each scan line's column, each column's scan line and first row, and the (K, W)
    image rows of the windows."""
    w = centre.size
    n_tiles = (w + tile - 1) // tile
    tile_w = tile + 2 * r
    top = np.empty(n_tiles, np.intp)
    start = np.empty(n_tiles, np.intp)
    spread = 0
    for t in range(n_tiles):
        lo = hi = centre[min(t * tile, w - 1)]
        for j in range(t * tile, t * tile + tile):
            c = centre[min(j, w - 1)]  # (past the end: the last scan line's)
            lo, hi = min(lo, c), max(hi, c)
        top[t] = lo - half
        spread = max(spread, hi - lo)
        start[t] = min(max(t * tile - r, 0), max(w, tile_w) - tile_w)
    height = spread + 2 * half + 1
    main_top = np.empty(w, np.intp)
    ccol = np.empty(w, np.intp)
    for j in range(w):
        t = j // tile
        main_top[j] = top[t]
        ccol[j] = t * tile_w + j - start[t]
    n_comp = n_tiles * tile_w
    colsrc = np.empty(n_comp, np.intp)
    coltop = np.empty(n_comp, np.intp)
    for cc in range(n_comp):
        t = cc // tile_w
        colsrc[cc] = min(start[t] + cc % tile_w, w - 1)
        coltop[cc] = top[t]
    kk = 2 * k_search + 1
    rows = np.empty((kk, w), np.intp)
    for o in range(kk):
        for j in range(w):
            rows[o, j] = centre[j] - k_search + o
    return main_top, height, ccol, colsrc, coltop, rows


@_jit
def coarse_scan(small, d):
    """`_coarse.coarse_track`'s first steps on a float32 `small` (no mask) in one pass:
    the ridge response (`ridge_rows`), the first maximum per scan line (`idx`), its
    response, the sub-coarse-pixel peak `pos` (parabola, float64 as NumPy promotes
    it) and the smallest and largest value of `small` (no NaN)."""
    ridge = ridge_rows(small, d)
    hs, ws = small.shape
    col_lo, col_hi = small[0].copy(), small[0].copy()  # (per column: vectorised)
    for i in range(1, hs):
        for j in range(ws):
            col_lo[j] = min(col_lo[j], small[i, j])
            col_hi[j] = max(col_hi[j], small[i, j])
    lo, hi = col_lo[0], col_hi[0]
    for j in range(1, ws):
        lo = min(lo, col_lo[j])
        hi = max(hi, col_hi[j])
    idx = column_argmax(ridge)
    resp = np.empty(ws, np.float32)
    pos = np.empty(ws)
    half, two = _F32(0.5), _F32(2.0)
    for j in range(ws):
        k = idx[j]
        c = ridge[k, j]
        up = ridge[max(k - 1, 0), j]
        down = ridge[min(k + 1, hs - 1), j]
        denom = up - two * c + down
        frac = half * (up - down) / denom if denom < 0 else _F32(0.0)
        frac = min(max(frac, _F32(-0.5)), _F32(0.5))
        resp[j] = c
        pos[j] = 4 * (np.float64(k) + np.float64(frac)) + 1.5
    return ridge, idx, resp, pos, lo, hi


@_jit
def downsample_u8(img):
    """`_coarse.downsample` of a uint8 image (two 2 x 2 area reductions as OpenCV's
    `INTER_AREA` does them on uint8: `(a + b + c + d + 2) >> 2` each, the result as
    float32) and the image's maximum, from one read of the frame (uint16 sums: at most
    4 x 255 + 2)."""
    h, w = img.shape
    hs, ws = h // 4, w // 4
    out = np.empty((hs, ws), np.float32)
    v0 = np.empty(4 * ws, np.uint16)
    v1 = np.empty(4 * ws, np.uint16)
    half = np.empty((2, 2 * ws), np.uint16)
    col_max = np.zeros(w, np.uint8)
    two = np.uint16(2)
    for i in range(hs):
        r0, r1, r2, r3 = img[4 * i], img[4 * i + 1], img[4 * i + 2], img[4 * i + 3]
        for c in range(4 * ws):  # the sums down the two row pairs
            v0[c] = np.uint16(r0[c]) + np.uint16(r1[c])
            v1[c] = np.uint16(r2[c]) + np.uint16(r3[c])
        for c in range(w):
            col_max[c] = max(col_max[c], max(max(r0[c], r1[c]), max(r2[c], r3[c])))
        for j in range(2 * ws):  # the first 2 x 2 reduction
            half[0, j] = np.uint16(v0[2 * j] + v0[2 * j + 1] + two) >> np.uint16(2)
            half[1, j] = np.uint16(v1[2 * j] + v1[2 * j + 1] + two) >> np.uint16(2)
        for j in range(ws):  # the second
            s = half[0, 2 * j] + half[0, 2 * j + 1] + half[1, 2 * j] + half[1, 2 * j + 1]
            out[i, j] = np.float32(np.uint16(s + two) >> np.uint16(2))
    for r in range(4 * hs, h):  # rows past the last whole block: the maximum only
        for c in range(w):
            col_max[c] = max(col_max[c], img[r, c])
    top = np.uint8(0)
    for c in range(w):
        top = max(top, col_max[c])
    return out, top


@_jit
def ridge_positive(small, d, dd, floor):
    """`_ridge.scan_direction`'s positive responses without a weight: for the two-sided
    responses `min(c - small[i - di, j - dj], c - small[i + di, j + dj])` (`c =
    small[i, j]`) along v, u and the two diagonals (offsets `d`, and `dd` on the
    diagonals) of the float32 image `small`, `r[r > 0]` of `r = response - floor` over
    the interior where both neighbours exist, in row-major order: row `k` of the
    result, its first `count[k]` entries. (NumPy sums them: `np.sum`'s pairwise order
    stays its own.)"""
    h, w = small.shape
    floor = _F32(floor)
    out = np.empty((4, max(h * w, 1)), np.float32)
    count = np.zeros(4, np.intp)
    resp = np.empty(w, np.float32)
    for k in range(4):
        di = d if k == 0 else (0 if k == 1 else dd)
        dj = 0 if k == 0 else (d if k == 1 else (dd if k == 2 else -dd))
        ai, aj = abs(di), abs(dj)
        dst = out[k]
        n = 0
        m = w - 2 * aj  # interior columns aj .. w - aj
        for i in range(ai, h - ai):
            # slices of the row and its two neighbours, aligned: one vectorised loop
            up = small[i - di, aj - dj : aj - dj + m]
            mid = small[i, aj : aj + m]
            down = small[i + di, aj + dj : aj + dj + m]
            for j in range(m):
                a = mid[j] - up[j]
                b = mid[j] - down[j]
                resp[j] = (a if a < b else b) - floor
            for j in range(m):
                if resp[j] > 0:
                    dst[n] = resp[j]
                    n += 1
        count[k] = n
    return out, count


@_jit
def second_diff_ranks_u8(img, n_rows):
    """`_image.estimate_noise`'s order statistics for a uint8 image: the values of rank
    `m - 1` and `m` (`m` = half the count; both rank `m` for an odd count) of the absolute
    second differences along every `H // n_rows`-th row from the middle of the first
    step, from a histogram (exact)."""
    h, w = img.shape
    step = max(h // n_rows, 1)
    hist = np.zeros(4 * 255 + 1, np.int64)
    n = 0
    for r in range(step // 2, h, step):
        row = img[r]
        for c in range(w - 2):
            v = np.int32(row[c]) - 2 * np.int32(row[c + 1]) + np.int32(row[c + 2])
            hist[abs(v)] += 1
        n += max(w - 2, 0)
    m = n // 2
    lo = hi = -1
    cum = 0
    for v in range(hist.size):
        cum += hist[v]
        if lo < 0 and cum >= m:
            lo = v
        if cum >= m + 1:
            hi = v
            break
    return (hi if n % 2 else lo), hi


@_jit
def block_noise_u8(img, n_rows):
    """`_image.block_noise`'s sorted second differences for a uint8 image: those along
    the rows of 2 x 2 block means (multiples of 1/4, exact in float32) of `n_rows` row
    pairs, their smallest 90 % in ascending order (from a histogram of 4 d: the sorted
    values themselves), float32. (NumPy takes their mean square, in its own order.)"""
    h, w = img.shape
    step = max((h - 1) // n_rows, 2)
    nb = w // 2
    q = _F32(0.25)
    two = _F32(2.0)
    hist = np.zeros(4 * 4 * 255 + 1, np.int64)
    block = np.empty(nb, np.float32)
    n = 0
    t = 0
    for k in range(n_rows):
        if t >= h - 1:
            break
        ra, rb = img[t], img[t + 1]
        for j in range(nb):
            p0 = np.float32(ra[2 * j]) + np.float32(rb[2 * j])
            p1 = np.float32(ra[2 * j + 1]) + np.float32(rb[2 * j + 1])
            block[j] = q * (p0 + p1)
        for j in range(nb - 2):
            d = abs(block[j] - two * block[j + 1] + block[j + 2])
            hist[np.int64(4 * d)] += 1
        n += max(nb - 2, 0)
        t += step
    keep = max(np.int64(0.9 * n), 1)
    out = np.empty(keep, np.float32)
    i = 0
    for v in range(hist.size):
        c = min(hist[v], keep - i)
        for _ in range(c):
            out[i] = _F32(v) * q
            i += 1
        if i >= keep:
            break
    return out


@_jit_inner
def _window_angle(uv, col, idx, w0, n_fit):
    """Angle (deg) to the scan axis of the straight line through the valid centres
    `idx[w0 : w0 + n_fit]` (`_steep._angle`)."""
    sx = 0.0
    sy = 0.0
    for t in range(n_fit):
        sx += uv[idx[w0 + t], col]
        sy += uv[idx[w0 + t], 1 - col]
    mx = sx / n_fit
    my = sy / n_fit
    den = 0.0
    num = 0.0
    for t in range(n_fit):
        dx = uv[idx[w0 + t], col] - mx
        den += dx * dx
        num += dx * (uv[idx[w0 + t], 1 - col] - my)
    return math.degrees(math.atan2(abs(num), den))


@_jit
def steep_end(
    uv, col, valid, segment, n_fit, n_back, steep_deg, turn_from_deg, turn_deg, n_span,
    n_min, bend_from_deg, bend_deg,
):  # fmt: skip
    """`_steep._may_turn_steep` (its NumPy reference) in one pass: whether a run of one
    `segment` label among the valid centres, `n_fit` long or longer, ends (at either
    end) with its last `n_fit` centres steeper than `steep_deg` to the scan axis, or
    steeper than `turn_from_deg` and turned by more than `turn_deg` since the `n_fit`
    centres `n_back` further in (runs of `n_fit + n_back` or more), or steeper than
    `bend_from_deg` and turned by more than `bend_deg` over min(K, `n_back`) centres by
    the straight line fitted to the window's angle taken 0..K centres further in (K =
    the run's length less `n_fit`, at most `n_span`, at least `n_min`; `_steep._bend`)."""
    n = valid.shape[0]
    idx = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        if valid[i]:
            idx[m] = i
            m += 1
    start = 0
    for k in range(1, m + 1):
        if k < m and segment[idx[k]] == segment[idx[k - 1]]:
            continue
        run = k - start
        if run >= n_fit:
            span = min(run - n_fit, n_span)
            for first_end in (True, False):
                w0 = start if first_end else k - n_fit
                a0 = _window_angle(uv, col, idx, w0, n_fit)
                if a0 > steep_deg:
                    return True
                if run >= n_fit + n_back and a0 > turn_from_deg:
                    w1 = w0 + n_back if first_end else w0 - n_back
                    if a0 - _window_angle(uv, col, idx, w1, n_fit) > turn_deg:
                        return True
                if span >= n_min and a0 > bend_from_deg:
                    kbar = span / 2.0
                    num = 0.0
                    for t in range(span + 1):
                        w = w0 + t if first_end else w0 - t
                        num += (t - kbar) * _window_angle(uv, col, idx, w, n_fit)
                    den = span * (span + 1.0) * (span + 2.0) / 12.0
                    if -num / den * min(span, n_back) > bend_deg:
                        return True
        start = k
    return False
