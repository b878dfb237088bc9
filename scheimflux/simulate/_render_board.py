"""Render checkerboard images through any board-plane → pixel map (NumPy/OpenCV).

The map `board_to_pixel` may be anything vectorised, for example a camera model's
projection of a posed board or the exact ray tracer, which has no closed-form inverse.
The renderer inverts it: Newton's method (finite-difference Jacobian) gives the board
coordinates of the pixels of a coarse grid (every `grid_step_px` pixels), a cubic spline
carries them, and their derivatives, to every pixel. Each pixel is then split into
`supersample × supersample` sub-squares and each sub-square is box-filtered
analytically: within it the board coordinates are affine in the pixel coordinates, so
the fraction of it on either side of a square edge is the CDF of a sum of two uniform
variables (a trapezoid). Corner and edge positions are therefore sub-pixel exact; the
only approximation is where two edges cross the same sub-square (at the corners
themselves), which is symmetric about the corner.

Board frame: the board's inner corners lie at `(i s, j s, 0)`, `i < cols`, `j < rows`,
`s = square_mm`; square `(i, j)` spans `[i s, (i + 1) s] × [j s, (j + 1) s]` for
`-1 ≤ i < cols`, `-1 ≤ j < rows` and is black when `i + j` is even, so square `(-1, -1)`,
diagonally outside corner 0, is black. A white quiet zone `margin_squares` squares wide
surrounds the pattern and a grey background lies beyond the board.

Pixel (0, 0) is the centre of the top-left pixel; u grows to the right, v downwards.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np
from scipy.interpolate import CubicSpline

__all__ = ["BoardMap", "board_map", "render_checkerboard", "rig_board_maps"]

_CHUNK_ELEMENTS = 1 << 20  # sub-samples evaluated at once


def _board_geometry(board) -> tuple[int, int, float]:
    cols, rows = int(board.cols), int(board.rows)
    square = float(board.square_mm)
    if cols < 2 or rows < 2 or not (square > 0 and math.isfinite(square)):
        raise ValueError(f"board needs at least 2 x 2 inner corners and a square > 0, got {board}")
    return cols, rows, square


def _call_map(board_to_pixel: Callable, xy: np.ndarray) -> np.ndarray:
    out = np.asarray(board_to_pixel(xy), dtype=np.float64)
    if out.shape != xy.shape:
        raise ValueError(
            f"board_to_pixel must map (N, 2) board points to (N, 2) pixels, got {out.shape} "
            f"for input {xy.shape}"
        )
    return out


def _homography(board_to_pixel: Callable, extent: tuple[float, float, float, float]) -> np.ndarray:
    """Pixel → board homography fitted to the map on a grid over the board's extent."""
    x0, x1, y0, y1 = extent
    gx, gy = np.meshgrid(np.linspace(x0, x1, 11), np.linspace(y0, y1, 11))
    xy = np.stack([gx.ravel(), gy.ravel()], axis=1)
    uv = _call_map(board_to_pixel, xy)
    ok = np.all(np.isfinite(uv), axis=1)
    if ok.sum() < 8:
        raise ValueError("board_to_pixel is not finite on enough of the board to invert it")
    H, _ = cv2.findHomography(uv[ok], xy[ok], 0)
    if H is None:
        raise ValueError("board_to_pixel is degenerate (could not fit a homography)")
    return H


