"""Steger's Hessian line detector, one sub-pixel centre per scan line.

Works in the *scan frame* (rows = scan coordinate y, columns = scan lines x); the caller
maps back to (u, v). Gaussian derivatives of the image at scale sigma give, per pixel,
the line normal n (eigenvector of the Hessian with the most negative eigenvalue λ) and
Steger's second-order Taylor step t = -(n·∇r) / λ; a pixel is a line point when the
centre lies inside it (|t n_x|, |t n_y| ≤ 0.5) and λ < 0. Per scan line the strongest
line point wins. Its centre is then moved onto the scan line exactly: the zero of the
normal derivative n·∇r along the scan line, from a cubic Hermite interpolant through
the two pixels that bracket it (values and derivatives), which removes the small
"pixel-locking" error of the plain Taylor step.

Two ways to get the derivatives:
- full frame: six separable OpenCV filters over the whole image (the baseline);
- band: the coarse track is cut into tiles of 64 scan lines; each tile's rows around the
  track (± band, plus the filter margins) are gathered side by side into one small
  image, filtered with the same kernels, and read back. Interior pixels see exactly the
  same data as in the full frame, so both give the same centres.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np

from . import _fast
from ._kernels import FWHM_PER_SIGMA, gaussian_kernels, kernel_radius, steger_sigma

_TILE = 64
# Steger accepts a pixel when its Taylor centre lies inside it, |t n| <= 0.5. The Taylor
# step overshoots by up to ~ 0.125 / S² px (S: smoothed stripe std) when the centre sits
# on a pixel border, so that neither neighbour would pass; allow 0.1 px for it (the
# position itself comes from the refinement below, not from t).
_INSIDE = 0.6
# Candidate rows searched on each side of the coarse track (band mode).
_SEARCH = 4


@dataclasses.dataclass(frozen=True)
class ScanLines:
    """Per scan line results in the scan frame (all shape (W,))."""

    y: np.ndarray  # sub-pixel scan coordinate of the centre (NaN if none)
    strength: np.ndarray  # -sigma² λ (0 if none)
    width: np.ndarray  # FWHM estimate (NaN if none)
    found: np.ndarray  # a line point was found
    row: np.ndarray  # integer row of the chosen line point
    asym: np.ndarray | None = None  # profile asymmetry (see `_asymmetry`), NaN if none
    ny: np.ndarray | None = None  # scan-line component of the line normal


def _derivative_images(img: np.ndarray, sigma: float) -> list[np.ndarray]:
    """r, r_x, r_y, r_xx, r_xy, r_yy of a float32 image (x along columns, y along rows)."""
    k0, k1, k2 = gaussian_kernels(sigma)
    pairs = ((k0, k0), (k1, k0), (k0, k1), (k2, k0), (k1, k1), (k0, k2))
    return [
        cv2.sepFilter2D(img, cv2.CV_32F, kx, ky, borderType=cv2.BORDER_REPLICATE)
        for kx, ky in pairs
    ]


_ONE = np.ones((1, 1), np.float32)


def _line_points(rx, ry, rxx, rxy, ryy):
    """Normal (nx, ny), eigenvalue λ, Taylor step t and the line-point test."""
    half_diff = 0.5 * (rxx - ryy)
    root = np.sqrt(half_diff * half_diff + rxy * rxy)
    lam = 0.5 * (rxx + ryy) - root
    # Eigenvector of the smaller eigenvalue, without trigonometry: (rxy, λ - rxx) and
    # (λ - ryy, rxy) both solve (H - λ) n = 0; the longer one is the well-conditioned
    # one. Normalised, sign chosen with ny >= 0 ((0, 1) where H is isotropic).
    ax, ay = rxy, lam - rxx
    bx, by = lam - ryy, rxy
    use_a = ax * ax + ay * ay >= bx * bx + by * by
    vx = np.where(use_a, ax, bx)
    vy = np.where(use_a, ay, by)
    norm = np.sqrt(vx * vx + vy * vy)
    flip = np.where(vy < 0, -1.0, 1.0).astype(norm.dtype)
    inv = np.where(norm > 0, flip / np.where(norm > 0, norm, 1.0), 0.0)
    nx = vx * inv
    ny = np.where(norm > 0, vy * inv, 1.0)
    g = nx * rx + ny * ry
    safe = np.where(lam < 0, lam, -1.0)
    t = -g / safe
    is_line = (lam < 0) & (np.abs(t * nx) <= _INSIDE) & (np.abs(t * ny) <= _INSIDE)
    return nx, ny, lam, t, is_line


def _hermite_root(p0, p1, m0, m1):
    """Zero in [0, 1] of the cubic Hermite interpolant (values p, slopes m); p0, p1 bracket.

    Newton's method (3 steps) from the secant's zero on the cubic in power form
    `h(x) = ((a3 x + a2) x + m0) x + p0`."""
    a2 = 3.0 * (p1 - p0) - 2.0 * m0 - m1
    a3 = 2.0 * (p0 - p1) + m0 + m1
    b3, b2 = 3.0 * a3, 2.0 * a2
    x = np.clip(p0 / np.where(p0 != p1, p0 - p1, 1.0), 0.0, 1.0)
    for _ in range(3):
        h = ((a3 * x + a2) * x + m0) * x + p0
        dh = (b3 * x + b2) * x + m0
        x = np.clip(x - h / np.where(dh != 0, dh, 1.0), 0.0, 1.0)
    return x


def _select(win: list[np.ndarray], lo: int, hi: int):
    """Strongest line point per column among the window rows `lo..hi-1`.

    Line points are a subset of the pixels, so where a column's most negative λ is a
    line point it is also the strongest line point: the full line-point test (normal,
    Taylor step) runs on that one pixel per column, and on the whole window only in the
    columns where it fails. Same result as testing every pixel.

    Returns `(k, found, nx, ny, lam, t)` per column (k: window row index).
    """
    _, rx, ry, rxx, rxy, ryy = win
    n = rx.shape[1]
    cols = np.arange(n)
    a, b, c = rxx[lo:hi], rxy[lo:hi], ryy[lo:hi]
    half_diff = 0.5 * (a - c)
    lam_all = 0.5 * (a + c) - np.sqrt(half_diff * half_diff + b * b)  # as `_line_points`
    best = np.argmin(lam_all, axis=0) + lo
    flat = best * n + cols
    nx, ny, lam, t, found = _line_points(*(np.take(x, flat) for x in win[1:]))
    miss = np.flatnonzero(~found)
    if miss.size:
        sub = [x[lo:hi, miss] for x in win[1:]]
        nx_m, ny_m, lam_m, t_m, is_line = _line_points(*sub)
        score = np.where(is_line, -lam_m, -np.inf)
        k = np.argmax(score, axis=0)
        j = np.arange(miss.size)
        best[miss] = k + lo
        found[miss] = np.isfinite(score[k, j])
        nx[miss], ny[miss], lam[miss], t[miss] = nx_m[k, j], ny_m[k, j], lam_m[k, j], t_m[k, j]
    return best, found, nx, ny, lam, t


# Scan lines over which the line normal is median-filtered (odd).
_NORMAL_WINDOW = 15


def _smooth_normal(nx: np.ndarray, ny: np.ndarray, found: np.ndarray):
    """The line normal per scan line, median-filtered over `_NORMAL_WINDOW` scan lines.

    Where the line's brightness changes along itself (an albedo edge crossing the line:
    black and white squares) the Hessian's normal tilts towards the edge, and the
    derivative along it picks up the along-line gradient `a'(s) f(d) t`, which shifts the
    zero by up to ~1 px. The line's direction changes slowly along it, so a median over
    neighbouring scan lines gives the geometric normal, along which the derivative of
    `a(s) f(d)` (separable under the isotropic Gaussian) is `a(s) f'(d)`: zero exactly
    at the centre.
    """
    if nx.size < _NORMAL_WINDOW or not found.any():
        return nx, ny
    flip = np.where(ny < 0, -1.0, 1.0)
    phi = np.arctan2(nx * flip, ny * flip)  # in (-pi/2, pi/2]: the sign of n is free
    half = _NORMAL_WINDOW // 2
    if found.all():  # the common case: a partial sort (median) of full windows
        padded = np.concatenate([np.full(half, phi[0]), phi, np.full(half, phi[-1])])
        win = np.lib.stride_tricks.as_strided(
            padded, (phi.size, _NORMAL_WINDOW), (padded.strides[0],) * 2, writeable=False
        )
        phi = np.partition(win, half, axis=1)[:, half]
        return np.sin(phi) * flip, np.cos(phi) * flip
    padded = np.pad(np.where(found, phi, np.inf), half, constant_values=np.inf)
    win = np.sort(np.lib.stride_tricks.sliding_window_view(padded, _NORMAL_WINDOW), axis=1)
    count = np.count_nonzero(np.isfinite(win), axis=1)
    mid = np.take_along_axis(win, np.maximum((count - 1) // 2, 0)[:, None], axis=1)[:, 0]
    phi = np.where(count >= 3, mid, phi)
    return np.sin(phi) * flip, np.cos(phi) * flip


def _evaluate(win: list[np.ndarray], rows: np.ndarray, selection, bg2, bg_off: int, sigma: float):
    """Sub-pixel centre, strength and width per column from the window (K, W) arrays.

    `rows` (K, W) are the image rows of the window, `selection` comes from `_select`.
    `bg2` (2, W) is the smoothed image `bg_off` rows before and after the chosen pixel:
    their mean is the background level and their slope, with the level's slope across
    scan lines, a linear background gradient that is taken out of the first derivatives
    (a background ramp would otherwise shift the centre).
    """
    r, rx, ry, rxx, rxy, ryy = win
    k, found, nxk, nyk, lamk, tk = selection
    bg = 0.5 * (bg2[0] + bg2[1])
    grad_y = (bg2[1] - bg2[0]) / (2.0 * bg_off)
    grad_x = np.gradient(bg) if bg.size > 1 else np.zeros_like(bg)
    k_rows, n = rx.shape
    cols = np.arange(n)
    nxk, nyk = _smooth_normal(nxk, nyk, found)

    # n·∇r (background ramp removed) and its derivative along y at the rows k, k - 1
    # and k + 1 of each column, in one (3, W) pass
    at = np.stack([k, np.maximum(k - 1, 0), np.minimum(k + 1, k_rows - 1)]) * n + cols
    g = nxk * (np.take(rx, at) - grad_x) + nyk * (np.take(ry, at) - grad_y)
    dg = nxk * np.take(rxy, at) + nyk * np.take(ryy, at)
    (g0, gm, gp), (d0, dm, dp) = g, dg
    rowk = np.take(rows, k * n + cols).astype(np.float64)
    # Fallback: project Steger's centre along the line onto the scan line.
    ny_safe = np.where(np.abs(nyk) > 0.2, nyk, np.copysign(0.2, nyk + 1e-300))
    y = rowk + tk / ny_safe
    up = (np.sign(g0) != np.sign(gp)) & (k + 1 < k_rows)
    down = ~up & (np.sign(gm) != np.sign(g0)) & (k >= 1)
    bracket = up | down
    if bracket.any():
        root = _hermite_root(
            np.where(up, g0, gm), np.where(up, gp, g0), np.where(up, d0, dm), np.where(up, dp, d0)
        )
        y = np.where(bracket, np.where(up, rowk, rowk - 1.0) + root, y)
    y = np.where(g0 == 0, rowk, y)

    strength = np.where(found, -lamk * sigma * sigma, 0.0)
    height = np.take(r, k * n + cols) - bg
    s2 = height / np.where(lamk < 0, -lamk, np.inf)
    width = FWHM_PER_SIGMA * np.sqrt(np.clip(s2 - sigma * sigma, 0.0, None))
    width = np.where(found & (s2 > 0), width, np.nan)
    y = np.where(found, y, np.nan)
    lines = ScanLines(y, strength.astype(np.float64), width.astype(np.float64), found, rowk)
    return lines, bg, grad_y, nyk


def _asymmetry(sample, lines: ScanLines, bg, grad_y, ny, s_total: float, reach: int):
    """Asymmetry of the smoothed profile about the found centre, per scan line:
    `(r(y + δ) - r(y - δ)) / (r(y) - bg)` with `δ` one standard deviation of the
    smoothed profile along the scan line (`s_total / |n_y|`, at most `reach` rows) and
    `bg` the background level. A profile symmetric about its centre gives 0 (plus
    noise; a smooth background slope adds only `2 δ slope / height`); a brightness step
    inside the profile (an albedo edge under the line), which also pulls the centre,
    does not. (The background slope is deliberately not taken out: across a step it
    would hide the step.)
    `sample(rows, cols)` reads the smoothed image at integer rows (clipped to the data).
    """
    n = lines.y.size
    cols = np.arange(n)
    ok = lines.found & np.isfinite(lines.y)
    y = np.where(ok, lines.y, lines.row)
    delta = np.minimum(s_total / np.maximum(np.abs(ny), 0.2), float(reach))

    # the smoothed profile at y, y + δ and y - δ (linear interpolation), one (3, W) pass
    pos = np.stack([y, y + delta, y - delta])
    lo = np.floor(pos)
    f = pos - lo
    lo = lo.astype(np.intp)
    centre, plus, minus = (1 - f) * sample(lo, cols) + f * sample(lo + 1, cols)
    height = centre - bg
    asym = (plus - minus) / np.where(height > 0, height, np.inf)
    return dataclasses.replace(lines, asym=np.where(ok & (height > 0), asym, np.nan), ny=ny)


def _geometry(width_px: float, band_px: int | None):
    sigma = steger_sigma(width_px)
    r = kernel_radius(sigma)
    s_total = math.hypot(width_px / FWHM_PER_SIGMA, sigma)
    bg_off = int(math.ceil(3.5 * s_total)) + 1
    if band_px is None:
        return sigma, r, bg_off, bg_off
    margin = max(int(band_px), _SEARCH + 2)
    return sigma, r, min(bg_off, margin - _SEARCH - 1), margin


def steger_full(img: np.ndarray, width_px: float, track, tolerance: float) -> ScanLines:
    """Full-frame Steger on the scan-frame image `img` (H, W).

    Every pixel is tested; per scan line the strongest line point within `tolerance` of
    `track` (W,) wins (`track=None`: anywhere in the scan line).
    """
    sigma, _, bg_off, _ = _geometry(width_px, None)
    h, w = img.shape
    d = _derivative_images(img.astype(np.float32, copy=False), sigma)
    _, _, lam, _, is_line = _line_points(*d[1:])
    score = np.where(is_line, -lam, -np.inf)
    if track is not None:
        far = np.abs(np.arange(h)[:, None] - track[None, :]) > tolerance
        score[far] = -np.inf
    best = np.argmax(score, axis=0)
    cols = np.arange(w)
    rows = np.clip(best[None, :] + np.arange(-1, 2)[:, None], 0, h - 1)
    win = [a[rows, cols] for a in d]
    bg_rows = np.clip(best[None, :] + np.array([-bg_off, bg_off])[:, None], 0, h - 1)
    res, bg, grad_y, ny = _evaluate(
        win, rows, _select(win, 1, 2), d[0][bg_rows, cols], bg_off, sigma
    )
    found = res.found & np.isfinite(score[best, cols])
    res = dataclasses.replace(res, found=found, y=np.where(found, res.y, np.nan))
    s_total = math.hypot(width_px / FWHM_PER_SIGMA, sigma)

    def sample(r, c):
        return d[0][np.clip(r, 0, h - 1), c]

    return _asymmetry(sample, res, bg, grad_y, ny, s_total, bg_off)


def _layout(w: int, centre: np.ndarray, half: int, r: int):
    """The composite's layout of `_tiles` for `w` scan lines: each scan line's first
    row, the composite's height, each tile's first scan line, the tile width and each
    scan line's column in the composite."""
    n_tiles = -(-w // _TILE)
    tile_w = _TILE + 2 * r
    tail = n_tiles * _TILE - w
    padded = np.concatenate([centre, np.full(tail, centre[-1])]) if tail else centre
    padded = padded.reshape(n_tiles, _TILE)
    lo, hi = padded.min(axis=1), padded.max(axis=1)
    top = lo - half
    height = int((hi - lo).max()) + 2 * half + 1
    start = np.clip(np.arange(n_tiles) * _TILE - r, 0, max(w, tile_w) - tile_w)
    tile = np.arange(w) // _TILE
    ccol = tile * tile_w + np.arange(w) - start[tile]
    return top, height, start, tile_w, tile, ccol


def _tiles(scan: np.ndarray, centre: np.ndarray, half: int, r: int):
    """The band's tiles of `_TILE` scan lines side by side in one image.

    Tile `t` holds the scan-frame rows `top[t] .. top[t] + height - 1` (clipped to the
    image: replicated rows) of the scan lines `start[t] .. start[t] + _TILE + 2 r - 1`:
    its own `_TILE` scan lines and `r` more on each side for the filters. The first tile
    starts at scan line 0 and the last one ends at the last scan line, so that the
    filters' replicated border at the composite's left and right edges is the image's
    own border. One fancy index of (height, n_tiles) row numbers into a sliding-window
    view copies whole tile rows (no per-pixel index arrays).

    **Returns:** `(comp, top, ccol)`: the composite (height, n_tiles (_TILE + 2 r))
    float32, each tile's first row, and each scan line's column in the composite.
    """
    h, w = scan.shape
    top, height, start, tile_w, tile, ccol = _layout(w, centre, half, r)
    n_tiles = start.size
    if w < tile_w:  # narrower than one tile: replicate the last scan line
        scan = np.concatenate([scan, np.repeat(scan[:, -1:], tile_w - w, axis=1)], axis=1)
    rows = np.clip(top[None, :] + np.arange(height)[:, None], 0, h - 1)
    sh, sw = scan.strides
    view = np.lib.stride_tricks.as_strided(
        scan, (h, scan.shape[1] - tile_w + 1, tile_w), (sh, sw, sw), writeable=False
    )
    if _fast.enabled:
        comp = _fast.tile_rows(scan, rows, start, tile_w)
    else:
        comp = view[rows, start[None, :]].reshape(height, n_tiles * tile_w)
        comp = comp.astype(np.float32, copy=False)
    return comp, top[tile], ccol


def _gather_window(images: list[np.ndarray], row0: np.ndarray, ccol: np.ndarray, k: int):
    """Per scan line `j` the rows `row0[j] .. row0[j] + k - 1` of column `ccol[j]` of
    each (C-contiguous) image: a list of (k, W) arrays."""
    if _fast.enabled:
        out = [_fast.gather_rows(a, row0, ccol, k) for a in images]
        if all(ok for _, ok in out):
            return [a for a, _ in out]
    n_cols = images[0].shape[1]
    flat = (row0 * n_cols + ccol)[None, :] + (np.arange(k) * n_cols)[:, None]
    return [np.take(a, flat) for a in images]


# Scan lines per tile of the compiled band (within one of the composite's `_TILE`).
_FAST_TILE = 32


_FLAT: dict[float, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}


def _kernels_flat(sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`gaussian_kernels(sigma)` as contiguous 1-D arrays (cached)."""
    out = _FLAT.get(sigma)
    if out is None:
        out = tuple(np.ascontiguousarray(k.ravel()) for k in gaussian_kernels(sigma))
        if len(_FLAT) < 256:
            _FLAT[sigma] = out
    return out


def _band_compiled(scan, centre, sigma, r, bg_off, margin, s_total) -> ScanLines | None:
    """`steger_band`'s result from the compiled loops (`_fast.band_window` and
    `_fast.band_lines`), None where they defer to the reference. They filter only the
    pixels that are read, tile by tile, with OpenCV's arithmetic and the reference
    composite's layout (`_layout`), so the values are the reference's."""
    k_search = _SEARCH + 1
    main_top, height, ccol, colsrc, coltop, rows = _fast.band_layout(
        centre, _TILE, margin + r, r, k_search
    )
    k0, k1, k2 = _kernels_flat(sigma)
    win, strip, strip_top = _fast.band_window(
        scan, centre, k0, k1, k2, k_search, _SEARCH + 2 + bg_off, colsrc, coltop, ccol, _FAST_TILE,
    )  # fmt: skip
    y, strength, width, found, row, asym, ny, ok = _fast.band_lines(
        *win, rows, strip, strip_top, main_top, height, scan, colsrc, coltop, ccol, k0, 1,
        2 * k_search, bg_off, sigma, s_total, bg_off, _INSIDE, FWHM_PER_SIGMA,
        _NORMAL_WINDOW,
    )  # fmt: skip
    if ok and found.any():
        return ScanLines(y, strength, width, found, row, asym, ny)
    return None


def steger_band(
    scan: np.ndarray, track: np.ndarray, width_px: float, band_px: int | None
) -> ScanLines:
    """Steger in a band of ± `band_px` rows around `track` (W,), scan frame.

    `scan` is the scan-frame image (H, W), a view of the image (for a horizontal scan its
    transpose: no copy is made). `band_px=None` picks the smallest band that holds the
    search window and the background samples.

    The derivatives are needed only in a window of ± (`_SEARCH` + 1) rows around the
    track. The row passes run on the tiles (they mix neighbouring scan lines); their
    results are then gathered per scan line into that window (plus the filters'
    reach) and the column passes run there: each output sees exactly the inputs it has
    in the full frame, so band and full frame give the same centres.
    """
    sigma, r, bg_off, margin = _geometry(width_px, band_px)
    if band_px is None:
        margin = bg_off + _SEARCH + 1
    h, w = scan.shape
    centre = np.rint(track).astype(np.intp)
    k_search = _SEARCH + 1
    s_total = math.hypot(width_px / FWHM_PER_SIGMA, sigma)
    if _fast.enabled and w >= _NORMAL_WINDOW:
        lines = _band_compiled(scan, centre, sigma, r, bg_off, margin, s_total)
        if lines is not None:
            return lines
    comp, top_c, ccol = _tiles(scan, centre, margin + r, r)
    crop = margin - k_search
    k0, k1, k2 = gaussian_kernels(sigma)

    def rows_pass(a, k):
        return cv2.sepFilter2D(a, cv2.CV_32F, k, _ONE, borderType=cv2.BORDER_REPLICATE)

    def cols_pass(a, k):
        return cv2.sepFilter2D(a, cv2.CV_32F, _ONE, k, borderType=cv2.BORDER_REPLICATE)

    h0 = rows_pass(comp, k0)
    smooth = cols_pass(h0, k0)
    # the window rows of the derivatives' inputs: ± (k_search + r) around the track
    n_cols = comp.shape[1]
    inner = comp[crop : comp.shape[0] - crop]
    reach = k_search + r
    g = _gather_window(
        [h0[crop : comp.shape[0] - crop], rows_pass(inner, k1), rows_pass(inner, k2)],
        centre - top_c - crop - reach, ccol, 2 * reach + 1,
    )  # fmt: skip
    g0, g1, g2 = g
    keep = slice(r, r + 2 * k_search + 1)
    d = [
        cols_pass(g1, k0)[keep],
        cols_pass(g0, k1)[keep],
        cols_pass(g2, k0)[keep],
        cols_pass(g1, k1)[keep],
        cols_pass(g0, k2)[keep],
    ]
    rows = centre[None, :] + np.arange(-k_search, k_search + 1)[:, None]
    win = _gather_window([smooth], centre - top_c - k_search, ccol, 2 * k_search + 1) + d
    # Background samples beside the strongest line point (as in the full frame).
    selection = _select(win, 1, 2 * k_search)
    cols = np.arange(w)
    best_row = rows[selection[0], cols]
    bg_crow = best_row[None, :] + np.array([-bg_off, bg_off])[:, None] - top_c[None, :]
    bg2 = np.take(smooth, bg_crow * n_cols + ccol)
    res, bg, grad_y, ny = _evaluate(win, rows, selection, bg2, bg_off, sigma)

    def sample(rr, cc):
        crow_s = np.clip(rr - top_c, 0, comp.shape[0] - 1)
        return np.take(smooth, crow_s * n_cols + ccol[cc])

    return _asymmetry(sample, res, bg, grad_y, ny, s_total, bg_off)
