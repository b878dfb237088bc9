"""Did the board move between a pair's two exposures?

A pair's stripe centres are lifted to 3-D with the board pose of its board image, and
the stripe image is read pixel by pixel against it: a board that moved between the two
exposures puts the line's points on the wrong board with no sign of it. Where the stripe
image shows the print by its room light (albedo x g x room light, `fit_gain`'s g
clearly above 0), the print's motion from the board image to the stripe image is
measured (`board_motion`): an affine warp of the board region by OpenCV's ECC
(`cv2.findTransformECC`), the stripe image's room-light part (a colour image's channel
minimum: the laser's channel left out; a grey image: the laser line's pixels masked out)
against g x the board image, and the displacement is the largest motion of the found
target points.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from ..stripe._gain import fit_gain
from ..stripe._image import estimate_noise
from ._region import laser_free

__all__ = ["MOVED_PX", "BoardMotion", "board_motion"]

# A board that moved more than this between a pair's exposures (largest displacement of
# a target point, px) has its stripe refused; see docs/capture.md ("Pairs: did the
# board move?") for how it was chosen.
MOVED_PX = 0.1
# The measurement counts only where its expected spread (the Cramer-Rao bound of the
# translation from the print's gradients and the stripe image's noise, times
# `_AFFINE_SPREAD` for the affine warp's corners) is below this fraction of `MOVED_PX`.
_PRECISION = 0.2
_AFFINE_SPREAD = 3.0
# The laser line's pixels left out of a grey stripe image: within this many FWHM of its
# centres (and 3 px more, for a board that moved).
_LINE_FWHM = 1.5
# Below this correlation of the registered images the print in the stripe image is not
# the board image's (the board moved beyond a small warp): refused as moved.
_MIN_CORRELATION = 0.5
_CROP_MARGIN = 8  # px around the board region kept for the warp
_END_FIT = 40  # centres at each end of the line that set its extension to the edges


@dataclasses.dataclass(frozen=True)
class BoardMotion:
    """The board's motion from a pair's board image to its stripe image.

    **Fields:**
    - `checked`: whether it could be measured (else `why`).
    - `displacement_px`: the largest displacement of a found target point (NaN when not
      checked; inf when the stripe image's print matches no warp of the board image's,
      `why` says so).
    - `shift_px`: `(du, dv)` mean displacement of the found target points.
    - `gain`: the median room-light gain g of the stripe image against the board image
      over the board region (0: room light off).
    - `spread_px`: the measurement's expected spread (px, one std).
    - `why`: why it was not measured ("" when it was).
    - `points_uv`: `(M, 2)` each target point's displacement (NaN: not found, or not
      checked).
    - `correlation`: ECC's correlation of the registered images (1: identical).
    """

    checked: bool
    displacement_px: float
    shift_px: tuple[float, float]
    gain: float
    spread_px: float
    why: str = ""
    points_uv: np.ndarray | None = None
    correlation: float = float("nan")


def _plane(img: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(laser_free(img), dtype=np.float32)


def _line_band(shape, stripe, width_px: float | None) -> np.ndarray:
    """The pixels within `_LINE_FWHM` FWHM (+3 px) of the stripe's valid centres, joined
    along the line (a polyline through them in scan order)."""
    band = np.zeros(shape, np.uint8)
    if stripe is None:
        return band.astype(bool)
    uv = stripe.uv[stripe.valid]
    uv = uv[np.all(np.isfinite(uv), axis=1)]
    if len(uv) == 0:
        return band.astype(bool)
    w = stripe.width[stripe.valid]
    w = float(np.nanmedian(w)) if np.isfinite(w).any() else 5.0
    if width_px is not None:
        w = max(w, float(width_px))
    half = int(np.ceil(_LINE_FWHM * w + 3.0))
    along = 0 if stripe.orientation == "vertical-scan" else 1
    uv = uv[np.argsort(uv[:, along])]
    uv = _extended(uv, along, shape[1 - along])
    pts = np.rint(uv).astype(np.int32).reshape(-1, 1, 2)
    cv2.polylines(band, [pts], False, 1, thickness=2 * half + 1)
    return band.astype(bool)


def _extended(uv: np.ndarray, along: int, length: int) -> np.ndarray:
    """The line's centres `uv` (sorted along it) extended to both image edges along the
    line, by a straight line fitted to the last `_END_FIT` centres at each end: where the
    extractor kept no centre (refused next to the print, or near the region's edge) the
    laser still lights the board, and left unmasked it pulls the registration (0.11 px
    of apparent motion for an unmoved board in a single image with a clipped line)."""
    if len(uv) < 2:
        return uv
    t = uv[:, along]
    parts = [uv]
    for end, stop in ((slice(0, _END_FIT), 0.0), (slice(-_END_FIT, None), length - 1.0)):
        seg = uv[end]
        if np.ptp(seg[:, along]) < 1.0:
            continue
        slope, icept = np.polyfit(seg[:, along], seg[:, 1 - along], 1)
        first = t[0] if stop == 0.0 else t[-1]
        ts = np.arange(stop, first, 2.0) if stop == 0.0 else np.arange(first + 2.0, stop + 1.0, 2.0)
        ext = np.empty((len(ts), 2))
        ext[:, along], ext[:, 1 - along] = ts, slope * ts + icept
        parts.insert(0 if stop == 0.0 else len(parts), ext)
    return np.concatenate(parts)


def board_motion(
    board: np.ndarray,
    stripe_image: np.ndarray,
    mask: np.ndarray,
    corners: np.ndarray,
    stripe=None,
    *,
    width_px: float | None = None,
) -> BoardMotion:
    """The print's motion from `board` (laser off) to `stripe_image` (laser on, its room
    light a multiple g of the board image's) inside the board region `mask`.

    **Arguments:**
    - `board`, `stripe_image`: the pair's images (grey or BGR, as read).
    - `mask`: `(H, W)` bool, the board region; `corners`: `(M, 2)` the target points
      found in the board image (NaN rows ignored).
    - `stripe`: the `StripeResult` of the stripe image (its line is masked out), or None.
    - `width_px`: the expected line FWHM (None: the stripe's measured one).

    **Returns:** [`BoardMotion`][].
    """
    # a colour image's channel minimum (a laser of one colour left out); a colour board
    # image beside a grey stripe image: its mean over the channels (as the line's reading)
    b, s = _plane(board), _plane(stripe_image)
    if np.ndim(board) == 3 and np.ndim(stripe_image) == 2:
        b = np.asarray(board, np.float32)[:, :, :3].mean(axis=2)
    allpts = np.asarray(corners, np.float64).reshape(-1, 2)
    found = np.all(np.isfinite(allpts), axis=1)
    pts = allpts[found]
    nan2 = (float("nan"), float("nan"))
    if not mask.any() or len(pts) < 3:
        return BoardMotion(False, float("nan"), nan2, float("nan"), float("nan"),
                           "no board region")  # fmt: skip
    vv, uu = np.nonzero(mask)
    h, w = mask.shape
    v0, v1 = max(int(vv.min()) - _CROP_MARGIN, 0), min(int(vv.max()) + _CROP_MARGIN + 1, h)
    u0, u1 = max(int(uu.min()) - _CROP_MARGIN, 0), min(int(uu.max()) + _CROP_MARGIN + 1, w)
    b, s, m = b[v0:v1, u0:u1], s[v0:v1, u0:u1], mask[v0:v1, u0:u1]
    # the line's pixels left out (a colour JPEG keeps some of the line in every channel)
    line = _line_band(mask.shape, stripe, width_px)[v0:v1, u0:u1]
    noise_b = estimate_noise(np.asarray(laser_free(board)))
    noise_s = estimate_noise(np.asarray(laser_free(stripe_image)))
    g = fit_gain(s, b, m & ~line, noise_b)
    # away from the region's edge (the warp samples a few px beyond) and the line
    inner = cv2.erode(m.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool) & ~line
    if inner.sum() < 100:
        return BoardMotion(False, float("nan"), nan2, float("nan"), float("nan"),
                           "too small a board region off the laser line")  # fmt: skip
    gain = float(np.median(g[inner]))
    t = g * b
    # expected spread of the translation (Cramer-Rao: noise / sqrt(sum of squared
    # gradients)), the affine warp's corners a few times more
    gu = cv2.Sobel(t, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gv = cv2.Sobel(t, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    info = min(float(np.sum(gu[inner] ** 2)), float(np.sum(gv[inner] ** 2)))
    spread = _AFFINE_SPREAD * noise_s / np.sqrt(max(info, 1e-30))
    if not spread < _PRECISION * MOVED_PX:
        return BoardMotion(False, float("nan"), nan2, gain, float(spread),
                           f"the laser-on image shows the board too faintly (room-light gain "
                           f"{gain:.3f} of the board image's)")  # fmt: skip
    warp = np.eye(2, 3, dtype=np.float32)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-7)
    try:
        rho, warp = cv2.findTransformECC(t, s, warp, cv2.MOTION_AFFINE, crit,
                                       inner.astype(np.uint8), 3)  # fmt: skip
    except cv2.error:
        # the stripe image shows a print (the gain above) that matches no warp of the
        # board image's: refused as moved, not passed
        return BoardMotion(True, float("inf"), nan2, gain, float(spread),
                           "the print in the stripe image matches no small warp of the "
                           "board image's")  # fmt: skip
    if not rho >= _MIN_CORRELATION:
        return BoardMotion(True, float("inf"), nan2, gain, float(spread),
                           f"the print in the stripe image matches the board image's warped "
                           f"with a correlation of only {rho:.2f}")  # fmt: skip
    local = pts - np.array([u0, v0])
    moved = local @ warp[:, :2].T.astype(np.float64) + warp[:, 2].astype(np.float64)
    d = moved - local
    disp = float(np.max(np.linalg.norm(d, axis=1)))
    mean = d.mean(axis=0)
    per = np.full(allpts.shape, np.nan)
    per[found] = d
    return BoardMotion(True, disp, (float(mean[0]), float(mean[1])), gain, float(spread), "",
                       per, float(rho))  # fmt: skip
