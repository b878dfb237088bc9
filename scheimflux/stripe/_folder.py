"""A folder of frame images → stripe centres per frame, streamed in small batches.

The frames of a capture folder are its image files (png, tif, tiff, bmp, jpg, jpeg; 8-
or 16-bit, grey or colour) in natural name order (`frame2` before `frame10`). With a
laser-off suffix, `NAME<SUFFIX>.EXT` beside `NAME.EXT` is that pose's laser-off image
(not a frame itself). `iter_folder_stripes` reads a few frames at a time, extracts them
on a pool of threads and yields one `FrameStripes` per frame, in file order: memory
holds one batch of images, whatever the number of frames. A frame that cannot be used
(unreadable, another size than the first readable frame, refused by the extractor)
is yielded with its reason and no centres, so that frame indices keep matching the file
order.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import os
import re
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np

from .._image import IMAGE_SUFFIXES as IMAGE_SUFFIXES, read_image as read_image
from ._extract import extract_stripe
from ._result import StripeResult


def _natural_key(name: str) -> list:
    return [(0, int(p), "") if p.isdigit() else (1, 0, p.lower()) for p in re.split(r"(\d+)", name)]


def frame_files(
    folder: str | os.PathLike, laser_off: str | None = None
) -> list[tuple[str, str | None]]:
    """`(laser-on path, laser-off path or None)` per frame of a capture folder.

    **Arguments:**
    - `folder`: the folder of frame images.
    - `laser_off`: suffix of the laser-off images (`"_off"`: `f3_off.png` is the
      laser-off image of `f3.png`); None: every image is a frame.

    **Returns:** the frames in natural name order. **Raises:** `ValueError` when `folder`
    is not a folder or holds no frame image.
    """
    folder = os.fspath(folder)
    if not os.path.isdir(folder):
        raise ValueError(f"{folder} is not a folder")
    names = [
        n
        for n in os.listdir(folder)
        if n.lower().endswith(IMAGE_SUFFIXES) and os.path.isfile(os.path.join(folder, n))
    ]
    paths = [os.path.join(folder, n) for n in sorted(names, key=_natural_key)]
    if not paths:
        raise ValueError(f"no image files ({', '.join(IMAGE_SUFFIXES)}) in {folder}")
    if not laser_off:
        return [(p, None) for p in paths]
    stems = {os.path.splitext(p)[0]: p for p in paths}
    off = {p for p in paths if os.path.splitext(p)[0].endswith(laser_off)}
    pairs = [(p, stems.get(os.path.splitext(p)[0] + laser_off)) for p in paths if p not in off]
    if not pairs:
        raise ValueError(f"only laser-off images (*{laser_off}.*) in {folder}")
    return pairs


def numbering_problem(names: Sequence[str]) -> str | None:
    """What is wrong with the numbering of a folder's frame files, or None.

    Frame i is the i-th image in natural name order, so in a rotary-table scan a missing
    file (`frame_5.tif` lost between `frame_4.tif` and `frame_6.tif`) or a stray image
    (`frame_0_copy.tif`) turns every later frame by a wrong angle, without any sign in
    the images themselves. Where most names are `PREFIX<N>.EXT` with one prefix, this
    names the numbers missing from their run, numbers used twice and the images that do
    not follow the pattern. Gaps count only in a counter (numbers mostly one apart, not
    time stamps). Names without a common numbering give None (nothing to check).

    **Arguments:** `names`: the frames' file names (or paths), laser-off images excluded.
    """
    stems = [os.path.splitext(os.path.basename(os.fspath(n)))[0] for n in names]
    parsed = [re.fullmatch(r"(.*?)(\d+)", s) for s in stems]
    prefixes = [m.group(1) for m in parsed if m]
    if not prefixes:
        return None
    prefix = max(set(prefixes), key=prefixes.count)
    numbered = {}  # number -> names
    odd = []
    for name, m in zip(names, parsed):
        base = os.path.basename(os.fspath(name))
        if m and m.group(1) == prefix:
            numbered.setdefault(int(m.group(2)), []).append(base)
        else:
            odd.append(base)
    if len(numbered) < 2 or 2 * sum(map(len, numbered.values())) < len(names):
        return None
    problems = []
    nums = sorted(numbered)
    missing = []  # a counter with lost files (not, e.g., time stamps: their steps vary)
    if np.median(np.diff(nums)) == 1:
        missing = sorted(set(range(nums[0], nums[-1] + 1)) - set(nums))
    if missing:
        shown = ", ".join(map(str, missing[:8])) + (", ..." if len(missing) > 8 else "")
        first, last = numbered[nums[0]][0], numbered[nums[-1]][0]
        problems.append(f"{len(missing)} frame number(s) missing between {first} and {last}: "
                        f"{shown}")  # fmt: skip
    twice = [" and ".join(v) for v in numbered.values() if len(v) > 1]
    if twice:
        problems.append("one number on two images: " + "; ".join(twice[:4]))
    if odd:
        shown = ", ".join(odd[:4]) + (", ..." if len(odd) > 4 else "")
        problems.append(f"{len(odd)} image(s) not numbered like the others "
                        f"({prefix}<N>): {shown}")  # fmt: skip
    return "; ".join(problems) or None


def numbering_refusal(folder: str, problem: str, step: str) -> str:
    """The one-line refusal of a rotary-table scan folder with a `numbering_problem`;
    `step` names the table step (the option that sets it)."""
    return (
        f"{folder}: {problem}. Frame i is the i-th image and is turned by i x {step}, so "
        "every frame after the gap or the odd image would be at a wrong table angle: put "
        "the missing image back (an image without a line keeps its place as an empty "
        "frame) or move the odd one out"
    )


@dataclasses.dataclass(frozen=True)
class FrameStripes:
    """One frame of a capture folder.

    **Fields:** `path` the laser-on image; `result` the `StripeResult` (None when the
    frame could not be used); `problem` why not (None when it could); `shape` the
    image's (H, W) (None if unreadable)."""

    path: str
    result: StripeResult | None
    problem: str | None
    shape: tuple[int, int] | None

    @property
    def uv(self) -> np.ndarray:
        """The valid centres `(N, 2)` (u, v) px; `(0, 2)` for an unusable frame."""
        return np.zeros((0, 2)) if self.result is None else self.result.valid_uv


