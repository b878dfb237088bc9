"""`scheimflux simulate`: a calibration data set ray-traced through a real lens.

Writes, into the folder given by --out,
  observations.json   target points and laser lines on a posed checkerboard (--target:
                      a ChArUco board or a circle grid), and a ring-gauge
                      scan on a rotary table (scheimflux.observations/1: the input of
                      `scheimflux calibrate`);
  truth.json          the exact poses, laser plane, stage, pixels and 3-D points
                      (scheimflux.truth/1);
  scan_stripes.json   the gauge scan's stripe pixels per frame (scheimflux.stripes/1:
                      the input of `scheimflux reconstruct`).
With --images, also rendered images for `scheimflux detect`:
  images/view_<k>_board.png, images/view_<k>_stripe.png   one pair per board pose
                              (--image-layout single: images/view_<k>.png, board and
                              laser line in one image);
  images/scan/frame_<i>.png                              the gauge scan's frames.
--image-ext jpg|tif|bmp, --bit-depth 12|16 and --colour (BGR, red laser) change the files'
type. --sensor, --pixel-pitch-um, --laser-angle-deg and --laser-azimuth-deg set the camera
and the laser plane.
Every board lies whole inside the sensor, as a photographer keeps a checkerboard in the
frame (a board cut by the border is slid across the laser plane until it fits).
Pixels come from Snell's-law ray tracing onto the tilted sensor, never from a camera
model. The default rig is the paper's x1.5 Scheimpflug system: the shipped double Gauss
scaled to f = 97 mm, the sensor tilted as in the paper's Table 1.
"""

from __future__ import annotations

import argparse
import math
import os

from ._common import CLIError, check_output_folder, refuse_to_clobber, require_positive

