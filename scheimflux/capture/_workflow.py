"""From a capture folder to observations: detect the target in every view, extract the
laser line on the board, leave out (and name) the views that cannot be used.

A view is dropped, with its reason recorded in the observations' `dropped_views`, when
- its board image cannot be read or decoded;
- there is only a stripe image (`view_<k>_stripe.<ext>` without `view_<k>_board.<ext>`);
- the target is not found, or fewer than `min_points` of its points are (ChArUco), or
  they lie on one line.
A kept view whose stripe image is missing or unreadable, or holds no laser line, or
whose board moved between its pair's two images, or between a single image and its
laser-off image (`_motion.py`; more than `MOVED_PX`), keeps its target points with an
empty stripe list (a note says so); a view whose motion cannot be measured is noted as
unchecked. A view with an image of
another size than the first one read is dropped too (it cannot come from the same
sensor), naming the file and both sizes: what the other views gave is kept. The
per-image logic (target, laser line, points within its reach) is `_image.py`, shared
with the steps of a target on the rotary table (`_stage_target.py`).
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Callable, Sequence

import numpy as np

from ..io._observations import DroppedView, Nominal, Observations, StageScan, View
from ..targets._target import Target
from ._folder import IMAGE_SUFFIXES, find_captures, natural_key, read_image
from ._image import _is_jpeg, dot_diameters_mm, find_target, line_and_points
from ._motion import MOVED_PX, BoardMotion, board_motion

__all__ = ["CaptureReport", "consistent_order", "detect_captures", "extract_scan"]


def _turns(target: Target) -> list[np.ndarray]:
    """The turns of the board about its centre (by 90 degrees k) that leave the target
    looking the same, as index permutations `perm` (point `k` of the turned order is
    point `perm[k]` of the given one), the identity first. A checkerboard's colours must
    match too (a half turn of one with both square counts even); a ChArUco board's
    markers tell every turn apart."""
    from ..targets._board import Checkerboard
    from ..targets._charuco import CharucoBoard

    xy = np.asarray(target.points_mm, np.float64)[:, :2]
    if isinstance(target, CharucoBoard):
        return [np.arange(len(xy))]
    c = xy.mean(axis=0)
    scale = float(np.abs(xy - c).max()) or 1.0
    out = []
    for k in range(4):
        a = k * math.pi / 2
        R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        q = (xy - c) @ R.T + c
        d = np.linalg.norm(q[:, None, :] - xy[None, :, :], axis=-1)
        perm = d.argmin(axis=1)
        if d[np.arange(len(xy)), perm].max() > 1e-6 * scale or len(set(perm)) != len(xy):
            continue
        if isinstance(target, Checkerboard) and not _colours_kept(target, R, c):
            continue
        out.append(perm)
    return out


def _colours_kept(board, R: np.ndarray, c: np.ndarray) -> bool:
    """Whether turning the checkerboard by `R` about `c` puts every square on one of its
    own colour (a half turn: when cols + rows is even, e.g. 11 x 7 or 8 x 6 inner
    corners)."""
    from ..targets._detect import _squares

    centres, colours = _squares(board.cols, board.rows, board.square_mm)
    q = (centres - c) @ R.T + c
    d = np.linalg.norm(q[:, None, :] - centres[None, :, :], axis=-1)
    j = d.argmin(axis=1)
    return bool(np.all(d[np.arange(len(q)), j] < 1e-6 * board.square_mm)
                and np.all(colours[j] == colours))  # fmt: skip


def _x_axis(uv: np.ndarray, xy: np.ndarray) -> float | None:
    """The direction (radians, image frame) of the board's x axis at its points' centre,
    from the homography of the found points; None without one."""
    import cv2

    ok = np.all(np.isfinite(uv), axis=1)
    if ok.sum() < 4:
        return None
    H, _ = cv2.findHomography(xy[ok], uv[ok], 0)
    if H is None:
        return None
    c = xy[ok].mean(axis=0)
    step = np.array([1e-3 * float(np.ptp(xy)), 0.0])
    q = cv2.perspectiveTransform(np.array([[c, c + step]]), H)[0]
    du, dv = q[1] - q[0]
    return math.atan2(dv, du)


def consistent_order(target: Target, corners: list[np.ndarray]) -> list[tuple[int, np.ndarray]]:
    """The views whose point order to turn so that a symmetric target is ordered alike in
    every view, with the turned points.

    A target that looks the same after a turn (`_turns`: a circle grid by a half turn, a
    square one by quarter turns, a checkerboard whose square counts are both even by a
    half turn) is ordered in each image by the board's handedness and then the point 0
    nearest the image's top-left: a board held upright in one view and turned a quarter
    in the other (portrait) gets orders a half turn apart from one view to the next
    (measured: mozhi-lightplane, 7 of 20 views near ±90 degrees, two of them ordered the
    other way). Here the order of each view is the turn whose board x axis in the image
    lies nearest the views' mean direction: first the mean of `exp(i n θ)` over the views
    (`n` the number of turns, θ each view's x axis, so that turned orders agree), its
    direction nearest the image's +u axis; then the mean of the chosen axes themselves,
    until no choice changes (a view in portrait, 90 degrees from the rest, then joins
    the other portrait views: measured on srv-turntable-webcam, ten views at -94 to -90
    degrees and one at +85 against 80 at -16 to +4).

    **Returns:** `[(index into corners, turned points)]`, only those that change.
    """
    perms = _turns(target)
    n = len(perms)
    if n < 2 or len(corners) < 2:
        return []
    xy = np.asarray(target.points_mm, np.float64)[:, :2]
    # each view's x axis under each turn of its order (None: no homography)
    axes = [[_x_axis(np.asarray(c, np.float64)[p], xy) for p in perms] for c in corners]
    known = [a[0] for a in axes if a[0] is not None]
    if not known:
        return []
    mean = np.angle(np.mean(np.exp(1j * n * np.asarray(known)))) / n
    # the branch of the mean nearest +u (the top-left rule's own preference)
    branches = mean + 2 * math.pi * np.arange(n) / n
    ref = branches[np.argmin(np.abs(np.angle(np.exp(1j * branches))))]
    usable = [i for i, a in enumerate(axes) if all(x is not None for x in a)]
    choice: dict[int, int] = {}
    for _ in range(10):  # then nearest the chosen axes' own mean, until none changes
        new = {i: int(np.argmin([abs(np.angle(np.exp(1j * (x - ref)))) for x in axes[i]]))
               for i in usable}  # fmt: skip
        if new == choice:
            break
        choice = new
        ref = float(np.angle(np.sum([np.exp(1j * axes[i][k]) for i, k in choice.items()])))
    return [(i, np.asarray(corners[i])[perms[k]]) for i, k in sorted(choice.items()) if k]


def _median_of_4(values) -> float | None:
    """The median of `values`, or None with fewer than 4."""
    d = np.asarray(values, dtype=np.float64)
    return float(np.median(d)) if len(d) >= 4 else None


@dataclasses.dataclass
class CaptureReport:
    """What `detect_captures` did besides the observations.

    **Fields:**
    - `kept`: view numbers used, in order (`observations.views[i]` is view `kept[i]`).
    - `dropped`: the [`DroppedView`][]s (also in `observations.dropped`).
    - `notes`: one-line remarks (missing stripe images, ignored files, orientation notes).
    - `ignored`: file names in the folder that are not capture images.
    - `previews`: paths of the preview images written.
    - `circle_diameters_mm`: a circle grid's diameters measured in the images the grid
      was found in, every measured circle of every kept view
      ([`measured_circle_diameter_mm`][] their median).
    - `table_circle_diameters_mm`: the same for the table target's steps
      (`detect_session(stage_target=...)` with a circle grid;
      [`measured_table_circle_diameter_mm`][]).
    - `motion`: per view number of a pair, or of a single image with a laser-off image,
      the board's motion from the image its target was found in (board image, laser-off
      image) to the one its line was read from ([`BoardMotion`][]; `checked` False: it
      could not be measured, `why` says why). A view whose board moved more than
      `MOVED_PX` has its stripe refused.
    - `speckle_px`: per kept view number whose laser line was read as speckled (with a
      laser-off image), its centres' scatter across the line (px,
      `StripeResult.speckle_px`), written as the view's `stripe_sigma_px` in the
      observations ([`speckle_summary`][] says so).
    """

    kept: list[int] = dataclasses.field(default_factory=list)
    dropped: list[DroppedView] = dataclasses.field(default_factory=list)
    notes: list[str] = dataclasses.field(default_factory=list)
    ignored: list[str] = dataclasses.field(default_factory=list)
    previews: list[str] = dataclasses.field(default_factory=list)
    motion: dict[int, BoardMotion] = dataclasses.field(default_factory=dict)
    speckle_px: dict[int, float] = dataclasses.field(default_factory=dict)
    circle_diameters_mm: list[float] = dataclasses.field(default_factory=list)
    table_circle_diameters_mm: list[float] = dataclasses.field(default_factory=list)

    def measured_circle_diameter_mm(self) -> float | None:
        """The median of the circles' diameters measured in the images (a circle grid;
        [`circle_diameters_mm`][]), or None with fewer than 4 measured."""
        return _median_of_4(self.circle_diameters_mm)

    def measured_table_circle_diameter_mm(self) -> float | None:
        """As [`measured_circle_diameter_mm`][] for the table target's steps."""
        return _median_of_4(self.table_circle_diameters_mm)

    def motion_summary(self) -> str:
        """One line on the views' board motion ("" when none was checked or not)."""
        if not self.motion:
            return ""
        ok = {k: m for k, m in self.motion.items() if m.checked}
        moved = sorted(k for k, m in ok.items() if m.displacement_px > MOVED_PX)
        unchecked = sorted(k for k, m in self.motion.items() if not m.checked)
        parts = []
        if ok:
            worst = max(m.displacement_px for m in ok.values())
            parts.append(f"checked in {len(ok)} view(s), largest {worst:.3f} px")
        if moved:
            parts.append(f"moved more than {MOVED_PX} px in view(s) {_views(moved)}: "
                         "their stripes refused")  # fmt: skip
        if unchecked:
            parts.append(f"UNCHECKED in view(s) {_views(unchecked)} (the laser-on image shows "
                         "the board too faintly: keep the room light on)")  # fmt: skip
        return "board motion between a view's laser-off and laser-on images: " + "; ".join(parts)

    def speckle_summary(self) -> str:
        """One line on the views whose laser line was speckled ("" when none was): their
        centres' scatter against the stripe noise `calibrate` assumes by default, and
        that `calibrate` weights those views by their own."""
        if not self.speckle_px:
            return ""
        from ..calibration._calibrate import SIGMA_STRIPE_PX

        px = sorted(self.speckle_px.values())
        med = float(np.median(px))
        line = (
            f"speckled laser line in {len(px)} view(s): its centres scatter "
            f"{px[0]:.2f}-{px[-1]:.2f} px (median {med:.2f}) across the line"
        )
        if px[-1] <= SIGMA_STRIPE_PX:
            return line
        return (
            f"{line}, more than the {SIGMA_STRIPE_PX} px of a clean line: written as each "
            "view's stripe_sigma_px, by which calibrate weights that view's stripe points"
        )


