"""From a capture folder to observations: detect the target in every view, extract the
laser line on the board, leave out (and name) the views that cannot be used.

A view is dropped, with its reason recorded in the observations' `dropped_views`, when
- its board image cannot be read or decoded;
- there is only a stripe image (`view_<k>_stripe.<ext>` without `view_<k>_board.<ext>`);
- the target is not found, or fewer than `min_points` of its points are (ChArUco), or
  they lie on one line.
A kept view whose stripe image is missing or unreadable, or holds no laser line, keeps
its target points with an empty stripe list (a note says so). A view with an image of
another size than the first one read is dropped too (it cannot come from the same
sensor), naming the file and both sizes: what the other views gave is kept.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Sequence

import numpy as np

from ..io._observations import DroppedView, Nominal, Observations, StageScan, View
from ..targets._circles import CircleGrid
from ..targets._result import DetectionResult
from ..targets._target import Target, detect_target
from ._folder import IMAGE_SUFFIXES, find_captures, natural_key, read_image
from ._laser import (
    JPEG_BLOCK_PX,
    laser_in_board,
    laser_removed,
    near_laser,
    off_local_grid,
    target_holes,
)
from ._region import board_region, board_stripe, laser_free

__all__ = ["CaptureReport", "detect_captures", "extract_scan"]


@dataclasses.dataclass
class CaptureReport:
    """What `detect_captures` did besides the observations.

    **Fields:**
    - `kept`: view numbers used, in order (`observations.views[i]` is view `kept[i]`).
    - `dropped`: the [`DroppedView`][]s (also in `observations.dropped`).
    - `notes`: one-line remarks (missing stripe images, ignored files, orientation notes).
    - `ignored`: file names in the folder that are not capture images.
    - `previews`: paths of the preview images written.
    """

    kept: list[int] = dataclasses.field(default_factory=list)
    dropped: list[DroppedView] = dataclasses.field(default_factory=list)
    notes: list[str] = dataclasses.field(default_factory=list)
    ignored: list[str] = dataclasses.field(default_factory=list)
    previews: list[str] = dataclasses.field(default_factory=list)


class _SizeCheck:
    def __init__(self):
        self.shape: tuple[int, int] | None = None
        self.first = ""

    def mismatch(self, image: np.ndarray, path: str) -> str:
        """"" when `image` has the size of the first one seen, else why not."""
        if self.shape is None:
            self.shape, self.first = image.shape[:2], os.path.basename(path)
        elif image.shape[:2] != self.shape:
            h, w = image.shape[:2]
            return (
                f"{os.path.basename(path)} is {w}x{h} px but {self.first} is "
                f"{self.shape[1]}x{self.shape[0]} px (not the same sensor)"
            )
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


def detect_captures(
    folder: str | os.PathLike,
    target: Target,
    *,
    pixel_pitch_mm: Sequence[float] | None = None,
    nominal: Nominal | None = None,
    stripe_width_px: float | None = None,
    margin_px: float | None = None,
    min_points: int = 6,
    mirrored: bool = False,
    preview_dir: str | os.PathLike | None = None,
    on_view: Callable[[int, str], None] | None = None,
) -> tuple[Observations, CaptureReport]:
    """Detect the target and the board stripes of every view in a capture folder.

    **Arguments:**
    - `folder`: the capture folder (layouts in `scheimflux.capture._folder`).
    - `target`: a `Checkerboard`, `CharucoBoard` or `CircleGrid`.
    - `pixel_pitch_mm`: the sensor's `(dx, dy)` from its datasheet, recorded in the
      observations; None records none (the thick-lens model will ask for it).
    - `nominal`: nominal device values to record.
    - `stripe_width_px`: expected stripe FWHM; None measures it per image.
    - `margin_px`: growth of the board region around the target (default: half a
      square or spacing, in pixels).
    - `min_points`: fewest target points a view needs (ChArUco; other targets are found
      whole or not at all).
    - `mirrored`: images taken through a mirror (see the detectors).
    - `preview_dir`: write one overlay PNG per view there (`view_<k>_preview.png`).
    - `on_view`: called as `on_view(k, message)` for each remark while running.

    **Returns:** `(observations, report)`. Raises `ValueError` when the folder has no
    capture images or when the target is found in no view (the message lists why for
    the first views).
    """
    views_in, ignored = find_captures(folder)
    report = CaptureReport(ignored=ignored)
    say = on_view or (lambda k, m: None)
    if not views_in:
        raise ValueError(
            f"no capture images in {os.fspath(folder)}: name them view_<k>.<ext> (board and "
            "laser line in one image) or view_<k>_board.<ext> + view_<k>_stripe.<ext>, "
            f"<ext> one of {', '.join(s[1:] for s in IMAGE_SUFFIXES)}"
        )
    if preview_dir is not None:
        os.makedirs(preview_dir, exist_ok=True)
    size = _SizeCheck()
    views: list[View] = []
    xy = np.asarray(target.points_mm, np.float64)[:, :2]

    def drop(cv, reason: str) -> None:
        d = DroppedView(cv.view, cv.names, reason)
        report.dropped.append(d)
        say(cv.view, f"view {cv.view} ({', '.join(cv.names)}) dropped: {reason}")

    def note(cv, text: str) -> None:
        report.notes.append(f"view {cv.view}: {text}")
        say(cv.view, f"view {cv.view}: {text}")

    for cv in views_in:
        if cv.board is None:
            drop(cv, "no board image (only a stripe image)")
            continue
        image = read_image(cv.board)
        if image is None:
            drop(cv, f"{os.path.basename(cv.board)} cannot be read or decoded")
            continue
        why = size.mismatch(image, cv.board)
        if why:
            drop(cv, why)
            continue
        off = None
        if cv.off is not None:
            off = read_image(cv.off)
            if off is None:
                note(cv, f"{os.path.basename(cv.off)} unreadable; detecting without it")
            elif size.mismatch(off, cv.off):
                drop(cv, size.mismatch(off, cv.off))
                continue
        # the target is detected in a laser-free image where there is one; a grey
        # single image of a circle grid without one: in the image with the line taken
        # out by an opening (`laser_removed`: a line across the dots splits their blobs
        # and the grid is lost); the dots it crossed are dropped below (`near_laser`)
        found_in, opened = image if off is None else off, None
        if (off is None and cv.layout == "single" and isinstance(target, CircleGrid)
                and laser_in_board(image)):  # fmt: skip
            opened = laser_removed(image, target)
            found_in = image if opened is None else opened
        res = detect_target(laser_free(found_in), target, mirrored=mirrored)
        reason = _too_few(res, target, min_points)
        if reason:
            if preview_dir is not None:
                report.previews.append(_preview(preview_dir, cv, image, res.corners_px, None,
                                                None, None, reason))  # fmt: skip
            drop(cv, reason)
            continue
        if res.message:
            note(cv, res.message)
        corners = res.corners_px
        shape = image.shape[:2]
        m = _default_margin(corners, target) if margin_px is None else float(margin_px)
        mask, hull = board_region(
            corners, shape, margin_px=m, board_xy_mm=xy, extent_mm=target.extent_mm
        )
        stripe_uv, stripe_res, simg = np.zeros((0, 2)), None, None
        if cv.stripe is None:
            note(cv, f"no stripe image (view_{cv.view}_stripe.<ext>); no stripe")
        else:
            simg = image if cv.stripe == cv.board else read_image(cv.stripe)
            if simg is None:
                note(cv, f"{os.path.basename(cv.stripe)} unreadable; no stripe")
            elif size.mismatch(simg, cv.stripe):
                drop(cv, size.mismatch(simg, cv.stripe))
                continue
            else:
                # one grey image of target and line (no laser-off image): keep the line
                # out of the dots, and the points out of the line's reach (_laser.py);
                # a colour JPEG keeps some of the line in every channel (_laser.py): its
                # points are kept out of the line's reach too, grown by a chroma block
                single = cv.layout == "single" and off is None
                grey = single and laser_in_board(image)
                jpeg = _is_jpeg(cv.board)
                shared = grey or (single and jpeg)
                attempts = [(simg, None)]  # (signal image, holes)
                if grey and isinstance(target, CircleGrid):
                    grow = _hole_margin(corners, target, stripe_width_px)
                    attempts = [(simg, target_holes(target, corners, shape, margin_px=grow))]
                    if opened is not None:
                        # first the line alone: the image less its opening; where the line
                        # crosses a dot's edge the opening leaves a notch, so no centre on
                        # a dot (grown by a line width) is kept. The attempt that keeps
                        # more centres wins (a saturated line can be refused in either)
                        w5 = 5.0 if stripe_width_px is None else float(stripe_width_px)
                        diff = image.astype(np.float32) - opened.astype(np.float32)
                        attempts.insert(0, (diff, target_holes(target, corners, shape,
                                                                margin_px=w5)))  # fmt: skip
                for signal, holes in attempts:
                    try:
                        res_i, inside = board_stripe(
                            signal, mask, width_px=stripe_width_px, background=off,
                            holes=holes,
                        )  # fmt: skip
                    except ValueError as err:
                        note(cv, f"no stripe extracted: {err}")
                        continue
                    ok_i = res_i.valid & inside
                    if stripe_res is None or ok_i.sum() > len(stripe_uv):
                        stripe_res, ok, stripe_uv = res_i, ok_i, res_i.uv[ok_i]
                if len(stripe_uv) == 0 and stripe_res is not None:
                    note(cv, "no laser line found on the board")
                if shared:
                    hit = off_local_grid(target, corners)
                    if len(stripe_uv):
                        w = stripe_res.width[ok]
                        w = float(np.nanmedian(w)) if np.isfinite(w).any() else 5.0
                        if stripe_width_px is not None:
                            w = max(w, float(stripe_width_px))
                        hit |= near_laser(target, corners, stripe_uv, w,
                                          orientation=stripe_res.orientation,
                                          extra_px=JPEG_BLOCK_PX if jpeg else 0.0)  # fmt: skip
                    if hit.any():
                        corners = corners.copy()
                        corners[hit] = np.nan
                        kind = "grey" if grey else "colour JPEG"
                        note(cv, f"{int(hit.sum())} point(s) within the laser line's "
                                 f"reach or off their local grid dropped ({kind} single "
                                 "image)")  # fmt: skip
                        res = DetectionResult(corners, True, res.message)
                        reason = _too_few(res, target, min_points)
                        if reason:
                            if preview_dir is not None:
                                report.previews.append(
                                    _preview(preview_dir, cv, image, corners, hull, stripe_res,
                                             mask, reason)
                                )  # fmt: skip
                            drop(cv, reason + " (the others lie under the laser line)")
                            continue
        if preview_dir is not None:
            report.previews.append(
                _preview(preview_dir, cv, simg if simg is not None else image, corners,
                         hull, stripe_res, mask, "")
            )  # fmt: skip
        views.append(View(corners, stripe_uv, cv.names))
        report.kept.append(cv.view)

    if not views:
        why = "; ".join(f"view {d.view}: {d.reason}" for d in report.dropped[:3])
        raise ValueError(
            f"no {target.kind} {target.size} found in any image of {os.fspath(folder)} ({why})"
        )
    h, w = size.shape
    obs = Observations(
        width=int(w),
        height=int(h),
        pixel_pitch_mm=None if pixel_pitch_mm is None else tuple(map(float, pixel_pitch_mm)),
        board_points_mm=np.asarray(target.points_mm, np.float64),
        views=views,
        nominal=nominal,
        dropped=list(report.dropped),
    )
    return obs, report


def _preview(preview_dir, cv, image, corners, hull, stripe_res, mask, reason) -> str:
    from ._preview import write_preview

    path = os.path.join(os.fspath(preview_dir), f"view_{cv.view}_preview.png")
    write_preview(path, image, corners, hull=hull, stripe=stripe_res, mask=mask, title=reason)
    return path


def extract_scan(
    folder: str | os.PathLike,
    delta_omega_deg: float,
    gauge_radius_mm: float,
    *,
    stripe_width_px: float | None = None,
    shape: tuple[int, int] | None = None,
    on_frame: Callable[[str], None] | None = None,
) -> StageScan:
    """The rotary-stage scan of a gauge: every image in `folder`, in natural name order,
    is one frame. An unreadable frame, one of another size than `shape` (or than the
    first frame) or one without a line is kept as an empty frame (so frame indices stay
    right) and reported through `on_frame`.

    Raises `ValueError` when the folder holds no images.
    """
    from ..stripe import extract_stripe

    folder = os.fspath(folder)
    if not os.path.isdir(folder):
        raise NotADirectoryError(f"scan folder {folder} is not a folder")
    names = sorted(
        (n for n in os.listdir(folder)
         if n.lower().endswith(IMAGE_SUFFIXES) and os.path.isfile(os.path.join(folder, n))),
        key=natural_key,
    )  # fmt: skip
    if not names:
        raise ValueError(f"no image files ({', '.join(IMAGE_SUFFIXES)}) in scan folder {folder}")
    say = on_frame or (lambda m: None)
    size = _SizeCheck()
    if shape is not None:
        size.shape, size.first = tuple(shape), "the board images"
    frames = []
    for name in names:
        path = os.path.join(folder, name)
        image = read_image(path)
        if image is None:
            say(f"unreadable scan frame {name} kept as an empty frame")
            frames.append(np.zeros((0, 2)))
            continue
        why = size.mismatch(image, path)
        if why:
            say(f"scan frame {why}: kept as an empty frame")
            frames.append(np.zeros((0, 2)))
            continue
        try:
            frames.append(extract_stripe(image, width_px=stripe_width_px).valid_uv)
        except ValueError as err:
            say(f"{name}: no stripe extracted: {err}")
            frames.append(np.zeros((0, 2)))
    return StageScan(float(delta_omega_deg), float(gauge_radius_mm), frames)