def _load(pair: tuple[str, str | None]):
    on, off = pair
    image = read_image(on)
    if image is None:
        return None, None, "unreadable image"
    background = None
    if off is not None:
        background = read_image(off)
        if background is None:
            return image, None, f"unreadable laser-off image {os.path.basename(off)}"
    return image, background, None


def iter_folder_stripes(
    frames: Sequence[tuple[str, str | None]],
    *,
    workers: int | None = None,
    batch: int | None = None,
    **kwargs: Any,
) -> Iterator[FrameStripes]:
    """Stripe centres of each frame, in order, a batch of frames at a time.

    **Arguments:**
    - `frames`: `(laser-on, laser-off or None)` paths per frame (`frame_files`).
    - `workers`: threads reading and extracting frames (default: the number of CPUs).
      OpenCV's own thread pool is set to one thread meanwhile (restored afterwards).
    - `batch`: frames read per batch (default `2 workers`): the memory bound.
    - `**kwargs`: `extract_stripe` options (`method`, `width_px`, `orientation`,
      `channel`, ...).

    **Returns:** an iterator of one `FrameStripes` per frame. Every frame must have the
    size of the first readable one; others are yielded with that as their problem.
    """
    import cv2

    workers = (os.cpu_count() or 1) if workers is None else int(workers)
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    batch = 2 * workers if batch is None else int(batch)
    if batch < 1:
        raise ValueError(f"batch must be >= 1, got {batch}")
    shape: list[tuple[int, int]] = []  # the first readable frame's size

    def work(pair):
        image, background, problem = _load(pair)
        size = None if image is None else tuple(image.shape[:2])
        return pair[0], image, background, problem, size

    def extract(item):
        path, image, background, problem, size = item
        if problem is None and size != shape[0]:
            h, w = shape[0]
            problem = f"size {size[1]}x{size[0]} differs from {w}x{h}"
        if problem is not None:
            return FrameStripes(path, None, problem, size)
        try:
            return FrameStripes(path, extract_stripe(image, background=background, **kwargs),
                                None, size)  # fmt: skip
        except ValueError as err:
            return FrameStripes(path, None, str(err), size)

    previous = cv2.getNumThreads()
    if workers > 1:
        cv2.setNumThreads(1)
    try:
        with concurrent.futures.ThreadPoolExecutor(max_workers=workers) as pool:
            for start in range(0, len(frames), batch):
                loaded = list(pool.map(work, frames[start : start + batch]))
                if not shape:
                    sizes = [it[4] for it in loaded if it[3] is None]
                    if sizes:
                        shape.append(sizes[0])
                if not shape:  # nothing readable yet: every frame of the batch is refused
                    for path, _, _, problem, size in loaded:
                        yield FrameStripes(path, None, problem, size)
                    continue
                yield from pool.map(extract, loaded)
                del loaded
    finally:
        cv2.setNumThreads(previous)


def folder_stripe_frames(
    frames: Sequence[tuple[str, str | None]],
    *,
    report=None,
    workers: int | None = None,
    batch: int | None = None,
    **kwargs: Any,
) -> Iterator[np.ndarray]:
    """The valid centres `(N_i, 2)` of each frame (`(0, 2)` for an unusable frame or one
    without a line), in file order: the input of `reconstruct.iter_reconstruct` straight
    from images.

    **Arguments:** as `iter_folder_stripes`; `report`, if given, is called with each
    `FrameStripes` (to tell the user about skipped or empty frames).
    """
    for frame in iter_folder_stripes(frames, workers=workers, batch=batch, **kwargs):
        if report is not None:
            report(frame)
        yield frame.uv
