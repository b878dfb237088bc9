"""`extract_stripe` / `extract_stripes`: laser-stripe centres of one or many images.

(One module, longer than most: `_extract_track` is one pass from the coarse track to the
linked centres, whose stages read and refine the same band, thresholds and per-scan-line
masks; the stages that stand alone live in their own modules: `_steger`, `_link`,
`_coarse`, `_clipped`, `_longridge`, `_stepfit`.)
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import functools
import math
import os
from collections.abc import Iterable
from typing import Any

import cv2
import numpy as np

from . import _fast
from ._centroid import centroid_band
from ._channel import ranked_channels
from ._clipped import (
    RIM_FLOOR,
    plain_surroundings,
    profile_reach,
    profile_std,
    rims_even,
    sides_even,
)
from ._coarse import FACTOR, coarse_track, downsample
from ._gain import fit_gain
from ._image import CHANNELS, _median, as_image, block_noise, channel_image, estimate_noise
from ._link import consistent, link_segments
from ._longridge import LongRidge, long_ridge_track, path_track
from ._mask import as_mask
from ._result import StripeResult
from ._ridge import is_ambiguous, ridge_offset, scan_direction
from ._rims import ONE_SIDE_LINE, ONE_SIDE_REACH, bracketed, edge_spread, rim_centres
from ._steep import _length as _line_length, follow_steep
from ._steger import ScanLines, steger_band, steger_full
from ._stepfit import MAX_SIGMA_C, refit_steps

_METHODS = ("steger", "centroid")
_ORIENTATIONS = ("auto", "vertical-scan", "horizontal-scan")
_DEFAULT_WIDTH = 5.0


# A profile whose two flanks one smoothed-profile std from the centre differ by more
# than this fraction of its height has a brightness step under it (an albedo edge, the
# rim of a glint), which pulls the centre: rejected. A symmetric line gives 0 plus noise.
ASYMMETRY_MAX = 0.12
# Accepted range of a centre's width over the median width of the line.
WIDTH_RATIO = (0.7, 1.4)
# A frame holds a line only if one segment spans this fraction of the scan lines (or
# three minimum segments), or a chain of segments that continue one another does
# (`_chain_span`): glints and short reflections alone are not a line.
MIN_LINE_FRACTION = 0.05
# Colour "X-minus-others" without a laser-off image: largest |log| ratio of the albedo
# (the other channels) on the two sides of a centre. 0.5 (a factor 1.65) refuses an
# albedo edge within ~2 px of a 5 px line's centre, where the albedo x laser profile
# puts the centre up to 0.9 px off (ChArUco bit borders along the line), and keeps the
# crossings of checker edges (their centres: 0.042 px RMS with the test, 0.039 without,
# on `render_capture`'s colour checkerboard at 15 degrees; 0.15 refused 11 % of them).
ALBEDO_EVEN_MAX = 0.5
# ... for a clipped profile (colour, no laser-off image): the albedo is read out to
# where the profile falls under this fraction of its peak (the farther side), one pixel
# beyond (see step 3b in docs/stripe.md).
CLIPPED_PROFILE_FRAC = 0.1
# Scan lines on each side over which `_noise_along` pools the noise beside a line.
_NOISE_POOL = 15
# Lowest ratio of that noise to the frame's estimate.
_LOCAL_NOISE_MIN = 0.25
# The laser-off frame subtracted from a laser-on image of the same exposure: its
# edge-keeping denoising (`_denoised`), the bilateral filter's diameter and spatial
# sigma (px); and the laser-off level divided by (`_off_level`): the half-width (px) of
# the mean taken where the frame is flat, and the range of the frame's 0.7 px blur over
# that window (noise stds) below which it is flat and from which it holds an edge.
BILATERAL_PX = 9
BILATERAL_SIGMA_PX = 3.0
FLAT_RADIUS_PX = 5
FLAT_RANGE = (3.0, 5.0)
# Scan lines on each side of a refused one on a long-ridge track whose centres must
# also agree with a straight line through the others: the print refuses the line where
# an albedo edge lies under its profile, and the centres next to a refusal are the ones
# the edge has begun to pull (on a ChArUco print with the line at 133 deg: up to 1.4 px
# off the exact line at an asymmetry of 0.05, under its bound).
_TRACK_TRIM = 3
# Hysteresis: a kept segment must reach this multiple of the acceptance threshold.
_HIGH = 2.0
# A speckled line. The speckle contrast (`_speckle_contrast`, measured with a laser-off
# image) above which the signal is smoothed along the line over `SPECKLE_SMOOTH` line
# widths before the centres are read; then (`_speckle_bound`) the median |asymmetry|
# of the candidate centres above which the whole line is asymmetric, and the
# autocorrelation of the signed asymmetry, a few line widths apart along the line,
# below which it is random (speckle grains) rather than a brightness step lying along
# the line; the asymmetry bound is then `SPECKLE_SIGMAS` spreads of the asymmetry (3
# sigma of a half-normal |asymmetry|). Measured contrasts: docs/stripe.md.
SPECKLE_CONTRAST = 0.1
SPECKLE_SMOOTH = 1.0
SPECKLE_MEDIAN = 0.06
SPECKLE_CORRELATION = 0.5
SPECKLE_SIGMAS = 3.0


def _slant(angle: float, orientation: str) -> float:
    """How many times wider a line whose normal is at `angle` (deg from the u axis) reads
    along the scan lines of `orientation` than across itself (at most 2)."""
    a = math.radians(angle)
    across = abs(math.sin(a)) if orientation == "vertical-scan" else abs(math.cos(a))
    return 1.0 / max(across, 0.5)


def _chain_span(y: np.ndarray, segment: np.ndarray, jump: float, min_line: int) -> int:
    """Scan lines spanned by the longest chain of linked segments (`segment` labels, -1:
    none) that continue one another: each next one begins within `min_line` scan lines
    of the last one's end, and the straight lines fitted to the two meet at the middle
    of the gap within `jump` px. A chain holding centres on fewer than half the scan
    lines it spans is no chain (0), as a long-ridge path with fewer ridge pixels is no
    track (`path_track`)."""
    pieces = []
    for label in np.unique(segment[segment >= 0]):
        at = np.flatnonzero(segment == label)
        slope, icpt = np.polyfit(at, y[at], 1) if at.size >= 2 else (0.0, float(y[at[0]]))
        pieces.append((int(at[0]), int(at[-1]), float(slope), float(icpt), at.size))
    best = 0
    chain = None  # (first scan line, centres, last piece)
    for piece in sorted(pieces):
        first, last, slope, icpt, n = piece
        if chain is not None:
            c_first, c_n, (_, p_last, p_slope, p_icpt, _) = chain
            mid = 0.5 * (p_last + first)
            if (
                first - p_last <= min_line
                and abs((p_slope * mid + p_icpt) - (slope * mid + icpt)) <= jump
            ):
                chain = (c_first, c_n + n, piece)
            else:
                chain = None
        if chain is None:
            chain = (first, n, piece)
        span = last - chain[0] + 1
        if chain[1] >= 0.5 * span:
            best = max(best, span)
    return best


def _frame_noise(img: np.ndarray) -> float:
    """`estimate_noise(img)`; for a uint8 image from its compiled histogram (the same
    order statistics, `_fast.second_diff_ranks_u8`)."""
    if not (_fast.enabled and img.dtype == np.uint8 and img.ndim == 2):
        return estimate_noise(img)
    lo, hi = _fast.second_diff_ranks_u8(img, 8)
    sigma = 1.4826 * float(np.float32((lo + hi) / 2)) / np.sqrt(6.0)
    return max(sigma, 0.3)


def _block_noise(img: np.ndarray) -> float:
    """`block_noise(img)`; for a uint8 image its sorted second differences from a
    compiled pass (the same float32 values, `_fast.block_noise_u8`), the rest as there."""
    if not (_fast.enabled and img.dtype == np.uint8 and img.ndim == 2) or min(img.shape) < 6:
        return block_noise(img)
    d = _fast.block_noise_u8(img, 16)
    return 2.0 * 1.267 * float(np.sqrt(np.mean(d * d))) / math.sqrt(6.0)


def _min_line(width: float, min_segment: int | None, n_scan: int) -> int:
    """Scan lines that the longest segment (or a long-ridge path) must span for the
    frame to hold a line: three minimum segments, or `MIN_LINE_FRACTION` of the scan
    lines."""
    min_pts = max(8, int(round(2 * width))) if min_segment is None else int(min_segment)
    return max(3 * min_pts, int(MIN_LINE_FRACTION * n_scan))


def _empty(n: int, orientation: str, method: str, **extra) -> StripeResult:
    return StripeResult(
        uv=np.full((n, 2), np.nan),
        strength=np.zeros(n),
        width=np.full(n, np.nan),
        valid=np.zeros(n, bool),
        saturated=np.zeros(n, bool),
        orientation=orientation,
        method=method,
        confidence=np.zeros(n),
        segment=np.full(n, -1, np.intp),
        **extra,
    )


def _check_options(method, width_px, orientation, band_px, min_strength, saturation, channel):
    if method not in _METHODS:
        raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
    if orientation not in _ORIENTATIONS:
        raise ValueError(f"orientation must be one of {_ORIENTATIONS}, got {orientation!r}")
    if channel not in CHANNELS:
        raise ValueError(f"channel must be one of {CHANNELS}, got {channel!r}")
    if width_px is not None and not (math.isfinite(width_px) and 1.0 <= width_px <= 200.0):
        raise ValueError(f"width_px must be a stripe FWHM between 1 and 200 px, got {width_px}")
    if band_px is not None and band_px != "auto":
        if isinstance(band_px, bool) or not isinstance(band_px, (int, np.integer)) or band_px < 1:
            raise ValueError(f"band_px must be 'auto', None or a positive integer, got {band_px!r}")
    if min_strength is not None and not (math.isfinite(min_strength) and min_strength >= 0):
        raise ValueError(f"min_strength must be a finite number >= 0, got {min_strength}")
    if saturation is not None and not math.isfinite(saturation):
        raise ValueError(f"saturation must be a finite grey level or None, got {saturation}")


def _check_gain(gain) -> None:
    if isinstance(gain, str):
        if gain != "auto":
            raise ValueError(f"background_gain must be 'auto' or a number >= 0, got {gain!r}")
    elif isinstance(gain, bool) or not isinstance(gain, (int, float, np.integer, np.floating)):
        raise ValueError(f"background_gain must be 'auto' or a number >= 0, got {gain!r}")
    elif not (math.isfinite(gain) and gain >= 0):
        raise ValueError(f"background_gain must be 'auto' or a number >= 0, got {gain}")


def _signal(image, background, channel, width, normalise, gain=1.0, mask=None):
    """The 2-D signal image, the plain image whose clipping marks saturation, the
    channel used, the signal before the albedo normalisation (the signal itself
    without one), the plain laser-off channel and the denoised laser-off signal that
    was subtracted (None and None without one) and the colour candidates in score
    order (the channel alone unless it was chosen)."""
    if background is not None and (isinstance(gain, str) or float(gain) != 1.0):
        return _gain_signal(image, background, channel, width, normalise, gain, mask)
    img = as_image(image)
    if background is not None:
        off = as_image(background, name="background")
        if off.shape != img.shape:
            raise ValueError(
                f"background (laser-off) image has shape {off.shape}, the image {img.shape}"
            )
    ranked = (channel,)
    if channel == "auto":
        probe = img if background is None else img.astype(np.float32) - off.astype(np.float32)
        ranked = ranked_channels(probe, width)
        channel = ranked[0]
    elif img.ndim == 2 and channel != "grey":
        raise ValueError(f"channel {channel!r} needs a colour image; this one is grey")
    sig, sat = channel_image(img, channel)
    plain, off_level, base = sig, None, None
    if background is not None:
        base, level = channel_image(off, channel)
        base = base.astype(np.float32)
        # the laser-off frame's noise: at the 2 x 2 block scale where that reads more
        # (a JPEG removes it at the pixel scale, where a quality 85 frame reads 0.3 grey
        # levels for the 1.2 put in, and neither filter below would smooth it)
        noise = max(estimate_noise(base), block_noise(base))
        base = _denoised(base, BILATERAL_PX, BILATERAL_SIGMA_PX, noise)
        sig = plain = sig.astype(np.float32) - base
        off_level = level
        if normalise:  # the plain channel's laser-off level: albedo x ambient light
            lev = level.astype(np.float32)
            if img.ndim == 3:
                noise = max(estimate_noise(lev), block_noise(lev))
            sig = _albedo_normalised(sig, _off_level(lev, noise), blur=0.0)
    return sig, sat, channel, plain, off_level, base, ranked


def _gain_signal(image, background, channel, width, normalise, gain, mask):
    """`_signal` against a laser-off reference at another exposure or room light
    (`background_gain` "auto" or a number other than 1): each plane of the image less
    g x the same plane of the denoised reference (g fitted per plane by `fit_gain`
    inside `mask` for "auto"), the channel chosen from that difference, and the
    difference divided by the reference's own level (not by g x it, which is about 0
    with the room light off)."""
    img = as_image(image)
    off = as_image(background, name="background")
    if off.shape[:2] != img.shape[:2]:
        raise ValueError(
            f"background (laser-off) image has shape {off.shape}, the image {img.shape}"
        )
    if off.ndim == 3 and img.ndim == 2:
        raise ValueError(f"background (laser-off) image is colour {off.shape}, the image grey")
    if off.ndim == 2 and img.ndim == 3:  # a grey reference for each colour plane
        off = np.dstack([off] * 3)
    roi = as_mask(mask, img.shape[:2])
    planes, subtracted, denoised = [], [], []
    for k in range(1 if img.ndim == 2 else 3):
        s = (img if img.ndim == 2 else img[:, :, k]).astype(np.float32)
        b = (off if off.ndim == 2 else off[:, :, k]).astype(np.float32)
        noise = estimate_noise(b)
        b = _denoised(b)
        g = fit_gain(s, b, roi, noise) if gain == "auto" else np.float32(gain)
        denoised.append(b)
        subtracted.append(g * b)
        planes.append(s - subtracted[-1])
    one = img.ndim == 2
    diff = planes[0] if one else np.dstack(planes)
    base_all = subtracted[0] if one else np.dstack(subtracted)
    ranked = (channel,)
    if channel == "auto":
        ranked = ranked_channels(diff, width)
        channel = ranked[0]
    elif img.ndim == 2 and channel != "grey":
        raise ValueError(f"channel {channel!r} needs a colour image; this one is grey")
    sig, _ = channel_image(diff, channel)
    _, sat = channel_image(img, channel)
    _, level = channel_image(off, channel)
    base = channel_image(base_all, channel)[0].astype(np.float32)
    sig = plain = np.ascontiguousarray(sig, dtype=np.float32)
    if normalise:
        # the reference's level (albedo x its room light), edge-kept denoised and not
        # blurred further: the laser light x albedo divided by a blurred albedo keeps
        # a step at every print edge under the line (a circle grid's dots: 0.12 px RMS
        # off the exact line with the blur, 0.03-0.04 px without)
        smooth = channel_image(denoised[0] if one else np.dstack(denoised), channel)[1]
        sig = _albedo_normalised(sig, np.ascontiguousarray(smooth, dtype=np.float32), blur=0.0)
    return sig, sat, channel, plain, level, base, ranked


def _others_mean(image: Any, channel: str) -> np.ndarray:
    """The mean of the two channels other than the laser's (`channel` "X-minus-others"):
    albedo x room light, without the laser (float32, image frame)."""
    img = as_image(image)
    k = {"blue": 0, "green": 1, "red": 2}[channel.removesuffix("-minus-others")]
    a, b = (img[:, :, j].astype(np.float32) for j in range(3) if j != k)
    return 0.5 * (a + b)


def _denoised(
    off: np.ndarray, px: int = 5, sigma_px: float = 1.5, noise: float | None = None
) -> np.ndarray:
    """The laser-off frame with its noise smoothed away but its edges kept (a bilateral
    filter, `px` wide with a spatial sigma `sigma_px`, grey-level scale four noise
    stds): subtracted as it is, the laser-off frame adds its own noise to the
    difference (sqrt(2) x the centre RMS), while a plain blur would smear the albedo
    edges it is there to remove. `noise`: the frame's noise std (default: its pixel
    estimate)."""
    noise = estimate_noise(off) if noise is None else noise
    if not noise > 0:
        return off
    return cv2.bilateralFilter(off, px, 4.0 * noise, sigma_px)


def _off_level(off: np.ndarray, noise: float) -> np.ndarray:
    """The laser-off level that `_albedo_normalised` divides by (float32): the mean over
    (2 FLAT_RADIUS_PX + 1)^2 pixels where the frame is flat there, its 0.7 px Gaussian
    blur near an albedo edge, blended in between.

    The divisor multiplies the line's profile, so its noise across the line moves the
    centre as additive noise of the same relative size would: with the 0.7 px blur alone
    (noise / 2.5) it was half the error over the paper rig's black squares. The print is
    piecewise constant, and the room light smooth, so away from an edge a wide plain
    mean is unbiased and 11 x less noisy than a pixel; near an edge the divisor stays
    the linear 0.7 px blur, whose edge profile matches the laser-on image's (the same
    optics blurred both): an edge-keeping filter there (a bilateral filter) steepens the
    ramp's feet, which biased a line running along a checker edge by +0.013-0.018 px.
    Flat: the 0.7 px blur's range (max - min) over the window under FLAT_RANGE[0] noise
    stds (the blurred noise's own range over 121 pixels stays under ~2.5 stds); an edge
    from FLAT_RANGE[1] stds on, linear in between (`noise`: the frame's noise std)."""
    near = cv2.GaussianBlur(off, (0, 0), 0.7)
    if not noise > 0:
        return near
    side = 2 * FLAT_RADIUS_PX + 1
    box = cv2.getStructuringElement(cv2.MORPH_RECT, (side, side))
    spread = cv2.dilate(near, box) - cv2.erode(near, box)
    wide = cv2.blur(off, (side, side), borderType=cv2.BORDER_REFLECT)
    lo, hi = FLAT_RANGE
    w = np.clip((hi * noise - spread) / ((hi - lo) * noise), 0.0, 1.0).astype(np.float32)
    return near + w * (wide - near)


def _albedo_normalised(diff: np.ndarray, off: np.ndarray, blur: float = 0.7) -> np.ndarray:
    """`diff · typical / max(off, floor)`: the laser light over the ambient light of the
    same pixel. Brightness is albedo x (ambient + laser), so the laser-on minus laser-off
    difference still carries the target's albedo (the line is dimmer on black squares
    and an albedo edge under it pulls its centre); dividing by the laser-off level takes
    the albedo out. `typical` (the median laser-off level) keeps grey-level units;
    `floor` (a tenth of the 90th percentile) keeps dark pixels from amplifying noise.
    `blur`: the Gaussian (px) `off` is smoothed with first (0: `off` is smooth already)."""
    smooth = cv2.GaussianBlur(off, (0, 0), blur) if blur > 0 else off
    typical = float(np.median(smooth))
    floor = 0.1 * float(np.percentile(smooth, 90))
    if not floor > 0:
        return diff
    return diff * (max(typical, floor) / np.maximum(smooth, floor))


def extract_stripe(
    image: Any,
    *,
    method: str = "steger",
    width_px: float | int | None = None,
    orientation: str = "auto",
    band_px: int | str | None = "auto",
    min_strength: float | int | None = None,
    saturation: float | int | None = None,
    mask: Any = None,
    channel: str = "auto",
    background: Any = None,
    normalise_background: bool = True,
    background_gain: float | int | str = 1.0,
    max_jump_px: float | None = None,
    min_segment: int | None = None,
) -> StripeResult:
    """Sub-pixel centres of a bright laser line in one image, at most one per scan line.

    Pipeline: (1) the signal image: the chosen channel of a colour image (or a
    combination such as red minus the others), minus the laser-off `background` if
    given; (2) a 4 x 4 block average; its two-sided ridge response (bright on both sides,
    so step edges give none) chooses the scan direction (`"auto"`) and positions a
    coarse track, one peak per scan line, with outliers from the median of their
    neighbours searched again near it; (3) Steger's Hessian method (or the grey
    centroid) in a band around the track; (4) per-centre ridge tests: a negative second
    derivative across the line of at least the noise threshold, the first derivative's
    zero inside the band, a plausible width and a symmetric profile (a brightness step
    under the line, such as a checker edge, pulls the centre); (5) the centres refused
    there (and the noticeably asymmetric ones) measured again by a least-squares fit of
    albedo step x Gaussian line to the raw profile, kept where that fit is well
    determined (`_stepfit.py`); (6) linking into segments (largest jump `max_jump_px`
    per scan line), hysteresis on the strength and removal of short segments.

    **Arguments:**
    - `image`: grey (H, W) or colour (H, W, 3|4) image, colour in **BGR** order as
      `cv2.imread` returns it (alpha ignored); uint8, uint16, int16 or float.
    - `method`: `"steger"` (Hessian line detector, sub-pixel) or `"centroid"`
      (background-subtracted grey gravity, the classical baseline).
    - `width_px`: expected line width (FWHM, px); `None`: measured from the image.
    - `orientation`: `"vertical-scan"` (one centre per column u: a mostly horizontal
      line), `"horizontal-scan"` (one per row v), or `"auto"` (from the ridge-normal
      tensor of the image; `StripeResult.ambiguous` tells when no direction dominates).
      With `"auto"` the parts of a curved line too steep for the scan direction (its
      segments end steeper than 50 degrees to the scan-perpendicular, or past 35
      degrees and still turning)
      are taken from the other scan direction and merged in order along the line
      (`StripeResult.steep`, `_steep.py`); with a given direction their length is
      reported (`StripeResult.steep_left_out_px`).
    - `band_px`: half-height of the band around the coarse track for Steger; `"auto"`:
      from `width_px`; `None`: filter the whole frame (slow baseline, same centres).
    - `min_strength`: smallest accepted strength (grey levels of the signal); `None`:
      eight times the strength's noise, estimated from the image.
    - `saturation`: level at which the sensor clips; `None`: for integer images the
      frame's maximum. Clipped line cores are measured from the plateau (`saturated`).
    - `mask`: region of interest: None, a bool (H, W) array, or a polygon (N, 2) of
      `(u, v)` pixels. Only ridges inside it are tracked and centres outside it are not
      returned (see `region_mask`).
    - `channel`: `"auto"`, `"grey"`, `"red"`, `"green"`, `"blue"`, `"red-minus-others"`,
      `"green-minus-others"` or `"blue-minus-others"` (`X - (Y + Z) / 2`). Grey images
      take `"auto"` or `"grey"`.
    - `background`: optional laser-off image of the same pose (same shape); the centres
      are found in the difference image (laser-off frame denoised by an edge-keeping
      filter). (Taking the laser-on image's own centre where it agrees was tried: on
      grey single images of a ChArUco board those centres are biased by up to 0.2 px.)
    - `normalise_background`: with a `background`, divide the difference by the
      laser-off level (albedo-free: the line keeps its brightness and its centre across
      black and white squares); False: the plain difference.
    - `background_gain`: the room light of `image` as a multiple g of the
      `background`'s: 1 (default) for a laser-off image at the same light and exposure;
      `"auto"` for a reference taken at another exposure or room light (a pair
      capture's board image: the stripe image's room light may be the same, dimmer or
      off), g fitted per colour plane as a smooth map over the image (inside `mask`),
      the laser line left out (`_gain.py`); or a number. The image less g x the
      background is divided by the background's own level (with a floor for its dark
      pixels), not by g x it. (In a colour JPEG pair the laser's own channel holds the
      line over the dark print as a few levels of half-resolution chroma, its centres
      there and next to print edges up to 1.3 px off; `scheimflux detect` reads such a
      pair in luma, `channel="grey"`, and drops the centres on the dark print and next
      to it.)
    - `max_jump_px`: largest change of the centre between neighbouring scan lines within
      a segment; `None`: `max(2, width / 2)`.
    - `min_segment`: fewest centres of a kept segment; `None`: `max(8, 2 width)`.

    **Returns:** a `StripeResult` with one entry per scan line (W for a vertical scan,
    H for a horizontal one); where steep parts were merged, their centres inserted
    among them in order along the line; a frame without a line gives all-invalid
    entries.

    **Raises:** `ValueError` for input that is not a numeric grey or colour image, a
    mask or background of the wrong shape, or bad options.
    """
    return _extract_one(
        image, method=method, width_px=width_px, orientation=orientation, band_px=band_px,
        min_strength=min_strength, saturation=saturation, mask=mask, channel=channel,
        max_jump_px=max_jump_px, min_segment=min_segment, background=background,
        normalise_background=normalise_background, background_gain=background_gain,
    )  # fmt: skip


def _extract_one(image: Any, **options: Any) -> StripeResult:
    """`extract_stripe` on one signal (laser-on image, or its laser-off difference);
    where the coarse track finds no line, the longest continuous narrow ridge
    (`_longridge.py`) is tried as the track instead (in each other colour candidate
    first, for a colour image with `channel="auto"`).

    Every pass here reads the same image pair, so its signal (per channel asked) is
    computed once and shared (`signals`): the steep parts of a line and the long-ridge
    retries each took a whole-frame pass again, the bilateral filters and gain fits
    of a colour laser-off pair included (a 2448 x 2048 JPEG pair with a 45 degree
    line: seven passes)."""
    options = {**options, "signals": {}}
    result, retry = _extract_track(image, **options)
    if result.valid.any():
        return _with_steep(image, result, options)
    if retry is None:
        return result
    signals = {result.channel: retry}  # each channel's failed pass, for the search below
    if options.get("channel", "auto") == "auto" and np.ndim(image) == 3:
        # the colour candidates in the order of their scores: the print of a board can
        # outscore a dim laser in the grey image, not in the laser's own colour
        for ch in retry.ranked[1:]:
            res_c, retry_c = _extract_track(image, **{**options, "channel": ch})
            if res_c.valid.any():
                return _with_steep(image, res_c, options)
            if retry_c is not None:
                signals[ch] = retry_c
    for ch, sig in signals.items():
        res_l = _on_long_ridge(image, {**options, "channel": ch}, sig, sig.orientation)
        if res_l is not None and res_l.valid.any():
            return _with_steep(image, res_l, options)
    return _whole_line_too_steep(image, result, options)


def _on_long_ridge(image: Any, options: dict, sig, orientation: str, **extra: Any):
    """`_extract_track` along the longest continuous narrow ridge of a pass that found
    no coarse track (`sig`, its retry signal), searched in `orientation`; None where
    there is no such ridge. `extra`: further `_extract_track` arguments (a band)."""
    found = long_ridge_track(sig.img, sig.width, sig.noise, sig.roi, orientation)
    if found is None:
        return None
    opts = {**options, "orientation": found[0]}
    return _extract_track(image, **opts, **extra, track=found[1])[0]


def _whole_line_too_steep(image: Any, result: StripeResult, options: dict) -> StripeResult:
    """`result` (no line found with the scan direction asked for) with the length of a
    line the other scan direction finds reported as left out (`steep_left_out_px`,
    fraction 1): a straight line steeper than the given orientation can scan is there,
    not missing. Only for a given orientation (`"auto"` already tried both)."""
    asked = options.get("orientation", "auto")
    if asked not in ("vertical-scan", "horizontal-scan"):
        return result
    other = "horizontal-scan" if asked == "vertical-scan" else "vertical-scan"
    found, _ = _extract_track(image, **{**options, "orientation": other})
    length = _line_length(found.uv[found.valid])
    if length <= 0.0:
        return result
    return dataclasses.replace(result, steep_left_out_px=length, steep_left_out_fraction=1.0)


def _with_steep(image: Any, result: StripeResult, options: dict) -> StripeResult:
    """`result` with the parts of its line too steep for its scan direction (a curved
    line) found by the other scan direction (`_steep.py`): merged in line order for
    `orientation="auto"`, their length reported for a given orientation."""
    shape = np.shape(image)[:2]

    def extract_other(orientation: str, band: np.ndarray) -> StripeResult:
        widths = result.width[result.valid & np.isfinite(result.width)]
        width = float(np.median(widths)) if widths.size else _DEFAULT_WIDTH
        min_segment = options.get("min_segment")
        min_pts = max(8, int(round(2 * width))) if min_segment is None else int(min_segment)
        opts = {**options, "orientation": orientation, "channel": result.channel}
        found, retry = _extract_track(image, **opts, min_line=min_pts, band=band)
        if found.valid.any() or retry is None:
            return found
        # no coarse track in the band (a dim line): the longest narrow ridge there, as
        # `_extract_one` tries for the whole frame
        ridge = _on_long_ridge(image, opts, retry, orientation, min_line=min_pts, band=band)
        return found if ridge is None else ridge

    merge = options.get("orientation", "auto") == "auto"
    return follow_steep(result, shape, extract_other, merge)


def _noise_along(
    gather, centre: np.ndarray, n_rows: int, width: float, integer: bool
) -> np.ndarray:
    """(W,) pixel-noise std at the line on each scan line of a track `centre` (scan
    frame; `gather(rows, cols)` reads the image at integer index arrays).

    The frame's noise (`estimate_noise`) is a median over the whole image; shot noise
    grows with the level, so over a black print the line sits in noise several times
    lower than over the white (and than that median). Here: the std of the second
    differences along the scan lines beside the line (1.5 to 3 FWHM from the track:
    their mean absolute value, clipped at 4 x its median, 2.7 stds of Gaussian noise,
    so that the print's edges drop out; continuous where a median of integer
    differences steps by whole grey levels), pooled over `_NOISE_POOL` scan lines on
    each side, times the square root of the ratio of the level at the track to the
    level beside it (shot noise at the line's peak; an upper bound where read noise
    adds to it). Edges that stay in only raise it. Never below the quantisation noise
    0.3 of integer images.
    """
    n = centre.size
    reach = int(math.ceil(3.0 * width)) + 1
    offs = np.arange(-reach, reach + 1)
    row = np.rint(centre).astype(np.intp)
    rows = np.clip(row[None, :] + offs[:, None], 0, n_rows - 1)
    block = gather(rows, np.arange(n)).astype(np.float64)
    d = np.abs(block[:-2] - 2.0 * block[1:-1] + block[2:])
    p = _NOISE_POOL
    beside = np.pad(d[np.abs(offs[1:-1]) > 1.5 * width], ((0, 0), (p, p)), mode="edge")
    win = np.lib.stride_tricks.sliding_window_view(beside, 2 * p + 1, axis=1)
    vals = win.transpose(1, 0, 2).reshape(n, -1)
    clip = np.maximum(4.0 * np.median(vals, axis=1), 2.0 if integer else 0.0)[:, None]
    inside = vals <= clip
    mean_abs = np.sum(np.where(inside, vals, 0.0), axis=1) / np.maximum(inside.sum(axis=1), 1)
    # E|d| = sqrt(2 / pi) std(d) for Gaussian d; std(d) = sqrt(6) pixel stds
    sigma = mean_abs / math.sqrt(2.0 / math.pi) / math.sqrt(6.0)
    side = np.median(block[np.abs(offs) > 1.5 * width], axis=0)
    ratio = np.maximum(block[reach], 1.0) / np.maximum(side, 1.0)
    ratio = np.median(np.lib.stride_tricks.sliding_window_view(
        np.pad(ratio, p, mode="edge"), 2 * p + 1), axis=1)  # fmt: skip
    sigma = sigma * np.sqrt(np.maximum(ratio, 1.0))
    return np.maximum(sigma, 0.3) if integer else sigma


def _lag_pairs(idx: np.ndarray, lag: int) -> tuple[np.ndarray, np.ndarray]:
    """Positions `(i, j)` in the sorted scan-line indices `idx` with
    `idx[j] == idx[i] + lag`."""
    j = np.searchsorted(idx, idx + lag)
    pair = j < idx.size
    pair[pair] &= idx[j[pair]] == idx[pair] + lag
    return np.flatnonzero(pair), j[pair]


def _speckle_contrast(gather, coarse, rows: int, width: float, plain=None,
                      sat_level: float | None = None) -> float:  # fmt: skip
    """The laser speckle's contrast along a line (std / mean of its peak): grains of a
    few pixels make the line's peak vary between scan lines a few widths apart more than
    between neighbours, while pixel noise (shot and read) varies both alike and a smooth
    line neither; so the robust spread of the peak's changes over `2 width` scan lines,
    less that over one, over the median peak (albedo steps and glints: a few outliers
    the medians ignore), on the unclipped scan lines whose peak reaches a quarter of
    the line's."""
    cols = np.flatnonzero(coarse.support)
    if cols.size < 32:
        return 0.0
    reach = max(int(math.ceil(width)), 2)
    r = np.clip(np.rint(coarse.centre[cols]).astype(np.intp)[None, :]
                + np.arange(-reach, reach + 1)[:, None], 0, rows - 1)  # fmt: skip
    peak = gather(r, cols[None, :]).astype(np.float64).max(axis=0)
    # the line's own scan lines (the coarse track also spans scan lines of noise), not
    # clipped in the plain image (`plain`, at `sat_level`): a clipped core divided by
    # the laser-off level follows the albedo, not the laser
    on = peak >= 0.25 * float(np.quantile(peak, 0.95))
    if plain is not None:
        on &= plain(r, cols[None, :]).max(axis=0) < sat_level
    cols, peak = cols[on], peak[on]
    if cols.size < 32:
        return 0.0
    level = float(np.median(peak))
    lag = max(int(round(2.0 * width)), 4)
    if not level > 0 or cols.size < 4 * lag:
        return 0.0
    spreads = []
    for k in (1, lag):
        i, j = _lag_pairs(cols, k)
        if i.size < 16:
            return 0.0
        spreads.append(1.4826 * float(np.median(np.abs(peak[j] - peak[i]))))
    return math.sqrt(max(spreads[1] ** 2 - spreads[0] ** 2, 0.0) / 2.0) / level


def _along_line(img: np.ndarray, direction_deg: float, sigma: float) -> np.ndarray:
    """`img` smoothed by a 1-D Gaussian of std `sigma` (px) along the direction
    `direction_deg` (degrees from the u axis), as float32. A straight line keeps its
    centre; a curved one moves towards its inside by about curvature x sigma² / 2."""
    n = int(math.ceil(3.0 * sigma))
    size = 2 * n + 1
    t = np.linspace(-n, n, 8 * size)
    c, s_ = math.cos(math.radians(direction_deg)), math.sin(math.radians(direction_deg))
    x, y = n + t * c, n + t * s_
    x0, y0 = np.floor(x).astype(np.intp), np.floor(y).astype(np.intp)
    fx, fy = x - x0, y - y0
    g = np.exp(-(t**2) / (2.0 * sigma**2))
    kernel = np.zeros((size + 1, size + 1))
    for dx, dy, wgt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)),
                        (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):  # fmt: skip
        np.add.at(kernel, (y0 + dy, x0 + dx), g * wgt)
    kernel = kernel[:size, :size] / kernel[:size, :size].sum()
    return cv2.filter2D(img.astype(np.float32), -1, kernel.astype(np.float32),
                        borderType=cv2.BORDER_REFLECT)  # fmt: skip


