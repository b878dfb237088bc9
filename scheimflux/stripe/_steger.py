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


def _band_derivatives(comp: np.ndarray, crop: int, sigma: float) -> list[np.ndarray]:
    """The smoothed band `comp` and r_x, r_y, r_xx, r_xy, r_yy of its rows
    `crop .. -crop`, from three row passes and six column passes (nine 1-D filters
    instead of the twelve of six separable filters). OpenCV's separable filter runs the
    row pass first, then the column pass, both in float32; split into a row pass (column
    kernel `[1]`) and a column pass (row kernel `[1]`) it gives the same numbers bit for
    bit, so the band's centres are those of `_derivative_images` on the same rows."""
    k0, k1, k2 = gaussian_kernels(sigma)
    inner = comp[crop : comp.shape[0] - crop]

    def rows(a, k):
        return cv2.sepFilter2D(a, cv2.CV_32F, k, _ONE, borderType=cv2.BORDER_REPLICATE)

    def cols(a, k):
        return cv2.sepFilter2D(a, cv2.CV_32F, _ONE, k, borderType=cv2.BORDER_REPLICATE)

    h0 = rows(comp, k0)
    h0_inner = h0[crop : comp.shape[0] - crop]
    h1, h2 = rows(inner, k1), rows(inner, k2)
    return [
        cols(h0, k0),
        cols(h1, k0),
        cols(h0_inner, k1),
        cols(h2, k0),
        cols(h1, k1),
        cols(h0_inner, k2),
    ]


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
    """Zero in [0, 1] of the cubic Hermite interpolant (values p, slopes m); p0, p1 bracket."""
    x = np.clip(p0 / np.where(p0 != p1, p0 - p1, 1.0), 0.0, 1.0)
    for _ in range(3):
        x2 = x * x
        x3 = x2 * x
        h = (
            (2 * x3 - 3 * x2 + 1) * p0
            + (x3 - 2 * x2 + x) * m0
            + (-2 * x3 + 3 * x2) * p1
            + (x3 - x2) * m1
        )
        dh = (6 * x2 - 6 * x) * p0 + (3 * x2 - 4 * x + 1) * m0 + (-6 * x2 + 6 * x) * p1
        dh = dh + (3 * x2 - 2 * x) * m1
        step = h / np.where(dh != 0, dh, 1.0)
        x = np.clip(x - step, 0.0, 1.0)
    return x


def _select(win: list[np.ndarray], lo: int, hi: int):
    """Strongest line point per column among the window rows `lo..hi-1`.

    Returns `(k, found, nx, ny, lam, t)` per column (k: window row index).
    """
    _, rx, ry, rxx, rxy, ryy = win
    cols = np.arange(rx.shape[1])
    nx, ny, lam, t, is_line = _line_points(rx[lo:hi], ry[lo:hi], rxx[lo:hi], rxy[lo:hi], ryy[lo:hi])
    score = np.where(is_line, -lam, -np.inf)
    best = np.argmax(score, axis=0)
    found = np.isfinite(score[best, cols])
    return (
        best + lo,
        found,
        nx[best, cols],
        ny[best, cols],
        lam[best, cols],
        t[best, cols],
    )


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
        padded = np.pad(phi, half, mode="edge")
        win = np.lib.stride_tricks.sliding_window_view(padded, _NORMAL_WINDOW)
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

    def along(i):  # n·∇r (background ramp removed) and its derivative along y, per column
        return (
            nxk * (rx[i, cols] - grad_x) + nyk * (ry[i, cols] - grad_y),
            nxk * rxy[i, cols] + nyk * ryy[i, cols],
        )

    g0, d0 = along(k)
    gm, dm = along(np.maximum(k - 1, 0))
    gp, dp = along(np.minimum(k + 1, k_rows - 1))
    rowk = rows[k, cols].astype(np.float64)
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
    height = r[k, cols] - bg
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

    def at(pos):
        lo = np.floor(pos)
        f = pos - lo
        lo = lo.astype(np.intp)
        return (1 - f) * sample(lo, cols) + f * sample(lo + 1, cols)

    centre = at(y)
    plus, minus = at(y + delta), at(y - delta)
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


def steger_band(
    gather, shape: tuple[int, int], track: np.ndarray, width_px: float, band_px: int | None
) -> ScanLines:
    """Steger in a band of ± `band_px` rows around `track` (W,), scan frame.

    `gather(rows, cols)` returns the scan-frame image at integer index arrays (so that a
    horizontal scan needs no transposed copy of the image). `band_px=None` picks the
    smallest band that holds the search window and the background samples.
    """
    sigma, r, bg_off, margin = _geometry(width_px, band_px)
    if band_px is None:
        margin = bg_off + _SEARCH + 1
    h, w = shape
    n_tiles = -(-w // _TILE)
    centre = np.rint(track).astype(np.intp)
    padded = np.pad(centre, (0, n_tiles * _TILE - w), mode="edge").reshape(n_tiles, _TILE)
    lo, hi = padded.min(axis=1), padded.max(axis=1)
    half = margin + r
    top = lo - half
    height = int((hi - lo).max()) + 2 * half + 1
    tile_w = _TILE + 2 * r
    rows_idx = np.clip(top[None, :, None] + np.arange(height)[:, None, None], 0, h - 1)
    cols_idx = np.arange(n_tiles)[:, None] * _TILE - r + np.arange(tile_w)[None, :]
    cols_idx = np.clip(cols_idx, 0, w - 1)[None, :, :]
    comp = gather(rows_idx, cols_idx).reshape(height, n_tiles * tile_w)
    comp = comp.astype(np.float32, copy=False)
    # The derivatives are only read within ± (search + 1) rows of the track.
    k_search = _SEARCH + 1
    crop = margin - k_search
    smooth, *d = _band_derivatives(comp, crop, sigma)

    cols = np.arange(w)
    tile = cols // _TILE
    ccol = tile * tile_w + r + (cols - tile * _TILE)
    rows = centre[None, :] + np.arange(-k_search, k_search + 1)[:, None]
    crow = rows - top[tile][None, :]
    flat = crow * comp.shape[1] + ccol
    win = [np.take(smooth, flat)]
    flat_d = flat - crop * comp.shape[1]
    win += [np.take(a, flat_d) for a in d]
    # Background samples beside the strongest line point (as in the full frame).
    selection = _select(win, 1, 2 * k_search)
    best_row = rows[selection[0], cols]
    bg_crow = best_row[None, :] + np.array([-bg_off, bg_off])[:, None] - top[tile][None, :]
    bg2 = np.take(smooth, bg_crow * comp.shape[1] + ccol)
    res, bg, grad_y, ny = _evaluate(win, rows, selection, bg2, bg_off, sigma)
    s_total = math.hypot(width_px / FWHM_PER_SIGMA, sigma)
    top_c = top[tile]

    def sample(rr, cc):
        crow_s = np.clip(rr - top_c, 0, comp.shape[0] - 1)
        return np.take(smooth, crow_s * comp.shape[1] + ccol[cc])

    return _asymmetry(sample, res, bg, grad_y, ny, s_total, bg_off)
