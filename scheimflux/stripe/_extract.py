"""`extract_stripe` / `extract_stripes`: laser-stripe centres of one or many images."""

from __future__ import annotations

import concurrent.futures
import math
import os
from collections.abc import Iterable
from typing import Any

import cv2
import numpy as np

from ._centroid import centroid_band
from ._coarse import FACTOR, coarse_track, dominant_scan, downsample
from ._image import as_grey_image, estimate_noise
from ._result import StripeResult
from ._steger import ScanLines, steger_band, steger_full

_METHODS = ("steger", "centroid")
_ORIENTATIONS = ("auto", "vertical-scan", "horizontal-scan")
_DEFAULT_WIDTH = 5.0


def _empty(n: int, orientation: str, method: str) -> StripeResult:
    return StripeResult(
        uv=np.full((n, 2), np.nan),
        strength=np.zeros(n),
        width=np.full(n, np.nan),
        valid=np.zeros(n, bool),
        saturated=np.zeros(n, bool),
        orientation=orientation,
        method=method,
    )


def _check_options(method, width_px, orientation, band_px, min_strength, saturation):
    if method not in _METHODS:
        raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
    if orientation not in _ORIENTATIONS:
        raise ValueError(f"orientation must be one of {_ORIENTATIONS}, got {orientation!r}")
    if width_px is not None and not (math.isfinite(width_px) and 1.0 <= width_px <= 200.0):
        raise ValueError(f"width_px must be a stripe FWHM between 1 and 200 px, got {width_px}")
    if band_px is not None and band_px != "auto":
        if isinstance(band_px, bool) or not isinstance(band_px, (int, np.integer)) or band_px < 1:
            raise ValueError(f"band_px must be 'auto', None or a positive integer, got {band_px!r}")
    if min_strength is not None and not (math.isfinite(min_strength) and min_strength >= 0):
        raise ValueError(f"min_strength must be a finite number >= 0, got {min_strength}")
    if saturation is not None and not math.isfinite(saturation):
        raise ValueError(f"saturation must be a finite grey level or None, got {saturation}")


