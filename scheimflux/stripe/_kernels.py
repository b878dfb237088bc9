"""Sampled Gaussian derivative kernels for OpenCV's (correlating) separable filters."""

from __future__ import annotations

import math

import numpy as np

#: FWHM of a Gaussian divided by its standard deviation, 2 sqrt(2 ln 2).
FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))


def steger_sigma(width_px: float) -> float:
    """Steger's smoothing scale for a stripe of full width `width_px` (pixels).

    Steger (1998) needs `sigma >= w / sqrt(3)` for a bar of half-width `w`; with the full
    width at half maximum `W = 2 w` this is `sigma = W / (2 sqrt(3))`. Never below 0.7 px,
    where sampled Gaussian kernels stop behaving like Gaussians.
    """
    return max(float(width_px) / (2.0 * math.sqrt(3.0)), 0.7)


def kernel_radius(sigma: float) -> int:
    """Half-length of the kernels for `sigma` (3.5 sigma, at least 2 pixels)."""
    return max(int(math.ceil(3.5 * sigma)), 2)


_CACHE: dict[float, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}


def gaussian_kernels(sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Smoothing, first- and second-derivative kernels as float32 column vectors.

    Normalised on their moments so that, used with OpenCV's correlation
    (`out[i] = sum_j in[i + j] k[j]`), they return exactly 1 for a constant (`k0`),
    a unit ramp (`k1`) and `x² / 2` (`k2`), and 0 for lower-order terms.
    """
    cached = _CACHE.get(sigma)
    if cached is not None:
        return cached
    r = kernel_radius(sigma)
    x = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-0.5 * (x / sigma) ** 2)
    k0 = g / g.sum()
    k1 = x * g
    k1 = k1 / np.sum(x * k1)
    k2 = (x**2 / sigma**2 - 1.0) * g
    k2 = k2 - k0 * k2.sum()
    k2 = k2 / np.sum(0.5 * x**2 * k2)
    out = tuple(k.astype(np.float32).reshape(-1, 1) for k in (k0, k1, k2))
    if len(_CACHE) < 256:
        _CACHE[sigma] = out
    return out
