"""From a capture folder to observations: detect the target in every view, extract the
laser line on the board, leave out (and name) the views that cannot be used.

A view is dropped, with its reason recorded in the observations' `dropped_views`, when
- its board image cannot be read or decoded;
- there is only a stripe image (`view_<k>_stripe.<ext>` without `view_<k>_board.<ext>`);
- the target is not found, or fewer than `min_points` of its points are (ChArUco), or
  they lie on one line.
A kept view whose stripe image is missing or unreadable, or holds no laser line, keeps
its target points with an empty stripe list (a note says so). Images of another size
than the first one are an error (they cannot come from one sensor).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Sequence

import numpy as np

from ..io._observations import DroppedView, Nominal, Observations, StageScan, View
from ..targets._target import Target, detect_target
from ._folder import IMAGE_SUFFIXES, find_captures, natural_key, read_image
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

    def __call__(self, image: np.ndarray, path: str) -> None:
        if self.shape is None:
            self.shape, self.first = image.shape[:2], os.path.basename(path)
        elif image.shape[:2] != self.shape:
            h, w = image.shape[:2]
            raise ValueError(
                f"{path} is {w}x{h} px but {self.first} is {self.shape[1]}x{self.shape[0]} px; "
                "all images must come from the same sensor"
            )


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
    capture images, when images differ in size, or when the target is found in no view
    (the message lists why for the first views).
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

    for cv in views_in:
        if cv.board is None:
            drop(cv, "no board image (only a stripe image)")
            continue
        image = read_image(cv.board)
        if image is None:
            drop(cv, f"{os.path.basename(cv.board)} cannot be read or decoded")
            continue
        size(image, cv.board)
        res = detect_target(laser_free(image), target, mirrored=mirrored)
        n = int(res.mask.sum())
        reason = ""
        if not res.found:
            reason = res.message or f"{target.kind} not found"
        elif n < min_points:
            reason = f"only {n} target points found; {min_points} needed"
        if reason:
            if preview_dir is not None:
                report.previews.append(_preview(preview_dir, cv, image, res.corners_px, None,
                                                None, None, reason))  # fmt: skip
            drop(cv, reason)
            continue
        if res.message:
            report.notes.append(f"view {cv.view}: {res.message}")
            say(cv.view, f"view {cv.view}: {res.message}")
        shape = image.shape[:2]
        m = _default_margin(res.corners_px, target) if margin_px is None else float(margin_px)
        mask, hull = board_region(
            res.corners_px, shape, margin_px=m, board_xy_mm=xy, extent_mm=target.extent_mm
        )
        stripe_uv, stripe_res, simg = np.zeros((0, 2)), None, None
        if cv.stripe is None:
            note = f"view {cv.view}: no stripe image (view_{cv.view}_stripe.<ext>); no stripe"
            report.notes.append(note)
            say(cv.view, note)
        else:
            simg = image if cv.stripe == cv.board else read_image(cv.stripe)
            if simg is None:
                note = f"view {cv.view}: {os.path.basename(cv.stripe)} unreadable; no stripe"
                report.notes.append(note)
                say(cv.view, note)
            else:
                size(simg, cv.stripe)
                try:
                    stripe_res, inside = board_stripe(simg, mask, width_px=stripe_width_px)
                    ok = stripe_res.valid & inside
                    stripe_uv = stripe_res.uv[ok]
                except ValueError as err:
                    note = f"view {cv.view}: no stripe extracted: {err}"
                    report.notes.append(note)
                    say(cv.view, note)
                if len(stripe_uv) == 0 and stripe_res is not None:
                    note = f"view {cv.view}: no laser line found on the board"
                    report.notes.append(note)
                    say(cv.view, note)
        if preview_dir is not None:
            report.previews.append(
                _preview(preview_dir, cv, simg if simg is not None else image, res.corners_px,
                         hull, stripe_res, mask, "")
            )  # fmt: skip
        views.append(View(res.corners_px, stripe_uv, cv.names))
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
    is one frame. An unreadable frame or one without a line is kept as an empty frame (so
    frame indices stay right) and reported through `on_frame`.

    Raises `ValueError` when the folder holds no images or a frame's size differs from
    `shape`.
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
        size(image, path)
        try:
            frames.append(extract_stripe(image, width_px=stripe_width_px).valid_uv)
        except ValueError as err:
            say(f"{name}: no stripe extracted: {err}")
            frames.append(np.zeros((0, 2)))
    return StageScan(float(delta_omega_deg), float(gauge_radius_mm), frames)
