"""`scheimflux extract FRAMES_DIR --out STRIPES.json`: laser-line centres of a folder
of images.

Frames are the image files (png, tif, tiff, bmp, jpg, jpeg; 8- or 16-bit, grey or
colour) in FRAMES_DIR in natural name order (frame2 before frame10). Colour images are
used in the laser's channel (`--channel auto` picks it from each image, e.g. red minus
the other channels for a red laser under white light). With `--laser-off SUFFIX`, a
file NAME<SUFFIX>.EXT beside NAME.EXT is that pose's laser-off image: it is not a frame
itself, and the centres are found in the difference. Unreadable images, images of
another size than the first one, and images without a line are reported by name and
written as empty frames, so that frame indices match the file order.
"""

from __future__ import annotations

import argparse
import os

import numpy as np

from ..io._stripes import write_stripes
from ..stripe._extract import extract_stripe
from ..stripe._image import CHANNELS
from ._common import CLIError, check_output, list_images, progress, refuse_to_clobber, warn

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".bmp", ".jpg", ".jpeg")


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "extract",
        help="extract sub-pixel laser-line centres from a folder of images",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("frames_dir", metavar="FRAMES_DIR", help="folder of image files")
    parser.add_argument("--out", required=True, metavar="STRIPES.json", help="output file")
    parser.add_argument("--method", choices=("steger", "centroid"), default="steger")
    parser.add_argument(
        "--width-px",
        type=float,
        default=None,
        metavar="W",
        help="expected line width (FWHM, px); measured from the images if left out",
    )
    parser.add_argument(
        "--orientation",
        choices=("auto", "vertical-scan", "horizontal-scan"),
        default="auto",
        help="scan columns (vertical-scan, for a horizontal line) or rows; auto: per image",
    )
    parser.add_argument(
        "--channel",
        choices=CHANNELS,
        default="auto",
        help="colour channel or combination holding the laser (default: %(default)s)",
    )
    parser.add_argument(
        "--laser-off",
        metavar="SUFFIX",
        default=None,
        help="NAME<SUFFIX>.EXT is the laser-off image of NAME.EXT (e.g. _off); "
        "the difference is used",
    )
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    parser.set_defaults(func=run)


def read_image(path: str) -> np.ndarray | None:
    """The image as stored (grey (H, W) or BGR (H, W, 3); alpha dropped), or None when it
    cannot be read."""
    import cv2

    try:
        image = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    except cv2.error:
        return None
    if image is None or image.size == 0 or image.ndim not in (2, 3):
        return None
    if image.ndim == 3:
        if image.shape[2] == 1:
            image = image[:, :, 0]
        elif image.shape[2] >= 3:
            image = np.ascontiguousarray(image[:, :, :3])
        else:
            return None
    return image


def _pair(paths: list[str], suffix: str | None) -> list[tuple[str, str | None]]:
    """(laser-on, laser-off or None) per frame; laser-off files are not frames."""
    if not suffix:
        return [(p, None) for p in paths]
    stems = {os.path.splitext(p)[0]: p for p in paths}
    off = {p for p in paths if os.path.splitext(p)[0].endswith(suffix)}
    out = []
    for p in paths:
        if p in off:
            continue
        out.append((p, stems.get(os.path.splitext(p)[0] + suffix)))
    return out


def run(args: argparse.Namespace) -> int:
    paths = list_images(args.frames_dir, IMAGE_SUFFIXES)
    if not paths:
        raise CLIError(f"no image files ({', '.join(IMAGE_SUFFIXES)}) in {args.frames_dir}")
    pairs = _pair(paths, args.laser_off)
    if not pairs:
        raise CLIError(f"only laser-off images (*{args.laser_off}.*) in {args.frames_dir}")
    refuse_to_clobber(args.out, overwrite=args.overwrite)
    check_output(args.out, overwrite=True)  # its folder takes a file: before the long part
    frames: list = []
    skipped: list[str] = []
    empty: list[str] = []
    shape = None
    n_points = 0
    for path, off_path in progress(pairs, "extract", "frame"):
        name = os.path.basename(path)
        image = read_image(path)
        problem = None
        if image is None:
            problem = "unreadable image"
        elif shape is not None and image.shape[:2] != shape:
            problem = f"size {image.shape[1]}x{image.shape[0]} differs from {shape[1]}x{shape[0]}"
        background = None
        if problem is None and off_path is not None:
            background = read_image(off_path)
            if background is None:
                problem = f"unreadable laser-off image {os.path.basename(off_path)}"
        if problem is None:
            try:
                result = extract_stripe(
                    image,
                    method=args.method,
                    width_px=args.width_px,
                    orientation=args.orientation,
                    channel=args.channel,
                    background=background,
                )
            except ValueError as err:
                problem = str(err)
        if problem is not None:
            skipped.append(name)
            warn("extract", f"skipped {name}: {problem}")
            frames.append(np.zeros((0, 2)))
            continue
        shape = image.shape[:2] if shape is None else shape
        if not result.valid.any():
            empty.append(name)
            warn("extract", f"{name}: no laser line found (blank, line-free or saturated frame)")
        elif result.ambiguous and args.orientation == "auto":
            warn(
                "extract",
                f"{name}: no dominant line direction; scanned {result.orientation} "
                "(set --orientation to choose)",
            )
        frames.append(result)
        n_points += int(result.valid.sum())
    if len(skipped) == len(pairs):
        raise CLIError(f"none of the {len(pairs)} images in {args.frames_dir} could be read")
    write_stripes(args.out, frames, overwrite=args.overwrite)
    read = len(pairs) - len(skipped)
    print(
        f"extracted {n_points} points from {read} frame(s) into {args.out}"
        + (f"; {len(empty)} frame(s) without a line" if empty else "")
        + (f"; skipped {len(skipped)} unreadable frame(s)" if skipped else "")
    )
    return 0
