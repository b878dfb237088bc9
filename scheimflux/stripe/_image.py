"""Input checks shared by the extractors: one 2-D grey image of a numeric type."""

from __future__ import annotations

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


def estimate_noise(img: np.ndarray, *, n_rows: int = 8) -> float:
    """Robust pixel-noise standard deviation (grey levels) from a few rows of `img`.

    Median absolute second difference along the rows (variance 6 sigma² for white
    noise), which ignores the stripe and smooth backgrounds. Never below the
    quantisation noise 0.3 of integer images.
    """
    step = max(img.shape[0] // n_rows, 1)
    rows = img[step // 2 :: step].astype(np.float32)
    d = rows[:, :-2] - 2.0 * rows[:, 1:-1] + rows[:, 2:]
    sigma = 1.4826 * float(np.median(np.abs(d))) / np.sqrt(6.0)
    if np.issubdtype(img.dtype, np.integer):
        return max(sigma, 0.3)
    return max(sigma, 1e-9 * max(float(np.abs(img).max()), 1e-30))
