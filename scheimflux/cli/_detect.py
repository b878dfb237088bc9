"""`scheimflux detect IMAGES_DIR --board 11x8 --square-mm 0.3 --out OBS.json`: target points
and laser-stripe pixels of a calibration session, written as an observations file
(`scheimflux.observations/1`).

File naming in IMAGES_DIR, per board pose (view) k = 0, 1, 2, ... either
  view_<k>.<ext>          one image with the board and the laser line on it, or
  view_<k>_board.<ext>    the board, laser off, and
  view_<k>_stripe.<ext>   the laser line on the board in the same pose;
beside a single image optionally view_<k>_off.<ext>, the same pose with the laser off
(the target is then detected in it and the line found in the difference: best for grey
cameras). <ext>: png, jpg, jpeg, tif, tiff or bmp (grey or colour, 8 or 16 bits). Views are
sorted by the number <k> (view_2 before view_10). Other files are ignored (and listed).

Targets (--target): checkerboard (--board = inner corners COLSxROWS), charuco (--board =
squares SXxSY, --marker-mm, --dictionary; partly visible boards count), circles and
acircles (symmetric / asymmetric circle grids, --board = circles per row x rows,
--spacing-mm, --circle-diameter-mm). Point orders: see docs/capture.md.

A view whose target is not found (or whose image cannot be read, or that has only a
stripe image) is left out of the observations; it is printed with the reason and listed
under "dropped_views" in the file. Every view records its source image names. In a pair
(and a single image with its laser-off image) the board's motion between its two images
is measured where the laser-on image shows the board by room light: a board that moved
more than 0.1 px has its stripe refused (its points kept), and a view whose laser-on
image is too dark to tell is reported unchecked (keep the room light on). The laser
line is extracted only inside the board region (the target's outline, grown by
--board-margin-px). --preview DIR writes view_<k>_preview.png overlays.

--scan SCAN_DIR adds the rotary-stage scan of a ring gauge: every image in SCAN_DIR, in
natural name order, is one frame (the table turned by --delta-omega-deg between frames);
an unreadable frame is reported and kept as an empty frame so frame indices stay right.

--stage-target DIR adds a target fixed to the rotary table (the table axis from its
turning, docs/stage.md): every image in DIR, in natural name order, is one table step (the
table turned by --delta-omega-deg between images); NAME_off.EXT beside NAME.EXT is that
step with the laser off (no step of its own). The laser line on the table target is
extracted as on the boards (into the step's stripe_px), and in grey images without a
laser-off image the target points within its reach are dropped. A step whose target is
not found is dropped with the reason and the others keep their step numbers. The table
target is the
calibration target unless --stage-target-board/--stage-target-square-mm give another
(same --target kind); a circle grid's dot diameter there is
--stage-target-circle-diameter-mm, else --circle-diameter-mm, else measured in the step
images.

Exits 0 when the target was found in at least one view.
"""

from __future__ import annotations

import argparse
import glob
import math
import os

from ._common import CLIError, check_output, refuse_to_clobber, require_positive, warn


def _report(message: str) -> None:
    warn("detect", message)


