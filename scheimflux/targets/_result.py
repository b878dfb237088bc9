"""The result of detecting a target in one image, and the image conversions the detectors
share (grey, robust normalisation, 8-bit copy)."""

from __future__ import annotations

import dataclasses
from typing import Any

import cv2
import numpy as np

__all__ = ["DetectionResult"]


@dataclasses.dataclass(frozen=True)
class DetectionResult:
    """The target points found in one image.

    **Fields:**
    - `corners_px`: `(M, 2)` float64 pixels in the order of the target's `points_mm`;
      NaN rows where a point was not found (all of them when `found` is False).
    - `found`: whether the target was detected (enough points to use the view).
    - `message`: why detection failed, or notes on a successful one (may be empty).
    """

    corners_px: np.ndarray
    found: bool
    message: str = ""

    @property
    def mask(self) -> np.ndarray:
        """`(M,)` bool: points with finite pixel coordinates."""
        return np.all(np.isfinite(self.corners_px), axis=1)

    @classmethod
    def failed(cls, n: int, message: str) -> DetectionResult:
        return cls(np.full((n, 2), np.nan), False, message)


def homography_jacobian(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """The Jacobians `(N, 2, 2)` (px per mm) of the board → pixel homography `H` at the
    board points `xy` `(N, 2)`."""
    x, y = xy[:, 0], xy[:, 1]
    w = H[2, 0] * x + H[2, 1] * y + H[2, 2]
    u = (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / w
    v = (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / w
    return np.stack(
        [
            np.stack([(H[0, 0] - u * H[2, 0]) / w, (H[0, 1] - u * H[2, 1]) / w], -1),
            np.stack([(H[1, 0] - v * H[2, 0]) / w, (H[1, 1] - v * H[2, 1]) / w], -1),
        ],
        axis=1,
    )


def grey(image: Any) -> np.ndarray:
    """Float32 grey image from `(H, W)`, `(H, W, 1)`, BGR or BGRA input (any bit depth).

    Raises `ValueError` for a non-numeric, non-2-D or tiny image."""
    arr = np.asarray(image)
    if arr.dtype == np.bool_ or not (
        np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)
    ):
        raise ValueError(f"image must hold integer or float grey levels, got dtype {arr.dtype}")
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    elif arr.ndim == 3 and arr.shape[2] in (3, 4):
        arr = arr[:, :, :3].astype(np.float32) @ np.array([0.114, 0.587, 0.299], np.float32)
    if arr.ndim != 2:
        raise ValueError(f"image must be a 2-D grey image (H, W), got shape {arr.shape}")
    if min(arr.shape) < 16:
        raise ValueError(f"image is too small ({arr.shape})")
    return arr.astype(np.float32)


def normalise(img: np.ndarray) -> tuple[np.ndarray, str]:
    """Float32 image scaled so the dark and bright extremes (0.5 and 99.5 percentiles)
    map to 0 and 1, and a message when the image has no contrast."""
    sample = img[::4, ::4]
    finite = np.isfinite(sample)
    if not finite.any():
        return np.zeros_like(img), "image has no finite pixels"
    lo, hi = np.percentile(sample[finite], [0.5, 99.5])
    if not hi > lo:
        return np.zeros_like(img), "image is blank (no contrast)"
    out = (np.nan_to_num(img, nan=float(lo)) - np.float32(lo)) / np.float32(hi - lo)
    return np.clip(out, -0.25, 1.25).astype(np.float32), ""


def grey_float(image: Any) -> tuple[np.ndarray, str]:
    """`normalise(grey(image))`."""
    return normalise(grey(image))


def to_uint8(norm: np.ndarray) -> np.ndarray:
    """8-bit copy of a normalised image (0 → 0, 1 → 255)."""
    return np.rint(np.clip(norm, 0.0, 1.0) * 255.0).astype(np.uint8)


def grid_residuals(
    uv: np.ndarray, xy_mm: np.ndarray, pitch_mm: float, *, reach: float = 2.5
) -> np.ndarray:
    """Each found point's distance (px) from its prediction by the homography of the
    found points within `reach` pitches of it on the board (RANSAC, then least squares
    on its inliers; the point itself left out). Over so small a patch lens distortion
    bends the grid by far less than a pixel, so the residual is the detection noise
    unless something (a marker misread, a laser line or a glint) moved the point.

    **Returns:** `(M,)` residuals, NaN where a point was not found or has fewer than 6
    found neighbours (or fewer than 8 points are found at all).
    """
    ok = np.all(np.isfinite(uv), axis=1)
    idx = np.flatnonzero(ok)
    out = np.full(len(uv), np.nan)
    if idx.size < 8:
        return out
    xy = np.asarray(xy_mm, np.float64)[idx, :2]
    pts = uv[idx]
    dist = np.linalg.norm(xy[:, None, :] - xy[None, :, :], axis=-1)
    for a in range(len(idx)):
        near = np.flatnonzero((dist[a] <= reach * pitch_mm) & (np.arange(len(idx)) != a))
        if near.size < 6:
            continue
        Hm, _ = cv2.findHomography(xy[near], pts[near], cv2.RANSAC, 0.25)
        if Hm is None:
            continue
        pred = cv2.perspectiveTransform(xy[a][None, None], Hm)[0, 0]
        out[idx[a]] = float(np.linalg.norm(pred - pts[a]))
    return out


def reject_off_grid(
    uv: np.ndarray, xy_mm: np.ndarray, pitch_mm: float, *, reach: float = 2.5
) -> tuple[np.ndarray, int]:
    """Drop points that disagree with the homography of their neighbours.

    Each found point is predicted from the found points within `reach` pitches of it on
    the board (a local homography: RANSAC, then least squares on its inliers; the point
    itself left out): over so small a patch lens distortion bends the grid by far less
    than a pixel. A point further from its prediction than `max(0.5 px, 1 % of a
    pitch)` (a marker misread, a laser line or a glint across a corner or circle) and
    than `_OFF_GRID_K` times the view's own spread of these residuals is set to NaN.

    The spread is the residuals' median over 1.1774 (the Rayleigh σ of a 2-D residual):
    a print that is not regular, or a board that is not flat, moves every point off its
    neighbours' grid, by its own amount. On a hand-held paper board (mozhi-lightplane in
    benchmarks/realdata_detect.py) the median residual is 0.3-0.7 px and 28 % of the
    corners lay beyond 0.5 px, at the same places in every view (the print), where
    OpenCV's detectors put them too (within 0.1-0.3 px): they are where the board is.

    **Returns:** `(uv, n_rejected)`.
    """
    ok = np.all(np.isfinite(uv), axis=1)
    idx = np.flatnonzero(ok)
    if idx.size < 8:
        return uv, 0
    xy = np.asarray(xy_mm, np.float64)[idx, :2]
    pts = uv[idx]
    dist = np.linalg.norm(xy[:, None, :] - xy[None, :, :], axis=-1)
    resid = np.full(len(idx), np.nan)
    tols = np.full(len(idx), np.nan)
    for a in range(len(idx)):
        near = np.flatnonzero((dist[a] <= reach * pitch_mm) & (np.arange(len(idx)) != a))
        if near.size < 6:
            continue
        step_px = float(np.median(np.linalg.norm(pts[near] - pts[a], axis=1) / dist[a, near]))
        tol = max(0.5, 0.01 * step_px * pitch_mm)
        Hm, _ = cv2.findHomography(xy[near], pts[near], cv2.RANSAC, 0.5 * tol)
        if Hm is None:
            continue
        pred = cv2.perspectiveTransform(xy[a][None, None], Hm)[0, 0]
        resid[a], tols[a] = float(np.linalg.norm(pred - pts[a])), tol
    fin = np.isfinite(resid)
    if not fin.any():
        return uv, 0
    spread = float(np.median(resid[fin])) / 1.1774
    bad = idx[fin & (resid > np.maximum(tols, _OFF_GRID_K * spread))]
    out = uv.copy()
    out[bad] = np.nan
    return out, len(bad)


#: `reject_off_grid`: a point is off the grid beyond this many times the residuals' spread
_OFF_GRID_K = 5.0
