"""Circle-grid targets, symmetric and asymmetric: geometry and detection through OpenCV's
`findCirclesGrid` with a blob detector sized to the image, dark or light circles.

Board frame (mm): x along a row of circles, y from one row to the next, z = 0 on the
board, +z into the board (away from a camera that sees the printed side).

- Symmetric grid, `cols × rows` circles (OpenCV's `patternSize = (cols, rows)`):
  circle `k` at `(i s, j s, 0)` with `i = k % cols`, `j = k // cols`, `s = spacing_mm`.
- Asymmetric grid (OpenCV's `CALIB_CB_ASYMMETRIC_GRID`, its calibration sample's
  layout): `cols` circles per row, `rows` rows, circle `k` at `((2 i + j % 2) s, j s, 0)`;
  rows are `s` apart, circles within a row `2 s` apart, diagonal neighbours `s √2`.

Point order: a grid of circles looks the same after some rotations (180° for a
rectangular symmetric grid, 90° for a square one; an asymmetric grid's own symmetries),
and no colour tells them apart. The order kept is (1) the handedness of a camera that
sees the printed side (`mirrored=True` for a mirror image), then (2) among the orders
that remain, the one whose circle 0 is nearest the image's top-left corner. This
changes only each view's board pose, never the camera calibrated from it; the message
says when the choice was needed.

Circle centres are the blob detector's centroids: under perspective and distortion the
centre of a circle's image is not the image of its centre (the shift grows with the
square of the circle's size over its distance). The observations state the circles'
diameter (`circle_diameter_mm`) and calibration predicts the centroid of each circle's
image (`calibrate._model.board_images_px`), so the shift is modelled, not an error.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import cv2
import numpy as np

from ._result import DetectionResult, grey_float, homography_jacobian, to_uint8

__all__ = ["CircleGrid", "circle_diameters_mm", "detect_circles"]


@dataclasses.dataclass(frozen=True)
class CircleGrid:
    """A grid of circles (see the module doc for the frame and the point order).

    **Arguments:**
    - `cols`, `rows`: circles per row and number of rows.
    - `spacing_mm`: `s`, the distance between neighbouring circles (symmetric) or
      between neighbouring rows (asymmetric).
    - `diameter_mm`: circle diameter (mm).
    - `asymmetric`: OpenCV's asymmetric layout.
    """

    cols: int
    rows: int
    spacing_mm: float
    diameter_mm: float
    asymmetric: bool = False

    def __post_init__(self):
        for name in ("cols", "rows"):
            v = getattr(self, name)
            if isinstance(v, bool) or int(v) != v or v < 2:
                raise ValueError(f"circle grid {name} must be an integer >= 2, got {v!r}")
            object.__setattr__(self, name, int(v))
        s, d = float(self.spacing_mm), float(self.diameter_mm)
        if not (math.isfinite(s) and s > 0):
            raise ValueError(f"spacing_mm must be a positive number, got {self.spacing_mm!r}")
        nearest = s * (math.sqrt(2.0) if self.asymmetric else 1.0)
        if not (math.isfinite(d) and 0 < d < nearest):
            raise ValueError(
                f"diameter_mm must be positive and below the nearest-neighbour distance "
                f"{nearest:g} mm, got {self.diameter_mm!r}"
            )
        object.__setattr__(self, "spacing_mm", s)
        object.__setattr__(self, "diameter_mm", d)
        object.__setattr__(self, "asymmetric", bool(self.asymmetric))

    def __str__(self) -> str:
        kind = "asymmetric" if self.asymmetric else "symmetric"
        return (
            f"{kind} circle grid {self.cols}x{self.rows}, spacing {self.spacing_mm:g} mm, "
            f"diameter {self.diameter_mm:g} mm"
        )

    @property
    def kind(self) -> str:
        return "acircles" if self.asymmetric else "circles"

    @property
    def size(self) -> str:
        return f"{self.cols}x{self.rows}"

    @property
    def num_corners(self) -> int:
        return self.cols * self.rows

    @property
    def pattern_size(self) -> tuple[int, int]:
        return (self.cols, self.rows)

    @property
    def points_mm(self) -> np.ndarray:
        """Circle centres, board frame, `(cols · rows, 3)`, row by row."""
        k = np.arange(self.num_corners)
        i, j = k % self.cols, k // self.cols
        x = (2 * i + j % 2) if self.asymmetric else i
        xy = np.stack([x * self.spacing_mm, j * self.spacing_mm], axis=1).astype(np.float64)
        return np.concatenate([xy, np.zeros((len(xy), 1))], axis=1)

    @property
    def centre_mm(self) -> np.ndarray:
        p = self.points_mm
        return 0.5 * (p.min(axis=0) + p.max(axis=0))

    @property
    def extent_mm(self) -> tuple[float, float, float, float]:
        """`(x_min, x_max, y_min, y_max)` of the board: the circles plus one spacing."""
        p, s = self.points_mm, self.spacing_mm
        return (p[:, 0].min() - s, p[:, 0].max() + s, p[:, 1].min() - s, p[:, 1].max() + s)

    def pattern(self, px_per_mm: float, *, dark_circles: bool = True) -> np.ndarray:
        """The printed pattern over `extent_mm`, uint8 (255 white), anti-aliased circles."""
        x0, x1, y0, y1 = self.extent_mm
        w, h = int(round((x1 - x0) * px_per_mm)), int(round((y1 - y0) * px_per_mm))
        ss = 4  # sub-texels per texel side
        img = np.zeros((h * ss, w * ss), np.uint8)
        shift = 4  # fixed-point bits of cv2.circle
        scale = px_per_mm * ss * (1 << shift)
        for x, y, _ in self.points_mm:
            # texel (r, c) covers x in [c, c + 1] / ppm: a centre at x mm is at x * ppm - 0.5
            cu = ((x - x0) * px_per_mm * ss - 0.5) * (1 << shift)
            cv = ((y - y0) * px_per_mm * ss - 0.5) * (1 << shift)
            r = 0.5 * self.diameter_mm * scale
            cv2.circle(img, (int(round(cu)), int(round(cv))), int(round(r)), 255, -1,
                       cv2.LINE_8, shift)  # fmt: skip
        img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
        return img if not dark_circles else 255 - img


def _blob_detector(shape: tuple[int, int], n: int, light: bool):
    p = cv2.SimpleBlobDetector_Params()
    h, w = shape
    p.filterByColor = True
    p.blobColor = 255 if light else 0
    p.filterByArea = True
    p.minArea = 6.0  # a circle of ~3 px diameter
    p.maxArea = float(max(50.0, 0.5 * h * w / max(n, 1)))  # a grid cell's share of the image
    p.minDistBetweenBlobs = 2.0
    p.filterByConvexity = True
    p.minConvexity = 0.8
    p.filterByInertia = True
    p.minInertiaRatio = 0.05  # ellipses of boards tilted by up to ~85°
    p.filterByCircularity = False
    p.minThreshold, p.maxThreshold, p.thresholdStep = 20.0, 235.0, 10.0
    return cv2.SimpleBlobDetector_create(p)


def _symmetries(xy: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """Index permutations that map the point set onto itself (rotations by 90° k and
    reflections about its centre), with the determinant (±1) of each."""
    c = xy.mean(axis=0)
    d = xy - c
    scale = float(np.abs(d).max()) or 1.0
    out = []
    for flip in (1.0, -1.0):
        for k in range(4):
            a = k * math.pi / 2
            M = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
            M = M @ np.diag([1.0, flip])
            q = d @ M.T
            dist = np.linalg.norm(q[:, None, :] - d[None, :, :], axis=-1)
            perm = dist.argmin(axis=1)
            if dist[np.arange(len(d)), perm].max() < 1e-6 * scale and len(set(perm)) == len(d):
                out.append((perm, float(np.linalg.det(M))))
    return out


def _handedness(xy: np.ndarray, uv: np.ndarray) -> tuple[float, float]:
    """Sign of the board → image map's Jacobian at the centre, and the homography fit's
    worst residual (px)."""
    H, _ = cv2.findHomography(xy, uv, 0)
    if H is None:
        return 0.0, math.inf
    c = xy.mean(axis=0)
    eps = 1e-3 * float(np.ptp(xy, axis=0).max())
    pts = np.array([c, c + [eps, 0.0], c + [0.0, eps]])[None]
    q = cv2.perspectiveTransform(pts, H)[0]
    du, dv = q[1] - q[0], q[2] - q[0]
    fit = cv2.perspectiveTransform(xy[None], H)[0]
    return float(np.sign(du[0] * dv[1] - du[1] * dv[0])), float(
        np.linalg.norm(fit - uv, axis=1).max()
    )


def _rows_reordered(
    xy: np.ndarray, uv: np.ndarray, pattern_size: tuple[int, int]
) -> tuple[np.ndarray, float, float]:
    """OpenCV's centres with its rows (`pattern_size = (per row, rows)` consecutive
    points each) sorted by their position across the rows, in whichever direction fits
    the grid better: `(centres, handedness, worst residual px)` of that order (its
    residual decides whether it is used, as for OpenCV's own order)."""
    cols, rows = pattern_size
    R = uv.reshape(rows, cols, 2)
    along = np.sum(R[:, -1] - R[:, 0], axis=0)
    normal = np.array([-along[1], along[0]]) / max(float(np.hypot(*along)), 1e-12)
    key = R.mean(axis=1) @ normal
    best = (uv, 0.0, math.inf)
    for order in (np.argsort(key), np.argsort(-key)):
        cand = R[order].reshape(-1, 2)
        sign, worst = _handedness(xy, cand)
        if worst < best[2]:
            best = (cand, sign, worst)
    return best


# `findCirclesGrid` finds a symmetric grid's basis by k-means, seeded from OpenCV's global
# random number generator: on real photographs (zcy, 12 views of a 7 x 7 grid in daylight)
# the same image was found or not from one call to the next (10-12 of 12 views, by the
# state earlier OpenCV calls left). Each attempt is seeded, so a detection depends on the
# image alone, and a failed one is tried again with the next seed (as the checkerboard's
# `_SB_SEEDS`).
_GRID_SEEDS = (0, 1, 2)


def detect_circles(
    image: Any, grid: CircleGrid, *, polarity: str = "auto", mirrored: bool = False
) -> DetectionResult:
    """Find the circle centres of `grid` in `image`.

    **Arguments:**
    - `image`: `(H, W)` grey or `(H, W, 3)` BGR image, 8- or 16-bit or float.
    - `grid`: the [`CircleGrid`][].
    - `polarity`: `"dark"` (dark circles on a light board), `"light"`, or `"auto"`
      (dark first, then light).
    - `mirrored`: the image is mirrored: keep the order of opposite handedness.

    **Returns:** a [`DetectionResult`][] in the order of `grid.points_mm` (see the
    module doc); all NaN when the grid was not found (OpenCV finds all circles or none).
    """
    if polarity not in ("auto", "dark", "light"):
        raise ValueError(f"polarity must be 'auto', 'dark' or 'light', got {polarity!r}")
    norm, problem = grey_float(image)
    if problem:
        return DetectionResult.failed(grid.num_corners, problem)
    img8 = to_uint8(norm)
    flags = cv2.CALIB_CB_ASYMMETRIC_GRID if grid.asymmetric else cv2.CALIB_CB_SYMMETRIC_GRID
    uv = None
    for light in {"auto": (False, True), "dark": (False,), "light": (True,)}[polarity]:
        det = _blob_detector(img8.shape, grid.num_corners, light)
        for seed in _GRID_SEEDS:
            cv2.setRNGSeed(seed)
            found, centres = cv2.findCirclesGrid(img8, grid.pattern_size, None, flags, det)
            if found and centres is not None and len(centres) == grid.num_corners:
                uv = np.asarray(centres, np.float64).reshape(-1, 2)
                break
        if uv is not None:
            uv = _refine_centres(norm, grid, uv, light)
            break
    what = f"no {grid.size} {'asymmetric ' if grid.asymmetric else ''}circle grid found"
    if uv is None:
        return DetectionResult.failed(
            grid.num_corners,
            what + " (all circles and a plain border around them must be visible)",
        )
    xy = grid.points_mm[:, :2]
    sign, worst = _handedness(xy, uv)
    spacing = float(np.linalg.norm(uv[1] - uv[0]))
    if not worst < 0.25 * spacing:
        # OpenCV's rows are right but their order is not (seen under strong perspective:
        # rows taken in pairs, the pairs in reverse order): the rows re-ordered across
        # the grid, kept only if they then fit it as well as a right order must
        uv, sign, better = _rows_reordered(xy, uv, grid.pattern_size)
        if not better < 0.25 * spacing:
            return DetectionResult.failed(
                grid.num_corners,
                what + f": OpenCV's order does not fit the grid ({worst:.1f} px)",
            )
    cands = []
    for perm, d in _symmetries(xy):
        if (sign * d > 0) == mirrored:
            continue
        out = np.empty_like(uv)
        out[perm] = uv  # the point OpenCV labels k is board point perm[k]
        cands.append(out)
    if not cands:
        return DetectionResult.failed(grid.num_corners, what + ": handedness unresolved")
    best = min(cands, key=lambda c: float(np.hypot(*c[0])))
    note = "" if len(cands) == 1 else "point 0 taken nearest the image's top-left (symmetric grid)"
    return DetectionResult(np.ascontiguousarray(best), True, note)


_LEVELS = np.linspace(0.1, 0.9, 17)  # _refine_centres: levels between dot and paper


def _refine_centres(norm: np.ndarray, grid: CircleGrid, uv: np.ndarray, light: bool) -> np.ndarray:
    """The circles' centres measured again, each in its own window: the mean centroid of
    the region around the centre beyond each of 17 levels from 10 to 90 % of the way from
    the circle's own grey level (median of its inner half) to the paper's around it
    (median of a ring from 1.3 to 1.8 radii), where that region is one blob inside the
    window.

    The blob detector thresholds the whole image at fixed levels (from 20 to 235 of the
    normalised 8-bit copy, to find faint and small circles): where the light falls off
    across the board, or the print is blurred, the outer levels cut a circle's edge
    where shading or its neighbours pull it. Levels set by each circle's own contrast
    do not. On real daylight photographs (zcy, 12 views of a 7 x 7 grid, 1920 x 1080
    JPEG) `calibrateCamera` fits the blob detector's centres to 0.138 px RMS, OpenCV's
    own `findCirclesGrid` (levels 50-220 of the raw image) to 0.099 px, these to 0.096
    px (0.098 px in the channel minimum). The levels span most of the edge, as the blob
    detector's do: the mean over them is the centroid of the circle's image, which the
    calibration models (on a noise-free render through the Tessar: 0.007 px RMS from the
    traced centroids; levels 20-80 % only: 0.017 px, 35-65 %: 0.03 px). A circle under
    4 px in radius, at the image's edge or whose levels do not give at least 3 blobs
    keeps its blob centre, as does one the measurement would move by more than a
    quarter of its radius.
    """
    out = uv.copy()
    xy = grid.points_mm[:, :2]
    H, _ = cv2.findHomography(xy, uv, 0)
    if H is None:
        return out
    img = -norm if light else norm  # dark circles on light paper
    h, w = img.shape
    dets = np.abs(np.linalg.det(homography_jacobian(H, xy)))
    for k in range(len(uv)):
        scale = math.sqrt(float(dets[k]))  # px per mm
        rad = 0.5 * grid.diameter_mm * scale
        r = int(math.ceil(max(0.75 * grid.spacing_mm * scale, 1.9 * rad))) + 2
        u0, v0 = int(round(uv[k, 0])), int(round(uv[k, 1]))
        if rad < 4.0 or not (r <= u0 < w - r and r <= v0 < h - r):
            continue
        win = img[v0 - r : v0 + r + 1, u0 - r : u0 + r + 1]
        yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
        d = np.hypot(xx + u0 - uv[k, 0], yy + v0 - uv[k, 1])
        inner = float(np.median(win[d < 0.5 * rad]))
        paper = float(np.median(win[(d > 1.3 * rad) & (d < 1.8 * rad)]))
        if not paper - inner > 0:
            continue
        cs = []
        for f in _LEVELS:
            n, lab = cv2.connectedComponents((win < inner + f * (paper - inner)).astype(np.uint8))
            if n < 2 or lab[r, r] == 0:
                continue
            reg = (lab == lab[r, r]).astype(np.uint8)
            if reg[0].any() or reg[-1].any() or reg[:, 0].any() or reg[:, -1].any():
                continue
            m = cv2.moments(reg, True)
            if m["m00"] > 0:
                cs.append((m["m10"] / m["m00"], m["m01"] / m["m00"]))
        if len(cs) < 3:
            continue
        c = np.mean(cs, axis=0) + (u0 - r, v0 - r)
        if np.hypot(*(c - uv[k])) <= 0.25 * rad:
            out[k] = c
    return out


def circle_diameters_mm(image: Any, grid: CircleGrid, corners_px: np.ndarray) -> np.ndarray:
    """The printed diameter of each detected circle, measured in the image (mm; NaN where
    it cannot be measured: not detected, too near the image's edge, no contrast).

    Each circle's image is the region around its detected centre darker (lighter, for
    light circles) than the midpoint between the centre's grey level and the
    background's (the 90th or 10th percentile of a window 1.5 spacings wide); its area
    `A` px over the local area scale `|det J|` (px² per mm², from the homography of the
    view's points) gives `d = sqrt(4 A / (π |det J|))`. On rendered circle grids the
    median over a view is within 0.1 % of the printed diameter (0.1454 for 0.1455 mm).

    **Arguments:** `image` grey or BGR (the one the grid was detected in); `grid`;
    `corners_px` `(M, 2)` the detected centres in `grid`'s order.
    """
    out = np.full(grid.num_corners, np.nan)
    uv = np.asarray(corners_px, dtype=np.float64).reshape(-1, 2)
    ok = np.all(np.isfinite(uv), axis=1)
    norm, problem = grey_float(image)
    if problem or ok.sum() < 4:
        return out
    xy = grid.points_mm[:, :2]
    H, _ = cv2.findHomography(xy[ok], uv[ok])
    if H is None:
        return out
    h, w = norm.shape
    dets = np.abs(np.linalg.det(homography_jacobian(H, xy)))
    for k in np.flatnonzero(ok):
        det = float(dets[k])
        r = int(math.ceil(0.75 * grid.spacing_mm * math.sqrt(det))) + 2
        u0, v0 = int(round(uv[k, 0])), int(round(uv[k, 1]))
        if not (r <= u0 < w - r and r <= v0 < h - r) or det <= 0:
            continue
        win = norm[v0 - r : v0 + r + 1, u0 - r : u0 + r + 1]
        inner = float(win[r - 1 : r + 2, r - 1 : r + 2].mean())
        dark = inner < float(np.median(win))
        bg = float(np.percentile(win, 90 if dark else 10))
        if abs(bg - inner) < 1e-3:
            continue
        mask = (win < 0.5 * (inner + bg)) if dark else (win > 0.5 * (inner + bg))
        _, lab = cv2.connectedComponents(mask.astype(np.uint8))
        if lab[r, r] == 0:
            continue
        region = lab == lab[r, r]
        if region[0].any() or region[-1].any() or region[:, 0].any() or region[:, -1].any():
            continue  # the region runs out of the window: not one circle
        out[k] = math.sqrt(4.0 * float(region.sum()) / (math.pi * det))
    return out
