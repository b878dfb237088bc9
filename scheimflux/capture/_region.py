"""The board region of a view, and the one place where detect extracts board stripes.

`board_region` is the part of the image where the laser line lies on the board: the
convex hull of the detected target points and of the target's outer edge (mapped into
the image by the homography of the detected points, so the outer squares and a board
partly outside the image count), grown by a margin. `board_stripe` extracts the laser
line inside it.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

__all__ = [
    "board_region",
    "board_stripe",
    "laser_free",
]


def laser_free(image: Any) -> np.ndarray:
    """The image for target detection: a colour image's per-pixel minimum over its
    channels (a laser of one colour adds light to one or two channels, a grey board
    reflects room light into all three); a grey image as it is."""
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] >= 3:
        return img[:, :, :3].min(axis=2)
    return img


def board_region(
    corners_px: np.ndarray,
    shape: tuple[int, int],
    *,
    margin_px: float = 10.0,
    board_xy_mm: np.ndarray | None = None,
    extent_mm: tuple[float, float, float, float] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The board region as a mask and its outline.

    **Arguments:**
    - `corners_px`: `(M, 2)` detected points (NaN rows ignored).
    - `shape`: `(H, W)` of the image.
    - `margin_px`: growth of the hull (px).
    - `board_xy_mm`, `extent_mm`: the points' board coordinates `(M, 2)` and the board's
      `(x_min, x_max, y_min, y_max)`; with both, the board's outline joins the hull.

    **Returns:** `(mask, polygon)`: `(H, W)` bool, and the hull `(P, 2)` px (before the
    margin). An empty mask when fewer than 3 points are finite.
    """
    H, W = int(shape[0]), int(shape[1])
    uv = np.asarray(corners_px, np.float64).reshape(-1, 2)
    ok = np.all(np.isfinite(uv), axis=1)
    mask = np.zeros((H, W), np.uint8)
    if ok.sum() < 3:
        return mask.astype(bool), np.zeros((0, 2))
    pts = uv[ok]
    if board_xy_mm is not None and extent_mm is not None and ok.sum() >= 4:
        Hm, _ = cv2.findHomography(np.asarray(board_xy_mm, np.float64)[ok], pts, 0)
        if Hm is not None:
            x0, x1, y0, y1 = extent_mm
            outline = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], np.float64)
            edge = cv2.perspectiveTransform(outline[None], Hm)[0]
            if np.all(np.isfinite(edge)) and np.abs(edge).max() < 10 * (H + W):
                pts = np.concatenate([pts, edge])
    hull = cv2.convexHull(pts.astype(np.float32)).reshape(-1, 2).astype(np.float64)
    shift = 4  # fixed-point bits of fillConvexPoly
    poly = np.rint((hull) * (1 << shift)).astype(np.int32)
    cv2.fillConvexPoly(mask, poly, 1, cv2.LINE_8, shift)
    m = int(round(max(0.0, float(margin_px))))
    if m > 0:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * m + 1, 2 * m + 1))
        mask = cv2.dilate(mask, kernel)
    return mask.astype(bool), hull


def board_stripe(
    image: Any,
    mask: np.ndarray,
    *,
    width_px: float | None = None,
    background: Any = None,
    holes: np.ndarray | None = None,
    background_gain: float | int | str = 1.0,
    channel: str = "auto",
):
    """The laser line on the board: `extract_stripe` inside the board region `mask`
    (colour images: the laser's channel, chosen by the extractor unless `channel` names
    one), in the difference from the laser-off image `background` when there is one
    (`background_gain`: as for `extract_stripe`; `"auto"` for a pair's board image,
    taken at its own exposure).

    This is the single place where `detect` extracts board stripes. The extractor accepts
    ridges only (checker edges, dots and marker borders are refused) and returns no centre
    outside `mask`. `holes` (`(H, W)` bool, e.g. the dots of a circle grid in a grey
    single image, `target_holes`) are bridged along rows, then along columns
    (`fill_holes`), so the line is tracked as one; the bridging that keeps more centres
    wins, and no centre inside a hole is kept.

    **Returns:** `(StripeResult, inside)`: `inside` `(N,)` bool marks the centres on the
    board region and off the holes. Raises `ValueError` when nothing can be extracted.
    """
    from ..stripe import extract_stripe
    from ._laser import fill_holes

    if not np.any(mask):
        raise ValueError("empty board region")
    keep = mask if holes is None else mask & ~holes
    if holes is None or not holes.any():
        candidates = [(image, background)]
    else:
        candidates = [(fill_holes(image, holes, axis), background) for axis in (1, 0)]
    best = None
    for img, bg in candidates:
        result = extract_stripe(
            img, width_px=width_px, mask=mask, background=bg, background_gain=background_gain,
            channel=channel,
        )
        uv = result.uv
        inside = np.zeros(len(uv), bool)
        fin = np.all(np.isfinite(uv), axis=1)
        iu = np.clip(np.rint(uv[fin, 0]).astype(int), 0, mask.shape[1] - 1)
        iv = np.clip(np.rint(uv[fin, 1]).astype(int), 0, mask.shape[0] - 1)
        inside[fin] = keep[iv, iu]
        n = int((inside & result.valid).sum())
        if best is None or n > best[0]:
            best = (n, result, inside)
    return best[1], best[2]
