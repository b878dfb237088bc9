"""`scheimflux extract FRAMES_DIR --out STRIPES.json`: laser-line centres of a folder
of images.

Frames are the image files (png, tif, tiff, bmp, jpg, jpeg; 8- or 16-bit, grey or
colour) in FRAMES_DIR in natural name order (frame2 before frame10). Colour images are
used in the laser's channel (`--channel auto` picks it from each image, e.g. red minus
the other channels for a red laser under white light). With `--laser-off SUFFIX`, a
file NAME<SUFFIX>.EXT beside NAME.EXT is that pose's laser-off image: it is not a frame
itself, and the centres are found in the difference. Unreadable images, images of
another size than the first one, and images without a line are reported by name and
written as empty frames, so that frame indices match the file order. The parts of a
curved line too steep for the scan direction are taken from the other one (with
`--orientation auto`); with a given `--orientation` their length is reported as left out.
"""

from __future__ import annotations

import argparse
import os

import numpy as np

from ..io._stripes import write_stripes
from ..stripe._folder import (
    IMAGE_SUFFIXES as IMAGE_SUFFIXES,
    frame_files,
    iter_folder_stripes,
    read_image as read_image,
)
from ..stripe._image import CHANNELS
from ..stripe._steep import steep_note
from ._common import (
    CLIError,
    check_output,
    progress,
    refuse_to_clobber,
    require_positive,
    warn,
    warn_unmatched_laser_off,
)


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
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="threads extracting frames (default: the number of CPUs)",
    )
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    require_positive(args, "width_px")
    try:
        pairs = frame_files(args.frames_dir, args.laser_off)
    except ValueError as err:
        raise CLIError(str(err)) from None
    warn_unmatched_laser_off("extract", args.frames_dir, args.laser_off, pairs)
    if args.workers is not None and args.workers < 1:
        raise CLIError(f"--workers must be >= 1, got {args.workers}")
    refuse_to_clobber(args.out, overwrite=args.overwrite)
    check_output(args.out, overwrite=True)  # its folder takes a file: before the long part
    frames: list = []
    skipped: list[str] = []
    empty: list[str] = []
    n_points = 0
    n_steep = 0
    options = dict(
        method=args.method,
        width_px=args.width_px,
        orientation=args.orientation,
        channel=args.channel,
    )
    found = iter_folder_stripes(pairs, workers=args.workers, **options)
    for frame in progress(found, "extract", "frame"):
        name = os.path.basename(frame.path)
        result = frame.result
        if result is None:
            skipped.append(name)
            warn("extract", f"skipped {name}: {frame.problem}")
            frames.append(np.zeros((0, 2)))
            continue
        if not result.valid.any():
            empty.append(name)
            if result.steep_left_out_px <= 0:  # else: the line is there, too steep (below)
                warn(
                    "extract",
                    f"{name}: no laser line found (blank, line-free or saturated frame)",
                )
        elif result.ambiguous and args.orientation == "auto":
            warn(
                "extract",
                f"{name}: no dominant line direction; scanned {result.orientation} "
                "(set --orientation to choose)",
            )
        if result.steep_left_out_px > 0:
            warn("extract", steep_note(name, result))
        n_steep += bool(result.steep.any())
        frames.append(result)
        n_points += int(result.valid.sum())
    if len(skipped) == len(pairs):
        raise CLIError(f"none of the {len(pairs)} images in {args.frames_dir} could be read")
    write_stripes(args.out, frames, overwrite=args.overwrite)
    read = len(pairs) - len(skipped)
    print(
        f"extracted {n_points} points from {read} frame(s) into {args.out}"
        + (f"; {len(empty)} frame(s) without a line" if empty else "")
        + (
            f"; the steep parts of {n_steep} curved line(s) from the other scan direction"
            if n_steep
            else ""
        )
        + (f"; skipped {len(skipped)} unreadable frame(s)" if skipped else "")
    )
    return 0