def extract_stripe(
    image: Any,
    *,
    method: str = "steger",
    width_px: float | int | None = None,
    orientation: str = "auto",
    band_px: int | str | None = "auto",
    min_strength: float | int | None = None,
    saturation: float | int | None = None,
) -> StripeResult:
    """Sub-pixel centres of the laser stripe in one grey image, one per scan line.

    Coarse step: the image is averaged over 4 x 4 blocks, a ridge filter picks the peak
    in each scan line, and peaks that disagree with the median of their neighbours are
    searched again near it (so a weaker second reflection, or a brighter one in a few
    scan lines, is not taken). Fine step: Steger's Hessian method in a band around the
    coarse track (or in the whole frame), or the grey-gravity centroid.

    **Arguments:**
    - `image`: (H, W) grey image: uint8, uint16 (12- or 16-bit data), int16 or float.
    - `method`: `"steger"` (Hessian line detector, sub-pixel) or `"centroid"`
      (background-subtracted grey gravity, the classical baseline).
    - `width_px`: expected stripe width, full width at half maximum in pixels. Steger
      smooths with `sigma = width_px / (2 sqrt(3))`. `None`: measured from the image
      (one extra pass when it differs much from 5 px).
    - `orientation`: `"vertical-scan"` (one centre per column u: for a mostly
      horizontal stripe), `"horizontal-scan"` (one per row v: a mostly vertical
      stripe), or `"auto"` (from the image's dominant gradient direction).
    - `band_px`: half-height of the band around the coarse track in which Steger's
      derivatives are computed; `"auto"` sizes it from `width_px`; `None` filters the whole
      frame (slow baseline, same centres).
    - `min_strength`: smallest accepted strength (see `StripeResult.strength`), in the
      image's grey levels; `None`: eight times the strength's noise, estimated from the
      image.
    - `saturation`: grey level at which the sensor clips. `None`: for integer images the
      frame's maximum (it only matters where a plateau of it sits on the stripe). Where
      the stripe is clipped, Steger is rerun with a scale matched to the plateau so that
      it finds the plateau's centre; those points are flagged `saturated`.

    **Returns:** a `StripeResult` with one entry per scan line (W for a vertical scan,
    H for a horizontal one).

    **Raises:** `ValueError` for input that is not a numeric 2-D image or bad options.
    """
    _check_options(method, width_px, orientation, band_px, min_strength, saturation)
    img = as_grey_image(image)
    small = downsample(img)
    if orientation == "auto":
        orientation = dominant_scan(small)
    flat = img.reshape(-1)
    if orientation == "vertical-scan":
        shape = img.shape
        stride_y, stride_x = img.shape[1], 1
    else:
        shape = img.shape[::-1]
        small = np.ascontiguousarray(small.T)
        stride_y, stride_x = 1, img.shape[1]

    def gather(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """The scan-frame image at integer (row, column) index arrays (broadcast)."""
        return np.take(flat, rows * stride_y + cols * stride_x)

    integer = bool(np.issubdtype(img.dtype, np.integer))
    width = _DEFAULT_WIDTH if width_px is None else float(width_px)
    noise = estimate_noise(img)
    coarse = coarse_track(
        small, shape[0], shape[1], width_px=width, integer_input=integer, pixel_noise=noise
    )
    if not coarse.found:
        return _empty(shape[1], orientation, method)

    sat_level = saturation
    if sat_level is None and integer:
        sat_level = float(img.max())

    def run(w: float) -> tuple[ScanLines, np.ndarray]:
        if method == "centroid":
            lines = centroid_band(gather, shape, coarse.centre, w)
            noise_level = 6.0 * noise
        else:
            if band_px is None:
                scan = img if orientation == "vertical-scan" else np.ascontiguousarray(img.T)
                lines = steger_full(scan, w, coarse.centre, coarse.tolerance)
            else:
                band = None if band_px == "auto" else int(band_px)
                lines = steger_band(gather, shape, coarse.centre, w, band)
            sigma = max(w / (2.0 * math.sqrt(3.0)), 0.7)
            # Std of sigma² G''*noise for white noise is sqrt(3 / (16 pi)) noise / sigma.
            noise_level = 8.0 * 0.2443 * noise / sigma
        thr = noise_level if min_strength is None else float(min_strength)
        y = lines.y
        valid = lines.found & coarse.support & (lines.strength >= max(thr, 1e-12))
        valid &= np.abs(y - coarse.centre) <= coarse.tolerance
        valid &= (y >= -0.5) & (y <= shape[0] - 0.5)
        return lines, valid

    lines, valid = run(width)
    if width_px is None and valid.sum() >= 8:
        measured = float(np.nanmedian(lines.width[valid & np.isfinite(lines.width)]))
        if math.isfinite(measured) and abs(measured - width) > 0.3 * width:
            width = min(max(measured, 1.5), 100.0)
            lines, valid = run(width)

    saturated = np.zeros(shape[1], bool)
    if sat_level is not None and valid.any():
        cols = np.arange(shape[1])
        row = np.clip(lines.row.astype(np.intp), 0, shape[0] - 1)
        near = gather(np.clip(row[None, :] + np.arange(-1, 2)[:, None], 0, shape[0] - 1), cols)
        saturated = valid & (np.count_nonzero(near >= sat_level, axis=0) >= 2)
        if method == "steger" and saturated.any():
            reach = int(math.ceil(4 * width)) + FACTOR
            rows = np.clip(row[None, :] + np.arange(-reach, reach + 1)[:, None], 0, shape[0] - 1)
            plateau = np.count_nonzero(gather(rows, cols) >= sat_level, axis=0)
            wide = float(np.median(plateau[saturated])) + width
            lines2, valid2 = run(wide)
            lines = ScanLines(
                y=np.where(saturated, lines2.y, lines.y),
                strength=np.where(saturated, lines2.strength, lines.strength),
                width=np.where(saturated, lines2.width, lines.width),
                found=np.where(saturated, lines2.found, lines.found),
                row=lines.row,
            )
            valid = np.where(saturated, valid2, valid)
            saturated &= valid

    x = np.arange(shape[1], dtype=np.float64)
    y = np.where(valid, lines.y, np.nan)
    x = np.where(valid, x, np.nan)
    uv = np.stack([x, y], axis=1) if orientation == "vertical-scan" else np.stack([y, x], axis=1)
    return StripeResult(
        uv=uv,
        strength=np.where(valid, lines.strength, 0.0),
        width=np.where(valid, lines.width, np.nan),
        valid=valid,
        saturated=saturated,
        orientation=orientation,
        method=method,
    )


def extract_stripes(
    frames: Iterable[Any], *, workers: int | None = None, **kwargs: Any
) -> list[StripeResult]:
    """`extract_stripe` on several frames, in order, with a pool of threads.

    **Arguments:**
    - `frames`: an iterable of images, or an array of shape (n_frames, H, W).
    - `workers`: number of threads (default: the number of CPUs; 1 runs in this thread).
      NumPy and OpenCV release the GIL in their loops, so the frames overlap. OpenCV's
      own thread pool is set to one thread meanwhile (restored afterwards).
    - `**kwargs`: passed to `extract_stripe`.

    **Returns:** one `StripeResult` per frame.
    """
    frames = list(frames)
    if workers is None:
        workers = os.cpu_count() or 1
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    workers = min(workers, max(len(frames), 1))
    if workers == 1:
        return [extract_stripe(f, **kwargs) for f in frames]
    previous = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with concurrent.futures.ThreadPoolExecutor(max_workers=workers) as pool:
            return list(pool.map(lambda f: extract_stripe(f, **kwargs), frames))
    finally:
        cv2.setNumThreads(previous)
