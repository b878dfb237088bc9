"""Checkerboard corner detection (OpenCV), ordered like `Checkerboard.points_mm`.

`detect_checkerboard` runs OpenCV's `findChessboardCornersSB` (sector-based detector,
with its accuracy refinement) on a robustly normalised 8-bit copy of the image, then,
where it finds nothing, OpenCV's classic `findChessboardCorners` (quads of an adaptive
threshold), and refines the corners with `cornerSubPix` on the full-precision image.
The sector-based detector's own accuracy refinement is then run on the plain image
(unstretched 8 bits, a crop around the board), and the two corner sets averaged with
weights 1 / r², r each set's median residual about its points' local grids: neither
estimator is the better on every image (on real webcam JPEGs the sector-based one's
residuals were 0.07 px against cornerSubPix's 0.105, `calibrateCamera` per view 0.103
against 0.122 px; on a DSLR's PNGs of a print lit by a laser 0.21 against 0.20 px, 0.213
against 0.190), and the weights follow the one that is.
Neither detector finds every board the other does: on real photographs (benchmarks/
realdata_detect.py) the sector-based one missed 8 of 14 views of a board lit by a red
laser line and a second board beside it that the classic one found, and the classic one
missed boards under strong barrel distortion that the sector-based one found.

OpenCV returns the corner grid in an order fixed only up to the pattern's symmetry
(180° for a rectangular board, 90° for a square one). The order is resolved here:
1. handedness: a camera that sees the printed side of the board (no mirror in the path)
   images the board frame with the same handedness as the pixel frame (u right,
   v down), so mirrored orders are dropped (pass `mirrored=True` for a mirror image);
2. colour: the square diagonally outside corner 0 is black (see `Checkerboard`). For a
   board with an odd number of squares along one side and an even number along the
   other (e.g. 11 x 8 inner corners, 12 x 9 squares) the squares at the four outer
   corners of the pattern are not all alike, and the one that matches decides. For a
   board whose counts are both even or both odd (e.g. 9 x 7 inner corners: 10 x 8
   squares; 8 x 6: 9 x 7 squares), a half turn puts every square on its own colour and
   no image can tell; the order that puts corner 0 nearest the image's top-left corner
   is kept and `message` says so.

Pixel (0, 0) is the centre of the top-left pixel; u grows to the right, v downwards.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from ._result import DetectionResult, grey, grid_residuals, normalise

__all__ = ["DetectionResult", "detect_checkerboard"]

_SB_FLAGS = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY


_grey = grey
_normalise = normalise


def _failed(board, message: str) -> DetectionResult:
    return DetectionResult(np.full((board.cols * board.rows, 2), np.nan), False, message)


def _sample(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear grey levels at pixels `(N, 2)`; NaN outside the image."""
    h, w = img.shape
    u, v = uv[:, 0], uv[:, 1]
    ok = np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    out = np.full(len(uv), np.nan)
    u, v = u[ok], v[ok]
    u0 = np.clip(np.floor(u).astype(int), 0, w - 2)
    v0 = np.clip(np.floor(v).astype(int), 0, h - 2)
    a, b = u - u0, v - v0
    out[ok] = (
        (1 - a) * (1 - b) * img[v0, u0]
        + a * (1 - b) * img[v0, u0 + 1]
        + (1 - a) * b * img[v0 + 1, u0]
        + a * b * img[v0 + 1, u0 + 1]
    )
    return out


def _squares(cols: int, rows: int, s: float) -> tuple[np.ndarray, np.ndarray]:
    """Centres (board mm) of every square of the pattern, and their colours.

    Colour 0 is black: the square diagonally outside corner 0 is black and colours
    alternate along rows and columns (`cols + 1` squares across, `rows + 1` down).
    All of them are read, not only the four at the outer corners: those lie half a
    square beyond the outer corners and fall off the image first when a board fills
    it, and the laser line may cross any one of them.
    """
    i, j = np.meshgrid(np.arange(cols + 1), np.arange(rows + 1))
    centres = np.stack([(i.ravel() - 0.5) * s, (j.ravel() - 0.5) * s], axis=1)
    return centres, (i.ravel() + j.ravel()) % 2


def _square_brightness(img, H, centres, s) -> np.ndarray:
    """`(K,)` median grey level of the central half of each square (board mm centres),
    NaN where fewer than 5 of its 25 samples lie in the image."""
    g = np.linspace(-0.25, 0.25, 5) * s
    gx, gy = np.meshgrid(g, g)
    offsets = np.stack([gx.ravel(), gy.ravel()], axis=1)  # (25, 2)
    pts = (centres[:, None, :] + offsets[None]).reshape(-1, 2)
    uv = cv2.perspectiveTransform(pts[None], H)[0]
    vals = _sample(img, uv).reshape(len(centres), -1)
    enough = np.isfinite(vals).sum(axis=1) >= 5
    out = np.full(len(centres), np.nan)
    if enough.any():
        out[enough] = np.nanmedian(vals[enough], axis=1)
    return out


