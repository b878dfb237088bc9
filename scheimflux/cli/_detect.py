"""`scheimflux detect IMAGES_DIR --board 11x8 --square-mm 0.3 --out OBS.json`: checkerboard
corners and laser-stripe pixels of a calibration session, written as an observations file
(`scheimflux.observations/1`).

File naming in IMAGES_DIR, one pair per board pose (view) k = 0, 1, 2, ...:
  view_<k>_board.png    the checkerboard, laser off
  view_<k>_stripe.png   the laser stripe on the board in the same pose, room light dim
(.tif, .tiff and .bmp are accepted as well.) Views are sorted by the number <k> (view_2
before view_10). A view without a stripe image gets an empty stripe list; a stripe image
without a board image is ignored; both are reported. Other files are ignored.

Corners follow the board's point order (first corner top-left on the upright board,
running along the first row; see `scheimflux.targets.Checkerboard`). A board image in
which the board is not found still gives a view, with all corners null and the reason
printed. Unreadable or corrupt images are reported by name and skipped. All images must
have the size of the first one.

--scan SCAN_DIR adds the rotary-stage scan of a ring gauge: every image in SCAN_DIR, in
natural name order, is one frame (the table turned by --delta-omega-deg between frames);
an unreadable frame is reported and kept as an empty frame so frame indices stay right.

Exits 0 when at least one board was detected.
"""

from __future__ import annotations

import argparse
import os
import re

import numpy as np

from ._common import (
    CLIError,
    list_images,
    natural_key,
    progress,
    read_grey,
    refuse_to_clobber,
    require_positive,
    warn,
)

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".bmp")
_VIEW = re.compile(r"^view_(\d+)_(board|stripe)\.(png|tif|tiff|bmp)$", re.IGNORECASE)


def _report(message: str) -> None:
    warn("detect", message)