def _speckle_bound(asym: np.ndarray, candidate: np.ndarray, width: float) -> float:
    """The asymmetry bound for a speckled line, 0 when the line is not speckled.

    Laser speckle multiplies the line by grains about as wide as the line: nearly every
    profile is asymmetric, each centre is off at random (zero mean along the line), and
    the fixed bound `ASYMMETRY_MAX`, made for the few profiles a brightness step lies
    under, refuses most of the line (measured on a 45-degree 5 px line, grains of
    1.5-3 px, contrast 0.3-0.6: 0-60 % of its centres kept, their RMS error 10-20 %
    below that of all of them).
    A line is speckled when the median |asymmetry| of its `candidate` centres (every
    test passed but the asymmetry's) exceeds `SPECKLE_MEDIAN` and the signed asymmetry
    decorrelates along the line within `max(2 width, 6)` scan lines; its bound is then
    `SPECKLE_SIGMAS` spreads of the asymmetry (1.4826 x its median absolute value)."""
    idx = np.flatnonzero(candidate & np.isfinite(asym))
    if idx.size < 32:
        return 0.0
    a = asym[idx]
    med = float(np.median(np.abs(a)))
    if med <= SPECKLE_MEDIAN:
        return 0.0
    lag = max(int(round(2.0 * width)), 6)
    i, j = _lag_pairs(idx, lag)
    if i.size < 16:
        return 0.0
    x, y = a[i], a[j]
    x, y = x - x.mean(), y - y.mean()
    rho = float(np.sum(x * y) / max(math.sqrt(float(np.sum(x * x) * np.sum(y * y))), 1e-300))
    if rho >= SPECKLE_CORRELATION:
        return 0.0
    return max(ASYMMETRY_MAX, SPECKLE_SIGMAS * 1.4826 * med)


