"""Capture folders: which image files make up which view, and reading them.

Per board pose (view) `k = 0, 1, 2, ...` a folder holds either

- one image with the board and the laser line: `view_<k>.<ext>` (layout `"single"`), or
- a pair: `view_<k>_board.<ext>` (laser off) and `view_<k>_stripe.<ext>` (laser on, the
  board in the same pose; layout `"pair"`),

and, beside a single image, optionally `view_<k>_off.<ext>`: the same pose with the laser
off (room light as in `view_<k>`). With it the target is detected in a laser-free image
and the line is extracted from the difference (`extract_stripe(..., background=)`),
which is what makes grey single-image captures as good as pairs.

`<ext>` is one of `png`, `jpg`, `jpeg`, `tif`, `tiff`, `bmp` (any case). Views are
sorted by the number `k` (view_2 before view_10); the numbers need not be contiguous.
The two layouts may be mixed across views, not within one view. Any other file is
ignored (and listed).
"""

from __future__ import annotations

import dataclasses
import os
import re

from .._image import IMAGE_SUFFIXES as IMAGE_SUFFIXES, read_image as read_image

__all__ = ["IMAGE_SUFFIXES", "CaptureView", "find_captures", "natural_key", "read_image"]

_VIEW = re.compile(r"^view_(\d+)(?:_(board|stripe|off))?\.(png|jpe?g|tiff?|bmp)$", re.IGNORECASE)


def natural_key(name: str) -> list:
    """Sort key that orders embedded numbers by value: `f2 < f10`."""
    return [(0, int(p), "") if p.isdigit() else (1, 0, p.lower()) for p in re.split(r"(\d+)", name)]


@dataclasses.dataclass(frozen=True)
class CaptureView:
    """The image files of one view.

    **Fields:**
    - `view`: the number `k` in the file names.
    - `board`: path of the image the target is detected in (`view_<k>.<ext>` or
      `view_<k>_board.<ext>`); None when only a stripe image exists.
    - `stripe`: path of the image the laser line is extracted from (the same file as
      `board` in the single-image layout); None when a pair lacks its stripe image.
    - `off`: path of the laser-off image of a single-image view (`view_<k>_off.<ext>`),
      or None.
    """

    view: int
    board: str | None
    stripe: str | None
    off: str | None = None

    @property
    def layout(self) -> str:
        return "single" if self.board is not None and self.board == self.stripe else "pair"

    @property
    def names(self) -> tuple[str, ...]:
        """The distinct file names of the view (board first)."""
        out = []
        for p in (self.board, self.stripe, self.off):
            if p is not None and os.path.basename(p) not in out:
                out.append(os.path.basename(p))
        return tuple(out)


def find_captures(folder: str | os.PathLike) -> tuple[list[CaptureView], list[str]]:
    """The views of a capture folder (see the module doc) and the names ignored.

    **Returns:** `(views, ignored)`: views sorted by number, ignored names in natural
    order (a folder's with a trailing "/"). Raises `ValueError` naming the files when a
    view has two images of one kind (e.g. `view_3.png` and `view_3.jpg`, or `view_3.png`
    and `view_3_board.png`) or a laser-off image without its single image
    (`view_3_off.png` beside a pair, or alone), and `NotADirectoryError` /
    `FileNotFoundError` for a missing folder.
    """
    folder = os.fspath(folder)
    if not os.path.exists(folder):
        raise FileNotFoundError(f"capture folder {folder} not found")
    if not os.path.isdir(folder):
        raise NotADirectoryError(f"{folder} is not a folder")
    slots: dict[int, dict[str, str]] = {}
    ignored = []
    for name in sorted(os.listdir(folder), key=natural_key):
        path = os.path.join(folder, name)
        m = _VIEW.match(name)
        if m is None or not os.path.isfile(path):
            ignored.append(name + "/" if os.path.isdir(path) else name)  # a folder shown as one
            continue
        k, kind = int(m.group(1)), (m.group(2) or "single").lower()
        slot = slots.setdefault(k, {})
        if kind == "off":
            clash = slot.get("off")
        elif kind == "single":
            clash = slot.get("single") or slot.get("board") or slot.get("stripe")
        else:
            clash = slot.get(kind) or slot.get("single")
        if clash is not None:
            raise ValueError(
                f"view {k} has two images for one purpose in {folder}: "
                f"{os.path.basename(clash)} and {name} (keep one)"
            )
        slot[kind] = path
    views = []
    for k, slot in sorted(slots.items()):
        if "off" in slot and "single" not in slot:
            raise ValueError(
                f"{os.path.basename(slot['off'])} in {folder} is a laser-off image for the "
                f"single-image layout, but there is no view_{k}.<ext> (a pair's board image "
                "is already laser off: remove it or rename the view)"
            )
        if "single" in slot:
            views.append(CaptureView(k, slot["single"], slot["single"], slot.get("off")))
        else:
            views.append(CaptureView(k, slot.get("board"), slot.get("stripe")))
    return views, ignored