def _orient(grid: np.ndarray, img: np.ndarray, board, mirrored: bool) -> tuple[np.ndarray, str]:
    """Reorder OpenCV's `(rows, cols, 2)` grid into the board's order (see module doc)."""
    cols, rows, s = board.cols, board.rows, board.square_mm
    cands = []
    for g in (grid, grid.transpose(1, 0, 2)):
        for k in range(4):
            c = np.rot90(g, k)
            if c.shape[:2] == (rows, cols):
                cands.append(np.ascontiguousarray(c))
    xy = np.asarray(board.points_mm, dtype=np.float64)[:, :2]
    centres, colours = _squares(cols, rows, s)
    scored = []
    for c in cands:
        du = (c[:, -1] - c[:, 0]).mean(axis=0)
        dv = (c[-1, :] - c[0, :]).mean(axis=0)
        handed = du[0] * dv[1] - du[1] * dv[0]
        if (handed > 0) == mirrored:
            continue
        H, _ = cv2.findHomography(xy, c.reshape(-1, 2), 0)
        if H is None:
            continue
        b = _square_brightness(img, H, centres, s)
        ok = np.isfinite(b)
        white, black = ok & (colours == 1), ok & (colours == 0)
        # medians: the laser line or a glint brightens a few squares
        score = np.median(b[white]) - np.median(b[black]) if white.any() and black.any() else np.nan
        scored.append((score, c))
    if not scored:
        return grid, "could not resolve the board's orientation (degenerate corner grid)"
    finite = [t for t in scored if np.isfinite(t[0])]
    if finite:
        finite.sort(key=lambda t: -t[0])
        best = finite[0]
        if len(finite) == 1 or best[0] - finite[1][0] > 0.1:
            return best[1], ""
        if (cols + rows) % 2 == 0:  # a half turn puts every square on its own colour
            note = (f"symmetric board ({cols + 1} x {rows + 1} squares: a half turn looks "
                    "the same)")  # fmt: skip
        else:
            note = "orientation ambiguous (squares too faint)"
    else:
        note = "orientation ambiguous: no square of the board could be read in the image"
    # fall back on the order whose corner 0 is nearest the image's top-left
    best = min(scored, key=lambda t: float(np.hypot(*t[1][0, 0])))
    return best[1], note + "; corner 0 taken nearest the image's top-left"


def _spacing(grid: np.ndarray) -> float:
    du = np.linalg.norm(np.diff(grid, axis=1), axis=-1)
    dv = np.linalg.norm(np.diff(grid, axis=0), axis=-1)
    return float(min(du.min(), dv.min()))


def _refine(img: np.ndarray, corners: np.ndarray, spacing: float) -> np.ndarray:
    half = int(np.clip(round(0.3 * spacing), 2, 30))
    pts = corners.astype(np.float32).reshape(-1, 1, 2).copy()
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    cv2.cornerSubPix(img, pts, (half, half), (-1, -1), crit)
    out = pts.reshape(-1, 2).astype(np.float64)
    # keep OpenCV's corner where the refinement ran away (e.g. at the image border)
    moved = np.linalg.norm(out - corners, axis=1) > 0.25 * spacing
    out[moved] = corners[moved]
    return out


# `findChessboardCornersSB` samples with OpenCV's global random number generator, so on a
# hard image (a clipped laser line across the board) whether it finds the board depended
# on every OpenCV call made before it (measured: 6 of 8 repeated calls on one image, 6 of
# 10 seeds). Each attempt is seeded, so a detection depends on the image alone, and a
# failed one is tried again with the next seed.
_SB_SEEDS = (0, 1, 2)


_SB_PLAIN_FLAGS = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY  # on the plain image


def _sector_based(img8: np.ndarray, size: tuple[int, int], *, flags: int = _SB_FLAGS):
    """`cv2.findChessboardCornersSB` seeded with each of `_SB_SEEDS` until it finds the
    board (OpenCV's random state is left seeded)."""
    found, corners = False, None
    for seed in _SB_SEEDS:
        cv2.setRNGSeed(seed)
        found, corners = cv2.findChessboardCornersSB(img8, size, flags=flags)
        if found:
            break
    return found, corners


def _plain8(img: np.ndarray, eight_bit: bool) -> np.ndarray:
    """An 8-bit copy of the grey image (float) without clipping: its levels as they are
    when the image was 8-bit, else scaled linearly from its finite range."""
    if eight_bit:
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)
    f = np.nan_to_num(np.asarray(img, np.float64), nan=0.0)
    lo, hi = float(f.min()), float(f.max())
    return np.rint((f - lo) * (255.0 / max(hi - lo, 1e-12))).astype(np.uint8)