def _apply_h(H: np.ndarray, uv: np.ndarray) -> np.ndarray:
    p = uv @ H[:, :2].T + H[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        out = p[:, :2] / p[:, 2:]
    out[~(p[:, 2] * H[2, 2] > 0)] = np.nan  # beyond the horizon
    return out


def _newton(
    board_to_pixel: Callable,
    uv: np.ndarray,
    xy0: np.ndarray,
    h: float,
    *,
    tol_px: float = 1e-9,
    max_iter: int = 30,
) -> np.ndarray:
    """Solve `board_to_pixel(xy) = uv` per point; NaN where it does not converge."""
    xy = xy0.copy()
    n = len(xy)
    active = np.all(np.isfinite(xy), axis=1)
    done = np.zeros(n, bool)
    best = np.full(n, np.inf)
    step = np.zeros_like(xy)
    for _ in range(max_iter):
        idx = np.flatnonzero(active & ~done)
        if idx.size == 0:
            break
        # evaluate every point each time: a constant shape lets a jitted map (a camera
        # model, the ray tracer) reuse its compilation
        x = np.where(np.isfinite(xy), xy, 0.0)
        f = _call_map(board_to_pixel, np.concatenate([x, x + [h, 0.0], x + [0.0, h]]))
        f0, fx, fy = f[idx], f[n + idx], f[2 * n + idx]
        r = f0 - uv[idx]
        err = np.hypot(r[:, 0], r[:, 1])
        bad = ~np.isfinite(err)
        worse = ~bad & (err > best[idx])  # overshoot: halve the previous step
        if np.any(worse):
            w = idx[worse]
            step[w] *= 0.5
            xy[w] -= step[w]
        good = ~bad & ~worse
        g = idx[good]
        best[g] = err[good]
        done[g] = err[good] < tol_px
        J = np.stack([(fx - f0) / h, (fy - f0) / h], axis=-1)[good]  # (n, 2, 2)
        det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
        rr = r[good]
        with np.errstate(divide="ignore", invalid="ignore"):
            dx = -(J[:, 1, 1] * rr[:, 0] - J[:, 0, 1] * rr[:, 1]) / det
            dy = -(-J[:, 1, 0] * rr[:, 0] + J[:, 0, 0] * rr[:, 1]) / det
        st = np.stack([dx, dy], axis=1)
        st[done[g]] = 0.0
        step[g] = st
        xy[g] += st
        active[idx[bad]] = False
        active[~np.all(np.isfinite(xy), axis=1)] = False
    # points that never reached the tolerance but are very close are accepted
    ok = active & (done | (best < 1e-6))
    xy[~ok] = np.nan
    return xy


def _spline_weights(nodes: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The matrix `W` with `f(x) = W f(nodes)` for the not-a-knot cubic spline."""
    return CubicSpline(nodes, np.eye(len(nodes)), axis=0, bc_type="not-a-knot")(x)


class BoardMap:
    """The inverse of a board → pixel map: board coordinates (mm) of every pixel.

    Built by [`board_map`][]; evaluate rows with [`BoardMap.rows`][] or the whole image
    with [`BoardMap.xy`][].
    """

    def __init__(self, shape, nodes_u, nodes_v, coarse_xy, node_ok):
        self.shape = (int(shape[0]), int(shape[1]))
        self.nodes_u, self.nodes_v = nodes_u, nodes_v
        self.coarse_xy = coarse_xy  # (nv, nu, 2), holes filled
        self.node_ok = node_ok  # (nv, nu)
        H, W = self.shape
        self._wu = _spline_weights(nodes_u, np.arange(W, dtype=np.float64))
        self._wv = _spline_weights(nodes_v, np.arange(H, dtype=np.float64))
        # a pixel is valid when the nodes of its cell and their neighbours are valid
        bad = (~node_ok).astype(np.uint8)
        bad = cv2.dilate(bad, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
        step = nodes_u[1] - nodes_u[0]
        iu = np.clip(np.floor((np.arange(W) - nodes_u[0]) / step).astype(int), 0, len(nodes_u) - 1)
        iv = np.clip(np.floor((np.arange(H) - nodes_v[0]) / step).astype(int), 0, len(nodes_v) - 1)
        self._bad_u, self._bad_v = iu, iv
        self._bad = bad.astype(bool)

    def rows(self, v0: int, v1: int) -> dict[str, np.ndarray]:
        """Board coordinates and their pixel derivatives for image rows `v0:v1`.

        Returns arrays of shape `(v1 - v0, W)`: `x`, `y` (mm), `x_u`, `x_v`, `y_u`, `y_v`
        (mm/px, central differences of the spline) and `valid` (bool).
        """
        out = {}
        lo, hi = max(0, v0 - 1), min(self.shape[0], v1 + 1)
        for k, name in enumerate("xy"):
            full = (self._wv[lo:hi] @ self.coarse_xy[..., k]) @ self._wu.T
            out[name + "_u"] = np.gradient(full, axis=1)[v0 - lo : v1 - lo]
            out[name + "_v"] = np.gradient(full, axis=0)[v0 - lo : v1 - lo]
            out[name] = full[v0 - lo : v1 - lo]
        out["valid"] = ~self._bad[np.ix_(self._bad_v[v0:v1], self._bad_u)]
        return out

    def xy(self) -> np.ndarray:
        """Board coordinates of every pixel, `(H, W, 2)` mm, NaN where the map is invalid."""
        r = self.rows(0, self.shape[0])
        xy = np.stack([r["x"], r["y"]], axis=-1)
        xy[~r["valid"]] = np.nan
        return xy


def board_map(
    board_to_pixel: Callable,
    shape: tuple[int, int],
    extent_mm: tuple[float, float, float, float],
    *,
    grid_step_px: int = 16,
) -> BoardMap:
    """Invert `board_to_pixel` on a coarse pixel grid and return the interpolating map.

    **Arguments:**
    - `board_to_pixel`: vectorised map of board-plane points `(N, 2)` mm → pixels `(N, 2)`.
    - `shape`: `(H, W)` of the image.
    - `extent_mm`: `(x_min, x_max, y_min, y_max)` of the board, used to fit the
      homography that starts Newton's method and to scale its finite differences.
    - `grid_step_px`: spacing of the coarse grid on which Newton's method runs.
    """
    H, W = int(shape[0]), int(shape[1])
    if H < 2 or W < 2:
        raise ValueError(f"shape must be (H, W) with both at least 2, got {shape}")
    step = int(grid_step_px)
    if step < 1:
        raise ValueError(f"grid_step_px must be >= 1, got {grid_step_px}")
    # one extra node beyond each edge keeps the spline's end conditions off the image
    nodes_u = np.arange(-step, W - 1 + 2 * step, step, dtype=np.float64)
    nodes_v = np.arange(-step, H - 1 + 2 * step, step, dtype=np.float64)
    gu, gv = np.meshgrid(nodes_u, nodes_v)
    uv = np.stack([gu.ravel(), gv.ravel()], axis=1)
    Hm = _homography(board_to_pixel, extent_mm)
    xy0 = _apply_h(Hm, uv)
    size = max(extent_mm[1] - extent_mm[0], extent_mm[3] - extent_mm[2])
    xy = _newton(board_to_pixel, uv, xy0, h=1e-7 * size)
    ok = np.all(np.isfinite(xy), axis=1)
    fill = np.where(ok[:, None], xy, xy0)
    fill[~np.all(np.isfinite(fill), axis=1)] = 0.0
    shape2 = (len(nodes_v), len(nodes_u))
    return BoardMap((H, W), nodes_u, nodes_v, fill.reshape(*shape2, 2), ok.reshape(shape2))


def _cdf(c: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """`P(S < c)` for `S = U(-a, a) + U(-b, b)` (a trapezoidal distribution)."""
    out = (c > 0).astype(np.float64)
    near = np.abs(c) < a + b
    if not np.any(near):
        return out
    c, a, b = c[near], a[near], b[near]
    A = np.maximum(np.maximum(a, b), 1e-300)
    B = np.maximum(np.minimum(a, b), 1e-9 * A)
    lo = (c + A + B) ** 2 / (8 * A * B)
    mid = (c + A) / (2 * A)
    hi = 1.0 - (A + B - c) ** 2 / (8 * A * B)
    out[near] = np.clip(np.where(c < B - A, lo, np.where(c <= A - B, mid, hi)), 0.0, 1.0)
    return out


def _shade(r: dict, cols, rows, s, margin, black, white, background, n) -> np.ndarray:
    """Box-filtered grey level (fraction of full scale) of each pixel of a row block."""
    x, y = r["x"], r["y"]
    xu, xv, yu, yv = r["x_u"], r["x_v"], r["y_u"], r["y_v"]
    # the board's outer edge (quiet zone → background), box-filtered over the whole pixel
    ax, bx, ay, by = np.abs(xu) / 2, np.abs(xv) / 2, np.abs(yu) / 2, np.abs(yv) / 2
    x_lo, x_hi = -s * (1 + margin), s * (cols + margin)
    y_lo, y_hi = -s * (1 + margin), s * (rows + margin)
    mask = (
        _cdf(x - x_lo, ax, bx)
        * _cdf(x_hi - x, ax, bx)
        * _cdf(y - y_lo, ay, by)
        * _cdf(y_hi - y, ay, by)
    )
    # the pattern: each sub-square sees at most one x edge and one y edge
    h = 1.0 / n
    ax, bx, ay, by = ax * h, bx * h, ay * h, by * h
    acc = np.zeros_like(x)
    offsets = (np.arange(n) + 0.5) / n - 0.5
    for du in offsets:
        for dv in offsets:
            xs = x + xu * du + xv * dv
            ys = y + yu * du + yv * dv
            k = np.rint(xs / s)
            m = np.rint(ys / s)
            px = _cdf(xs - k * s, ax, bx)  # fraction of the sub-square with x > k s
            py = _cdf(ys - m * s, ay, by)
            # squares (k, m), (k-1, m), (k, m-1), (k-1, m-1) around the nearest crossing
            x0 = px * ((k >= -1) & (k <= cols - 1))
            x1 = (1 - px) * ((k >= 0) & (k <= cols))
            y0 = py * ((m >= -1) & (m <= rows - 1))
            y1 = (1 - py) * ((m >= 0) & (m <= rows))
            even = (k + m) % 2 == 0
            dark = np.where(even, x0 * y0 + x1 * y1, x1 * y0 + x0 * y1)
            acc += dark
    val = white + (black - white) * (acc / (n * n))
    out = background + mask * (val - background)
    out[~r["valid"]] = background
    return out


def _blur(img: np.ndarray, sigma: np.ndarray | float) -> np.ndarray:
    """Gaussian blur, spatially varying: a few levels blended linearly by the sigma map."""
    if np.isscalar(sigma) or np.ndim(sigma) == 0:
        s = float(sigma)
        return img if s <= 0 else cv2.GaussianBlur(img, (0, 0), s, borderType=cv2.BORDER_REFLECT)
    sigma = np.clip(np.nan_to_num(np.asarray(sigma, dtype=np.float64), nan=0.0), 0.0, None)
    lo, hi = float(sigma.min()), float(sigma.max())
    if hi - lo < 0.02:
        return _blur(img, 0.5 * (lo + hi))
    levels = np.linspace(lo, hi, min(8, int(math.ceil((hi - lo) / 0.25)) + 1))
    stack = [_blur(img, float(s)) for s in levels]
    t = (sigma - lo) / (hi - lo) * (len(levels) - 1)
    i = np.clip(np.floor(t).astype(int), 0, len(levels) - 2)
    w = t - i
    out = np.zeros_like(img)
    for k in range(len(levels) - 1):
        sel = i == k
        out[sel] = (1 - w[sel]) * stack[k][sel] + w[sel] * stack[k + 1][sel]
    return out


def rig_board_maps(
    rig: Any, T_c_b: Any, *, imaging: str = "chief", sampling: Any = None
) -> tuple[Callable, float | Callable]:
    """`board_to_pixel` and `blur_sigma_px` for [`render_checkerboard`][] through a rig.

    **Arguments:**
    - `rig`: a `Rig`; `T_c_b`: the board pose (camera from board).
    - `imaging`: `"chief"`: board points imaged by their chief rays, no blur;
      `"centroid"`: by the centroid of the bundle filling the stop
      (`simulate._pupil.pupil_points`), and each point blurred by the Gaussian fit of its
      spot: an isotropic Gaussian of σ = sqrt(trace(cov) / 2) px, cov the bundle's second
      moments on the sensor (a Gaussian fit of the ray bundle, not a splat of its rays:
      coma's asymmetry moves the centroid, which the map carries, but not the blur).
    - `sampling`: the stop quadrature for `"centroid"` (default `pupil_grid(6)`).

    **Returns:** `(board_to_pixel, blur_sigma_px)`; pixels are NaN only where no ray of the
    bundle gets through.
    """
    import jax.numpy as jnp

    from ._pupil import pupil_grid, pupil_points

    R = np.asarray(T_c_b.R, dtype=np.float64)
    t = np.asarray(T_c_b.translation, dtype=np.float64)

    def posed(xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64)
        return xy @ R[:, :2].T + t

    if imaging == "chief":

        def chief(xy):  # the hit of every traced chief ray, on or off the sensor
            return np.asarray(rig.project(jnp.asarray(posed(xy)))[0])

        return chief, 0.0
    if imaging != "centroid":
        raise ValueError(f"imaging must be 'chief' or 'centroid', got {imaging!r}")
    sampling = pupil_grid(6) if sampling is None else sampling

    def centroid(xy):
        return pupil_points(rig, posed(xy), sampling, on_sensor=False)[0]

    def sigma(xy):
        return pupil_points(rig, posed(xy), sampling, on_sensor=False)[3]

    return centroid, sigma


def render_checkerboard(
    board: Any,
    board_to_pixel: Callable,
    *,
    shape: tuple[int, int] = (1200, 1600),
    blur_sigma_px: float | Callable = 0.0,
    vignetting: float = 0.0,
    bit_depth: int = 8,
    black: float = 0.08,
    white: float = 0.85,
    background: float = 0.45,
    noise_sigma: float = 0.0,
    seed: int | None = None,
    margin_squares: float = 1.0,
    supersample: int = 2,
    grid_step_px: int = 16,
) -> np.ndarray:
    """Render a checkerboard seen through `board_to_pixel`.

    **Arguments:**
    - `board`: a checkerboard with `cols`, `rows` (inner corners per row and per column)
      and `square_mm`, e.g. `scheimflux.targets.Checkerboard`.
    - `board_to_pixel`: vectorised map of board-plane points `(N, 2)` mm → pixels
      `(N, 2)` (e.g. `lambda xy: cam.project(pose.apply(xyz(xy)))` or the ray tracer's
      `Rig.project`); NaN only where no ray gets through the lens. Return pixels beyond
      the sensor's edges too (do not mask them): the inversion samples a grid one step
      beyond the image. It is inverted numerically; a jitted map is called with one
      array shape throughout.
    - `shape`: `(H, W)` in pixels.
    - `blur_sigma_px`: Gaussian blur (px), a number or a callable mapping board points
      `(N, 2)` mm → sigma `(N,)` px (defocus from the real geometry), applied through a
      few blur levels blended by the per-pixel sigma.
    - `vignetting`: relative loss of light at the image corners, `1 - vignetting r²`
      with `r` the distance from the image centre over the half-diagonal.
    - `bit_depth`: 8 (uint8), 12 or 16 (uint16).
    - `black`, `white`, `background`: grey levels of the black squares, the white
      squares and quiet zone, and the background beyond the board (fractions of full
      scale).
    - `noise_sigma`: additive Gaussian noise, fraction of full scale.
    - `seed`: seed of the noise generator.
    - `margin_squares`: width of the white quiet zone around the pattern, in squares.
    - `supersample`: sub-squares per pixel side, each box-filtered analytically.
    - `grid_step_px`: spacing of the grid on which the map is inverted by Newton's method.

    **Returns:** the `(H, W)` image, uint8 for 8 bits and uint16 otherwise.
    """
    cols, rows, s = _board_geometry(board)
    if bit_depth not in (8, 12, 16):
        raise ValueError(f"bit_depth must be 8, 12 or 16, got {bit_depth}")
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    if not (noise_sigma >= 0 and margin_squares >= 0 and 0 <= vignetting < 1):
        raise ValueError("noise_sigma and margin_squares must be >= 0 and vignetting in [0, 1)")
    H, W = int(shape[0]), int(shape[1])
    margin = float(margin_squares)
    extent = (-s * (1 + margin), s * (cols + margin), -s * (1 + margin), s * (rows + margin))
    bmap = board_map(board_to_pixel, (H, W), extent, grid_step_px=grid_step_px)

    img = np.empty((H, W), np.float64)
    block = max(1, _CHUNK_ELEMENTS // (W * supersample * supersample))
    for v0 in range(0, H, block):
        v1 = min(H, v0 + block)
        img[v0:v1] = _shade(
            bmap.rows(v0, v1), cols, rows, s, margin, black, white, background, supersample
        )

    return _finish(img, bmap, blur_sigma_px, vignetting, noise_sigma, seed, bit_depth)


def _finish(img, bmap, blur_sigma_px, vignetting, noise_sigma, seed, bit_depth) -> np.ndarray:
    """Blur, vignetting, noise and quantisation of a rendered float image (full scale 1)."""
    H, W = img.shape
    if callable(blur_sigma_px):
        c = bmap.coarse_xy.reshape(-1, 2)
        sig = np.asarray(blur_sigma_px(c), dtype=np.float64).reshape(bmap.node_ok.shape)
        sig = np.where(bmap.node_ok & np.isfinite(sig), sig, np.nan)
        if np.all(np.isnan(sig)):
            sig[:] = 0.0
        sig = np.where(np.isnan(sig), np.nanmedian(sig), sig)
        sigma_map = bmap._wv @ sig @ bmap._wu.T
        img = _blur(img, sigma_map)
    elif blur_sigma_px:
        if not (float(blur_sigma_px) >= 0):
            raise ValueError(f"blur_sigma_px must be >= 0, got {blur_sigma_px}")
        img = _blur(img, float(blur_sigma_px))

    if vignetting > 0:
        vv, uu = np.mgrid[0:H, 0:W]
        r2 = ((uu - (W - 1) / 2) ** 2 + (vv - (H - 1) / 2) ** 2) / (
            ((W - 1) / 2) ** 2 + ((H - 1) / 2) ** 2
        )
        img = img * (1.0 - vignetting * r2)
    if noise_sigma > 0:
        img = img + np.random.default_rng(seed).normal(0.0, noise_sigma, img.shape)
    full = float(2**bit_depth - 1)
    out = np.rint(np.clip(img, 0.0, 1.0) * full)
    return out.astype(np.uint8 if bit_depth == 8 else np.uint16)