_FILES = ("observations.json", "truth.json", "scan_stripes.json")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate",
        help="simulate calibration observations by ray tracing through a real lens",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", required=True, help="output folder (created if missing)")
    p.add_argument(
        "--lens",
        default="double-gauss",
        help="shipped lens name or prescription JSON file (default: %(default)s, scaled to "
        "f = 97 mm as in the paper)",
    )
    p.add_argument(
        "--magnification", type=float, default=1.5, help="|beta| on the axis (default: 1.5)"
    )
    p.add_argument(
        "--sensor",
        default="1600x1200",
        metavar="WxH",
        help="sensor size in pixels (default: %(default)s)",
    )
    p.add_argument(
        "--pixel-pitch-um",
        type=float,
        nargs="+",
        default=[4.4],
        metavar="UM",
        help="pixel pitch in micrometres: one value, or the x and y pitch (default: 4.4)",
    )
    p.add_argument(
        "--laser-angle-deg",
        type=float,
        default=None,
        help="angle between the laser plane and the optical axis, in (0, 90] (default: 60; "
        "for the default lens the plane of the paper's rig)",
    )
    p.add_argument(
        "--laser-azimuth-deg",
        type=float,
        default=0.0,
        help="direction the laser plane's normal leans towards, about the optical axis "
        "(0 = the sensor's +u, 90 = +v; default: %(default)s); with --laser-angle-deg",
    )
    p.add_argument("--views", type=int, default=15, help="checkerboard poses (default: 15)")
    p.add_argument(
        "--target",
        choices=("checkerboard", "charuco", "circles", "acircles"),
        default="checkerboard",
        help="calibration target, as `detect --target` (default: %(default)s)",
    )
    p.add_argument(
        "--board",
        default="11x8",
        help="COLSxROWS: checkerboard inner corners, ChArUco squares, or circles per row x "
        "rows (default: %(default)s)",
    )
    p.add_argument(
        "--square-mm",
        "--spacing-mm",
        dest="square_mm",
        type=float,
        default=None,
        help="square side (circle spacing for circle grids) in mm (default: 0.3 mm at "
        "|beta| = 1.5, scaled with 1/|beta|, smaller where the board would span more than "
        "80%% of the field's narrowest side)",
    )
    p.add_argument("--marker-mm", type=float, help="ChArUco marker side (default: 0.7 x square)")
    p.add_argument(
        "--dictionary",
        default="DICT_4X4_50",
        help="ChArUco: OpenCV predefined ArUco dictionary (default: %(default)s)",
    )
    p.add_argument(
        "--circle-diameter-mm", type=float, help="circle diameter (default: half the spacing)"
    )
    p.add_argument(
        "--corner-noise-px", type=float, default=0.03, help="corner noise sigma (default: 0.03)"
    )
    p.add_argument(
        "--stripe-noise-px", type=float, default=0.05, help="stripe noise sigma (default: 0.05)"
    )
    p.add_argument(
        "--frames", type=int, default=36, help="rotary-stage frames, 0 for none (default: 36)"
    )
    p.add_argument(
        "--delta-omega-deg", type=float, default=10.0, help="table step (default: 10 deg)"
    )
    p.add_argument(
        "--gauge-radius-mm", type=float, default=17.5, help="ring gauge radius (default: 17.5)"
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    p.add_argument(
        "--no-refine",
        action="store_true",
        help="skip the real-ray focus refinement of the sensor pose (faster)",
    )
    p.add_argument(
        "--images",
        action="store_true",
        help="also render the board, stripe and scan images into OUT/images (slow: "
        "seconds per image)",
    )
    p.add_argument(
        "--ambient",
        choices=("dark", "low", "bright"),
        default="low",
        help="background light of the rendered stripe images (default: %(default)s)",
    )
    p.add_argument(
        "--image-layout",
        choices=("pair", "single"),
        default="pair",
        help="with --images: board and stripe images per view, or one image holding both "
        "(default: %(default)s)",
    )
    p.add_argument(
        "--image-ext",
        choices=("png", "jpg", "tif", "bmp"),
        default="png",
        help="with --images: file type (default: %(default)s)",
    )
    p.add_argument("--colour", action="store_true", help="with --images: BGR images, red laser")
    p.add_argument(
        "--bit-depth",
        type=int,
        choices=(8, 12, 16),
        default=8,
        help="with --images: bits per sample; 12 and 16 are written as 16-bit PNG or TIFF "
        "(12-bit data in the low bits, as most machine-vision cameras; default: 8)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace existing output files")
    p.set_defaults(func=run)


def _check(args) -> None:
    if not 0.5 <= args.magnification <= 2.0:
        raise CLIError(f"--magnification must be in [0.5, 2], got {args.magnification}")
    if args.views < 1:
        raise CLIError(f"--views must be at least 1, got {args.views}")
    if args.frames < 0:
        raise CLIError(f"--frames must be >= 0, got {args.frames}")
    dw = args.delta_omega_deg
    if args.frames > 0 and not (math.isfinite(dw) and 0 < abs(dw) < 360):
        # a table step of 0 turns nothing: detect and the calibration reader refuse it
        raise CLIError(
            f"--delta-omega-deg must be a non-zero table step within ±360°, got {dw:g}"
        )
    require_positive(args, "corner_noise_px", "stripe_noise_px", zero_ok=True)
    require_positive(args, "gauge_radius_mm", "square_mm", "marker_mm", "circle_diameter_mm")
    if args.marker_mm is not None and args.target != "charuco":
        raise CLIError("--marker-mm is for --target charuco")
    if args.circle_diameter_mm is not None and args.target not in ("circles", "acircles"):
        raise CLIError("--circle-diameter-mm is for --target circles or acircles")
    _sensor_size(args)
    _pixel_pitch_mm(args)
    if args.laser_angle_deg is not None and not 0.0 < args.laser_angle_deg <= 90.0:
        raise CLIError(f"--laser-angle-deg must be in (0, 90], got {args.laser_angle_deg:g}")
    if args.laser_angle_deg is None and args.laser_azimuth_deg != 0.0:
        raise CLIError("--laser-azimuth-deg needs --laser-angle-deg (the plane's angle)")
    if args.bit_depth != 8 and (not args.images or args.image_ext in ("jpg", "bmp")):
        why = "--images" if not args.images else f"PNG or TIFF images (not {args.image_ext})"
        raise CLIError(f"--bit-depth {args.bit_depth} needs {why}")


def _sensor_size(args) -> tuple[int, int]:
    """`--sensor WxH` as `(w, h)` pixels."""
    try:
        w, h = (int(x) for x in str(args.sensor).lower().split("x"))
    except ValueError:
        raise CLIError(f"--sensor must be WIDTHxHEIGHT in pixels, e.g. 2448x2048, got "
                       f"{args.sensor!r}") from None  # fmt: skip
    if not (64 <= w <= 20000 and 64 <= h <= 20000):
        raise CLIError(f"--sensor {w}x{h}: each side must be 64 to 20000 pixels")
    return w, h


def _pixel_pitch_mm(args) -> tuple[float, float]:
    """`--pixel-pitch-um` (one value or x and y) as `(dx, dy)` in mm."""
    p = list(args.pixel_pitch_um)
    if len(p) not in (1, 2):
        raise CLIError(f"--pixel-pitch-um takes one or two values, got {len(p)}")
    if not all(math.isfinite(x) and 0.5 <= x <= 50.0 for x in p):
        raise CLIError(f"--pixel-pitch-um must be 0.5 to 50 um, got {' '.join(map(str, p))}")
    dx, dy = (p[0], p[0]) if len(p) == 1 else p
    # µm → mm on the typed decimal (3.45 / 1000 is 0.0034500000000000004 in binary)
    return float(f"{dx!r}e-3"), float(f"{dy!r}e-3")


def _build_rig(args):
    from ..simulate._lens import load_lens, paraxial, resolve_lens
    from ..simulate._rig import PAPER_PHI, PAPER_THETA, _laser_plane_for_tilt, build_rig

    refine = not args.no_refine
    sensor = dict(sensor=_sensor_size(args), pixel_pitch_mm=_pixel_pitch_mm(args))
    if args.lens == "double-gauss":
        # The paper's rig (paper_rig), at any magnification: f = 97 mm, stop 2.5 mm, the
        # laser plane whose paraxial Scheimpflug conjugate has the paper's tilt.
        base = load_lens("double-gauss")
        lens = base.scaled(97.0 / float(paraxial(base).efl), name="double-gauss-f97")
        lens = lens.with_stop_semi_diameter(2.5)
        if args.laser_angle_deg is None:
            plane = _laser_plane_for_tilt(
                paraxial(lens), args.magnification, PAPER_PHI, PAPER_THETA
            )
            return build_rig(lens, args.magnification, laser_plane=plane, refine=refine, **sensor)
    else:
        lens = resolve_lens(args.lens)
    angle = 60.0 if args.laser_angle_deg is None else args.laser_angle_deg
    return build_rig(
        lens, args.magnification, angle, args.laser_azimuth_deg, refine=refine, **sensor
    )


SHARP_SPOT_PX = 2.0  # RMS spot radius (pixels) beyond which the rig's focus is called poor


def _focus_note(rig) -> str:
    """A warning when the lens images the laser plane with spots wider than
    `SHARP_SPOT_PX` RMS (a bundle over the whole aperture, 25 points over the sensor),
    else "". The pixels simulated are chief rays (or the bundles' centroids): they stay
    sharp whatever the spots, real images through such a rig would not."""
    s = rig.summary()
    px = 1e-3 * s["rms_spot_um_mean"] / min(float(rig.dx), float(rig.dy))
    if not px > SHARP_SPOT_PX:
        return ""
    return (
        f"warning: the lens images the laser plane with spots of {s['rms_spot_um_mean']:.0f} "
        f"um RMS ({px:.0f} px; worst {s['rms_spot_um_max']:.0f} um) at its aperture: the "
        "simulated pixels are the rays' and stay sharp, real images through this rig "
        "would be blurred; stop the lens down (its prescription's stop semi_diameter) "
        "or choose another lens or magnification"
    )


def _target(args, pitch_mm: float):
    """The target of `--target`, `--board` and its options, with pitch `pitch_mm`."""
    from ..targets._target import make_target

    try:
        return make_target(
            args.target, args.board, pitch_mm, marker_mm=args.marker_mm,
            dictionary=args.dictionary, diameter_mm=args.circle_diameter_mm,
        )  # fmt: skip
    except ValueError as err:
        raise CLIError(f"--target {args.target}: {err}") from None


def _target_span(target) -> tuple[float, float]:
    """The target's extent along its x and y in units of its pitch: its points' span
    plus one pitch on each side (a checkerboard's outer squares, a ChArUco board's border
    squares, a circle grid's outer circles and margin)."""
    import numpy as np

    pts = np.asarray(target.points_mm, dtype=float)
    pitch = float(target.spacing_mm if hasattr(target, "spacing_mm") else target.square_mm)
    span = (pts.max(axis=0) - pts.min(axis=0))[:2] / pitch
    return float(span[0]) + 2.0, float(span[1]) + 2.0


def _default_square(rig, cols: float, rows: float, magnification: float) -> float:
    """The default pitch (mm) of a target `cols` × `rows` pitches wide ([`_target_span`]):
    0.3 mm at |β| = 1.5 scaled with 1/|β|, smaller where the board would span more than
    80 % of the laser-plane field's narrowest side (a short lens images the inclined plane
    as a strong trapezoid: the Tessar's field at ×2 is 2.3 mm on one side and 3.2 mm on
    the other), so that every pose can keep it whole inside the sensor; rounded down to
    1 µm. A checkerboard of C × R inner corners spans (C + 1) × (R + 1) squares."""
    import jax.numpy as jnp
    import numpy as np

    w, h = rig.sensor_size
    sensor = [[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]]
    c = np.asarray(rig.laser_points(jnp.asarray(sensor, dtype=float)))
    side = np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1)  # top, right, bottom, left
    fit = 0.8 * min(min(side[0], side[2]) / cols, min(side[1], side[3]) / rows)
    return min(round(0.3 * 1.5 / magnification, 3), math.floor(fit * 1000) / 1000)