def _local_line(y: np.ndarray, w: np.ndarray, half: int) -> tuple[np.ndarray, np.ndarray]:
    """Prediction of `y` at each scan line from a straight line fitted to the scan
    lines within +- `half` where `w` (bool) holds, and how many there are (prefix sums;
    a scan line's own value is in the fit only where `w` holds there)."""
    n = y.size
    x = np.arange(n, dtype=np.float64)
    wf = w.astype(np.float64)
    yw = np.where(w, y, 0.0)
    cols = np.stack([wf, wf * x, wf * x * x, yw, yw * x])
    c = np.zeros((5, n + 1))
    np.cumsum(cols, axis=1, out=c[:, 1:])
    lo = np.clip(np.arange(n) - half, 0, n)
    hi = np.clip(np.arange(n) + half + 1, 0, n)
    s0, s1, s2, t0, t1 = c[:, hi] - c[:, lo]
    det = s0 * s2 - s1 * s1
    ok = (s0 >= 2) & (det > 1e-9 * np.maximum(s0, 1.0) ** 2)
    safe = np.where(ok, det, 1.0)
    slope = (s0 * t1 - s1 * t0) / safe
    icpt = (s2 * t0 - s1 * t1) / safe
    return np.where(ok, icpt + slope * x, np.nan), np.where(ok, s0, 0.0)


