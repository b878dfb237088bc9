"""One image of a target (and perhaps the laser line): the target found in it, the laser
line inside the target's region, and the points the line may have displaced left out.

This is the per-image logic of a capture folder's views ([`detect_captures`][]) and of
the table target's steps ([`detect_stage_target`][]): one grey image of target and line
(no laser-off image) keeps the line out of a circle grid's dots and the points out of
the line's reach (`_laser.py`), a laser-off image beside it lets both be detected as in
a pair, a colour JPEG's points are kept out of the line's reach grown by a chroma block.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable

import cv2
import numpy as np

from ..stripe._image import channel_image, estimate_noise
from ..targets._charuco import _spans_plane
from ..targets._circles import CircleGrid, circle_diameters_mm
from ..targets._result import DetectionResult
from ..targets._target import Target, detect_target
from ._albedo import laser_off_model
from ._laser import (
    JPEG_BLOCK_PX,
    clipped_pixels,
    displaced,
    laser_in_board,
    laser_removed,
    near_laser,
    off_local_grid,
    target_holes,
)
from ._region import board_region, board_stripe, laser_free

__all__ = ["ImageLine", "dot_diameters_mm", "find_target", "line_and_points"]

# The pixels within this many line widths (FWHM) of a clipped line's own pixels are left
# out of the drawn laser-off image's level fit: a line clipped 150-fold on white (a
# plateau of ~14 px for 5 px) falls to the noise ~2 FWHM from its centre.
_LINE_REACH_FWHM = 6.0
_BGR = {"blue": 0, "green": 1, "red": 2}
# A colour JPEG pair is read in luma; centres where the board image's luma, within
# `_DARK_REACH` px across the line, falls under `_DARK_PRINT` of its bright level (the
# 90th percentile on the board) lie on the dark print or next to it (see `_dark_print`).
_DARK_PRINT = 0.3
_DARK_REACH = 3
# A laser line found on a colour single image is kept only where it is a ridge in the
# image's brightest channel, its median height (centre over the brighter of the two
# sides 2 FWHM away) above `_RIDGE_K` times that channel's noise: see `_not_a_line`.
_RIDGE_K = 5.0


def _sample(plane: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear values of `plane` at `(u, v)` (clamped to the image)."""
    h, w = plane.shape
    u = np.clip(u, 0.0, w - 1.001)
    v = np.clip(v, 0.0, h - 1.001)
    u0, v0 = np.floor(u).astype(np.intp), np.floor(v).astype(np.intp)
    a, b = u - u0, v - v0
    return ((1 - a) * (1 - b) * plane[v0, u0] + a * (1 - b) * plane[v0, u0 + 1]
            + (1 - a) * b * plane[v0 + 1, u0] + a * b * plane[v0 + 1, u0 + 1])  # fmt: skip