def register(subparsers) -> None:
    from ..targets._charuco import aruco_dictionary_names  # noqa: F401 (fail early on old cv2)
    from ..targets._target import TARGET_KINDS

    p = subparsers.add_parser(
        "detect",
        help="detect calibration targets and laser stripes in a folder of captures",
        description=__doc__.split("\n\n")[0],
        epilog="\n\n".join(__doc__.split("\n\n")[1:]),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "images_dir", metavar="IMAGES_DIR", help="folder of view_<k>[_board|_stripe|_off].*"
    )
    p.add_argument(
        "--target",
        choices=TARGET_KINDS,
        default="checkerboard",
        help="calibration target (default: %(default)s)",
    )
    p.add_argument(
        "--board",
        required=True,
        metavar="COLSxROWS",
        help="checkerboard inner corners, ChArUco squares, or circles per row x rows",
    )
    p.add_argument(
        "--square-mm",
        "--spacing-mm",
        dest="square_mm",
        required=True,
        type=float,
        metavar="S",
        help="square side (checkerboard, ChArUco) or circle spacing (circle grids), mm",
    )
    p.add_argument("--marker-mm", type=float, metavar="M", help="ChArUco marker side (0.7 S)")
    p.add_argument(
        "--dictionary",
        default="DICT_4X4_50",
        metavar="NAME",
        help="ChArUco: OpenCV predefined ArUco dictionary (default: %(default)s)",
    )
    p.add_argument(
        "--circle-diameter-mm",
        type=float,
        metavar="D",
        help="printed circle diameter (default: measured in the images)",
    )
    p.add_argument("--mirrored", action="store_true", help="images taken through a mirror")
    p.add_argument(
        "--min-points", type=int, default=6, metavar="N",
        help="fewest target points a view needs (default: %(default)s)",
    )  # fmt: skip
    p.add_argument("--out", required=True, metavar="OBS.json", help="observations file to write")
    p.add_argument(
        "--pixel-pitch-mm",
        nargs=2,
        type=float,
        default=None,
        metavar=("DX", "DY"),
        help="sensor pixel pitch from the datasheet, recorded in the file (the thick-lens "
        "model needs it; no default)",
    )
    p.add_argument("--focal-length-mm", type=float, metavar="F", help="nominal focal length")
    p.add_argument("--magnification", type=float, metavar="M", help="nominal magnification")
    p.add_argument(
        "--tilt-deg", nargs=2, type=float, metavar=("PHI", "THETA"), help="nominal sensor tilt"
    )
    p.add_argument("--scan", metavar="SCAN_DIR", help="folder of rotary-stage scan frames")
    p.add_argument(
        "--stage-target", metavar="DIR", help="folder of a target on the rotary table, one "
        "image per table step (natural name order)",
    )  # fmt: skip
    p.add_argument(
        "--stage-target-board", metavar="COLSxROWS", help="the table target's --board "
        "(default: --board)",
    )  # fmt: skip
    p.add_argument(
        "--stage-target-square-mm", type=float, metavar="S", help="the table target's "
        "--square-mm (default: --square-mm)",
    )  # fmt: skip
    p.add_argument(
        "--stage-target-circle-diameter-mm", type=float, metavar="D", help="the table "
        "target's --circle-diameter-mm (default: --circle-diameter-mm, else measured in "
        "its images)",
    )  # fmt: skip
    p.add_argument(
        "--delta-omega-deg", type=float, metavar="D",
        help="table step between scan frames / stage-target images",
    )  # fmt: skip
    p.add_argument("--gauge-radius-mm", type=float, metavar="R", help="nominal gauge radius")
    p.add_argument(
        "--stripe-width-px",
        type=float,
        metavar="W",
        help="expected stripe width (FWHM, px); measured from the images if left out",
    )
    p.add_argument(
        "--board-margin-px",
        type=float,
        metavar="PX",
        help="growth of the board region for stripes (default: half a square / spacing)",
    )
    p.add_argument("--preview", metavar="DIR", help="write view_<k>_preview.png overlays here")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out/previews")
    p.set_defaults(func=run)


