"""`scheimflux extract FRAMES_DIR --out STRIPES.json`: laser-stripe centres of a folder
of images.

Frames are the image files (png, tif, tiff, bmp, jpg, jpeg) in FRAMES_DIR in natural name
order (frame2 before frame10). Unreadable images are reported and written as empty
frames, so that frame indices match the file order.
"""

from __future__ import annotations

import argparse
import os

import numpy as np

from ..io._stripes import write_stripes
from ..stripe._extract import extract_stripe
from ._common import CLIError, list_images, progress, read_grey, refuse_to_clobber, warn

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".bmp", ".jpg", ".jpeg")


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "extract",
        help="extract sub-pixel laser-stripe centres from a folder of images",
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
        help="expected stripe width (FWHM, px); measured from the images if left out",
    )
    parser.add_argument(
        "--orientation",
        choices=("auto", "vertical-scan", "horizontal-scan"),
        default="auto",
        help="scan columns (vertical-scan, for a horizontal stripe) or rows",
    )
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    paths = list_images(args.frames_dir, IMAGE_SUFFIXES)
    if not paths:
        raise CLIError(f"no image files ({', '.join(IMAGE_SUFFIXES)}) in {args.frames_dir}")
    refuse_to_clobber(args.out, overwrite=args.overwrite)
    frames: list[np.ndarray] = []
    skipped: list[str] = []
    n_points = 0
    for path in progress(paths, "extract", "frame"):
        name = os.path.basename(path)
        image = read_grey(path)
        if image is None:
            skipped.append(name)
            warn("extract", f"skipped unreadable image {name}")
            frames.append(np.zeros((0, 2)))
            continue
        try:
            result = extract_stripe(
                image, method=args.method, width_px=args.width_px, orientation=args.orientation
            )
        except ValueError as err:
            skipped.append(name)
            warn("extract", f"skipped {name}: {err}")
            frames.append(np.zeros((0, 2)))
            continue
        frames.append(result.valid_uv)
        n_points += len(frames[-1])
    if len(skipped) == len(paths):
        raise CLIError(f"none of the {len(paths)} images in {args.frames_dir} could be read")
    write_stripes(args.out, frames, overwrite=args.overwrite)
    read = len(paths) - len(skipped)
    print(
        f"extracted {n_points} points from {read} frame(s) into {args.out}"
        + (f"; skipped {len(skipped)} unreadable frame(s)" if skipped else "")
    )
    return 0