def _swap_in(staging: str, out: str, names: list[str]) -> None:
    """Move the finished outputs `names` from `staging` into `out`.

    Old outputs are first moved aside into a hidden folder, then the new ones are moved
    in (renames only, in one file system), then the old ones are deleted. A kill at any
    point leaves `out` holding old files only or new files only, never a mix; what was
    moved aside stays in `.tmp-simulate-old-*` until then.
    """
    import shutil
    import tempfile

    aside = tempfile.mkdtemp(prefix=".tmp-simulate-old-", dir=out)
    try:
        for name in names:
            target = os.path.join(out, name)
            if os.path.lexists(target):
                os.replace(target, os.path.join(aside, name))
        for name in names:
            os.replace(os.path.join(staging, name), os.path.join(out, name))
    finally:
        shutil.rmtree(aside, ignore_errors=True)


def output_paths(args) -> dict[str, list[str]]:
    """The files this command writes into the --out folder (checked against its inputs,
    e.g. a --lens prescription file, by `_main`)."""
    return {"out": [os.path.join(os.fspath(args.out), name) for name in _FILES]}


def run(args) -> int:
    _check(args)
    import shutil
    import tempfile

    from ..io._observations import write_observations
    from ..io._stripes import write_stripes
    from ..simulate._observe import simulate_observations, write_truth

    out = os.fspath(args.out)
    if os.path.exists(out) and not os.path.isdir(out):
        raise CLIError(f"--out {out} exists and is not a folder")
    paths = [os.path.join(out, name) for name in _FILES]
    images = os.path.join(out, "images")
    outputs = list(paths)
    with_images = bool(getattr(args, "images", False))
    if with_images and os.path.isdir(images):
        if any(n.startswith("view_") for n in os.listdir(images)):  # an earlier --images run
            outputs.append(images)
    refuse_to_clobber(*outputs, overwrite=args.overwrite)
    board = _target(args, 1.0 if args.square_mm is None else args.square_mm)
    check_output_folder(out)  # before the ray tracing, not after it

    rig = _build_rig(args)
    if args.square_mm is None:
        square = _default_square(rig, *_target_span(board), args.magnification)
        board = _target(args, square)
    obs, truth = simulate_observations(
        rig,
        board,
        n_views=args.views,
        corner_noise_px=args.corner_noise_px,
        stripe_noise_px=args.stripe_noise_px,
        stage_scan=args.frames > 0,
        n_frames=max(args.frames, 1),
        delta_omega_deg=args.delta_omega_deg,
        gauge_radius_mm=args.gauge_radius_mm,
        seed=args.seed,
        whole_boards=True,
    )
    # Every output is written into a hidden staging folder first and swapped in at the
    # end, so an interrupted run (--overwrite or not) never leaves new and old files
    # side by side (e.g. a new observations.json beside an old truth.json).
    staging = tempfile.mkdtemp(prefix=".tmp-simulate-", dir=out)
    try:
        staged = [os.path.join(staging, name) for name in _FILES]
        write_observations(staged[0], obs)
        write_truth(staged[1], truth)
        frames = [] if obs.stage is None else obs.stage.frames
        write_stripes(staged[2], frames)
        names = list(_FILES)
        if with_images:
            import time

            from ..simulate._images import write_scene_images

            t0 = time.perf_counter()
            written = write_scene_images(
                os.path.join(staging, "images"),
                rig,
                board,
                truth,
                layout=args.image_layout,
                ext=args.image_ext,
                colour=args.colour,
                bit_depth=args.bit_depth,
                ambient=args.ambient,
                seed=args.seed,
                overwrite=True,
            )
            dt = time.perf_counter() - t0
            names.append("images")
        if not args.overwrite:  # a file may have appeared during the run
            refuse_to_clobber(*paths, overwrite=False)
            if with_images and os.path.isdir(images) and os.listdir(images):
                raise CLIError(f"{images} is not empty; pass --overwrite to replace it")
        _swap_in(staging, out, names)
    finally:
        shutil.rmtree(staging, ignore_errors=True)

    _, mask = obs.corners()
    stripe_pts = sum(len(v.stripe_px) for v in obs.views)
    scan_pts = sum(len(f) for f in frames)
    r = truth.rig
    pitch = r["pixel_pitch_mm"]
    print(
        f"rig: {r['lens']}, |beta| = {r['magnification']:.3f}, sensor {r['sensor'][0]}x"
        f"{r['sensor'][1]} px at {pitch[0]:g} x {pitch[1]:g} mm, tilt phi = "
        f"{math.degrees(r['phi_rad']):.3f} deg, theta = {math.degrees(r['theta_rad']):.3f} "
        f"deg, z0 = {r['z0_mm']:.3f} mm"
    )
    focus = _focus_note(rig)
    if focus:
        print(focus)
    print(
        f"board: {board}; {len(obs.views)} views, {int(mask.sum())} of "
        f"{mask.size} corners seen, {stripe_pts} stripe points on the board"
    )
    cut = [k for k in range(len(obs.views)) if not mask[k].all()]
    if cut:
        kind = "checkerboard" if args.target == "checkerboard" else "circle-grid"
        whole = (
            "a ChArUco detector uses the corners it sees, but fewer"
            if args.target == "charuco"
            else f"a {kind} detector finds only whole boards"
        )
        print(
            f"note: the sensor's border cuts the board in {len(cut)} view(s) "
            f"({', '.join(map(str, cut))}): it is larger than the field at those poses, and "
            f"{whole}; a smaller --square-mm keeps every board whole"
        )
    if obs.stage is not None:
        print(
            f"gauge scan: r = {obs.stage.gauge_radius_mm:g} mm, {len(frames)} frames "
            f"{obs.stage.delta_omega_deg:g} deg apart, {scan_pts} stripe points"
        )
    print(f"wrote {', '.join(paths)}")
    if with_images:
        scan = f" (scan frames in {os.path.join(images, 'scan')})" if frames else ""
        print(f"rendered {len(written)} images into {images}{scan} in {dt:.1f} s")
        print(f"next, as from photos: {_detect_command(obs, board, images)}")
    return 0


