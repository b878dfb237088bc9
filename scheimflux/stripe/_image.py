"""Input checks shared by the extractors: one 2-D grey image of a numeric type."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

_SUPPORTED = (np.uint8, np.uint16, np.int16, np.float32, np.float64)


def as_grey_image(image: Any, *, name: str = "image") -> np.ndarray:
    """Return `image` as a C-contiguous 2-D array of a dtype OpenCV filters directly.

    Accepts uint8, uint16 (8-, 12- and 16-bit data), int16, float32 and float64 as they are;
    other integer types become float32 and other float types float64; booleans, complex,
    strings and objects are rejected. Raises `ValueError` with a clear message otherwise.
    """
    try:
        arr = np.asarray(image)
    except Exception as err:  # ragged nested lists, objects that refuse conversion
        raise ValueError(f"{name} could not be converted to an array: {err}") from None
    if arr.dtype == np.bool_ or not (
        np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)
    ):
        raise ValueError(f"{name} must hold integer or float grey levels, got dtype {arr.dtype}")
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    if arr.ndim != 2:
        raise ValueError(
            f"{name} must be a 2-D grey image of shape (H, W), got shape {arr.shape}"
            + (" (convert colour images to grey first)" if arr.ndim == 3 else "")
        )
    if arr.shape[0] < 8 or arr.shape[1] < 8:
        raise ValueError(f"{name} is too small ({arr.shape}); at least 8 x 8 pixels are needed")
    if arr.dtype.type not in _SUPPORTED:
        arr = arr.astype(np.float32 if np.issubdtype(arr.dtype, np.integer) else np.float64)
    if np.issubdtype(arr.dtype, np.floating) and not np.isfinite(arr).all():
        raise ValueError(f"{name} contains NaN or infinite values")
    return np.ascontiguousarray(arr)


def _median(x: np.ndarray) -> float:
    """`float(np.median(x))` of a 1-D array without NaN, from one partial sort."""
    m = x.size // 2
    if x.size == 0:
        return float("nan")
    if x.size % 2:
        return float(np.partition(x, m)[m])
    part = np.partition(x, [m - 1, m])
    return float((part[m - 1] + part[m]) / 2)


def estimate_noise(img: np.ndarray, *, n_rows: int = 8) -> float:
    """Robust pixel-noise standard deviation (grey levels) from a few rows of `img`.

    Median absolute second difference along the rows (variance 6 sigma² for white
    noise), which ignores the stripe and smooth backgrounds. Never below the
    quantisation noise 0.3 of integer images.
    """
    step = max(img.shape[0] // n_rows, 1)
    if np.issubdtype(img.dtype, np.integer) and img.dtype.itemsize <= 2:
        # integer second differences: their median from a histogram (exact, and much
        # faster than a partial sort of many equal values)
        rows = img[step // 2 :: step].astype(np.int32)
        d = np.abs(rows[:, :-2] - 2 * rows[:, 1:-1] + rows[:, 2:]).reshape(-1)
        cum = np.cumsum(np.bincount(d))
        m = d.size // 2
        hi = int(np.searchsorted(cum, m + 1))  # the order statistic of rank m
        lo = hi if d.size % 2 else int(np.searchsorted(cum, m))  # rank m - 1
        sigma = 1.4826 * float(np.float32((lo + hi) / 2)) / np.sqrt(6.0)
        return max(sigma, 0.3)
    rows = img[step // 2 :: step].astype(np.float32)
    d = np.abs(rows[:, :-2] - 2.0 * rows[:, 1:-1] + rows[:, 2:]).reshape(-1)
    sigma = 1.4826 * _median(d) / np.sqrt(6.0)
    if np.issubdtype(img.dtype, np.integer):
        return max(sigma, 0.3)
    return max(sigma, 1e-9 * max(float(np.abs(img).max()), 1e-30))


def block_noise(img: np.ndarray, n_rows: int = 16) -> float:
    """Pixel-noise std (grey levels) measured on 2 x 2 block means (twice their robust
    std, as `estimate_noise`): the same as the pixel estimate for white noise, but not
    fooled by JPEG, which removes the noise at the pixel scale (its second differences)
    and leaves it, and its block artefacts, at coarser ones: at quality 85 the pixel
    estimate reads 0.3 grey levels where the renderer put 1.2 (this one reads 0.9)."""
    h, w = img.shape[:2]
    if h < 4 or w < 6:
        return 0.0
    step = max((h - 1) // n_rows, 2)
    top = np.arange(0, h - 1, step)[:n_rows]
    pair = img[top].astype(np.float32) + img[top + 1].astype(np.float32)
    w2 = (w // 2) * 2
    block = 0.25 * (pair[:, 0:w2:2] + pair[:, 1:w2:2])
    d = np.abs(block[:, :-2] - 2.0 * block[:, 1:-1] + block[:, 2:]).reshape(-1)
    # the RMS of the 90 % smallest (edges and the line are few), scaled to a Gaussian's
    # std (1 / sqrt(0.623)): unlike the median, not stuck to the grey-level steps
    d = np.sort(d)[: max(int(0.9 * d.size), 1)]
    return 2.0 * 1.267 * float(np.sqrt(np.mean(d * d))) / math.sqrt(6.0)


CHANNELS = (
    "auto",
    "grey",
    "red",
    "green",
    "blue",
    "red-minus-others",
    "green-minus-others",
    "blue-minus-others",
)
_BGR_INDEX = {"blue": 0, "green": 1, "red": 2}
_GREY_WEIGHTS = (0.114, 0.587, 0.299)  # B, G, R (ITU-R BT.601, as cv2.cvtColor)


def as_image(image: Any, *, name: str = "image") -> np.ndarray:
    """`image` as a grey (H, W) or BGR colour (H, W, 3) array (an alpha channel is
    dropped); the same checks as `as_grey_image` otherwise."""
    try:
        arr = np.asarray(image)
    except Exception as err:
        raise ValueError(f"{name} could not be converted to an array: {err}") from None
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        if arr.dtype == np.bool_ or not (
            np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)
        ):
            raise ValueError(f"{name} must hold integer or float levels, got dtype {arr.dtype}")
        if arr.shape[0] < 8 or arr.shape[1] < 8:
            raise ValueError(f"{name} is too small ({arr.shape}); at least 8 x 8 pixels are needed")
        arr = arr[:, :, :3]
        if arr.dtype.type not in _SUPPORTED:
            arr = arr.astype(np.float32 if np.issubdtype(arr.dtype, np.integer) else np.float64)
        if np.issubdtype(arr.dtype, np.floating) and not np.isfinite(arr).all():
            raise ValueError(f"{name} contains NaN or infinite values")
        return np.ascontiguousarray(arr)
    if arr.ndim == 3 and arr.shape[2] != 1:
        raise ValueError(
            f"{name} must be grey (H, W) or colour (H, W, 3|4) BGR, got shape {arr.shape}"
        )
    return as_grey_image(arr, name=name)


def channel_image(img: np.ndarray, channel: str) -> tuple[np.ndarray, np.ndarray]:
    """The signal image for `channel` (not "auto") and the plain channel whose clipping
    marks saturation.

    For a grey image every channel name except the colour ones gives the image itself.
    `"X-minus-others"` is `X - (Y + Z) / 2` (float32): white light and grey targets
    cancel in it and a laser of colour X remains.
    """
    if img.ndim == 2:
        if channel not in ("grey", "auto"):
            raise ValueError(f"channel {channel!r} needs a colour image; this one is grey")
        return img, img
    if channel == "grey":
        b, g, r = (img[:, :, k].astype(np.float32) for k in range(3))
        wb, wg, wr = _GREY_WEIGHTS
        grey = wb * b + wg * g + wr * r
        return grey, img.max(axis=2)
    if channel in _BGR_INDEX:
        plane = np.ascontiguousarray(img[:, :, _BGR_INDEX[channel]])
        return plane, plane
    base = channel.removesuffix("-minus-others")
    k = _BGR_INDEX[base]
    others = [j for j in range(3) if j != k]
    plane = img[:, :, k]
    signal = plane.astype(np.float32) - 0.5 * (
        img[:, :, others[0]].astype(np.float32) + img[:, :, others[1]].astype(np.float32)
    )
    return np.ascontiguousarray(signal), np.ascontiguousarray(plane)
