"""Clipped line cores (flat tops): the plateau's tests in `extract_stripe`.

A clipped line's plateau ends where albedo x (ambient + laser) reaches the sensor's full
scale, nearer the centre over a darker albedo. Where the line runs along or across an
albedo edge its two rims can lie on different albedos: the plateau is then shifted off
the line's centre by up to ~2 px with a symmetric shape. These helpers read the albedo
at (or beyond) the rims and along the line (see docs/stripe.md, step 4a).
"""

from __future__ import annotations

import math

import numpy as np

from ._kernels import FWHM_PER_SIGMA, steger_sigma

# Largest |log| of the ratio of the albedo levels at a clipped plateau's two rims (see
# `rims_even`): 0.15 (16 % more light on one side) moves the plateau's centre by
# ~0.05 px on a 5 px line clipped 100-fold (rim shift s² / y_rim per unit log albedo).
RIM_RATIO_MAX = 0.15
# ... levels below this fraction of the clipping level (or 3 noise stds) count as it: a
# surface that dark shows its albedo too faintly (and the line's far tail, ~1 % of the
# clipped level 2 FWHM out, would count as one).
RIM_FLOOR = 0.05


def profile_std(width: float) -> float:
    """Std (px) of a line of FWHM `width` smoothed by Steger's Gaussian for it."""
    return math.hypot(width / FWHM_PER_SIGMA, steger_sigma(width))


def rims_even(gather, flat, y, plateau, ny, gap, floor, n_rows, ratio_max=RIM_RATIO_MAX):
    """Scan lines whose clipped plateau has the same albedo at both rims.

    A clipped line's plateau ends where albedo x (ambient + laser) reaches the sensor's
    full scale: over a darker albedo that happens nearer the centre. Where the line runs
    along an albedo edge (a checker or marker border between its rims), the plateau is
    then shifted off the line's centre by up to ~2 px while it stays perfectly
    symmetric in shape, so no profile test sees it. The albedo on either side is read
    `gap` px (along the line's normal) beyond each rim, as the mean of 5 samples a pixel
    apart, linearly interpolated at positions symmetric about the centre: a plateau is
    kept when the two differ by at most `RIM_RATIO_MAX` (levels under `floor` count as
    `floor`). The caller passes the laser-off image at the rims themselves, or the
    laser-on image beyond the line's reach (where its level does not move with the
    centre's own error)."""
    cols = np.arange(y.size)
    yc = np.nan_to_num(y, nan=0.0)
    out = 0.5 * plateau + gap / np.maximum(np.abs(np.nan_to_num(ny, nan=1.0)), 0.5)
    off = out[None, :] + np.arange(5)[:, None]  # 5 samples a pixel apart on each side

    def level(pos):  # mean of the linearly interpolated samples (exactly symmetric)
        lo = np.floor(pos)
        f = pos - lo
        lo = np.clip(lo.astype(np.intp), 0, n_rows - 2)
        return ((1 - f) * gather(lo, cols, flat) + f * gather(lo + 1, cols, flat)).mean(0)

    left, right = level(yc[None, :] - off), level(yc[None, :] + off)
    inside = (yc - off[-1] >= 0) & (yc + off[-1] <= n_rows - 1)
    ratio = np.abs(np.log(np.maximum(left, floor) / np.maximum(right, floor)))
    return inside & np.isfinite(y) & (ratio <= ratio_max), left, right


def plain_surroundings(left, right, ok, reach, floor):
    """Scan lines whose albedo levels beside the line (`left`, `right`, valid at `ok`)
    stay within `RIM_RATIO_MAX` (in log) over the `reach` scan lines on either side:
    no albedo edge near the line at all (levels under `floor` count as `floor`)."""
    n = left.size
    if n < 2 * reach + 1:
        return np.zeros(n, bool)
    out = np.ones(n, bool)
    for lev in (left, right):
        v = np.where(ok, np.log(np.maximum(lev, floor)), np.nan)
        win = np.lib.stride_tricks.sliding_window_view(
            np.pad(v, reach, constant_values=np.nan), 2 * reach + 1
        )
        count = np.count_nonzero(np.isfinite(win), axis=1)
        hi = np.max(np.where(np.isfinite(win), win, -np.inf), axis=1)
        lo = np.min(np.where(np.isfinite(win), win, np.inf), axis=1)
        out &= (count >= reach) & (hi - lo <= RIM_RATIO_MAX)
    return out & ok


def profile_reach(gather, y, n_rows, max_reach, frac=0.1):
    """(W,) how far (px, along the scan lines) the profile about each centre `y` of the
    signal `gather` reads stays above `frac` of its peak (the largest value within 2 px
    of the centre), the farther of its two sides; at most `max_reach`."""
    cols = np.arange(y.size)
    row = np.rint(np.nan_to_num(y, nan=0.0)).astype(np.intp)
    offs = np.arange(-max_reach, max_reach + 1)
    rows = np.clip(row[None, :] + offs[:, None], 0, n_rows - 1)
    prof = gather(rows, cols).astype(np.float64)
    peak = prof[np.abs(offs) <= 2].max(axis=0)
    above = prof >= frac * peak[None, :]
    reach = np.zeros(y.size, np.intp)
    for side in (offs < 0, offs > 0):
        idx = np.abs(offs[side])
        # the first offset on this side below the fraction (max_reach + 1: none)
        below = ~above[side]
        order = np.argsort(idx)
        first = np.where(below[order].any(0), idx[order][np.argmax(below[order], 0)],
                         max_reach + 1)  # fmt: skip
        reach = np.maximum(reach, first)
    return np.minimum(reach, max_reach)


def sides_even(gather, flat, y, start, reach, floor, n_rows, ratio_max):
    """Scan lines whose level in `flat` (read by `gather`), averaged over the samples a
    pixel apart from `start` to `reach` (per scan line) px on each side of the centre
    `y` (linearly interpolated, symmetric about it), is the same on both sides within
    `ratio_max` in log (levels under `floor` count as `floor`)."""
    cols = np.arange(y.size)
    yc = np.nan_to_num(y, nan=0.0)
    n = int(max(np.max(reach - start), 0)) + 1
    off = start + np.arange(n)[:, None] * np.ones(y.size)[None, :]
    use = off <= np.maximum(reach, start)[None, :]

    def level(pos):
        lo = np.floor(pos)
        f = pos - lo
        lo = np.clip(lo.astype(np.intp), 0, n_rows - 2)
        v = (1 - f) * gather(lo, cols, flat) + f * gather(lo + 1, cols, flat)
        return np.sum(np.where(use, v, 0.0), axis=0) / np.maximum(use.sum(axis=0), 1)

    left, right = level(yc[None, :] - off), level(yc[None, :] + off)
    far = start + n - 1
    inside = (yc - far >= 0) & (yc + far <= n_rows - 1)
    ratio = np.abs(np.log(np.maximum(left, floor) / np.maximum(right, floor)))
    return inside & np.isfinite(y) & (ratio <= ratio_max)