def _detect_command(obs, board, images: str) -> str:
    """The `scheimflux detect` command line for the rendered images, with the nominal
    values the simulated observations state (what a user takes from datasheets and the
    rig's drawing: pixel pitch, focal length, magnification, the sensor tilt in whole
    degrees), not the traced truth."""
    import shlex

    from ..targets import CharucoBoard, CircleGrid

    words = ["scheimflux", "detect", images]
    if isinstance(board, CharucoBoard):
        words += ["--target", "charuco", "--board", f"{board.squares_x}x{board.squares_y}",
                  "--square-mm", f"{board.square_mm:g}",
                  "--marker-mm", f"{board.marker_mm:g}"]  # fmt: skip
        if board.dictionary != "DICT_4X4_50":
            words += ["--dictionary", board.dictionary]
    elif isinstance(board, CircleGrid):
        words += ["--target", "acircles" if board.asymmetric else "circles", "--board",
                  f"{board.cols}x{board.rows}", "--spacing-mm", f"{board.spacing_mm:g}",
                  "--circle-diameter-mm", f"{board.diameter_mm:g}"]  # fmt: skip
    else:
        words += ["--board", f"{board.cols}x{board.rows}", "--square-mm", f"{board.square_mm:g}"]
    if obs.pixel_pitch_mm is not None:
        words += ["--pixel-pitch-mm", *(f"{p:g}" for p in obs.pixel_pitch_mm)]
    nom = obs.nominal
    if nom.focal_length_mm is not None:
        words += ["--focal-length-mm", f"{nom.focal_length_mm:g}"]
    if nom.magnification is not None:
        words += ["--magnification", f"{nom.magnification:g}"]
    if nom.tilt_deg is not None:
        words += ["--tilt-deg", *(f"{t:g}" for t in nom.tilt_deg)]
    if obs.stage is not None:
        words += [
            "--scan", os.path.join(images, "scan"), "--gauge-radius-mm",
            f"{obs.stage.gauge_radius_mm:g}", "--delta-omega-deg",
            f"{obs.stage.delta_omega_deg:g}",
        ]  # fmt: skip
    return shlex.join(words + ["--out", "obs.json"])
