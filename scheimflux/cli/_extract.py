"""`scheimflux extract FRAMES_DIR --out STRIPES.json`: laser-stripe centres of a folder
of images.

Frames are the image files (png, tif, tiff, bmp, jpg, jpeg) in FRAMES_DIR in natural name
order (frame2 before frame10). Unreadable images are reported and written as empty
frames, so that frame indices match the file order.
"""

from __future__ import annotations

import argparse
import os
import re
import sys

import cv2
import numpy as np
from tqdm import tqdm

from ..io._stripes import write_stripes
from ..stripe._extract import extract_stripe
from ._main import CLIError

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".bmp", ".jpg", ".jpeg")


def natural_key(name: str) -> list:
    """Sort key that orders embedded numbers by value: `f2 < f10`."""
    return [int(p) if p.isdigit() else p.lower() for p in re.split(r"(\d+)", name)]


def list_frames(folder: str) -> list[str]:
    """Image files in `folder`, natural order."""
    if not os.path.isdir(folder):
        raise CLIError(f"{folder} is not a folder")
    names = [
        n
        for n in os.listdir(folder)
        if n.lower().endswith(IMAGE_SUFFIXES) and os.path.isfile(os.path.join(folder, n))
    ]
    return [os.path.join(folder, n) for n in sorted(names, key=natural_key)]


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
    paths = list_frames(args.frames_dir)
    if not paths:
        raise CLIError(f"no image files ({', '.join(IMAGE_SUFFIXES)}) in {args.frames_dir}")
    if os.path.exists(args.out) and not args.overwrite:
        raise CLIError(f"{args.out} exists; pass --overwrite to replace it")
    frames: list[np.ndarray] = []
    skipped: list[str] = []
    n_points = 0
    bar = tqdm(
        paths, desc="extract", unit="frame", file=sys.stderr, disable=not sys.stderr.isatty()
    )
    for path in bar:
        image = cv2.imread(path, cv2.IMREAD_UNCHANGED)
        if image is not None and image.ndim == 3:
            code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
            image = cv2.cvtColor(image, code)
        if image is None or image.size == 0:
            skipped.append(os.path.basename(path))
            tqdm.write(
                f"scheimflux extract: skipped unreadable image {os.path.basename(path)}",
                file=sys.stderr,
            )
            frames.append(np.zeros((0, 2)))
            continue
        try:
            result = extract_stripe(
                image, method=args.method, width_px=args.width_px, orientation=args.orientation
            )
        except ValueError as err:
            skipped.append(os.path.basename(path))
            tqdm.write(
                f"scheimflux extract: skipped {os.path.basename(path)}: {err}", file=sys.stderr
            )
            frames.append(np.zeros((0, 2)))
            continue
        frames.append(result.valid_uv)
        n_points += len(frames[-1])
    bar.close()
    if len(skipped) == len(paths):
        raise CLIError(f"none of the {len(paths)} images in {args.frames_dir} could be read")
    try:
        write_stripes(args.out, frames, overwrite=args.overwrite)
    except FileExistsError as err:
        raise CLIError(str(err)) from None
    read = len(paths) - len(skipped)
    print(
        f"extracted {n_points} points from {read} frame(s) into {args.out}"
        + (f"; skipped {len(skipped)} unreadable frame(s)" if skipped else "")
    )
    return 0