def _sector_corners(plain8: np.ndarray, uv: np.ndarray, size, spacing: float):
    """`findChessboardCornersSB`'s own corners (its accuracy refinement, full resolution)
    in the order of `uv`, found in a crop of `plain8` around the board (the board's
    corners plus four squares: with two, its accuracy refinement
    lost 2 % at the outer corners); None where it finds no board there or its corners do not
    match `uv` one to one within a quarter of a square."""
    h, w = plain8.shape
    m = 4.0 * spacing
    u0, v0 = (int(max(0, np.floor(x - m))) for x in uv.min(axis=0))
    u1, v1 = (int(min(n, np.ceil(x + m) + 1)) for x, n in zip(uv.max(axis=0), (w, h)))
    crop = np.ascontiguousarray(plain8[v0:v1, u0:u1])
    if min(crop.shape) < 16:
        return None
    found, corners = _sector_based(crop, size, flags=_SB_PLAIN_FLAGS)
    if not found or corners is None or len(corners) != len(uv):
        return None
    c = corners.reshape(-1, 2).astype(np.float64) + (u0, v0)
    d = np.linalg.norm(uv[:, None, :] - c[None, :, :], axis=-1)
    j = d.argmin(axis=1)
    if len(set(j)) != len(uv) or d[np.arange(len(uv)), j].max() > 0.25 * spacing:
        return None
    return c[j]


def _combined(uv_a: np.ndarray, uv_b: np.ndarray, board) -> tuple[np.ndarray, float]:
    """The two corner sets averaged with weights 1 / r², `r` each set's median residual
    against its points' local grids (`grid_residuals`: detection noise, plus what the
    print and the lens add alike to both); and the weight of `uv_b`."""
    r = [float(np.nanmedian(grid_residuals(x, board.points_mm, board.square_mm)))
         for x in (uv_a, uv_b)]  # fmt: skip
    if not all(np.isfinite(r)):
        return uv_a, 0.0
    wa, wb = (1.0 / max(x, 1e-6) ** 2 for x in r)
    return (wa * uv_a + wb * uv_b) / (wa + wb), wb / (wa + wb)


_CLASSIC_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE


def _classic(img8: np.ndarray, size: tuple[int, int]):
    """`cv2.findChessboardCorners` (adaptive threshold): whole-pixel corners of the quads
    it found, to be refined with `cornerSubPix`."""
    found, corners = cv2.findChessboardCorners(img8, size, flags=_CLASSIC_FLAGS)
    return bool(found), corners


def detect_checkerboard(
    image: Any,
    board: Any,
    *,
    refine: bool = True,
    mirrored: bool = False,
) -> DetectionResult:
    """Find the inner corners of `board` in `image`.

    **Arguments:**
    - `image`: `(H, W)` grey image (uint8, uint16 with 12- or 16-bit data, or float;
      `(H, W, 3)` BGR is converted to grey).
    - `board`: a `Checkerboard` (inner corners `cols x rows`, `points_mm`).
    - `refine`: refine the corners with `cv2.cornerSubPix` on the full-precision image
      and weigh them with the sector-based detector's own on the plain image (module
      doc); `cornerSubPix` alone runs when the classic detector found the board and
      `refine` is False. The search then runs on a half-size copy of images at least 480
      px high, which is about five times faster. On rendered 1600 x 1200 images of an
      11 x 8 board (five poses, some tilted 25°) the worst corner error is 0.03–0.08 px
      with `cornerSubPix` for blur sigma 0–2.5 px and 0.5–1 % noise, against 0.1 px
      (sharp) to 0.38 px (blurred) with `findChessboardCornersSB`'s `CALIB_CB_ACCURACY`
      on the normalised copy alone.
    - `mirrored`: the image is mirrored (taken through a mirror): keep the order with the
      opposite handedness.

    The sector-based detector runs first (on the half-size copy, then, failing that,
    the classic detector and the sector-based one at full size).

    **Returns:** a [`DetectionResult`][]: corners in the order of `board.points_mm`,
    all NaN when the board was not found (OpenCV finds all corners or none), with a
    message that says why.
    """
    img = _grey(image)
    norm, problem = _normalise(img)
    if problem:
        return _failed(board, problem)
    img8 = np.rint(np.clip(norm, 0.0, 1.0) * 255.0).astype(np.uint8)
    size = (int(board.cols), int(board.rows))
    found, corners = False, None
    if refine and min(img8.shape) >= 480:
        # with cornerSubPix at full resolution afterwards, a half-size search is as
        # accurate and about five times faster
        small = cv2.resize(img8, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
        found, corners = _sector_based(small, size)
        if found and corners is not None:
            corners = (corners.astype(np.float64) + 0.5) * 2.0 - 0.5  # pixel centres
    classic = False
    if not found:
        found, corners = _classic(img8, size)
        classic = found
    if not found:
        found, corners = _sector_based(img8, size)
    if not found or corners is None or len(corners) != size[0] * size[1]:
        return _failed(
            board,
            f"no {size[0]}x{size[1]} checkerboard found (the whole pattern and a white "
            "border around it must be visible and in focus)",
        )
    grid = corners.reshape(size[1], size[0], 2).astype(np.float64)
    grid, note = _orient(grid, norm, board, mirrored)
    uv = grid.reshape(-1, 2)
    if refine or classic:  # the classic detector's corners are the quads' (whole pixels)
        uv = _refine(norm, uv, _spacing(grid))
    if refine:
        eight_bit = np.asarray(image).dtype == np.uint8
        sb = _sector_corners(_plain8(img, eight_bit), uv, size, _spacing(grid))
        if sb is not None:
            uv, _ = _combined(uv, sb, board)
    return DetectionResult(np.ascontiguousarray(uv), True, note)
