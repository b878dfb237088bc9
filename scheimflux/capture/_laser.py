"""The laser line and the target in one image (the single-image layout): keep each out
of the other's way.

In a grey image of board and laser line together, the line crosses the target:

- **Circle grids**: the dots cut the line into pieces and their edges put steps under
  it, so the extractor (which accepts ridges only) refuses it. [`target_holes`][] masks
  every dot of the grid (the detected centres, and the grid's homography for the dots
  the detector lost), grown by a margin, out of the stripe region: the line is then
  extracted in the gaps between the dots.
- **Every target**: the line's light pulls the points it falls near (a corner's
  `cornerSubPix` window, a dot's blob). [`near_laser`][] marks the points within the
  reach of the line: the extracted centres joined into a polyline (across the holes
  and gaps), a point dropped when the line comes within `influence + 2.5 FWHM` of it.
  `influence` is where the detector looks: a corner's refinement half-window (square:
  the Chebyshev distance), a dot's radius (the Euclidean distance). At 2.5 FWHM the
  line's Gaussian profile is down to 1e-7 of its peak (measured: on a 0.2 mm checkerboard
  at ×1.5, corners 20 px from a 5 px line, inside the 20 px window, are off by 0.3-0.6
  px and pass the neighbour check; from 28 px on they are at the detection noise).

A colour image needs neither when it is stored losslessly: the laser falls in one
channel and the target is detected in the channel minimum. [`laser_in_board`][] tells
the two apart. A colour **JPEG** keeps the line in every channel: JPEG stores colour as
luma at full resolution and chroma at half resolution (4:2:0), both quantised in DCT
blocks, so decoding puts `0.299 (L - L_s)` of the laser `L` (`L_s` its half-resolution
chroma copy) and the chroma blocks' ringing into the channels the laser is not in.
Measured on a 0.2 mm checkerboard at ×1.5, quality 95: corners 13-26 px from the line
off by 0.16-0.57 px in the channel minimum (0.03 px in the same image saved as PNG).
Its points within the line's reach are dropped as in a grey image, the reach grown by
one chroma block (`JPEG_BLOCK_PX`, 16 px: the ringing fills the block the line is in).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from ..targets._charuco import CharucoBoard
from ..targets._circles import CircleGrid
from ..targets._result import homography_jacobian

__all__ = [
    "fill_holes",
    "laser_in_board",
    "laser_removed",
    "near_laser",
    "off_local_grid",
    "displaced",
    "target_holes",
]

_NOISE_K = 5.0  # off_local_grid: threshold in robust standard deviations of the residuals
_NOISE_MIN_PX = 0.1  # ... and never below (the detection noise of a sharp target)

_REACH_FWHM = 2.5  # line reach beyond a point's influence, in line widths (FWHM)
_MIN_CLIPPED = 20  # fewest pixels at the clip level that make a clipped line
JPEG_BLOCK_PX = 16.0  # a JPEG chroma block (8 x 8 DCT at half resolution) in image pixels


def laser_in_board(image: Any) -> bool:
    """Whether the image the target is detected in still holds the laser line: a grey
    image, or a colour one without coloured pixels (a grey camera saved as colour: the
    channel minimum keeps the laser)."""
    img = np.asarray(image)
    if img.ndim == 2 or img.shape[2] < 3:
        return True
    c = img[:, :, :3].astype(np.float32)
    full = 255.0 if img.dtype == np.uint8 else float(max(c.max(), 1.0))
    # a coloured line: some pixels (1 in 10^4: a 5 px line 2 % of the image long) whose
    # channels differ by a tenth of full scale; JPEG noise on grey stays far below
    return bool(np.mean(c.max(axis=2) - c.min(axis=2) > 0.1 * full) < 1e-4)


def laser_removed(image: Any, grid: CircleGrid) -> np.ndarray | None:
    """A grey image of a circle grid with the laser line taken out: its morphological
    opening (grey erosion, then dilation) by a disc half the size of the smaller of a
    dot and the white gap between dots, measured from the image's blobs.

    An opening removes every bright feature the disc does not fit into and keeps the
    rest: the thin line (a 5 px line is down to 1e-5 of its peak at 4 FWHM) goes, on
    the white board and across the dots it crosses, while the dots (dark on white, or
    light dots larger than the disc) and the white gaps (wider than the disc) stay. The
    result stands in for a laser-off image: the grid is detected in it (a line across
    the dots splits and moves their blobs, and the grid is then lost), and the line is
    extracted from the difference, as with `view_<k>_off`.

    **Returns:** the opened image (input dtype), or None when no dots are seen.
    """
    from ..targets._circles import _blob_detector
    from ..targets._result import grey_float, to_uint8

    img = np.asarray(image)
    if img.ndim != 2:
        return None
    norm, problem = grey_float(img)
    if problem:
        return None
    u8 = to_uint8(norm)
    n = grid.num_corners
    sizes = []
    for light in (False, True):
        kp = _blob_detector(u8.shape, n, light).detect(u8)
        if len(kp) > len(sizes):
            sizes = [k.size for k in kp]
    if len(sizes) < max(4, n // 4):
        return None
    dot = float(np.median(sizes))  # blob diameter, px
    nearest = grid.spacing_mm * (np.sqrt(2.0) if grid.asymmetric else 1.0)
    gap = dot * (nearest / grid.diameter_mm - 1.0)
    d = int(0.5 * min(dot, gap)) | 1  # odd disc diameter
    if d < 3:
        return None
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (d, d))
    return cv2.morphologyEx(img, cv2.MORPH_OPEN, disc)


def _homography(corners_px: np.ndarray, xy_mm: np.ndarray):
    ok = np.all(np.isfinite(corners_px), axis=1)
    if ok.sum() < 4:
        return None, ok
    Hm, _ = cv2.findHomography(xy_mm[ok], corners_px[ok], cv2.RANSAC, 2.0)
    return Hm, ok


def _scale_px_per_mm(Hm: np.ndarray, xy_mm: np.ndarray) -> np.ndarray:
    """The largest local scale (px/mm) of the homography at each board point (the larger
    singular value of its Jacobian)."""
    return np.linalg.svd(homography_jacobian(Hm, xy_mm), compute_uv=False)[:, 0]


def _all_points(target, corners_px: np.ndarray):
    """Every target point in the image: detected where found, else predicted by the
    homography of the found ones; and the local scale (px/mm). None without 4 points."""
    xy = np.asarray(target.points_mm, np.float64)[:, :2]
    uv = np.asarray(corners_px, np.float64).reshape(-1, 2)
    Hm, ok = _homography(uv, xy)
    if Hm is None:
        return None, None
    pred = cv2.perspectiveTransform(xy[None], Hm)[0]
    pts = np.where(ok[:, None], uv, pred)
    return pts, _scale_px_per_mm(Hm, xy)


def target_holes(target, corners_px: np.ndarray, shape, *, margin_px: float) -> np.ndarray:
    """Pixels the stripe must not be searched in: for a circle grid, every dot (radius
    from the grid's local scale) grown by `margin_px`; nothing for other targets.

    **Arguments:**
    - `target`: the target; `corners_px`: its detected points `(M, 2)` (NaN rows: lost).
    - `shape`: `(H, W)`; `margin_px`: growth beyond each dot's edge (px).

    **Returns:** `(H, W)` bool, True on the holes.
    """
    H, W = int(shape[0]), int(shape[1])
    holes = np.zeros((H, W), np.uint8)
    if not isinstance(target, CircleGrid):
        return holes.astype(bool)
    pts, scale = _all_points(target, corners_px)
    if pts is None:
        return holes.astype(bool)
    radius = 0.5 * target.diameter_mm * scale + float(margin_px)
    for (u, v), r in zip(pts, radius):
        if -r <= u < W + r and -r <= v < H + r:
            cv2.circle(holes, (int(round(u * 16)), int(round(v * 16))), int(round(r * 16)), 1,
                       -1, cv2.LINE_8, 4)  # fmt: skip
    return holes.astype(bool)


def fill_holes(image: Any, holes: np.ndarray, axis: int) -> np.ndarray:
    """The image with every hole bridged by straight interpolation along image rows
    (`axis=1`) or columns (`axis=0`) between the pixels beside it.

    A laser line running along that axis continues through the bridged holes with its
    profile across it, so the extractor tracks one line instead of pieces too short to
    count; the centres it finds inside the holes are made up and must be discarded.
    Holes touching the image border take the one pixel beside them.

    **Returns:** float32 image, the input's shape.
    """
    img = np.asarray(image, np.float32)
    if img.ndim == 2:
        img = img[:, :, None]
    h = np.asarray(holes, bool)
    if axis == 0:
        img, h = img.transpose(1, 0, 2), h.T
    n = h.shape[1]
    idx = np.broadcast_to(np.arange(n), h.shape)
    left = np.maximum.accumulate(np.where(h, -1, idx), axis=1)
    right = np.minimum.accumulate(np.where(h, n, idx)[:, ::-1], axis=1)[:, ::-1]
    has_l, has_r = left >= 0, right < n
    lc, rc = np.clip(left, 0, n - 1), np.clip(right, 0, n - 1)
    rows = np.arange(h.shape[0])[:, None]
    a, b = img[rows, lc], img[rows, rc]
    t = np.where(has_l & has_r, (idx - left) / np.maximum(right - left, 1), 0.0)
    t = np.where(has_l, t, 1.0)[..., None].astype(np.float32)
    filled = np.where((h & (has_l | has_r))[..., None], (1 - t) * a + t * b, img)
    if axis == 0:
        filled = filled.transpose(1, 0, 2)
    return filled[:, :, 0] if np.ndim(image) == 2 else filled


def _influence_mm(target) -> tuple[float, bool]:
    """How far from a point (board mm) its detector looks, and whether that region is a
    square window (corners) rather than a disc (dots). The corner windows are the
    detectors' `cornerSubPix` half-windows: 0.3 of a square for checkerboards, limited
    to the white gap beside the markers on ChArUco boards."""
    if isinstance(target, CircleGrid):
        return 0.5 * target.diameter_mm, False
    if isinstance(target, CharucoBoard):
        gap = 0.5 * (target.square_mm - target.marker_mm)
        return min(0.3 * target.square_mm, gap), True
    return 0.3 * target.square_mm, True


def _dense_line(stripe_uv: np.ndarray, orientation: str) -> np.ndarray:
    """The stripe centres joined into a polyline sampled every pixel along the scan
    direction (gaps bridged by straight pieces)."""
    uv = np.asarray(stripe_uv, np.float64).reshape(-1, 2)
    uv = uv[np.all(np.isfinite(uv), axis=1)]
    if len(uv) < 2:
        return uv
    a = 0 if orientation != "horizontal-scan" else 1  # along the line
    order = np.argsort(uv[:, a])
    s, c = uv[order, a], uv[order, 1 - a]
    grid = np.arange(np.ceil(s[0]), np.floor(s[-1]) + 1)
    out = np.empty((len(grid), 2))
    out[:, a], out[:, 1 - a] = grid, np.interp(grid, s, c)
    return np.concatenate([out, uv])


def clipped_pixels(image: Any, mask: np.ndarray, max_halfwidth_px: float) -> np.ndarray:
    """`(N, 2)` `(u, v)` of the pixels of a grey integer image at its clip level (its
    maximum, where at least `_MIN_CLIPPED` pixels inside `mask` reach it) inside
    `mask`, in connected regions no wider than a line: at most `max_halfwidth_px` from
    their edge (a board whose white squares clip is no line); none otherwise. In a grey
    single image these are a clipped laser line's own pixels: they show where the line
    is even where the extractor refuses its centres (a clipped plateau over checker
    edges), so that the points next to it can be dropped."""
    img = np.asarray(image)
    if img.ndim != 2 or not np.issubdtype(img.dtype, np.integer) or not np.any(mask):
        return np.zeros((0, 2))
    top = img[mask].max()
    clip = ((img >= top) & mask).astype(np.uint8)
    if int(clip.sum()) < _MIN_CLIPPED:
        return np.zeros((0, 2))
    n, labels = cv2.connectedComponents(clip, connectivity=8)
    inner = cv2.distanceTransform(clip, cv2.DIST_L2, 3)
    widest = np.zeros(n)
    np.maximum.at(widest, labels.reshape(-1), inner.reshape(-1))
    thin = widest <= max_halfwidth_px
    thin[0] = False  # the background label
    v, u = np.nonzero(thin[labels])
    if len(u) < _MIN_CLIPPED:
        return np.zeros((0, 2))
    return np.stack([u, v], axis=1).astype(np.float64)


def near_laser(
    target,
    corners_px: np.ndarray,
    stripe_uv: np.ndarray,
    width_px: float,
    *,
    orientation: str = "vertical-scan",
    extra_px: float = 0.0,
    join: bool = True,
) -> np.ndarray:
    """The target points the laser line may have displaced (see the module doc).

    **Arguments:**
    - `target`, `corners_px`: the target and its detected points `(M, 2)`.
    - `stripe_uv`: `(N, 2)` laser centres found in the same image.
    - `width_px`: the line's FWHM (px).
    - `orientation`: the extractor's scan direction (`"vertical-scan"`: one centre per
      column), to join the centres across gaps.
    - `extra_px`: added to the reach (`JPEG_BLOCK_PX` for a JPEG image).
    - `join`: join the centres across gaps (False: `stripe_uv` are the line's pixels
      themselves, e.g. `clipped_pixels`).

    **Returns:** `(M,)` bool, True for found points within the line's reach.
    """
    uv = np.asarray(corners_px, np.float64).reshape(-1, 2)
    found = np.all(np.isfinite(uv), axis=1)
    line = _dense_line(stripe_uv, orientation) if join else np.asarray(stripe_uv, np.float64)
    out = np.zeros(len(uv), bool)
    if len(line) == 0 or not found.any():
        return out
    pts, scale = _all_points(target, uv)
    if pts is None:  # too few points for a scale: the median spacing is not needed here
        return out
    infl_mm, square = _influence_mm(target)
    reach = infl_mm * scale + _REACH_FWHM * float(width_px) + float(extra_px)
    d = np.abs(uv[found, None, :] - line[None, :, :])
    dist = d.max(axis=-1) if square else np.hypot(d[..., 0], d[..., 1])
    out[found] = dist.min(axis=1) < reach[found]
    return out


def off_local_grid(target, corners_px: np.ndarray) -> np.ndarray:
    """Points displaced from their neighbours' local grid by more than the detection
    noise allows: `grid_residuals` above `max(0.1 px, 5 σ)`, σ the residuals' robust
    spread (1.4826 × their median absolute value: most points are untouched).

    In a grey single image the laser line moves the corners it passes near by 0.3-2 px,
    under the detectors' own check (0.5 px); where the line itself is not found (a line
    along the checker edges is refused by the extractor), this is what finds them.

    **Returns:** `(M,)` bool.
    """
    from ..targets._result import grid_residuals

    pitch = float(getattr(target, "square_mm", None) or target.spacing_mm)
    r = grid_residuals(np.asarray(corners_px, np.float64), target.points_mm, pitch)
    fin = np.isfinite(r)
    if fin.sum() < 8:
        return np.zeros(len(r), bool)
    sigma = 1.4826 * float(np.median(r[fin]))
    return fin & (r > max(_NOISE_MIN_PX, _NOISE_K * sigma))


_DISPLACED_K = 3.0  # displaced: threshold in the untouched points' residual spreads
_DISPLACED_REACH = 2.5  # displaced: neighbours within this many pitches on the board


def displaced(target, corners_px: np.ndarray, suspects: np.ndarray) -> np.ndarray:
    """Of the `suspects` (found points within the laser line's reach), those measured to
    be displaced.

    Each suspect is predicted by the homography (RANSAC, then least squares on its
    inliers) of the untouched found points (not suspects) within `_DISPLACED_REACH`
    pitches of it on the board; it is displaced when further from that prediction than
    `max(_NOISE_MIN_PX, _DISPLACED_K σ)`, σ the spread of the untouched points' own
    residuals against their untouched neighbours (the median over 1.1774, the Rayleigh σ
    of a 2-D residual: detection noise, the print's irregularity and the lens's bending
    of the grid over a few pitches, all as they are in this view). A suspect with fewer
    than 6 untouched neighbours cannot be measured and counts as displaced. At 3 σ an
    untouched point is taken for displaced about once in 90.

    **Returns:** `(M,)` bool.
    """
    uv = np.asarray(corners_px, np.float64).reshape(-1, 2)
    found = np.all(np.isfinite(uv), axis=1)
    sus = np.asarray(suspects, bool) & found
    out = np.zeros(len(uv), bool)
    if not sus.any():
        return out
    free = found & ~sus
    pitch = float(getattr(target, "square_mm", None) or target.spacing_mm)
    xy = np.asarray(target.points_mm, np.float64)[:, :2]
    fidx = np.flatnonzero(free)

    def residual(a):
        d = np.linalg.norm(xy[fidx] - xy[a], axis=1)
        near = fidx[(d <= _DISPLACED_REACH * pitch) & (fidx != a)]
        if near.size < 6:
            return np.nan
        Hm, _ = cv2.findHomography(xy[near], uv[near], cv2.RANSAC, 0.5)
        if Hm is None:
            return np.nan
        pred = cv2.perspectiveTransform(xy[a][None, None], Hm)[0, 0]
        return float(np.linalg.norm(pred - uv[a]))

    own = np.array([residual(int(a)) for a in fidx])
    own = own[np.isfinite(own)]
    if len(own) < 4:  # the view's spread cannot be measured: every suspect goes
        out[sus] = True
        return out
    tol = max(_NOISE_MIN_PX, _DISPLACED_K * float(np.median(own)) / 1.1774)
    for a in np.flatnonzero(sus):
        r = residual(int(a))
        out[a] = not (np.isfinite(r) and r <= tol)
    return out