def _not_a_line(image, stripe, uv: np.ndarray, width: float, pitch: float,
                colour_single: bool) -> str:  # fmt: skip
    """Why the centres `uv` the extractor found on the board are no laser line ("" when
    they may be one).

    - Wider than half the target's pitch (FWHM `width` against `pitch`, px): a line that
      wide cannot be told from the print (a white square between dark ones is a ridge
      of about a pitch); `clipped_pixels` assumes the same.
    - Shorter than one pitch end to end: the print's own features (a white gap between
      two dark squares, a glint) make ridges that short; a laser plane crosses a board.
    - `colour_single` (board and line in one colour image): not a ridge in the image's
      brightest channel. A laser adds light; the extractor reads a colour image in the
      channel, or the channel less the others, where the line stands out most, and
      there the colour fringes of the lens and of JPEG's half-resolution chroma along
      the print's and the panel's edges are ridges of a few grey levels. Measured on
      srv-turntable-webcam's 27 laser-free images: such "lines" were found in 8 (up to
      132 centres, along the panel's top edge), their median height in the brightest
      channel -17 to -5.5 grey levels; the real green lines of its laser images and of
      hjamal3-greenstripe 19-85 levels, the channel's noise 0.6-1.2.
    """
    fin = np.all(np.isfinite(uv), axis=1)
    uv = uv[fin]
    if pitch > 0 and np.isfinite(width) and width > 0.5 * pitch:
        return f"{width:.0f} px wide, more than half the target's pitch ({pitch:.0f} px)"
    a = 0 if stripe.orientation != "horizontal-scan" else 1  # along the line
    extent = float(np.ptp(uv[:, a])) if len(uv) else 0.0
    if pitch > 0 and extent < pitch:
        return f"{extent:.0f} px long, shorter than the target's pitch ({pitch:.0f} px)"
    if not colour_single or np.ndim(image) != 3:
        return ""
    plane = np.asarray(image)[:, :, :3].max(axis=2)
    d = max(2.0 * (width if np.isfinite(width) else 5.0), 3.0)
    u, v = uv[:, 0], uv[:, 1]
    du, dv = (0.0, d) if a == 0 else (d, 0.0)
    f = plane.astype(np.float32)
    height = _sample(f, u, v) - np.maximum(_sample(f, u - du, v - dv), _sample(f, u + du, v + dv))
    noise = estimate_noise(plane)
    h = float(np.median(height))
    if h <= _RIDGE_K * noise:
        return (f"no ridge in the brightest channel (median height {h:.1f} grey levels, "
                f"noise {noise:.2f}): colour fringes along edges, not a laser")  # fmt: skip
    return ""


def _default_margin(uv: np.ndarray, target: Target) -> float:
    """Half a target pitch in pixels (board region growth), at least 3 px."""
    ok = np.all(np.isfinite(uv), axis=1)
    if ok.sum() < 2:
        return 3.0
    xy = target.points_mm[ok, :2]
    span_mm = float(np.ptp(xy, axis=0).max())
    span_px = float(np.ptp(uv[ok], axis=0).max())
    pitch = float(getattr(target, "square_mm", None) or target.spacing_mm)
    return max(3.0, 0.5 * pitch * span_px / max(span_mm, 1e-12))


def _is_jpeg(path: str) -> bool:
    """Whether the file is stored as JPEG (by its name: `.jpg`, `.jpeg`, any case)."""
    return os.path.splitext(os.fspath(path))[1].lower() in (".jpg", ".jpeg")


def _too_few(res, target, min_points: int) -> str:
    """Why a detection cannot be used ("" when it can)."""
    n = int(res.mask.sum())
    if not res.found:
        return res.message or f"{target.kind} not found"
    if n < min_points:
        return f"only {n} target points found; {min_points} needed"
    pitch = float(getattr(target, "square_mm", None) or target.spacing_mm)
    if not _spans_plane(np.asarray(target.points_mm, np.float64)[res.mask, :2], pitch):
        # a board's pose needs its points to span the board's plane, not one line of it
        return f"the {n} target points found lie on one line of the board: no pose"
    return ""


def _hole_margin(uv: np.ndarray, target: Target, stripe_width_px: float | None) -> float:
    """Growth of the dot holes beyond the dots' edges: a quarter of the gap between
    neighbouring dots (half of it stays free for the line), at least twice a given
    stripe width."""
    if not isinstance(target, CircleGrid):
        return 0.0
    ok = np.all(np.isfinite(uv), axis=1)
    xy = target.points_mm[ok, :2]
    span_mm = float(np.ptp(xy, axis=0).max()) if ok.sum() >= 2 else 0.0
    if span_mm <= 0:
        return 3.0
    px_per_mm = float(np.ptp(uv[ok], axis=0).max()) / span_mm
    gap_mm = target.spacing_mm - target.diameter_mm
    m = 0.25 * gap_mm * px_per_mm
    return max(m, 2.0 * float(stripe_width_px)) if stripe_width_px is not None else m