def _check_args(args) -> None:
    require_positive(args, "square_mm")
    if args.pixel_pitch_mm is not None and any(not (p > 0) for p in args.pixel_pitch_mm):
        raise CLIError(f"--pixel-pitch-mm must be positive, got {args.pixel_pitch_mm}")
    require_positive(
        args, "focal_length_mm", "magnification", "gauge_radius_mm", "stripe_width_px",
        "marker_mm", "circle_diameter_mm", "stage_target_circle_diameter_mm",
    )  # fmt: skip
    require_positive(args, "board_margin_px", zero_ok=True)
    if args.min_points < 4:
        raise CLIError(f"--min-points must be at least 4, got {args.min_points}")
    if args.marker_mm is not None and args.target != "charuco":
        raise CLIError("--marker-mm is for --target charuco")
    for name in ("circle_diameter_mm", "stage_target_circle_diameter_mm"):
        if getattr(args, name) is not None and args.target not in ("circles", "acircles"):
            raise CLIError(f"--{name.replace('_', '-')} is for --target circles or acircles")
    if args.scan is not None:
        if args.delta_omega_deg is None or args.gauge_radius_mm is None:
            raise CLIError("--scan needs --delta-omega-deg and --gauge-radius-mm")
        if not os.path.isdir(args.scan):
            raise CLIError(f"--scan {args.scan} is not a folder")
        from ..stripe._folder import frame_files, numbering_problem, numbering_refusal

        try:
            numbering = numbering_problem([p for p, _ in frame_files(args.scan)])
        except ValueError as err:  # no image in it
            raise CLIError(f"--scan: {err}") from None
        if numbering:
            raise CLIError("--scan " + numbering_refusal(args.scan, numbering, "--delta-omega-deg"))
    elif args.gauge_radius_mm is not None:
        raise CLIError("--gauge-radius-mm needs --scan SCAN_DIR")
    if args.stage_target is not None:
        if args.delta_omega_deg is None:
            raise CLIError("--stage-target needs --delta-omega-deg (the table step per image)")
        if not os.path.isdir(args.stage_target):
            raise CLIError(f"--stage-target {args.stage_target} is not a folder")
    elif (
        args.stage_target_board is not None
        or args.stage_target_square_mm is not None
        or args.stage_target_circle_diameter_mm is not None
    ):
        raise CLIError(
            "--stage-target-board, --stage-target-square-mm and "
            "--stage-target-circle-diameter-mm need --stage-target"
        )
    if args.delta_omega_deg is not None:
        if args.scan is None and args.stage_target is None:
            raise CLIError("--delta-omega-deg needs --scan SCAN_DIR or --stage-target DIR")
        if not (math.isfinite(args.delta_omega_deg) and args.delta_omega_deg != 0.0):
            raise CLIError(
                f"--delta-omega-deg must be a non-zero angle, got {args.delta_omega_deg}"
            )
    require_positive(args, "stage_target_square_mm")
    if not os.path.isdir(args.images_dir):
        raise CLIError(f"{args.images_dir} is not a folder")
    refuse_to_clobber(args.out, overwrite=args.overwrite)
    check_output(args.out, overwrite=True)  # its folder takes a file: before the long part
    if args.preview is not None:
        if os.path.exists(args.preview) and not os.path.isdir(args.preview):
            raise CLIError(f"--preview {args.preview} exists and is not a folder")
        old = sorted(glob.glob(os.path.join(glob.escape(args.preview), "view_*_preview.png")))
        if old and not args.overwrite:
            raise CLIError(f"{old[0]} exists; pass --overwrite to replace the previews")


def run(args: argparse.Namespace) -> int:
    from ..capture._session import detect_session
    from ..io._observations import write_observations
    from ..targets._target import make_target

    _check_args(args)
    target = make_target(
        args.target,
        args.board,
        args.square_mm,
        marker_mm=args.marker_mm,
        dictionary=args.dictionary,
        diameter_mm=args.circle_diameter_mm,
    )
    table_target = None
    table_given = args.stage_target_circle_diameter_mm
    if table_given is None:
        table_given = args.circle_diameter_mm
    own_table = args.stage_target_board is not None or args.stage_target_square_mm is not None
    if own_table or args.stage_target_circle_diameter_mm is not None:
        table_target = make_target(
            args.target,
            args.stage_target_board or args.board,
            args.stage_target_square_mm or args.square_mm,
            marker_mm=args.marker_mm,
            dictionary=args.dictionary,
            diameter_mm=table_given,
        )
    obs, report = detect_session(
        args.images_dir,
        target,
        pixel_pitch_mm=args.pixel_pitch_mm,
        focal_length_mm=args.focal_length_mm,
        magnification=args.magnification,
        tilt_deg=args.tilt_deg,
        scan=args.scan,
        delta_omega_deg=args.delta_omega_deg,
        gauge_radius_mm=args.gauge_radius_mm,
        stage_target=args.stage_target,
        stage_target_board=table_target,
        stripe_width_px=args.stripe_width_px,
        margin_px=args.board_margin_px,
        min_points=args.min_points,
        mirrored=args.mirrored,
        preview_dir=args.preview,
        on_note=_report,
    )
    obs, circle_notes = _circle_diameters(args, obs, report, table_given, own_table)
    write_observations(args.out, obs, overwrite=args.overwrite)
    n_stripe = sum(len(v.stripe_px) for v in obs.views)
    n_points = sum(int(v.corner_mask.sum()) for v in obs.views)
    total = len(obs.views) + len(report.dropped)
    print(
        f"{target}: found in {len(obs.views)} of {total} view(s) ({n_points} points), "
        f"{n_stripe} stripe points"
        + (f", {len(obs.stage.frames)} scan frame(s)" if obs.stage else "")
        + (
            f", table target at {len(obs.stage_target.table_steps)} of "
            f"{len(obs.stage_target.table_steps) + len(obs.stage_target.dropped)} table step(s)"
            f" ({sum(len(p) for p in obs.stage_target.stripe_px)} laser-line points on it)"
            if obs.stage_target
            else ""
        )
        + f" -> {args.out}"
    )
    if report.dropped:
        print(f"dropped {len(report.dropped)} view(s): {_by_reason(report.dropped, 'view')}")
    if report.motion_summary():
        print(report.motion_summary())
    if report.speckle_summary():
        print(report.speckle_summary())
    if obs.stage_target is not None and obs.stage_target.dropped:
        dropped = obs.stage_target.dropped
        print(f"dropped {len(dropped)} table step(s): {_by_reason(dropped, 'step')}")
    if report.previews:
        print(f"{len(report.previews)} preview(s) in {args.preview}")
    for line in circle_notes:
        print(line)
    return 0


