"""Synthetic laser-stripe images with exactly known sub-pixel centres.

The stripe's profile across the line is Gaussian with the given full width at half
maximum (FWHM), measured perpendicular to the stripe. Along each scan line (column for a
horizontal stripe) the profile is that Gaussian about the exact centre `f(u)`, stretched
by `1 / cos(slope)`; it is integrated exactly over each pixel's height (difference of
error functions) and averaged over `supersample` sub-columns across its width. The
profile in every column is therefore symmetric about `f(u)` and the truth is exact (up
to the curvature of `f` inside one pixel, ~ f'' / 24 px).

Intensities (`peak`, `ambient`, `noise_sigma`) are fractions of the full scale
`2**bit_depth - 1`. Pixel (0, 0) is the centre of the top-left pixel.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

_AMBIENT = {"dark": 0.02, "low": 0.15, "bright": 0.45}
_FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))
_BLOCK_ELEMENTS = 1 << 21  # float64 elements of one block's intermediates (16 MiB)


@dataclasses.dataclass(frozen=True)
class StripeTruth:
    """The exact stripe centres of a rendered image, one per scan line (a curve's: one
    per pixel of its length).

    - `uv`: (N, 2) float64 centres `(u, v)`: for a horizontal stripe `(u, f(u))` for every
      column u, for a vertical one `(f(v), v)` for every row v.
    - `valid`: (N,) bool: the stripe is present (not in a gap) and its centre is inside the
      image.
    - `saturated`: (N,) bool: the stripe's peak pixel was clipped at full scale.
    - `width_px`: FWHM across the stripe (px); `sigma_px` the Gaussian's standard deviation.
    - `orientation`: `"horizontal"` or `"vertical"` (direction the stripe runs), or
      `"curve"` (`uv` then the curve every pixel of its length, in its order).
    - `peak_level`: the stripe's peak above the ambient, in grey levels.
    - `full_scale`: `2**bit_depth - 1`.
    """

    uv: np.ndarray
    valid: np.ndarray
    saturated: np.ndarray
    width_px: float
    sigma_px: float
    orientation: str
    peak_level: float
    full_scale: int


def _erf(x: np.ndarray) -> np.ndarray:
    """Error function (Abramowitz & Stegun 7.1.26, |error| < 1.5e-7)."""
    s = np.sign(x)
    a = np.abs(x)
    t = 1.0 / (1.0 + 0.3275911 * a)
    poly = t * (
        0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429)))
    )
    return s * (1.0 - poly * np.exp(-a * a))


def _centre_function(centre: Any, length: int, across: int) -> Callable[[np.ndarray], np.ndarray]:
    """Centre `f(s)` (across-coordinate as a function of the along-coordinate)."""
    if centre is None:
        level = 0.5 * (across - 1) + 0.3
        return lambda s: np.full_like(s, level, dtype=np.float64)
    if callable(centre):
        return lambda s: np.asarray(centre(s), dtype=np.float64) * np.ones_like(s)
    pts = np.asarray(centre, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] < 2 or not np.isfinite(pts).all():
        raise ValueError(
            "centre must be a callable or a polyline of shape (K >= 2, 2) of finite points"
        )
    along, acr = pts[:, 0], pts[:, 1]
    if np.any(np.diff(along) <= 0):
        raise ValueError("the polyline's along-stripe coordinate must increase strictly")
    return lambda s: np.interp(s, along, acr)


def _ambient(level: Any, shape: tuple[int, int]) -> np.ndarray:
    h, w = shape
    if isinstance(level, str):
        if level not in _AMBIENT:
            raise ValueError(f"ambient must be one of {tuple(_AMBIENT)} or a level, got {level!r}")
        base = _AMBIENT[level]
        u = np.linspace(-0.5, 0.5, w)[None, :]
        v = np.linspace(-0.5, 0.5, h)[:, None]
        field = base * (1.0 + 0.3 * u + 0.2 * v)
        if level != "dark":
            blob = np.exp(-((u + 0.2) ** 2 + (v - 0.1) ** 2) / (2 * 0.25**2))
            field = field + 0.4 * base * blob
        return field
    level = float(level)
    if not (math.isfinite(level) and level >= 0):
        raise ValueError(f"ambient level must be a finite fraction >= 0, got {level}")
    return np.full(shape, level)


def _expose(stripe, background, peak, speckle, noise_sigma, full, rng):
    """`(clean, noisy)` grey levels of the profile `stripe` (peak 1) on `background`:
    speckle on the laser light, then read noise (in that order of the random draws)."""
    if speckle > 0:
        k = 1.0 / speckle**2
        stripe = stripe * rng.gamma(k, 1.0 / k, size=stripe.shape)
    clean = full * (background + peak * stripe)
    if noise_sigma > 0:
        return clean, clean + rng.normal(0.0, noise_sigma * full, size=clean.shape)
    return clean, clean


def _quantised(img, full: float, bit_depth: int) -> np.ndarray:
    """Clipped at full scale and rounded like a sensor: uint8 for 8 bits, else uint16."""
    return np.clip(np.rint(img), 0, full).astype(np.uint8 if bit_depth == 8 else np.uint16)


def _render_profile(
    f, h: int, w: int, sigma: float, amplitude: float, gaps, supersample: int
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-integrated stripe (horizontal, scan = columns) on an (h, w) float image.

    Computed over blocks of columns and only over the image's rows: the memory stays
    bounded for a steep centre function (a slope of 10⁴ in one column once asked for a
    (35423, 1600, 8) array)."""
    u = np.arange(w, dtype=np.float64)
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    us = u[:, None] + sub[None, :]  # (w, S)
    vc = f(us)
    eps = 1e-3
    slope = (f(us + eps) - f(us - eps)) / (2 * eps)
    sv = sigma * np.sqrt(1.0 + slope * slope)  # along-column std
    lit = np.ones_like(us, dtype=bool)
    for start, stop in gaps:
        lit &= ~((us >= start - 0.5) & (us < stop - 0.5))
    # each column's rows within `reach` of its centre pixel (as one array once; the
    # reach from the steepest column), computed over blocks of columns
    reach = int(math.ceil(6.0 * float(sv.max()) + float(np.ptp(vc, axis=1).max()) + 2))
    centre_row = np.rint(f(u)).astype(np.int64)
    img = np.zeros((h, w))
    block = max(1, min(w, _BLOCK_ELEMENTS // (h * supersample)))
    for c0 in range(0, w, block):
        c1 = min(w, c0 + block)
        cr = centre_row[c0:c1]
        r0, r1 = max(0, int(cr.min()) - reach), min(h - 1, int(cr.max()) + reach)
        if r1 < r0:
            continue
        rows = np.arange(r0, r1 + 1)[:, None]  # (K, 1)
        vb, sb = vc[None, c0:c1], sv[None, c0:c1]
        lo = (rows[:, :, None] - 0.5 - vb) / (math.sqrt(2.0) * sb)
        hi = (rows[:, :, None] + 0.5 - vb) / (math.sqrt(2.0) * sb)
        # integral over the pixel height of exp(-(v - vc)^2 / (2 sv^2)), times the amplitude
        mass = 0.5 * (_erf(hi) - _erf(lo)) * (sb * math.sqrt(2.0 * math.pi))
        vals = amplitude * np.mean(mass * lit[None, c0:c1], axis=2)
        img[r0 : r1 + 1, c0:c1] = np.where(np.abs(rows - cr[None]) <= reach, vals, 0.0)
    present = lit.all(axis=1)
    return img, present


def _polyline_samples(pts: np.ndarray, step: float) -> np.ndarray:
    """Points every `step` px of arc length along the curve through `pts` (K, 2), in
    their order: a cubic spline in the chord length (a polyline for K < 4)."""
    t = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    s = np.linspace(0.0, t[-1], max(2, int(math.ceil(t[-1] / step)) + 1))
    if len(pts) >= 4:
        from scipy.interpolate import CubicSpline

        return CubicSpline(t, pts, axis=0)(s)
    return np.stack([np.interp(s, t, pts[:, 0]), np.interp(s, t, pts[:, 1])], axis=1)


def render_stripe(
    shape: Sequence[int] = (1200, 1600),
    centre: Any = None,
    *,
    orientation: str = "horizontal",
    width_px: float | int = 5.0,
    peak: float | int = 0.6,
    ambient: str | float | int = "dark",
    speckle: float | int = 0.0,
    noise_sigma: float | int = 0.004,
    bit_depth: int = 8,
    saturate: bool = True,
    gaps: Sequence[tuple[int, int]] = (),
    reflection: tuple[float, float] | None = None,
    supersample: int = 8,
    seed: int | None = 0,
) -> tuple[np.ndarray, StripeTruth]:
    """Render a laser-stripe image and its exact centres.

    **Arguments:**
    - `shape`: `(H, W)` in pixels.
    - `centre`: the stripe's centre line. For `orientation="horizontal"` a callable
      `v = f(u)` (vectorised over float64 arrays) or a polyline `[(u, v), ...]` with u
      increasing; for `"vertical"` a callable `u = f(v)` or a polyline `[(v, u), ...]` with
      v increasing. Default: a straight line through the middle of the image.
    - `orientation`: `"horizontal"` (runs left–right; truth per column) or `"vertical"`
      (runs top–bottom; truth per row), or `"curve"`: a line of any shape (an arc that
      turns back, a loop), `centre` a polyline `[(u, v), ...]` in order along it,
      rendered as the Gaussian of each point's distance to the smooth curve through
      those points (averaged over 2 × 2 points per pixel, as `render_capture`'s line);
      truth every pixel of its length.
    - `width_px`: full width at half maximum across the stripe (px); the Gaussian's
      standard deviation is `width_px / (2 sqrt(2 ln 2))`.
    - `peak`: the stripe's peak above the ambient, fraction of full scale.
    - `ambient`: `"dark"` (2 %), `"low"` (15 %) or `"bright"` (45 %) smooth backgrounds
      with gradients (and a broad blob for low/bright), or a uniform level (fraction).
    - `speckle`: contrast (std / mean) of multiplicative gamma-distributed speckle on the
      laser light, independent per pixel; 0 for none.
    - `noise_sigma`: additive Gaussian read noise, fraction of full scale.
    - `bit_depth`: 8 (uint8), 12 or 16 (uint16).
    - `saturate`: clip at full scale and quantise like a sensor; False returns the
      unclipped, unquantised float64 grey levels instead.
    - `gaps`: `(start, stop)` scan-line ranges (columns for a horizontal stripe) where
      the stripe is absent.
    - `reflection`: `(offset_px, relative_peak)`: a second, parallel stripe displaced
      across by `offset_px` with `relative_peak` times the main peak.
    - `supersample`: sub-columns per pixel for the area integral along the stripe.
    - `seed`: seed of the random generator (noise and speckle).

    **Returns:** `(image, truth)`: the (H, W) image (uint8 for 8 bits, uint16 otherwise,
    float64 if `saturate=False`) and a `StripeTruth`.
    """
    if len(shape) != 2 or min(int(s) for s in shape) < 8:
        raise ValueError(f"shape must be (H, W) with both at least 8, got {tuple(shape)}")
    if bit_depth not in (8, 12, 16):
        raise ValueError(f"bit_depth must be 8, 12 or 16, got {bit_depth}")
    if orientation not in ("horizontal", "vertical", "curve"):
        raise ValueError(
            f"orientation must be 'horizontal', 'vertical' or 'curve', got {orientation!r}"
        )
    if not (width_px > 0 and peak >= 0 and speckle >= 0 and noise_sigma >= 0):
        raise ValueError("width_px must be > 0 and peak, speckle, noise_sigma >= 0")
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    h_img, w_img = int(shape[0]), int(shape[1])
    if orientation == "curve":
        return _render_curve_image(
            (h_img, w_img), centre, width_px=float(width_px), peak=float(peak),
            ambient=ambient, speckle=float(speckle), noise_sigma=float(noise_sigma),
            bit_depth=bit_depth, saturate=saturate, gaps=gaps, reflection=reflection,
            seed=seed,
        )  # fmt: skip
    vertical = orientation == "vertical"
    h, w = (w_img, h_img) if vertical else (h_img, w_img)  # scan frame: stripe horizontal
    full = float(2**bit_depth - 1)
    sigma = float(width_px) / _FWHM_PER_SIGMA
    f = _centre_function(centre, w, h)
    rng = np.random.default_rng(seed)

    stripe, present = _render_profile(f, h, w, sigma, 1.0, gaps, supersample)
    if reflection is not None:
        offset, rel = float(reflection[0]), float(reflection[1])
        second, _ = _render_profile(lambda s: f(s) + offset, h, w, sigma, rel, gaps, supersample)
        stripe = stripe + second
    background = _ambient(ambient, (h_img, w_img))
    clean, img = _expose(stripe, background.T if vertical else background, float(peak),
                         float(speckle), float(noise_sigma), full, rng)  # fmt: skip

    s = np.arange(w, dtype=np.float64)
    c = f(s)
    valid = present & (c >= -0.5) & (c <= h - 0.5)
    peak_rows = np.clip(np.rint(c).astype(np.int64), 0, h - 1)
    saturated = valid & (clean[peak_rows, np.arange(w)] >= full)

    if saturate:
        img = _quantised(img, full, bit_depth)
    if vertical:
        img = np.ascontiguousarray(img.T)
        uv = np.stack([c, s], axis=1)
    else:
        uv = np.stack([s, c], axis=1)
    truth = StripeTruth(
        uv=uv,
        valid=valid,
        saturated=saturated,
        width_px=float(width_px),
        sigma_px=sigma,
        orientation=orientation,
        peak_level=float(peak) * full,
        full_scale=int(full),
    )
    return img, truth


def _render_curve_image(
    shape, centre, *, width_px, peak, ambient, speckle, noise_sigma, bit_depth, saturate,
    gaps, reflection, seed,
) -> tuple[np.ndarray, StripeTruth]:  # fmt: skip
    """`render_stripe(..., orientation="curve")`."""
    if gaps or reflection is not None:
        raise ValueError("gaps and reflection need a horizontal or vertical stripe, not a curve")
    pts = np.asarray(centre, dtype=np.float64) if centre is not None else None
    if pts is None or pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 2:
        raise ValueError("a curve needs centre as a polyline of shape (K >= 2, 2) of (u, v)")
    if not np.isfinite(pts).all() or np.any(np.linalg.norm(np.diff(pts, axis=0), axis=1) == 0):
        raise ValueError("the curve's points must be finite and consecutive points distinct")
    h, w = shape
    full = float(2**bit_depth - 1)
    sigma = width_px / _FWHM_PER_SIGMA
    rng = np.random.default_rng(seed)
    from ._render_capture import _profile  # the capture renderer's line of any shape

    dense = _polyline_samples(pts, 0.125)
    stripe = _profile((h, w), dense, np.r_[True, np.zeros(len(dense) - 1, bool)], sigma, 1.0)
    clean, img = _expose(stripe, _ambient(ambient, (h, w)), peak, speckle, noise_sigma, full, rng)
    uv = dense[::8]  # every pixel of the curve's length
    valid = (uv[:, 0] >= -0.5) & (uv[:, 0] <= w - 0.5)
    valid &= (uv[:, 1] >= -0.5) & (uv[:, 1] <= h - 0.5)
    r = np.clip(np.rint(uv[:, 1]).astype(np.int64), 0, h - 1)
    c = np.clip(np.rint(uv[:, 0]).astype(np.int64), 0, w - 1)
    saturated = valid & (clean[r, c] >= full)
    if saturate:
        img = _quantised(img, full, bit_depth)
    truth = StripeTruth(
        uv=uv,
        valid=valid,
        saturated=saturated,
        width_px=float(width_px),
        sigma_px=sigma,
        orientation="curve",
        peak_level=peak * full,
        full_scale=int(full),
    )
    return img, truth
