"""A laser-off image drawn from the target: what a grey single image of a printed
target and a clipped laser line would show with the laser off.

A clipped line's plateau ends where albedo x (ambient + laser) reaches full scale, so
its centre is the mean of its two rims only where both lie on the same albedo; the
laser-on image cannot show the albedo under a rim (the line covers it). A laser-off
image can (docs/stripe.md, step 4a), and for a target whose pattern is known it can be
drawn: [`laser_off_model`][] fits a smooth board-to-pixel map to the detected points
the line has not moved, draws the target's pattern through it (`render_target`, black
0 and white 1), and lights it as the image is lit, `a + b x pattern` (`a`, `b` linear
in the pixel coordinates), blurred as the image is blurred, fitted to the laser-on
image away from the line. The extractor then reads the plateau's rims against it as
against a real laser-off image (`extract_stripe(image, background=model)`).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from ..targets._circles import CircleGrid

__all__ = ["laser_off_model"]

# Largest RMS (px) of the smooth map's residuals at the points it is fitted to: a map
# that misplaces the squares' edges by more would draw albedo edges where there are
# none (the detection noise of a sharp target is ~0.02-0.03 px).
MAP_RMS_MAX = 0.1
# Largest RMS of the lit pattern's residuals away from the line, in noise stds (edges
# a little off and the noise itself; a pattern that does not fit reads far above).
LEVEL_RMS_MAX = 3.0
_BLURS = (0.0, 0.4, 0.6, 0.8, 1.0, 1.2, 1.5, 2.0)  # px, the blur candidates


def _poly_terms(uv: np.ndarray, centre: np.ndarray, scale: float, degree: int) -> np.ndarray:
    x, y = ((uv - centre) / scale).T
    return np.stack([x**i * y**j for i in range(degree + 1) for j in range(degree + 1 - i)], 1)


class _SmoothMap:
    """Board mm -> pixel: the homography of the points, then a polynomial correction
    of its residuals in the pixel coordinates (lens distortion), `(N, 2)` -> `(N, 2)`."""

    def __init__(self, xy: np.ndarray, uv: np.ndarray, degree: int):
        self.H, _ = cv2.findHomography(xy, uv, 0)
        h = self._homog(xy)
        self.centre = h.mean(axis=0)
        self.scale = float(np.ptp(h, axis=0).max()) / 2.0
        self.degree = degree
        self.lo, self.hi = h.min(axis=0), h.max(axis=0)
        A = _poly_terms(h, self.centre, self.scale, degree)
        self.coef, *_ = np.linalg.lstsq(A, uv - h, rcond=None)
        self.rms = float(np.sqrt(np.mean(np.sum((self(xy) - uv) ** 2, axis=1))))

    def _homog(self, xy):
        return cv2.perspectiveTransform(np.asarray(xy, np.float64)[None], self.H)[0]

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        h = self._homog(xy)
        # beyond the fitted points the correction is held at its value on their
        # bounding box (a polynomial grows fast outside its data)
        hc = np.clip(h, self.lo, self.hi)
        return h + _poly_terms(hc, self.centre, self.scale, self.degree) @ self.coef


def laser_off_model(
    image: Any,
    target,
    corners_px: np.ndarray,
    mask: np.ndarray,
    line_px: np.ndarray,
    *,
    reach_px: float,
    noise: float,
) -> np.ndarray | None:
    """The laser-off image of a grey single image of `target`, drawn (see the module doc).

    **Arguments:**
    - `image`: the grey laser-on image `(H, W)`.
    - `target`: a checkerboard or ChArUco board (a circle grid gives None: its dots
      are handled by the opening, `laser_removed`).
    - `corners_px`: `(M, 2)` the target points the line has not moved (NaN: left out).
    - `mask`: `(H, W)` bool, the target's region; the model is fitted and valid in it.
    - `line_px`: `(N, 2)` the line's own pixels (`clipped_pixels`): the pixels within
      `reach_px` of them are left out of the level fit.
    - `noise`: the image's noise std (grey levels).

    **Returns:** float32 `(H, W)` (the image itself outside `mask`), or None where the
    pattern cannot be drawn well enough (too few points, a map or a level fit that does
    not fit).
    """
    from ..simulate._render_target import render_target

    if isinstance(target, CircleGrid) or not hasattr(target, "square_mm"):
        return None
    img = np.asarray(image)
    if img.ndim != 2:
        return None
    uv = np.asarray(corners_px, np.float64).reshape(-1, 2)
    ok = np.all(np.isfinite(uv), axis=1)
    xy = np.asarray(target.points_mm, np.float64)[:, :2]
    degree = 3 if ok.sum() >= 40 else 2 if ok.sum() >= 20 else 1
    if ok.sum() < 12:
        return None
    if cv2.findHomography(xy[ok], uv[ok], 0)[0] is None:  # degenerate (collinear) points
        return None
    smooth = _SmoothMap(xy[ok], uv[ok], degree)
    if not smooth.rms <= MAP_RMS_MAX:
        return None
    H, W = img.shape
    pattern = render_target(target, smooth, shape=(H, W), black=0.0, white=1.0,
                            background=1.0, bit_depth=16).astype(np.float32) / 65535.0  # fmt: skip
    # the pixels the level fit reads: in the target's region, off the line's reach,
    # not at the image's clip level, on a coarse grid
    away = np.ones((H, W), np.uint8)
    line = np.rint(np.asarray(line_px, np.float64)).astype(np.intp)
    line = line[(line[:, 0] >= 0) & (line[:, 0] < W) & (line[:, 1] >= 0) & (line[:, 1] < H)]
    away[line[:, 1], line[:, 0]] = 0
    far = cv2.distanceTransform(away, cv2.DIST_L2, 3) > reach_px
    use = mask & far & (img < img.max())
    step = 3
    sub = np.zeros_like(use)
    sub[::step, ::step] = True
    vv, uu = np.nonzero(use & sub)
    if uu.size < 1000:
        return None
    I = img[vv, uu].astype(np.float64)
    x = (uu - 0.5 * (W - 1)) / (0.5 * W)
    y = (vv - 0.5 * (H - 1)) / (0.5 * W)
    best = None
    for sigma in _BLURS:
        p = pattern if sigma == 0 else cv2.GaussianBlur(pattern, (0, 0), sigma)
        t = p[vv, uu].astype(np.float64)
        A = np.stack([np.ones_like(x), x, y, t, t * x, t * y], axis=1)
        keep = np.ones(I.size, bool)
        for _ in range(2):  # once more without the outliers (a glint, a stray mark)
            coef, *_ = np.linalg.lstsq(A[keep], I[keep], rcond=None)
            r = I - A @ coef
            s = 1.4826 * float(np.median(np.abs(r[keep])))
            keep = np.abs(r) <= max(4.0 * s, 1e-9)
        rms = float(np.sqrt(np.mean(r[keep] ** 2)))
        if best is None or rms < best[0]:
            best = (rms, sigma, coef)
    rms, sigma, coef = best
    if not rms <= LEVEL_RMS_MAX * max(noise, 0.3):
        return None
    p = pattern if sigma == 0 else cv2.GaussianBlur(pattern, (0, 0), sigma)
    vg, ug = np.mgrid[0:H, 0:W].astype(np.float32)
    xg = (ug - 0.5 * (W - 1)) / (0.5 * W)
    yg = (vg - 0.5 * (H - 1)) / (0.5 * W)
    a = coef[0] + coef[1] * xg + coef[2] * yg
    b = coef[3] + coef[4] * xg + coef[5] * yg
    model = (a + b * p).astype(np.float32)
    # outside the region the image itself (no line is searched there)
    return np.where(mask, model, img.astype(np.float32))