@dataclasses.dataclass
class ImageLine:
    """The laser line on a detected target and the target points left after it
    ([`line_and_points`][]).

    **Fields:**
    - `corners`: `(M, 2)` target points, NaN where not found or within the line's reach.
    - `stripe_uv`: `(K, 2)` laser centres on the target's region (empty: no line).
    - `stripe`: the extractor's `StripeResult` the centres came from (None: none run).
    - `mask`, `hull`: the target's region (`board_region`) and its outline.
    - `reason`: why the image cannot be used ("" when it can: too few points are left
      once those under the line are dropped).
    """

    corners: np.ndarray
    stripe_uv: np.ndarray
    stripe: object
    mask: np.ndarray
    hull: np.ndarray
    reason: str = ""


def _pitch_px(corners: np.ndarray) -> float:
    """The median distance (px) from each found point to its nearest neighbour."""
    uv = corners[np.all(np.isfinite(corners), axis=1)]
    if len(uv) < 2:
        return 0.0
    d = np.linalg.norm(uv[:, None] - uv[None], axis=2)
    np.fill_diagonal(d, np.inf)
    return float(np.median(d.min(axis=1)))


def _dark_print(board, mask: np.ndarray, uv: np.ndarray, orientation: str) -> np.ndarray:
    """Which centres `uv` of a colour JPEG pair's line, read in luma, lie on the dark
    print or next to it: within `_DARK_REACH` px across the line (along the scan lines
    of `orientation`), the board image's luma falls under `_DARK_PRINT` of its bright
    level. The laser adds 0.3 x its red level to luma, so over a 0.08 albedo print the
    line is 3-4 grey levels in luma noise ~0.7: its centres there were 0.14-0.25 px RMS
    off the exact line, up to 0.66 px (checkerboard and ChArUco scenes), and with the
    room light off in the stripe image those next to the print's edges up to 0.69 px
    (a circle grid's dots 0.64 px). The centres kept were within 0.27 px, 0.02-0.05 px
    RMS, with the room light low, off or bright. (Read in the laser's own channel, the
    line's colour lives in the JPEG's chroma, kept at half resolution and quantised:
    its centres were up to 1.1 px off over the dark print, 1.3 px next to its edges.)"""
    plane = np.asarray(channel_image(np.asarray(board), "grey")[0], np.float32)
    bright = float(np.percentile(plane[mask], 90)) if mask.any() else float(plane.max())
    r = _DARK_REACH
    across = (2 * r + 1, 1) if orientation == "vertical-scan" else (1, 2 * r + 1)
    low = cv2.erode(plane, np.ones(across, np.uint8))  # the darkest within reach
    iu = np.clip(np.rint(uv[:, 0]).astype(np.intp), 0, plane.shape[1] - 1)
    iv = np.clip(np.rint(uv[:, 1]).astype(np.intp), 0, plane.shape[0] - 1)
    return low[iv, iu] < _DARK_PRINT * bright


def find_target(image, off, target: Target, *, single: bool, min_points: int,
                mirrored: bool) -> tuple[DetectionResult, np.ndarray | None, str]:  # fmt: skip
    """Detect the target in one image of target (and perhaps laser line).

    The target is detected in a laser-free image where there is one (`off`, the same
    pose with the laser off); a grey single image of a circle grid without one: in the
    image with the line taken out by an opening (`laser_removed`: a line across the dots
    splits their blobs and the grid is lost); the dots it crossed are dropped later
    (`near_laser`, in [`line_and_points`][]).

    **Arguments:**
    - `image`: the image (board and line in one when `single`); `off`: its laser-off
      image, or None.
    - `target`, `min_points`, `mirrored`: as for `detect_captures`.

    **Returns:** `(result, opened, reason)`: the detection, the opened image (None when
    not used) and why the detection cannot be used ("" when it can).
    """
    found_in, opened = image if off is None else off, None
    if off is None and single and isinstance(target, CircleGrid) and laser_in_board(image):
        opened = laser_removed(image, target)
        found_in = image if opened is None else opened
    # the channel minimum keeps a coloured laser out of an image that holds one; a laser-off
    # image (a pair's board image, a laser-off image) is read in luma, which has the
    # better signal (JPEG keeps it at full resolution, the colours at half)
    lit = single and off is None
    res = detect_target(laser_free(found_in) if lit else found_in, target, mirrored=mirrored)
    return res, opened, _too_few(res, target, min_points)


