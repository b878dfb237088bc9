"""Regions of interest: `region_mask` (a target's area, grown) and mask/polygon input."""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np


def region_mask(points_px: Any, shape: tuple[int, ...], *, margin_px: float = 0.0) -> np.ndarray:
    """The convex hull of some pixels, grown by a margin, as a bool mask.

    **Arguments:**
    - `points_px`: (N, 2) `(u, v)` pixels (e.g. a board's detected corners); rows with
      NaN are ignored.
    - `shape`: the image shape; its first two entries `(H, W)` are used.
    - `margin_px`: grow the hull by this distance (px, >= 0).

    **Returns:** (H, W) bool, True inside the grown hull; all False with fewer than 3
    finite points (no area to grow).
    """
    h, w = int(shape[0]), int(shape[1])
    pts = np.asarray(points_px, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"points_px must have shape (N, 2), got {pts.shape}")
    if not (math.isfinite(margin_px) and margin_px >= 0):
        raise ValueError(f"margin_px must be a finite distance >= 0, got {margin_px}")
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    out = np.zeros((h, w), np.uint8)
    if len(pts) < 3:
        return out.astype(bool)
    # Fixed-point vertices (1/16 px) for an accurate fill.
    hull = cv2.convexHull(np.round(pts * 16).astype(np.int32).reshape(-1, 1, 2))
    cv2.fillConvexPoly(out, hull, 1, lineType=cv2.LINE_8, shift=4)
    if margin_px > 0:
        dist = cv2.distanceTransform((1 - out).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_5)
        out = (dist <= margin_px).astype(np.uint8)
    return out.astype(bool)


def as_mask(mask: Any, shape: tuple[int, int]) -> np.ndarray | None:
    """A `mask` argument as an (H, W) bool array: None, a bool array of the image's
    shape, or a polygon (N >= 3, 2) of `(u, v)` pixels (filled, not necessarily convex)."""
    if mask is None:
        return None
    arr = np.asarray(mask)
    h, w = shape
    if arr.dtype == np.bool_:
        if arr.shape != (h, w):
            raise ValueError(f"mask must have the image's shape {(h, w)}, got {arr.shape}")
        return arr
    if arr.ndim == 2 and arr.shape[1] == 2 and np.issubdtype(arr.dtype, np.number):
        pts = arr.astype(np.float64)
        if len(pts) < 3 or not np.isfinite(pts).all():
            raise ValueError("a mask polygon needs at least 3 finite (u, v) vertices")
        out = np.zeros((h, w), np.uint8)
        poly = np.round(pts * 16).astype(np.int32).reshape(-1, 1, 2)
        cv2.fillPoly(out, [poly], 1, lineType=cv2.LINE_8, shift=4)
        return out.astype(bool)
    raise ValueError(
        f"mask must be None, a bool (H, W) array or an (N, 2) polygon, got {arr.dtype} "
        f"{arr.shape}"
    )