def find_views(folder: str) -> tuple[list[tuple[int, str | None, str | None]], list[str]]:
    """`[(k, board_path, stripe_path), ...]` sorted by k, and the names that were ignored."""
    if not os.path.isdir(folder):
        raise CLIError(f"{folder} is not a folder")
    views: dict[int, dict[str, str]] = {}
    ignored = []
    for name in sorted(os.listdir(folder), key=natural_key):
        path = os.path.join(folder, name)
        m = _VIEW.match(name)
        if m is None or not os.path.isfile(path):
            ignored.append(name)
            continue
        k, kind = int(m.group(1)), m.group(2).lower()
        slot = views.setdefault(k, {})
        if kind in slot:
            raise CLIError(
                f"two {kind} images for view {k}: {os.path.basename(slot[kind])}, {name}"
            )
        slot[kind] = path
    return [(k, v.get("board"), v.get("stripe")) for k, v in sorted(views.items())], ignored


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "detect",
        help="detect checkerboard corners and laser stripes in calibration images",
        description=__doc__.split("\n\n")[0],
        epilog="\n\n".join(__doc__.split("\n\n")[1:]),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("images_dir", metavar="IMAGES_DIR", help="folder of view_<k>_board/stripe.png")
    p.add_argument("--board", required=True, metavar="COLSxROWS", help="inner corners, e.g. 11x8")
    p.add_argument("--square-mm", required=True, type=float, metavar="S", help="square side (mm)")
    p.add_argument("--out", required=True, metavar="OBS.json", help="observations file to write")
    p.add_argument(
        "--pixel-pitch-mm",
        nargs=2,
        type=float,
        default=(0.0044, 0.0044),
        metavar=("DX", "DY"),
        help="sensor pixel pitch from the datasheet (default: 0.0044 0.0044)",
    )
    p.add_argument("--focal-length-mm", type=float, metavar="F", help="nominal focal length")
    p.add_argument("--magnification", type=float, metavar="M", help="nominal magnification")
    p.add_argument(
        "--tilt-deg", nargs=2, type=float, metavar=("PHI", "THETA"), help="nominal sensor tilt"
    )
    p.add_argument("--scan", metavar="SCAN_DIR", help="folder of rotary-stage scan frames")
    p.add_argument("--delta-omega-deg", type=float, metavar="D", help="stage step per frame")
    p.add_argument("--gauge-radius-mm", type=float, metavar="R", help="nominal gauge radius")
    p.add_argument(
        "--stripe-width-px",
        type=float,
        metavar="W",
        help="expected stripe width (FWHM, px); measured from the images if left out",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    p.set_defaults(func=run)


class _SizeCheck:
    def __init__(self):
        self.shape: tuple[int, int] | None = None
        self.first = ""

    def __call__(self, image: np.ndarray, path: str) -> None:
        if self.shape is None:
            self.shape, self.first = image.shape[:2], os.path.basename(path)
        elif image.shape[:2] != self.shape:
            h, w = image.shape[:2]
            raise CLIError(
                f"{path} is {w}x{h} px but {self.first} is {self.shape[1]}x{self.shape[0]} px; "
                "all images must come from the same sensor"
            )


def _stripe(image, width, path) -> np.ndarray:
    from ..stripe import extract_stripe

    try:
        return extract_stripe(image, width_px=width).valid_uv
    except ValueError as err:
        _report(f"{os.path.basename(path)}: no stripe extracted: {err}")
        return np.zeros((0, 2))


def _check_args(args) -> None:
    require_positive(args, "square_mm")
    if any(not (p > 0) for p in args.pixel_pitch_mm):
        raise CLIError(f"--pixel-pitch-mm must be positive, got {args.pixel_pitch_mm}")
    require_positive(args, "focal_length_mm", "magnification", "gauge_radius_mm", "stripe_width_px")
    if args.scan is not None:
        if args.delta_omega_deg is None or args.gauge_radius_mm is None:
            raise CLIError("--scan needs --delta-omega-deg and --gauge-radius-mm")
        if not os.path.isdir(args.scan):
            raise CLIError(f"--scan {args.scan} is not a folder")
    elif args.delta_omega_deg is not None or args.gauge_radius_mm is not None:
        raise CLIError("--delta-omega-deg and --gauge-radius-mm need --scan SCAN_DIR")
    refuse_to_clobber(args.out, overwrite=args.overwrite)


def run(args: argparse.Namespace) -> int:
    from ..io._observations import Nominal, Observations, StageScan, View, write_observations
    from ..targets._board import Checkerboard
    from ..targets._detect import detect_checkerboard

    _check_args(args)
    board = Checkerboard.parse(args.board, args.square_mm)
    entries, ignored = find_views(args.images_dir)
    if not entries:
        raise CLIError(
            f"no view_<k>_board.png images in {args.images_dir} (see scheimflux detect --help)"
        )
    if ignored:
        _report(
            f"ignored {len(ignored)} file(s) not named view_<k>_board/stripe: "
            + ", ".join(ignored[:5])
            + (" ..." if len(ignored) > 5 else "")
        )
    size = _SizeCheck()
    views: list = []
    n_found = 0
    problems = 0
    for k, board_path, stripe_path in progress(entries, "detect", "view"):
        if board_path is None:
            _report(f"view {k}: {os.path.basename(stripe_path)} has no board image; ignored")
            problems += 1
            continue
        image = read_grey(board_path)
        if image is None:
            _report(f"skipped unreadable image {os.path.basename(board_path)} (view {k})")
            problems += 1
            continue
        size(image, board_path)
        result = detect_checkerboard(image, board)
        if result.found:
            n_found += 1
            if result.message:
                _report(f"{os.path.basename(board_path)}: {result.message}")
        else:
            problems += 1
            _report(f"{os.path.basename(board_path)}: board not found: {result.message}")
        stripe = np.zeros((0, 2))
        if stripe_path is None:
            _report(f"view {k}: no stripe image (view_{k}_stripe.png); empty stripe list")
        else:
            simg = read_grey(stripe_path)
            if simg is None:
                problems += 1
                _report(f"skipped unreadable image {os.path.basename(stripe_path)} (view {k})")
            else:
                size(simg, stripe_path)
                stripe = _stripe(simg, args.stripe_width_px, stripe_path)
        views.append(View(result.corners_px, stripe))

    stage = None
    if args.scan is not None:
        paths = list_images(args.scan, IMAGE_SUFFIXES)
        if not paths:
            raise CLIError(f"no image files ({', '.join(IMAGE_SUFFIXES)}) in --scan {args.scan}")
        frames = []
        for path in progress(paths, "scan", "frame"):
            image = read_grey(path)
            if image is None:
                problems += 1
                _report(f"unreadable scan frame {os.path.basename(path)} kept as an empty frame")
                frames.append(np.zeros((0, 2)))
                continue
            size(image, path)
            frames.append(_stripe(image, args.stripe_width_px, path))
        stage = StageScan(float(args.delta_omega_deg), float(args.gauge_radius_mm), frames)

    if n_found == 0:
        raise CLIError(f"no checkerboard {board.size} found in any image of {args.images_dir}")
    nominal = None
    if args.focal_length_mm is not None or args.magnification is not None or args.tilt_deg:
        nominal = Nominal(
            args.focal_length_mm,
            args.magnification,
            None if args.tilt_deg is None else tuple(args.tilt_deg),
        )
    h, w = size.shape
    obs = Observations(
        width=int(w),
        height=int(h),
        pixel_pitch_mm=tuple(float(p) for p in args.pixel_pitch_mm),
        board_points_mm=board.points_mm,
        views=views,
        nominal=nominal,
        stage=stage,
    )
    write_observations(args.out, obs, overwrite=args.overwrite)
    n_stripe = sum(len(v.stripe_px) for v in views)
    print(
        f"{n_found} of {len(views)} view(s) with the board found, {n_stripe} stripe points"
        + (f", {len(stage.frames)} scan frame(s)" if stage else "")
        + f" -> {args.out}"
        + (f" ({problems} problem(s) reported above)" if problems else "")
    )
    return 0