def dot_diameters_mm(image, off, opened, target: Target, res: DetectionResult) -> list[float]:
    """A circle grid's printed dot diameters (mm) measured in the image its grid was found
    in ([`find_target`][]: the laser-off image, else the opened one, else the image), one
    per dot that could be measured ([`circle_diameters_mm`][]); `[]` for other targets."""
    if not isinstance(target, CircleGrid):
        return []
    found_in = off if off is not None else (opened if opened is not None else image)
    d = circle_diameters_mm(laser_free(found_in), target, res.corners_px)
    return [float(x) for x in d[np.isfinite(d)]]


def line_and_points(
    image,
    off,
    simg,
    opened,
    res: DetectionResult,
    target: Target,
    *,
    single: bool,
    jpeg: bool,
    stripe_width_px: float | None,
    margin_px: float | None,
    min_points: int,
    note: Callable[[str], None],
) -> ImageLine:
    """The laser line inside a detected target's region, and the target points out of
    its reach ([`find_target`][] gave `res` and `opened`).

    One grey image of target and line (no laser-off image): the line is kept out of the
    dots, and the points out of the line's reach (`_laser.py`); a colour JPEG keeps some
    of the line in every channel (`_laser.py`): its points are kept out of the line's
    reach too, grown by a chroma block.
    A pair's stripe image is read against its board image, a laser-off image of the same
    pose at its own exposure and room light (`background_gain="auto"`); a colour JPEG
    pair is read in luma (`channel="grey"`) and drops its centres on the dark print
    and next to it (`_dark_print`).

    **Arguments:**
    - `image`, `off`, `opened`: as for and from `find_target`; `simg`: the image the
      line is extracted from (`image` itself in a single image; None: no line).
    - `single`: `image` holds target and line; `jpeg`: it is stored as JPEG.
    - `stripe_width_px`, `margin_px`, `min_points`: as for `detect_captures`.
    - `note`: called with each one-line remark.

    **Returns:** [`ImageLine`][].
    """
    corners = res.corners_px
    shape = image.shape[:2]
    xy = np.asarray(target.points_mm, np.float64)[:, :2]
    m = _default_margin(corners, target) if margin_px is None else float(margin_px)
    mask, hull = board_region(
        corners, shape, margin_px=m, board_xy_mm=xy, extent_mm=target.extent_mm
    )
    out = ImageLine(corners, np.zeros((0, 2)), None, mask, hull)
    if simg is None:
        return out
    single = single and off is None
    grey = single and laser_in_board(image)
    shared = grey or (single and jpeg)
    w5 = 5.0 if stripe_width_px is None else float(stripe_width_px)
    clip, moved = np.zeros((0, 2)), np.zeros(len(corners), bool)
    if grey:
        # a clipped line's own pixels: where the line is, even where the extractor
        # refuses its centres (a plateau over checker edges); the points next to them
        # move (a line: no wider than half a pitch of the points; white squares that
        # clip are no line)
        clip = clipped_pixels(image, mask, 0.25 * _pitch_px(corners))
        moved = off_local_grid(target, corners)
        if len(clip):
            moved |= near_laser(target, corners, clip, w5, join=False)
    # (signal image, holes, laser-off image, its gain); a pair's board image is the
    # laser-off image of its stripe image, at its own exposure and room light
    pair = not single and off is None and simg is not image
    # a colour JPEG pair in luma: the board is taken out by the difference (no colour
    # needed to tell the line from it) and JPEG keeps luma at full resolution, the
    # laser's colour (chroma) at half and quantised (see `_dark_print`)
    luma = pair and jpeg and np.ndim(simg) == 3
    attempts = [(simg, None, off, 1.0)]
    if pair:
        ref = image
        if np.ndim(image) == 3 and np.ndim(simg) == 2:  # a colour board image, a grey line
            ref = image[:, :, :3].astype(np.float32).mean(axis=2)
        attempts = [(simg, None, ref, "auto")]
    if grey and isinstance(target, CircleGrid):
        grow = _hole_margin(corners, target, stripe_width_px)
        attempts = [(simg, target_holes(target, corners, shape, margin_px=grow), None, 1.0)]
        if opened is not None:
            # first the line alone: the image less its opening; where the line crosses a
            # dot's edge the opening leaves a notch, so no centre on a dot (grown by a line
            # width) is kept. The attempt that keeps more centres wins (a saturated line
            # can be refused in either)
            diff = image.astype(np.float32) - opened.astype(np.float32)
            attempts.insert(
                0, (diff, target_holes(target, corners, shape, margin_px=w5), None, 1.0)
            )
    elif grey and len(clip):
        # a clipped line on a printed pattern: its plateau's rims are read against the
        # pattern drawn from the points the line has not moved (`laser_off_model`), as
        # against a laser-off image; the image alone only where that cannot be drawn or
        # keeps no centre
        drawn = np.where(moved[:, None], np.nan, corners)
        model = laser_off_model(image, target, drawn, mask, clip, reach_px=_LINE_REACH_FWHM * w5,
                                noise=estimate_noise(image))  # fmt: skip
        if model is not None:
            attempts = [(simg, None, model, 1.0), (simg, None, None, 1.0)]
    ok = None
    for signal, holes, background, gain in attempts:
        try:
            res_i, inside = board_stripe(
                signal, mask, width_px=stripe_width_px, background=background, holes=holes,
                background_gain=gain, channel="grey" if luma else "auto",
            )  # fmt: skip
        except ValueError as err:
            note(f"no stripe extracted: {err}")
            continue
        ok_i = res_i.valid & inside
        if out.stripe is None or ok_i.sum() > len(out.stripe_uv):
            out.stripe, ok, out.stripe_uv = res_i, ok_i, res_i.uv[ok_i]
        if background is not None and off is None and not pair and len(out.stripe_uv):
            note("clipped line: its plateau read against the target drawn from its points")
            break  # the drawn laser-off image found the line
    if luma and len(out.stripe_uv):
        dark = _dark_print(image, mask, out.stripe_uv, out.stripe.orientation)
        if dark.any():
            ok = ok.copy()
            ok[np.flatnonzero(ok)[dark]] = False
            out.stripe_uv = out.stripe.uv[ok]
            note(f"{int(dark.sum())} stripe centre(s) on the dark print or next to it "
                 "dropped (colour JPEG pair, read in luma)")  # fmt: skip
    refused = ""
    if len(out.stripe_uv):
        w = out.stripe.width[ok]
        w = float(np.nanmedian(w)) if np.isfinite(w).any() else float("nan")
        refused = _not_a_line(image if single else simg, out.stripe, out.stripe_uv, w,
                              _pitch_px(corners), single)  # fmt: skip
        if refused:
            note(f"line of {len(out.stripe_uv)} centre(s) on the board refused: {refused}")
            ok = np.zeros_like(ok)
            out.stripe_uv = np.zeros((0, 2))
    if len(out.stripe_uv) == 0 and out.stripe is not None and not refused:
        note("no laser line found on the board")
    elif out.stripe is not None and out.stripe.speckle_px > 0:
        note(f"speckled laser line: read after smoothing along it, its centres scatter "
             f"{out.stripe.speckle_px:.2f} px about a straight line")  # fmt: skip
    colour = single and np.ndim(image) == 3 and not grey
    if not shared:
        if colour and len(out.stripe_uv) == 0:
            _luma(out, image, target, note)
        return out
    hit = moved if grey else off_local_grid(target, corners)
    near = np.zeros(len(corners), bool)  # within the line's reach
    base = getattr(out.stripe, "channel", "grey").removesuffix("-minus-others")
    if not grey and not refused and base in _BGR and np.ndim(image) == 3:
        # a clipped colour line's own pixels in its plain channel: where the line is, even
        # where the extractor refuses its centres (an albedo edge along a clipped line)
        clip = clipped_pixels(image[:, :, _BGR[base]], mask, 0.25 * _pitch_px(corners))
        if len(clip):
            near |= near_laser(target, corners, clip, w5, join=False, extra_px=JPEG_BLOCK_PX)
    if len(out.stripe_uv):
        w = out.stripe.width[ok]
        w = float(np.nanmedian(w)) if np.isfinite(w).any() else 5.0
        if stripe_width_px is not None:
            w = max(w, float(stripe_width_px))
        near |= near_laser(target, corners, out.stripe_uv, w, orientation=out.stripe.orientation,
                           extra_px=JPEG_BLOCK_PX if jpeg else 0.0)  # fmt: skip
    if grey:
        hit |= near
    elif near.any():
        # a colour JPEG: the line's chroma ringing moves some of the points within its
        # reach (0.16-0.57 px at 13-26 px from a rendered line), not all: those measured
        # off their untouched neighbours' grid go (on real webcam JPEGs the reach alone
        # took 30 % of the corners, up to every one of a view)
        hit |= displaced(target, corners, near)
    if hit.any():
        out.corners = corners = corners.copy()
        corners[hit] = np.nan
        if grey:
            note(f"{int(hit.sum())} point(s) within the laser line's reach or off their "
                 "local grid dropped (grey single image)")  # fmt: skip
        else:
            kept = int((near & ~hit).sum())
            note(f"{int(hit.sum())} point(s) off their local grid dropped, {kept} more "
                 "within the laser line's reach kept (measured in place; colour JPEG "
                 "single image)")  # fmt: skip
        reason = _too_few(DetectionResult(corners, True, res.message), target, min_points)
        if reason:
            out.reason = reason + " (the others lie under the laser line)"
    elif near.any():
        note(f"{int(near.sum())} point(s) within the laser line's reach kept (measured in "
             "place; colour JPEG single image)")  # fmt: skip
    elif colour and len(out.stripe_uv) == 0:
        _luma(out, image, target, note)
    return out