CIRCLE_DIAMETER_TOLERANCE = 0.1  # relative; the measurement is within ~0.1 % on renders


def _circle_diameters(args, obs, report, table_given, own_table) -> tuple:
    """`(observations, notes)`: the circle diameters to write (the boards' and the table
    target's; calibration models each circle's detected point as the centroid of its
    image, which needs the printed diameter) and one line per choice made. Given: kept,
    with a warning when the images measure it more than 10 % off. Not given: the
    diameter measured in the images (the table target's own steps, else, for the boards'
    own target, the boards'), else half the spacing, said either way."""
    import dataclasses

    notes = []
    if obs.circle_diameter_mm is not None:
        d, note = _circle_diameter(
            "the circles", "--circle-diameter-mm", obs.circle_diameter_mm,
            args.circle_diameter_mm, report.measured_circle_diameter_mm(),
            len(report.circle_diameters_mm), "in the images",
        )  # fmt: skip
        obs = dataclasses.replace(obs, circle_diameter_mm=d)
        notes.append(note)
    st = obs.stage_target
    if st is not None and st.circle_diameter_mm is not None:
        measured = report.measured_table_circle_diameter_mm()
        n, where = len(report.table_circle_diameters_mm), "in its step images"
        if measured is None and not own_table:  # the boards' target: measured there
            measured, where = report.measured_circle_diameter_mm(), "on the boards"
            n = len(report.circle_diameters_mm)
        option = (
            "--stage-target-circle-diameter-mm"
            if args.stage_target_circle_diameter_mm is not None
            else "--circle-diameter-mm"
        )
        d, note = _circle_diameter(
            "the table target's circles", option, st.circle_diameter_mm, table_given,
            measured, n, where,
        )  # fmt: skip
        obs = dataclasses.replace(obs, stage_target=dataclasses.replace(st, circle_diameter_mm=d))
        notes.append(note)
    return obs, [n for n in notes if n]


def _circle_diameter(what, option, assumed, given, measured, n, where) -> tuple[float, str]:
    """`(diameter, note)` for one target's circles (`what`): `given` (stated by `option`)
    kept, warned about when `measured` (the median of `n` measured `where`) is more than
    10 % off it; else `measured`, else `assumed` (half the spacing), said."""
    if given is not None:
        if measured is not None and abs(given - measured) > CIRCLE_DIAMETER_TOLERANCE * measured:
            return given, (
                f"warning: {what} measure {measured:.4g} mm across {where} (median of {n}), "
                f"not the {given:g} mm of {option}: calibration models each circle's image "
                "with the stated diameter; check it"
            )
        return given, ""
    name = what.replace("the circles", "circle").replace("circles", "circle")
    if measured is None:
        return assumed, (
            f"note: {name} diameter not given and not measurable in the images; "
            f"{assumed:g} mm (half the spacing) assumed: calibration models each point as "
            f"the centroid of its circle's image, so state the printed diameter with {option}"
        )
    return measured, (
        f"note: {name} diameter not given; {measured:.4g} mm measured {where} (median of "
        f"{n} circles) written: calibration models each point as the centroid of its "
        f"circle's image; state the printed diameter with {option}"
    )


def _by_reason(dropped, word: str) -> str:
    """`view 1, 4, 9: <reason>; view 2: <other reason>`: the dropped captures grouped by
    their reason (each view's own line above names its images)."""
    groups: dict[str, list] = {}
    for d in dropped:
        groups.setdefault(d.reason, []).append(str(d.view))
    return "; ".join(
        f"{word}{'s' if len(v) > 1 else ''} {', '.join(v)}: {r}" for r, v in groups.items()
    )
