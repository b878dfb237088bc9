"""Coarse stripe localisation: a 4x-downsampled ridge search, one peak per scan line.

Everything here works in the *scan frame*: rows are the scan coordinate (v for a vertical
scan) and columns are the scan lines (u for a vertical scan). The coarse track only
positions the band in which the sub-pixel extractors look; it is never reported.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np

from . import _fast
from ._ridge import ridge_offset, ridge_response

#: Downsampling factor of the coarse image along both axes.
FACTOR = 4
# Scan lines of the coarse image over which the median track is taken (odd).
_TRACK_WINDOW = 15


def downsample(image: np.ndarray, *, with_max: bool = False):
    """Average 4 x 4 blocks (two fast 2 x 2 area reductions), float32, shape (H//4, W//4);
    with `with_max`, also the image's maximum (a float; for a uint8 image from the same
    compiled pass, `_fast.downsample_u8`)."""
    if (
        _fast.enabled and image.dtype == np.uint8 and image.ndim == 2
        and min(image.shape) >= FACTOR and FACTOR == 4
    ):  # fmt: skip
        small, top = _fast.downsample_u8(np.ascontiguousarray(image))
        return (small, float(top)) if with_max else small
    h, w = (image.shape[0] // FACTOR) * FACTOR, (image.shape[1] // FACTOR) * FACTOR
    img = image[:h, :w]
    if img.dtype == np.float64:
        img = img.astype(np.float32)
    half = cv2.resize(img, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    quarter = cv2.resize(half, (w // 4, h // 4), interpolation=cv2.INTER_AREA)
    quarter = quarter.astype(np.float32, copy=False)
    return (quarter, float(image.max())) if with_max else quarter


def dominant_scan(small: np.ndarray) -> str:
    """`"vertical-scan"` if the image varies more along v than along u (a mostly
    horizontal stripe, best scanned column by column), else `"horizontal-scan"`."""
    gu = small[:, 1:] - small[:, :-1]
    gv = small[1:, :] - small[:-1, :]
    energy_u = float(np.einsum("ij,ij->", gu, gu))
    energy_v = float(np.einsum("ij,ij->", gv, gv))
    return "vertical-scan" if energy_v >= energy_u else "horizontal-scan"


@dataclasses.dataclass(frozen=True)
class CoarseTrack:
    """Coarse stripe position per full-resolution scan line (scan frame).

    - `centre`: (W,) float64, the coarse scan coordinate of the stripe (interpolated across
      scan lines without a detection).
    - `support`: (W,) bool, a coarse detection at or next to this scan line.
    - `tolerance`: how far (px) a centre may lie from `centre` and still count as the stripe.
    - `found`: False when no scan line had a detection at all.
    """

    centre: np.ndarray
    support: np.ndarray
    tolerance: float
    found: bool


def _windowed_median(values: np.ndarray, ok: np.ndarray, window: int) -> np.ndarray:
    """Median of the `ok` entries in a centred sliding window; NaN where there are none."""
    half = window // 2
    n = values.size
    if _fast.enabled and n > 0 and values.dtype == np.float64 and np.isfinite(values).all():
        return _fast.windowed_median(values, np.ascontiguousarray(ok, np.bool_), window)
    if n >= 4 * half and ok.all():
        # the common case: full windows away from the ends take a partial sort; the ends
        # (windows reaching past them) are those of the general case on the end pieces
        out = np.empty(n)
        step = values.strides[0]
        full = np.lib.stride_tricks.as_strided(
            values, (n - 2 * half, window), (step, step), writeable=False
        )
        out[half : n - half] = np.partition(full, half, axis=1)[:, half]
        out[:half] = _windowed_median(values[: 3 * half], ok[: 3 * half], window)[:half]
        out[n - half :] = _windowed_median(values[-3 * half :], ok[-3 * half :], window)[-half:]
        return out
    pad = np.full(half, np.inf)
    padded = np.concatenate([pad, np.where(ok, values, np.inf), pad])
    step = padded.strides[0]
    windows = np.lib.stride_tricks.as_strided(padded, (n, window), (step, step), writeable=False)
    windows = np.sort(windows, axis=1)
    count = np.count_nonzero(np.isfinite(windows), axis=1)
    mid = np.take_along_axis(windows, np.maximum((count - 1) // 2, 0)[:, None], axis=1)[:, 0]
    return np.where(count > 0, mid, np.nan)


def coarse_track(
    small: np.ndarray,
    n_rows: int,
    n_cols: int,
    *,
    width_px: float,
    integer_input: bool,
    pixel_noise: float,
    mask_small: np.ndarray | None = None,
) -> CoarseTrack:
    """Locate the stripe in the downsampled scan-frame image `small`.

    **Arguments:**
    - `small`: the 4x downsampled image in the scan frame (rows = scan coordinate).
    - `n_rows`, `n_cols`: shape of the full-resolution scan-frame image.
    - `width_px`: expected stripe FWHM (px).
    - `integer_input`: whether the image held integer grey levels (rounding noise).
    - `pixel_noise`: the image's noise standard deviation (grey levels).
    - `mask_small`: optional bool mask in the same frame as `small` (coarse pixels that
      are mostly inside the region of interest).
    """
    hs, ws = small.shape
    d = ridge_offset(width_px)
    # Two-sided ridge response (a step edge gives none), zero outside the mask.
    fast = _fast.enabled and small.dtype == np.float32 and hs > 2 * d
    if fast and mask_small is None and FACTOR == 4:
        # the steps below to the peak position in one compiled pass (same values)
        ridge, idx, resp, pos, lo_, hi_ = _fast.coarse_scan(small, d)
        return _track(ridge, idx, resp, pos, lo_, hi_, n_rows, n_cols, width_px, integer_input,
                      pixel_noise)  # fmt: skip
    ridge = _fast.ridge_rows(small, d) if fast else ridge_response(small, d, 0)
    if mask_small is not None:
        ridge = np.where(mask_small, ridge, 0.0).astype(np.float32)

    # first maximum per scan line
    idx = _fast.column_argmax(ridge) if fast else np.argmax(ridge, axis=0)
    cols = np.arange(ws)
    resp = ridge[idx, cols]
    # Sub-coarse-pixel peak (parabola through the ridge response).
    up = ridge[np.maximum(idx - 1, 0), cols]
    down = ridge[np.minimum(idx + 1, hs - 1), cols]
    denom = up - 2.0 * resp + down
    frac = np.where(denom < 0, 0.5 * (up - down) / np.where(denom < 0, denom, -1.0), 0.0)
    pos = FACTOR * (idx + np.clip(frac, -0.5, 0.5)) + (FACTOR - 1) / 2.0
    lo_, hi_, _, _ = cv2.minMaxLoc(small)  # np.ptp in one pass (float32 difference)
    return _track(ridge, idx, resp, pos, lo_, hi_, n_rows, n_cols, width_px, integer_input,
                  pixel_noise)  # fmt: skip


def _track(ridge, idx, resp, pos, lo_, hi_, n_rows, n_cols, width_px, integer_input, pixel_noise):
    """`coarse_track` from the ridge response, its first maximum per scan line, the
    response there, the sub-coarse-pixel peak and the range of the coarse image."""
    hs, ws = ridge.shape
    cols = np.arange(ws)
    # Noise of one difference of 4 x 4 block means: sqrt(2) / 4 = 0.354 times the pixel
    # noise, plus the rounding of integer block means (the minimum of two such
    # differences has about the same spread).
    ridge_noise = math.hypot(0.354 * pixel_noise, 0.35 if integer_input else 0.0)
    threshold = max(6.0 * ridge_noise, 1e-6 * max(float(np.float32(hi_) - np.float32(lo_)), 1e-30))
    ok = resp > threshold

    tolerance = max(3.0 * width_px, 12.0)
    if not ok.any():
        return CoarseTrack(np.zeros(n_cols), np.zeros(n_cols, bool), tolerance, False)

    # Consistency with the neighbours: re-search outliers near the median track.
    track = _windowed_median(pos, ok, _TRACK_WINDOW)
    outlier = ok & (np.abs(pos - track) > tolerance)
    if outlier.any():
        j = np.flatnonzero(outlier)
        rows = FACTOR * np.arange(hs)[:, None] + (FACTOR - 1) / 2.0
        near = np.abs(rows - track[j][None, :]) <= tolerance
        sub = np.where(near, ridge[:, j], -np.inf)
        best = np.argmax(sub, axis=0)
        best_resp = sub[best, np.arange(j.size)]
        good = best_resp > threshold
        pos[j] = np.where(good, FACTOR * best + (FACTOR - 1) / 2.0, pos[j])
        ok[j] = good
    if not ok.any():
        return CoarseTrack(np.zeros(n_cols), np.zeros(n_cols, bool), tolerance, False)

    centres = FACTOR * cols + (FACTOR - 1) / 2.0
    full = np.arange(n_cols, dtype=np.float64)
    centre = np.interp(full, centres[ok], pos[ok])
    centre = np.clip(centre, 0.0, n_rows - 1.0)
    # Support: a detection in the coarse scan line or one of its neighbours.
    okd = ok.copy()
    okd[1:] |= ok[:-1]
    okd[:-1] |= ok[1:]
    support = okd[np.minimum(np.arange(n_cols) // FACTOR, ws - 1)]
    return CoarseTrack(centre, support, tolerance, True)