def _luma(out: ImageLine, image, target: Target, note: Callable[[str], None]) -> None:
    """A colour single image with no laser line on the board: its target points measured
    again in luma (`out.corners` replaced where every found point is found there again,
    within a quarter of the points' spacing).

    The channel minimum keeps a coloured laser out of the target's image, at a cost: the
    minimum of three noisy channels, and in a JPEG the colour's half resolution in every
    channel. Where no line lies on the board the full-resolution luma is better: on 27
    laser-free webcam JPEGs (srv-turntable-webcam) `calibrateCamera`'s median per-view
    RMS was 0.109 px from the channel minimum, 0.103 px from luma (OpenCV's own
    detectors on the grey image: 0.103-0.123)."""
    corners = out.corners
    ok = np.all(np.isfinite(corners), axis=1)
    if not ok.any():
        return
    res = detect_target(image, target)
    if not res.found:
        return
    new = res.corners_px
    fin = np.all(np.isfinite(new), axis=1)
    if fin.sum() < ok.sum():
        return
    d = np.linalg.norm(corners[ok][:, None, :] - new[fin][None, :, :], axis=-1)
    j = d.argmin(axis=1)
    if len(set(j)) != ok.sum() or d[np.arange(ok.sum()), j].max() > 0.25 * _pitch_px(corners):
        return
    out.corners = corners.copy()
    out.corners[ok] = new[fin][j]
    note("no laser line on the board: its points measured in luma")