def _local_parabola(y: np.ndarray, w: np.ndarray, half: int) -> tuple[np.ndarray, np.ndarray]:
    """The offset of `y` across the curve at each scan line where `w` (bool) holds from
    a parabola fitted to the scan lines within +- `half` where `w` holds (prefix sums of
    the normal equations; the offset along the scan line times cos of the curve's
    slope), and how many there are; NaN where fewer than 4 or degenerate."""
    n = y.size
    t = np.arange(n, dtype=np.float64) / max(n, 1)  # scaled for conditioning
    wf = w.astype(np.float64)
    yw = np.where(w, y, 0.0)
    cols = np.stack([wf * t**k for k in range(5)] + [yw * t**k for k in range(3)])
    c = np.zeros((8, n + 1))
    np.cumsum(cols, axis=1, out=c[:, 1:])
    lo = np.clip(np.arange(n) - half, 0, n)
    hi = np.clip(np.arange(n) + half + 1, 0, n)
    s = c[:, hi] - c[:, lo]
    a = np.stack([np.stack([s[i + j] for j in range(3)], -1) for i in range(3)], -2)
    ok = w & (s[0] >= 4) & (np.abs(np.linalg.det(a)) > 1e-300)
    a[~ok] = np.eye(3)
    p = np.linalg.solve(a, np.stack([s[5 + i] for i in range(3)], -1)[..., None])[..., 0]
    pred = p[:, 0] + p[:, 1] * t + p[:, 2] * t**2
    slope = (p[:, 1] + 2.0 * p[:, 2] * t) / max(n, 1)
    across = (y - pred) / np.sqrt(1.0 + slope**2)
    return np.where(ok, across, np.nan), np.where(ok, s[0], 0.0)