def _views(ks: list[int]) -> str:
    return ", ".join(str(k) for k in ks)


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
        single = cv.layout == "single"
        res, opened, reason = find_target(image, off, target, single=single,
                                          min_points=min_points, mirrored=mirrored)  # fmt: skip
        if reason:
            if preview_dir is not None:
                report.previews.append(_preview(preview_dir, cv, image, res.corners_px, None,
                                                None, None, reason))  # fmt: skip
            drop(cv, reason)
            continue
        if res.message:
            note(cv, res.message)
        dots = dot_diameters_mm(image, off, opened, target, res)  # circle grids only
        simg = None
        if cv.stripe is None:
            note(cv, f"no stripe image (view_{cv.view}_stripe.<ext>); no stripe")
        else:
            simg = image if cv.stripe == cv.board else read_image(cv.stripe)
            if simg is None:
                note(cv, f"{os.path.basename(cv.stripe)} unreadable; no stripe")
            elif size.mismatch(simg, cv.stripe):
                drop(cv, size.mismatch(simg, cv.stripe))
                continue
        line = line_and_points(image, off, simg, opened, res, target, single=single,
                               jpeg=any(_is_jpeg(p) for p in (cv.board, cv.stripe) if p),
                               stripe_width_px=stripe_width_px,
                               margin_px=margin_px, min_points=min_points,
                               note=lambda text, cv=cv: note(cv, text))  # fmt: skip
        corners, stripe_uv, stripe_res = line.corners, line.stripe_uv, line.stripe
        # Did the board move between the exposures whose target points and laser line
        # are joined? A pair: its board image and stripe image; a single image with a
        # laser-off image: the target is found in the laser-off one.
        joined, motion_px = None, None
        if not single and simg is not None and simg is not image:
            joined = (image, simg, cv.board, cv.stripe)
        elif single and off is not None and simg is not None:
            joined = (off, simg, cv.off, cv.board)
        if joined is not None:
            ref, lit, ref_path, lit_path = joined
            mo = board_motion(ref, lit, line.mask, corners, stripe_res,
                              width_px=stripe_width_px)  # fmt: skip
            report.motion[cv.view] = mo
            # kept in the observations (NaN: not measurable; an unmatched print, whose
            # stripe is refused below, records nothing)
            if not mo.checked:
                motion_px = math.nan
            elif np.isfinite(mo.displacement_px):
                motion_px = float(mo.displacement_px)
            b_name, s_name = os.path.basename(ref_path), os.path.basename(lit_path)
            if not mo.checked:
                note(cv, f"board motion from {b_name} to {s_name} unchecked: {mo.why}")
            elif mo.displacement_px > MOVED_PX:
                stripe_uv, stripe_res = np.zeros((0, 2)), None  # (none drawn in a preview)
                by = (f"{mo.displacement_px:.2f} px" if np.isfinite(mo.displacement_px)
                      else f"by an unknown amount ({mo.why})")  # fmt: skip
                note(cv, f"the board moved {by} from {b_name} to {s_name} (more than "
                         f"{MOVED_PX} px): stripe refused, board points kept")  # fmt: skip
        if line.reason:
            if preview_dir is not None:
                report.previews.append(_preview(preview_dir, cv, image, corners, line.hull,
                                                stripe_res, line.mask, line.reason))  # fmt: skip
            drop(cv, line.reason)
            continue
        if preview_dir is not None:
            report.previews.append(
                _preview(preview_dir, cv, simg if simg is not None else image, corners,
                         line.hull, stripe_res, line.mask, "")
            )  # fmt: skip
        # a speckled line's own scatter, kept for calibrate's weights and gates
        sigma = None
        if stripe_res is not None and stripe_res.speckle_px > 0 and len(stripe_uv):
            sigma = report.speckle_px[cv.view] = float(stripe_res.speckle_px)
        views.append(View(corners, stripe_uv, cv.names, motion_px, sigma))
        report.kept.append(cv.view)
        report.circle_diameters_mm.extend(dots)

    for i, turned in consistent_order(target, [v.corners_px for v in views]):
        views[i] = dataclasses.replace(views[i], corners_px=turned)
        note(views_in[[c.view for c in views_in].index(report.kept[i])],
             "point order turned to agree with the other views (a symmetric target)")  # fmt: skip

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
        # a circle grid's points are the blobs' centroids (calibration models them)
        circle_diameter_mm=getattr(target, "diameter_mm", None),
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
