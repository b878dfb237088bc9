"""A target fixed to the rotary table: one image per table step, in a folder of its own.

Layout of the folder (`detect --stage-target DIR --delta-omega-deg D`): every image file
(`png`, `jpg`, `jpeg`, `tif`, `tiff`, `bmp`, any case) is one table step, in natural name
order (`step_2` before `step_10`): the k-th image was taken with the table turned by
`k · D` degrees from the first. Other files are ignored. An image in which the target is
not found (or with fewer than `min_points` of its points, unreadable, or of another size
than the board images) is dropped with the reason, and the steps of the others keep their
numbers: the angle of a view is its step × Δω, so a lost image must not shift the rest.
The laser may be on or off (the target is detected in the image with the line taken out).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable

import numpy as np

from ..io._observations import DroppedView, StageTargetViews
from ..targets._target import Target, detect_target
from ._folder import IMAGE_SUFFIXES, natural_key, read_image
from ._region import laser_free
from ._workflow import _SizeCheck, _too_few

__all__ = ["detect_stage_target", "stage_target_images"]


def stage_target_images(folder: str | os.PathLike) -> tuple[list[str], list[str]]:
    """`(images, ignored)`: the folder's image files in natural order (image k is table
    step k) and the other names. Raises `ValueError` when there is no image."""
    folder = os.fspath(folder)
    if not os.path.isdir(folder):
        raise NotADirectoryError(f"stage-target folder {folder} is not a folder")
    images, ignored = [], []
    for n in sorted(os.listdir(folder), key=natural_key):
        ok = n.lower().endswith(IMAGE_SUFFIXES) and os.path.isfile(os.path.join(folder, n))
        (images if ok else ignored).append(n)
    if not images:
        raise ValueError(
            f"no image files ({', '.join(IMAGE_SUFFIXES)}) in stage-target folder {folder}"
        )
    return images, ignored


def detect_stage_target(
    folder: str | os.PathLike,
    target: Target,
    delta_omega_deg: float,
    *,
    shape: tuple[int, int] | None = None,
    min_points: int = 6,
    mirrored: bool = False,
    on_step: Callable[[str], None] | None = None,
) -> StageTargetViews:
    """Detect a target fixed to the rotary table in every image of `folder` (module doc).

    **Arguments:**
    - `folder`: one image per table step, natural name order.
    - `target`: the table target (may differ from the calibration boards).
    - `delta_omega_deg`: the table step between consecutive images (non-zero).
    - `shape`: `(height, width)` the images must have (the board images'); default:
      the first image's.
    - `min_points`: fewest target points a step needs.
    - `on_step`: called with a one-line note per dropped step.

    **Returns:** [`StageTargetViews`][] (kept steps with their corners, dropped steps
    with reasons). **Raises:** `ValueError` (one line) for a zero or non-finite step, a
    folder without images, or fewer than two steps with the target found.
    """
    dw = float(delta_omega_deg) if delta_omega_deg is not None else math.nan
    if not math.isfinite(dw) or dw == 0.0:
        raise ValueError(f"the table step --delta-omega-deg must be a non-zero angle, got {dw}")
    images, _ = stage_target_images(folder)
    say = on_step or (lambda m: None)
    size = _SizeCheck()
    if shape is not None:
        size.shape, size.first = tuple(shape), "the board images"
    steps, corners, sources, dropped = [], [], [], []

    def drop(k, name, reason):
        dropped.append(DroppedView(k, (name,), reason))
        say(f"table step {k} ({name}) dropped: {reason}")

    for k, name in enumerate(images):
        path = os.path.join(os.fspath(folder), name)
        image = read_image(path)
        if image is None:
            drop(k, name, f"{name} cannot be read or decoded")
            continue
        why = size.mismatch(image, path)
        if why:
            drop(k, name, why)
            continue
        res = detect_target(laser_free(image), target, mirrored=mirrored)
        reason = _too_few(res, target, min_points)
        if reason:
            drop(k, name, reason)
            continue
        steps.append(k)
        corners.append(np.asarray(res.corners_px, dtype=np.float64))
        sources.append((name,))
    if len(steps) < 2:
        raise ValueError(
            f"the table target was found in {len(steps)} of {len(images)} image(s) in "
            f"{os.fspath(folder)}; the table axis needs two or more table steps"
        )
    return StageTargetViews(
        dw, np.asarray(target.points_mm), np.asarray(steps), np.stack(corners),
        tuple(sources), dropped,
    )  # fmt: skip