@dataclasses.dataclass(frozen=True)
class _Retry:
    """What the long-ridge search of `_extract_one` needs from a pass that found no
    line: the signal image, its noise, the region of interest, the line width, the
    orientation asked for and the colour candidates in score order."""

    img: np.ndarray
    noise: float
    roi: np.ndarray | None
    width: float
    orientation: str
    ranked: tuple[str, ...]


def _extract_track(
    image: Any,
    *,
    method: str = "steger",
    width_px: float | int | None = None,
    orientation: str = "auto",
    band_px: int | str | None = "auto",
    min_strength: float | int | None = None,
    saturation: float | int | None = None,
    mask: Any = None,
    channel: str = "auto",
    background: Any = None,
    normalise_background: bool = True,
    background_gain: float | int | str = 1.0,
    max_jump_px: float | None = None,
    min_segment: int | None = None,
    track: LongRidge | None = None,
    min_line: int | None = None,
    band: np.ndarray | None = None,
    signals: dict | None = None,
) -> tuple[StripeResult, _Retry | None]:
    """`extract_stripe` on one signal, from the coarse track or, given `track` (a
    long-ridge path in the scan frame of `orientation`), from that path. Also returns
    what a long-ridge search needs where no centre was found (None otherwise).
    `min_line`: scan lines the longest segment must span for the frame to hold a line
    (None: `_min_line`; the steep part of a line found already, `_steep.py`, needs only
    a segment's own minimum). `band`: (H, W) bool, where to look besides `mask` (the
    signal, and a gain map fitted inside `mask`, stay those of the whole image).
    `signals`: the signals of earlier passes over the same `image`, `background` and
    `mask`, by channel asked (filled here; never written to)."""
    _check_options(method, width_px, orientation, band_px, min_strength, saturation, channel)
    _check_gain(background_gain)
    asked = orientation
    width = _DEFAULT_WIDTH if width_px is None else float(width_px)
    key = (channel, width, normalise_background, str(background_gain))
    if signals is not None and key in signals:
        computed = signals[key]
    else:
        computed = _signal(
            image, background, channel, width, normalise_background, background_gain, mask
        )
        if signals is not None:
            signals[key] = computed
    img, sat_img, channel, unnormalised, off_level, off_signal, ranked = computed
    roi = as_mask(mask, img.shape)
    if band is not None:
        roi = band if roi is None else roi & band
    # the frame's maximum (the clipping level of an integer image without `saturation`)
    # from the same pass as the block average where the signal is the plain image
    top = None
    if saturation is None and sat_img is img and np.issubdtype(img.dtype, np.integer):
        small, top = downsample(img, with_max=True)
    else:
        small = downsample(img)
    mask_small = None
    if roi is not None:
        mask_small = downsample(roi.astype(np.float32)) > 0.5
    d = ridge_offset(width)
    integer = bool(np.issubdtype(img.dtype, np.integer))
    noise = _frame_noise(img)
    floor = 4.0 * math.hypot(0.354 * noise, 0.35 if integer else 0.0)
    auto_dir, angle, coherence = scan_direction(small, d, mask_small, floor)
    ambiguous = is_ambiguous(coherence)
    if orientation == "auto":
        orientation = auto_dir
    extra = dict(channel=channel, ambiguous=ambiguous, normal_angle_deg=angle)
    flat = img.reshape(-1)
    flat_sat = sat_img.reshape(-1)
    if orientation == "vertical-scan":
        shape = img.shape
        stride_y, stride_x = img.shape[1], 1
    else:
        shape = img.shape[::-1]
        small = np.ascontiguousarray(small.T)
        if mask_small is not None:
            mask_small = np.ascontiguousarray(mask_small.T)
        stride_y, stride_x = 1, img.shape[1]

    def gather(rows: np.ndarray, cols: np.ndarray, source=None) -> np.ndarray:
        """The scan-frame image (`flat`, or `source`) at integer (row, column) index
        arrays (broadcast)."""
        return np.take(flat if source is None else source, rows * stride_y + cols * stride_x)

    retry = _Retry(img, noise, roi, width, asked, ranked) if track is None else None
    if track is None:
        coarse = coarse_track(
            small,
            shape[0],
            shape[1],
            # the line reads wider along a scan line that crosses it at a slant (a 45
            # degree clipped line: a 20 px plateau for 14 px across it), and the
            # two-sided response must reach past it
            width_px=width if ambiguous else width * _slant(angle, orientation),
            integer_input=integer,
            pixel_noise=noise,
            mask_small=mask_small,
        )
    else:
        coarse = path_track(track, width, shape[0], _min_line(width, min_segment, shape[1]))
    local_noise = None
    if track is not None and coarse.found and min_strength is None:
        local_noise = _noise_along(gather, coarse.centre, shape[0], width, integer)
    if not coarse.found:
        return _empty(shape[1], orientation, method, **extra), retry
    sat_level = saturation
    if sat_level is None and np.issubdtype(sat_img.dtype, np.integer):
        sat_level = float(sat_img.max()) if top is None else top

    speckle = 0.0
    # (only with a laser-off image, whose albedo the signal is divided by: in a laser-on
    # image alone a printed pattern modulates the line at the speckle's scale)
    if method == "steger" and off_level is not None and normalise_background:
        plain = None if sat_level is None else functools.partial(gather, source=flat_sat)
        speckle = _speckle_contrast(gather, coarse, shape[0], width, plain, sat_level)
        if speckle > SPECKLE_CONTRAST:
            # a speckled line: the signal smoothed along the line, over several grains
            img = _along_line(img, angle + 90.0, SPECKLE_SMOOTH * width)
            flat = img.reshape(-1)

    candidate = [None]  # the last pass's centres before the asymmetry test

    def run(
        w: float, source=img, asym_max=None
    ) -> tuple[ScanLines, np.ndarray, np.ndarray]:
        asym_max = asym_bound if asym_max is None else asym_max
        if method == "centroid":
            flat_s = source.reshape(-1)
            lines = centroid_band(lambda r, c: gather(r, c, flat_s), shape, coarse.centre, w)
            noise_level = 6.0 * noise
        else:
            scan = source if orientation == "vertical-scan" else source.T
            if band_px is None:
                lines = steger_full(np.ascontiguousarray(scan), w, coarse.centre,
                                    coarse.tolerance)  # fmt: skip
            else:
                band = None if band_px == "auto" else int(band_px)
                lines = steger_band(scan, coarse.centre, w, band)
            sigma = max(w / (2.0 * math.sqrt(3.0)), 0.7)
            # Std of sigma² G''*noise for white noise is sqrt(3 / (16 pi)) noise / sigma.
            noise_level = 8.0 * 0.2443 * noise / sigma
        thr = np.full(
            shape[1], max(noise_level if min_strength is None else float(min_strength), 1e-12)
        )
        if local_noise is not None:
            # a long-ridge track has shown the line: each centre is judged against the
            # noise where it lies (`_noise_along`), never above the frame's estimate nor
            # below a quarter of it (a print of albedo 0.04 has 1/5 of the white's shot
            # noise, and the frame's median lies between; an area clipped to 0 beside
            # the line, as in a colour difference, has none)
            thr = thr * np.clip(local_noise / noise, _LOCAL_NOISE_MIN, 1.0)
        y = lines.y
        valid = lines.found & coarse.support & (lines.strength >= thr)
        valid &= np.abs(y - coarse.centre) <= coarse.tolerance
        valid &= (y >= -0.5) & (y <= shape[0] - 0.5)
        if lines.asym is not None:
            candidate[0] = valid.copy()  # (the test below narrows `valid` in place)
            valid &= np.abs(lines.asym) <= asym_max  # (NaN: refused)
        return lines, valid, thr

    def clipped(lines: ScanLines, valid: np.ndarray) -> np.ndarray:
        """Scan lines of `valid` with at least two clipped pixels among the three at the
        peak (the chosen line point's row; the coarse track's where none was found)."""
        if sat_level is None or not valid.any():
            return np.zeros(shape[1], bool)
        if _fast.enabled:
            return valid & _fast.clipped_lines(
                flat_sat, stride_y, stride_x, shape[0], lines.found, lines.row, coarse.centre,
                float(sat_level),
            )  # fmt: skip
        out = np.zeros(shape[1], bool)
        for at in (np.where(lines.found, lines.row, coarse.centre), coarse.centre):
            row = np.clip(np.rint(at).astype(np.intp), 0, shape[0] - 1)
            near_rows = np.clip(row[None, :] + np.arange(-1, 2)[:, None], 0, shape[0] - 1)
            near = gather(near_rows, np.arange(shape[1]), flat_sat)
            out |= np.count_nonzero(near >= sat_level, axis=0) >= 2
        return valid & out

    asym_bound = ASYMMETRY_MAX
    lines, valid, thr = run(width)
    if width_px is None:
        # the width of the unclipped part of the line (a clipped core looks wider)
        plain = valid & ~clipped(lines, coarse.support | valid) & np.isfinite(lines.width)
        if plain.sum() >= 8:
            measured = float(np.median(lines.width[plain]))
            if math.isfinite(measured) and abs(measured - width) > 0.3 * width:
                width = min(max(measured, 1.5), 100.0)
                lines, valid, thr = run(width)
    if method == "steger" and lines.asym is not None and speckle > SPECKLE_CONTRAST:
        # a speckled line: its asymmetric profiles are speckle, not brightness steps
        bound = _speckle_bound(lines.asym, candidate[0], width)
        if bound > asym_bound:
            asym_bound = bound
            lines, valid, thr = run(width)

    # Clipped scan lines. With a laser-off image every one on the track, accepted or
    # not: the first pass, at the unclipped line's width, refuses most of a wide flat
    # top (its second derivative vanishes on the plateau and the line points it finds
    # sit on the plateau's rims); the plateau's own pass decides, and the laser-off
    # image shows the albedo at the plateau's rims (`rims_even`). Without one, only
    # the ones the first pass accepted: the laser-on image cannot show an albedo edge
    # right under a rim (a line along a narrow white strip between black ones, as on a
    # ChArUco board: a symmetric plateau 1 px off the line).
    first_pass = valid
    rim_job = None  # step 4b, after the step fit
    saturated = clipped(lines, coarse.support)
    plateau = np.zeros(shape[1], np.intp)  # clipped pixels about the track, per scan line
    if saturated.any():
        cols = np.arange(shape[1])
        row = np.clip(np.rint(coarse.centre).astype(np.intp), 0, shape[0] - 1)
        if method == "steger" and saturated.any():
            reach = int(math.ceil(4 * width)) + FACTOR
            rows = np.clip(row[None, :] + np.arange(-reach, reach + 1)[:, None], 0, shape[0] - 1)
            plateau = np.count_nonzero(gather(rows, cols, flat_sat) >= sat_level, axis=0)
            # the plateau's width from the clipped scan lines the first pass accepted
            # (surely the line), from all clipped ones where fewer than 8
            sure = saturated & first_pass if (saturated & first_pass).sum() >= 8 else saturated
            wide = float(np.median(plateau[sure])) + width
            # The plateau's pass: on the signal before any albedo normalisation (a clipped
            # pixel holds no albedo x laser product: divided by the laser-off level, the
            # plateau would step by the albedo ratio where the line crosses a checker
            # edge).
            lines2, valid2, _ = run(wide, unnormalised)
            lines = ScanLines(
                y=np.where(saturated, lines2.y, lines.y),
                strength=np.where(saturated, lines2.strength, lines.strength),
                width=np.where(saturated, lines2.width, lines.width),
                found=np.where(saturated, lines2.found, lines.found),
                row=lines.row,
                asym=None if lines.asym is None else np.where(saturated, lines2.asym, lines.asym),
                ny=None if lines.ny is None else np.where(saturated, lines2.ny, lines.ny),
            )
            valid = np.where(saturated, valid2, valid)
            # The strict tests: the asymmetry bound held at the shift in pixels it allows
            # a line of the default width (~0.25 px: the asymmetry of a given shift falls
            # as the profile widens), and the same albedo at both rims.
            asym_max = asym_bound * min(profile_std(_DEFAULT_WIDTH) / profile_std(wide), 1.0)
            even = np.abs(np.nan_to_num(lines.asym, nan=np.inf)) <= asym_max
            if off_level is None:
                # Without a laser-off image: the laser-on image 2 FWHM beyond the rims
                # (every clipped scan line), and for the scan lines the first pass
                # refused, no albedo change along the line nearby either (a line along a
                # narrow white strip between black ones, as on a ChArUco board, has a
                # symmetric plateau 1 px off the line, with black on both sides). On a
                # grey signal the rim test applies to the ones the first pass accepted
                # too (with the plateau pass's own tests alone they were 0.115 px RMS off
                # the exact line on the paper rig's grey single checkerboard views; with
                # it 80 % of them are kept, at 0.044 px); the capture finds the points
                # next to a clipped line from its clipped pixels (`clipped_pixels` in
                # `capture/_laser.py`), not from these centres.
                rims, left, right = rims_even(
                    gather, flat_sat, lines.y, plateau, lines.ny, 2.0 * width,
                    max(3.0 * noise, RIM_FLOOR * sat_level), shape[0],
                )  # fmt: skip
                reach = int(math.ceil(np.median(plateau[saturated]) + 4.0 * width))
                plain = plain_surroundings(
                    left, right, saturated & np.isfinite(lines.y), reach, 3.0 * noise
                )
                if channel == "grey":
                    even &= rims & (first_pass | plain)
                else:
                    # colour (X minus the others): the first pass's centres keep the
                    # plateau pass's own tests, as before (a colour JPEG of a ChArUco
                    # board keeps its clipped line at 0.050 px RMS so, and loses it to
                    # the rim test: the JPEG's chroma puts laser light beside the line)
                    even = (even & rims & plain) | first_pass
            else:  # the laser-off image at the rims themselves (2 px in to 2 px out)
                even &= rims_even(
                    gather, off_level.reshape(-1), lines.y, plateau, lines.ny, -2.0,
                    3.0 * estimate_noise(off_level), shape[0],
                )[0]  # fmt: skip
            valid &= ~saturated | even
            if off_signal is not None and not channel.endswith("-minus-others"):
                # Step 4b: the clipped scan lines refused above (a checker edge under the
                # plateau or near a rim) that the step fit below does not recover either,
                # read from the plateau's flanks, the albedo taken out by the laser-off
                # level (`_rims.py`)
                rim_todo = saturated & ~valid & coarse.support
                if rim_todo.any() and (saturated & valid).sum() >= 8:
                    rows_w = np.clip(
                        row[None, :] + np.arange(-reach, reach + 1)[:, None], 0, shape[0] - 1
                    )
                    spread = edge_spread(off_signal, 3.0 * noise).reshape(-1)
                    rim_job = functools.partial(
                        rim_centres,
                        gather(rows_w, cols, flat_sat).astype(np.float64),
                        gather(rows_w, cols, off_signal.reshape(-1)).astype(np.float64),
                        gather(rows_w, cols, spread).astype(np.float64),
                        float(sat_level), row, reach, lines.y.copy(), saturated & valid,
                        noise=noise, floor=3.0 * noise,
                    )  # fmt: skip
            saturated &= valid

    # Width consistency: a line keeps its width along itself (blur across a Scheimpflug
    # field changes it by a few per cent); a profile much narrower or wider than the
    # line's median is a distorted one (a step under it, a glint beside it).
    # (a width of 0 is no measurement: where a profile gives none, e.g. a line over the
    # print of a ChArUco board found by its long-ridge track, the median must not be 0)
    widths = lines.width[valid & ~saturated & np.isfinite(lines.width) & (lines.width > 0)]
    med = _median(widths) if widths.size >= 8 else math.nan
    if widths.size >= 8 and method == "steger":
        wv = lines.width  # (NaN: refused)
        valid &= saturated | ((wv >= WIDTH_RATIO[0] * med) & (wv <= WIDTH_RATIO[1] * med))

    y_fit, refit_sigma = lines.y, np.full(shape[1], np.inf)
    if method == "steger" and widths.size >= 8:
        # the step fit's residual test needs the noise that is in the profiles: JPEG
        # keeps it at block scale (`block_noise`), where it reads well above the pixel
        # estimate (2-3x at quality 95-85; 1.1-1.2x without compression, where the
        # pixel estimate stays)
        # (a callable: read only where there is a profile to fit, which a plain frame
        # seldom has; the block pass costs a full-frame read)
        def fit_noise() -> float:
            block = _block_noise(img)
            return block if block > 1.5 * noise else noise

        y_fit, valid, refit_sigma = refit_steps(
            gather, shape, lines, valid, saturated, coarse, med, fit_noise
        )
    rim = rim_one = np.zeros(shape[1], bool)
    if rim_job is not None and (rim_todo & ~valid).any():
        y_rim, one_side = rim_job(todo=rim_todo & ~valid)
        rim = np.isfinite(y_rim)
        # one flank alone: only between centres of both flanks or of the plateau, and on
        # the straight line through them
        rim &= ~one_side | bracketed(one_side & rim, (valid | rim) & ~one_side)
        y_fit = np.where(rim, y_rim, y_fit)
        anchor = (valid | rim) & ~one_side
        pred, count = _local_line(np.where(anchor, y_fit, 0.0), anchor, ONE_SIDE_REACH)
        rim &= ~one_side | ((count >= 6) & (np.abs(y_fit - pred) <= ONE_SIDE_LINE))
        # and only between centres of the plateau: at the line's ends they would take
        # the end trim of `link_segments` that the centres there need (a line's end
        # pulls them: 0.14 px on a stage target's line)
        rim = bracketed(rim, valid, shape[1])
        rim_one = rim & one_side
        valid |= rim
        saturated |= rim
    albedo_refused, albedo_bad = False, np.zeros(shape[1], bool)
    if background is None and channel.endswith("-minus-others") and valid.any():
        # The laser's colour less the others holds albedo x laser light alone: an albedo
        # edge along the line, inside its profile (a marker's bit border), cuts the
        # profile into a narrower, nearly symmetric one up to 1 px off the line, and no
        # ambient light beside it shows the step to the profile tests or the step fit.
        # The other channels show the albedo (x the room light): a centre is kept only
        # where it is about the same on both sides of the line (`rims_even`: the means of
        # 5 samples a pixel apart from 0.1 FWHM out differ by at most `ALBEDO_EVEN_MAX`
        # in log; levels under 5 % of the bright print count as 5 %).
        # A clipped profile (a clipped pixel within its reach) reaches farther: its
        # plateau is the full scale less albedo x room light, and its rims and flanks
        # lie where albedo x (room light + laser) crosses the full scale, farther out
        # over the brighter albedo. An albedo edge along the line anywhere out to its
        # rims pulls the centre towards the brighter side while the profile stays
        # symmetric in shape (a 153-fold clipped 5 px line with a checker edge 6 px
        # from it: 0.65 px off the exact line at an asymmetry of 0.001). Its albedo is
        # read from 0.1 FWHM out to one pixel beyond where the signal falls under
        # `CLIPPED_PROFILE_FRAC` of its peak on the farther side (`profile_reach`,
        # `sides_even`), every pixel of it.
        others = _others_mean(image, channel)
        flat_o = others.reshape(-1)
        level = float(np.percentile(others, 99))
        floor_o = max(3.0 * estimate_noise(others), RIM_FLOOR * level)
        even, _, _ = rims_even(
            gather, flat_o, y_fit, np.zeros(shape[1]), lines.ny, 0.1 * width, floor_o,
            shape[0], ratio_max=ALBEDO_EVEN_MAX,
        )  # fmt: skip
        clipped_profile = saturated | (plateau > 0)
        far = None
        if clipped_profile.any():
            far = profile_reach(gather, y_fit, shape[0], int(math.ceil(3.0 * width)),
                                CLIPPED_PROFILE_FRAC) + 1  # fmt: skip
            even_far = sides_even(gather, flat_o, y_fit, 0.1 * width, far, floor_o, shape[0],
                                  ALBEDO_EVEN_MAX)  # fmt: skip
            even = np.where(clipped_profile, even_far, even)
        # a line found and refused here is the frame's line: no other channel or track
        # is searched for one (the plain colour or a long ridge would give its pulled
        # centres, or the print's)
        albedo_bad = valid & ~even
        albedo_refused = bool(albedo_bad.any())
        # (a clipped centre refused here still joins the linking, see below)
        valid &= even | clipped_profile
        albedo_bad &= clipped_profile
    x = np.arange(shape[1], dtype=np.float64)
    y = np.where(valid, y_fit, np.nan)
    if roi is not None and valid.any():
        u_, v_ = (x, y) if orientation == "vertical-scan" else (y, x)
        iu = np.clip(np.rint(np.nan_to_num(u_)).astype(np.intp), 0, img.shape[1] - 1)
        iv = np.clip(np.rint(np.nan_to_num(v_)).astype(np.intp), 0, img.shape[0] - 1)
        valid &= roi[iv, iu]
    valid &= consistent(y, valid)
    jump = max(2.0, 0.5 * width) if max_jump_px is None else float(max_jump_px)
    min_pts = max(8, int(round(2 * width))) if min_segment is None else int(min_segment)
    if min_line is None:
        min_line = _min_line(width, min_segment, shape[1])
    sigma_s = max(width / (2.0 * math.sqrt(3.0)), 0.7)
    if track is not None:
        # the centres beside a refused scan line of a long-ridge track (`_TRACK_TRIM`)
        # are judged against a straight line through the others within +- 40 scan
        # lines: farther than max(0.25 px, 3 x their robust spread), an edge pulls them
        refused = coarse.support & ~valid
        near = np.convolve(refused.astype(np.float64), np.ones(2 * _TRACK_TRIM + 1), "same")
        near = valid & (near > 0.5)
        interior = valid & ~near
        if interior.sum() >= 12:
            pred, count = _local_line(np.where(valid, y_fit, 0.0), interior, 40)
            r = np.abs(y_fit - pred)
            judged = interior & (count >= 6) & np.isfinite(r)
            if judged.any():
                lim = max(0.25, 3.0 * 1.4826 * float(np.median(r[judged])))
                valid &= ~(near & (count >= 6) & ~(r <= lim))
    link = dict(
        max_jump_px=jump,
        max_gap=2,
        min_points=min_pts,
        # (a long-ridge track: each centre has passed the noise test where it lies, and
        # the track is the line's evidence; over a black print the line holds 8-16 noise
        # stds, and a hysteresis at 16 kept 79 of its 224 centres at 95 deg)
        high=1.0 if track is not None else _HIGH,
        trim=int(math.ceil(2.0 * sigma_s)),
    )

    def linked_segments(valid):
        # a long-ridge track has shown the line already (`path_track`): each segment on
        # it is judged alone (the print can cut the line into pieces shorter than this)
        segment, linked = link_segments(
            y, valid, lines.strength / thr, **link,
            min_line=min_pts if track is not None else min_line,
        )  # fmt: skip
        if track is None and not linked.any() and valid.any():
            # no one segment spans `min_line`: the pieces of a line cut by the print (a
            # clipped line refused where its plateau's rims straddle a checker edge) are
            # the frame's line where they continue one another (`_chain_span`)
            segment, linked = link_segments(y, valid, lines.strength / thr, **link, min_line=0)
            if _chain_span(y, segment, jump, min_line) < min_line:
                segment, linked = np.full_like(segment, -1), np.zeros_like(linked)
        return segment, linked

    rim &= valid
    segment, linked = linked_segments(valid & ~rim)
    if rim.any() and linked.any():
        # The line stands without the flank centres (step 4b): its centres are those it
        # has without them (the flank centres would join pieces the linking drops, and
        # take the end trim that a line's ends need), and a flank centre is added only
        # between its centres, on the straight line through them within +- 60 scan
        # lines (within 3 robust spreads of theirs, at least 0.1 px; one flank alone
        # 0.05 px).
        pred, count = _local_line(np.where(linked, y_fit, 0.0), linked, 3 * ONE_SIDE_REACH)
        r = np.abs(y_fit - pred)
        own = linked & (count >= 6) & np.isfinite(r)
        lim = max(0.1, 3.0 * 1.4826 * float(np.median(r[own]))) if own.any() else 0.1
        lim = np.where(rim_one, min(lim, ONE_SIDE_LINE), lim)
        add = bracketed(rim, linked, shape[1]) & (count >= 6) & (r <= lim)
        idx = np.arange(shape[1])
        prev = np.maximum.accumulate(np.where(linked, idx, 0))
        segment = np.where(add, segment[prev], segment)
        linked = linked | add
        rim &= add
    elif rim.any():  # the flank centres make the line (a board's edges cut it short)
        segment, linked = linked_segments(valid)
        rim &= linked
    # a centre read from one flank (step 4b) only between others of its linked segment
    if rim_one.any():
        linked &= ~rim_one | bracketed(rim_one & linked, linked & ~rim_one)
    # the centres the albedo test refused (colour, no laser-off image) are part of the
    # line while it is linked (a line along a column of checker edges is refused over
    # long stretches, and its pieces alone would be too short to count as a line)
    linked &= ~albedo_bad
    segment = np.where(linked, segment, -1)
    valid = linked
    saturated &= valid
    y = np.where(valid, y_fit, np.nan)
    x = np.where(valid, x, np.nan)
    uv = np.stack([x, y], axis=1) if orientation == "vertical-scan" else np.stack([y, x], axis=1)
    asym = lines.asym
    asym = np.zeros(shape[1]) if asym is None else np.where(np.isnan(asym), 1.0, asym)
    confidence = np.clip(lines.strength / (4.0 * thr), 0.0, 1.0) * np.clip(
        1.0 - np.abs(asym) / asym_bound, 0.0, 1.0
    )
    # centres of the step fit: at most 0.5 (a model fit, not a symmetric ridge), lower
    # as the centre's standard error approaches the accepted limit
    refit = np.isfinite(refit_sigma)
    if refit.any():
        confidence = np.where(
            refit, 0.5 * np.clip(1.0 - refit_sigma / MAX_SIGMA_C, 0.05, 1.0), confidence
        )
    # centres read from the plateau's flanks (step 4b): 0.5, a model reading too
    if rim.any():
        confidence = np.where(rim, 0.5, confidence)
    speckle_px = 0.0
    if speckle > SPECKLE_CONTRAST and valid.sum() >= 8:
        # the centres' scatter across the line about a parabola through their
        # neighbours (what moves a stripe point off its board, not along it). Speckle
        # and the smoothing along the line correlate the centres' errors over tens of
        # scan lines: a fit over +-3 widths followed them and read 0.79-0.87 of the true
        # scatter (render_capture pairs, tests/test_speckle_capture.py), +-12 widths
        # 0.93; a parabola, not a line, so that a curved line's bend is not read as
        # scatter.
        across, count = _local_parabola(
            np.where(valid, y_fit, 0.0), valid, max(int(12 * width), 60)
        )
        near = count >= 8
        if near.any():
            across = across[near]
            speckle_px = 1.4826 * float(np.median(np.abs(across)))
    return StripeResult(
        uv=uv,
        strength=np.where(valid, lines.strength, 0.0),
        width=np.where(valid, lines.width, np.nan),
        valid=valid,
        saturated=saturated,
        orientation=orientation,
        method=method,
        confidence=np.where(valid, confidence, 0.0),
        segment=segment,
        speckle_px=speckle_px,
        **extra,
    ), (None if valid.any() or albedo_refused else retry)


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
