"""A target fixed to the rotary table: one image per table step, in a folder of its own.

Layout of the folder (`detect --stage-target DIR --delta-omega-deg D`): every image file
(`png`, `jpg`, `jpeg`, `tif`, `tiff`, `bmp`, any case) is one table step, in natural name
order (`step_2` before `step_10`): the k-th image was taken with the table turned by
`k · D` degrees from the first. Beside a step image `NAME.EXT`, `NAME_off.EXT` (any image
type) is the same step with the laser off: it is no step of its own (alone, without
`NAME.EXT`, it is that step). Other files are ignored. An image in which the target is
not found (or with fewer than `min_points` of its points, unreadable, or of another size
than the board images) is dropped with the reason, and the steps of the others keep
their numbers: the angle of a view is its step × Δω, so a lost image must not shift the
rest.

The laser may be on or off. Each step image goes through the board views' per-image
logic (`_image.py`): with the laser on, the line on the target is extracted inside the
target's region into the step's `stripe_px` (it ties the laser plane to the table); in a
grey image without a laser-off image the points within the line's reach are dropped (the
line displaces them), a circle grid is found in the image with the line opened away;
with `NAME_off.EXT` the target is found in the laser-off image and the line in the
difference, and every point is kept.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable

import numpy as np

from ..io._observations import DroppedView, StageTargetViews
from ..targets._target import Target
from ._folder import IMAGE_SUFFIXES, natural_key, read_image
from ._image import _is_jpeg, dot_diameters_mm, find_target, line_and_points
from ._workflow import _SizeCheck

__all__ = ["detect_stage_target", "stage_target_images", "stage_target_steps"]


def stage_target_steps(
    folder: str | os.PathLike,
) -> tuple[list[tuple[str, str | None]], list[str]]:
    """`(steps, ignored)`: per table step (natural order of the step images) its image
    name and the name of its laser-off image `NAME_off.EXT` (None without one), and the
    other names. Raises `ValueError` when there is no step image, when a step has two
    laser-off images, or for a laser-off image without its step image."""
    folder = os.fspath(folder)
    if not os.path.isdir(folder):
        raise NotADirectoryError(f"stage-target folder {folder} is not a folder")
    images, ignored = [], []
    for n in sorted(os.listdir(folder), key=natural_key):
        ok = n.lower().endswith(IMAGE_SUFFIXES) and os.path.isfile(os.path.join(folder, n))
        (images if ok else ignored).append(n)
    stems = {os.path.splitext(n)[0].lower() for n in images}
    offs: dict[str, str] = {}
    for n in images:
        stem = os.path.splitext(n)[0].lower()
        if stem.endswith("_off") and stem[:-4] in stems:
            if stem[:-4] in offs:
                raise ValueError(
                    f"two laser-off images for one table step in {folder}: "
                    f"{offs[stem[:-4]]} and {n} (keep one)"
                )
            offs[stem[:-4]] = n
    steps = [(n, offs.get(os.path.splitext(n)[0].lower())) for n in images
             if n not in offs.values()]  # fmt: skip
    if not steps:
        raise ValueError(
            f"no image files ({', '.join(IMAGE_SUFFIXES)}) in stage-target folder {folder}"
        )
    return steps, ignored


def stage_target_images(folder: str | os.PathLike) -> tuple[list[str], list[str]]:
    """`(images, ignored)`: the folder's step images in natural order (image k is table
    step k; laser-off images `NAME_off.EXT` are not steps) and the other names. Raises
    `ValueError` when there is no image."""
    steps, ignored = stage_target_steps(folder)
    return [n for n, _ in steps], ignored


def detect_stage_target(
    folder: str | os.PathLike,
    target: Target,
    delta_omega_deg: float,
    *,
    shape: tuple[int, int] | None = None,
    stripe_width_px: float | None = None,
    margin_px: float | None = None,
    min_points: int = 6,
    mirrored: bool = False,
    on_step: Callable[[str], None] | None = None,
    diameters_mm: list[float] | None = None,
) -> StageTargetViews:
    """Detect a target fixed to the rotary table in every image of `folder` (module doc).

    **Arguments:**
    - `folder`: one image per table step, natural name order.
    - `target`: the table target (may differ from the calibration boards).
    - `delta_omega_deg`: the table step between consecutive images (non-zero).
    - `shape`: `(height, width)` the images must have (the board images'); default:
      the first image's.
    - `stripe_width_px`, `margin_px`: the laser line's expected FWHM (None: measured)
      and the growth of the target's region, as for `detect_captures`.
    - `min_points`: fewest target points a step needs (after those within the laser
      line's reach are dropped).
    - `on_step`: called with a one-line note per dropped step and per remark (points
      dropped next to the line, an unreadable laser-off image).
    - `diameters_mm`: a list that, for a circle grid, is extended by the dots' diameters
      measured in the kept steps' images (`capture.dot_diameters_mm`; the file gets the
      target's stated diameter, `circle_diameter_mm`, as given).

    **Returns:** [`StageTargetViews`][] (kept steps with their corners and the laser
    line on the target, dropped steps with reasons). **Raises:** `ValueError` (one
    line) for a zero or non-finite step, a folder without images, two laser-off images
    of one step, or fewer than two steps with the target found.
    """
    dw = float(delta_omega_deg) if delta_omega_deg is not None else math.nan
    if not math.isfinite(dw) or dw == 0.0:
        raise ValueError(f"the table step --delta-omega-deg must be a non-zero angle, got {dw}")
    images, _ = stage_target_steps(folder)
    folder = os.fspath(folder)
    say = on_step or (lambda m: None)
    size = _SizeCheck()
    if shape is not None:
        size.shape, size.first = tuple(shape), "the board images"
    steps, corners, stripes, sources, dropped = [], [], [], [], []

    def drop(k, names, reason):
        dropped.append(DroppedView(k, names, reason))
        say(f"table step {k} ({', '.join(names)}) dropped: {reason}")

    for k, (name, off_name) in enumerate(images):
        names = (name,) if off_name is None else (name, off_name)
        path = os.path.join(folder, name)
        image = read_image(path)
        if image is None:
            drop(k, names, f"{name} cannot be read or decoded")
            continue
        why = size.mismatch(image, path)
        if why:
            drop(k, names, why)
            continue
        off = None
        if off_name is not None:
            off = read_image(os.path.join(folder, off_name))
            if off is None:
                say(f"table step {k}: {off_name} unreadable; detecting without it")
            elif size.mismatch(off, os.path.join(folder, off_name)):
                drop(k, names, size.mismatch(off, os.path.join(folder, off_name)))
                continue
        res, opened, reason = find_target(image, off, target, single=True,
                                          min_points=min_points, mirrored=mirrored)  # fmt: skip
        if reason:
            drop(k, names, reason)
            continue
        if res.message:
            say(f"table step {k}: {res.message}")
        line = line_and_points(image, off, image, opened, res, target, single=True,
                               jpeg=_is_jpeg(name), stripe_width_px=stripe_width_px,
                               margin_px=margin_px, min_points=min_points,
                               note=lambda m, k=k: say(f"table step {k}: {m}"))  # fmt: skip
        if line.reason:
            drop(k, names, line.reason)
            continue
        if diameters_mm is not None:
            diameters_mm.extend(dot_diameters_mm(image, off, opened, target, res))
        steps.append(k)
        corners.append(np.asarray(line.corners, dtype=np.float64))
        stripes.append(np.asarray(line.stripe_uv, dtype=np.float64).reshape(-1, 2))
        sources.append(names)
    if len(steps) < 2:
        raise ValueError(
            f"the table target was found in {len(steps)} of {len(images)} image(s) in "
            f"{folder}; the table axis needs two or more table steps"
        )
    return StageTargetViews(
        dw, np.asarray(target.points_mm), np.asarray(steps), np.stack(corners),
        tuple(sources), dropped, tuple(stripes), getattr(target, "diameter_mm", None),
    )  # fmt: skip
