"""`background_gain="auto"`: the room light of a laser-on image as a multiple of a
laser-off reference of the same pose taken at another exposure or room light.

A pair capture's stripe image is albedo x (g · room light + laser) and its board image
albedo x room light, with g unknown (0 with the room light off, about 1 at the same
light and exposure) and slowly varying over the image where the light changed between
the exposures. `fit_gain` fits g as a smooth map: per 16 x 16 px block, the least-squares
ratio of the laser-on to the reference image over the bright pixels of the region
(where the ratio is well determined), the laser line's pixels left out (first from the
blocks' median ratios, then twice from the residual of the fitted map: more than four
robust stds above or below it, grown by 2 px), then smoothed over the blocks and
interpolated to the pixels.
"""

from __future__ import annotations

import warnings

import cv2
import numpy as np

_BLOCK = 16
_MIN_PIXELS = 24  # fewest fitted pixels of a block that gets its own gain
# Pixels of the reference dimmer than this fraction of its bright level (90th
# percentile) are left out of the fit: their ratio is noise (a black print).
_BRIGHT_FRAC = 0.25
_REJECT = 4.0  # residual bound of the fit, in robust stds


def _blocks(a: np.ndarray, fill: float) -> np.ndarray:
    """(H, W) -> (nby, nbx, BLOCK²), padded with `fill`."""
    h, w = a.shape
    ph, pw = -h % _BLOCK, -w % _BLOCK
    a = np.pad(a, ((0, ph), (0, pw)), constant_values=fill)
    nby, nbx = a.shape[0] // _BLOCK, a.shape[1] // _BLOCK
    return a.reshape(nby, _BLOCK, nbx, _BLOCK).transpose(0, 2, 1, 3).reshape(nby, nbx, -1)


def _to_pixels(g: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A block map with NaN where no block fitted, filled from the fitted blocks nearby
    (normalised Gaussian smoothing, wider where needed; the median of all as the last
    resort), smoothed over one block and interpolated to the (H, W) pixels."""
    ok = np.isfinite(g)
    if not ok.any():
        return np.zeros(shape, np.float32)
    vals = np.where(ok, g, 0.0).astype(np.float32)
    weight = ok.astype(np.float32)
    out = np.full(g.shape, np.nan, np.float32)
    for sigma in (1.0, 3.0, 9.0):
        num = cv2.GaussianBlur(vals, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)
        den = cv2.GaussianBlur(weight, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)
        have = den > 0.05
        todo = ~np.isfinite(out)
        out[todo & have] = num[todo & have] / den[todo & have]
    out[~np.isfinite(out)] = float(np.median(g[ok]))
    h, w = shape
    nby, nbx = g.shape
    full = cv2.resize(out, (nbx * _BLOCK, nby * _BLOCK), interpolation=cv2.INTER_LINEAR)
    return np.maximum(full[:h, :w], 0.0)


def fit_gain(
    image: np.ndarray, reference: np.ndarray, roi: np.ndarray | None, noise: float
) -> np.ndarray:
    """The gain map g (H, W, float32, >= 0) with `image` ≈ g · `reference` away from
    the laser line (both (H, W) float planes; `roi`: the pixels to fit, None: all;
    `noise`: the reference's pixel noise)."""
    s = image.astype(np.float32, copy=False)
    b = reference.astype(np.float32, copy=False)
    region = np.ones(b.shape, bool) if roi is None else roi
    if not region.any():
        region = np.ones(b.shape, bool)
    bright = float(np.percentile(b[region], 90))
    floor = max(_BRIGHT_FRAC * bright, 3.0 * float(noise))
    if not (bright > 0 and floor < bright):
        return np.zeros(b.shape, np.float32)  # a black reference: nothing to subtract
    use = region & (b >= floor)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # (all-NaN blocks)
        q = _blocks(np.where(use, s / np.maximum(b, floor), np.nan), np.nan)
        count = np.sum(np.isfinite(q), axis=2)
        g = np.where(count >= _MIN_PIXELS, np.nanmedian(q, axis=2), np.nan)
    kernel = np.ones((5, 5), np.uint8)
    for _ in range(2):
        gmap = _to_pixels(g, b.shape)
        r = s - gmap * b
        spread = 1.4826 * float(np.median(np.abs(r[use] - np.median(r[use]))))
        spread = max(spread, 0.3 * float(noise), 1e-12)
        off = (np.abs(r) > _REJECT * spread).astype(np.uint8)
        keep = use & ~cv2.dilate(off, kernel).astype(bool)
        sb = _blocks(np.where(keep, s * b, 0.0), 0.0).sum(axis=2)
        bb = _blocks(np.where(keep, b * b, 0.0), 0.0).sum(axis=2)
        n = _blocks(keep.astype(np.float32), 0.0).sum(axis=2)
        g = np.where(n >= _MIN_PIXELS, sb / np.maximum(bb, 1e-30), np.nan)
    return _to_pixels(g, b.shape)
