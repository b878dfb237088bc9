"""`scheimflux reconstruct`: laser-stripe pixels → 3-D points with a calibration.

Reads CAL.json (scheimflux.calibration/1) and STRIPES.json (scheimflux.stripes/1: stripe
centres per frame), intersects each pixel's ray with the laser plane (paper eq. 3) and,
with --frame measurement, maps frame i by the rotary stage turned by i x delta omega
(eq. 13). The output format follows the extension of --out:
  .json  {"format": "scheimflux.points/1", "frame", "unit": "mm", "frames": [[[x, y, z],
         ...], ...]} with invalid points left out;
  .ply   every valid point of every frame (binary little-endian, double x y z);
  .npy   float64 (frames, longest frame, 3), one row per stripe pixel, NaN where invalid
         and as padding.
Pixels outside the sensor (when the calibration records its size) are reported and left
out, like pixels whose ray misses the plane. The command fails (exit 1, no file written)
when STRIPES has no frames, no pixel gives a valid point, or STRIPES turns out to be
malformed or cut short partway.

  .parquet  one row per valid point: frame, pixel (index within the frame), x, y, z
         (needs pyarrow: pip install "scheimflux[parquet]").

STRIPES may also be a folder of frame images (png, tif, tiff, bmp, jpg, jpeg; one frame
per image in natural name order, as for `scheimflux extract`): the stripes are extracted
(--method, --width-px, --orientation, --channel, --laser-off, --workers as for
`extract`) and reconstructed in one pass, a few images in memory at a time. Unreadable
images, images of another size than the first one and images without a line are
reported by name and kept as empty frames, so frame i is still the i-th image (which
matters for --frame measurement). For .npy output the row width is the larger image
side (at most one centre per scan line).

The scan streams: STRIPES is read one frame at a time, frames are reconstructed
--chunk-frames at a time and written as they come to a temporary file beside POINTS,
which is moved into place at the end; memory does not grow with the scan's length.
"""

from __future__ import annotations

import argparse

import numpy as np

from ._common import CLIError, check_output, require_positive, warn_unmatched_laser_off


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "reconstruct",
        help="reconstruct stripe pixels as 3-D points with a calibration",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("calibration", metavar="CAL.json", help="calibration file")
    p.add_argument(
        "stripes",
        metavar="STRIPES",
        help="STRIPES.json (stripe centres per frame) or a folder of frame images",
    )
    p.add_argument(
        "--out",
        required=True,
        metavar="POINTS",
        help="output: POINTS.json, .ply, .npy or .parquet",
    )
    p.add_argument(
        "--frame",
        choices=("camera", "measurement"),
        default="camera",
        help="camera frame, or the rotary table's measurement frame (needs a calibrated "
        "stage; frame i of STRIPES is turned by i x delta omega) (default: %(default)s)",
    )
    p.add_argument(
        "--chunk-frames",
        type=int,
        default=256,
        metavar="N",
        help="frames reconstructed per batch: memory stays bounded by N frames whatever the "
        "length of the scan (default: %(default)s)",
    )
    from ..stripe._image import CHANNELS

    g = p.add_argument_group("stripe extraction (when STRIPES is a folder of images)")
    g.add_argument("--method", choices=("steger", "centroid"), default="steger")
    g.add_argument("--width-px", type=float, default=None, metavar="W",
                   help="expected line width (FWHM, px); measured if left out")
    g.add_argument("--orientation", choices=("auto", "vertical-scan", "horizontal-scan"),
                   default="auto", help="scan columns or rows; auto: per image")
    g.add_argument("--channel", choices=CHANNELS, default="auto",
                   help="colour channel or combination holding the laser")
    g.add_argument("--laser-off", metavar="SUFFIX", default=None,
                   help="NAME<SUFFIX>.EXT is the laser-off image of NAME.EXT")
    g.add_argument("--workers", type=int, default=None, metavar="N",
                   help="threads extracting frames (default: the number of CPUs)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.set_defaults(func=run)


def _folder_source(args):
    """Stripe frames straight from the images of a folder, with the npy row width and
    a tally of the frames that gave nothing."""
    import os

    from ..stripe._folder import (
        folder_stripe_frames,
        frame_files,
        numbering_problem,
        numbering_refusal,
        read_image,
    )
    from ._common import warn

    if args.workers is not None and args.workers < 1:
        raise CLIError(f"--workers must be >= 1, got {args.workers}")
    require_positive(args, "width_px")
    try:
        pairs = frame_files(args.stripes, args.laser_off)
    except ValueError as err:
        raise CLIError(str(err)) from None
    warn_unmatched_laser_off("reconstruct", args.stripes, args.laser_off, pairs)
    numbering = numbering_problem([p for p, _ in pairs])
    if numbering and args.frame == "measurement":
        raise CLIError(numbering_refusal(args.stripes, numbering, "delta omega"))
    if numbering:
        warn("reconstruct", f"{args.stripes}: {numbering} (frame i is the i-th image)")
    first = next((im for im in (read_image(p) for p, _ in pairs) if im is not None), None)
    if first is None:
        raise CLIError(f"none of the {len(pairs)} images in {args.stripes} could be read")
    tally = {"skipped": 0, "empty": 0}

    def report(frame):
        name = os.path.basename(frame.path)
        if frame.result is None:
            tally["skipped"] += 1
            warn("reconstruct", f"{name}: kept as an empty frame ({frame.problem})")
        elif not frame.result.valid.any():
            tally["empty"] += 1
            warn("reconstruct", f"{name}: no laser line found (kept as an empty frame)")

    frames = folder_stripe_frames(
        pairs, report=report, workers=args.workers, method=args.method,
        width_px=args.width_px, orientation=args.orientation, channel=args.channel,
    )  # fmt: skip
    return frames, max(first.shape[:2]), tally


def reconstruct_frames(
    loaded, frames: list[np.ndarray], frame: str = "camera", *, sensor_size=None
):
    """Reconstruct stripe frames in one batch (kept for callers of the CLI module; the
    work is `scheimflux.reconstruct.reconstruct_frames`)."""
    from ..reconstruct._stream import reconstruct_frames as _frames

    if frame == "measurement" and loaded.stage is None:
        raise CLIError(
            "--frame measurement needs a calibrated rotary stage, and the calibration has "
            "none (calibrate with a gauge scan in the observations, or use --frame camera)"
        )
    stage = loaded.stage if frame == "measurement" else None
    return _frames(loaded.camera, loaded.plane, frames, stage=stage, sensor_size=sensor_size)


def _coverage_line(loaded, summary) -> str:
    """How many stripe pixels lay outside the calibration's coverage (counted in the
    reconstruction's own pass: `ScanSummary.outside`)."""
    cov = loaded.coverage
    if cov is None or summary.outside is None:
        return (
            "  coverage: unknown (the calibration file records no coverage of the sensor; "
            "re-calibrate with this version to have points outside it counted)"
        )
    out, n = summary.outside, summary.on_sensor
    pct = f" ({100 * out / n:.1f} %)" if n else ""
    note = ": the model extrapolates there, errors can be several times larger" if out else ""
    return (
        f"  outside the calibration's coverage ({100 * cov.fraction:.0f} % of the sensor): "
        f"{out} of {n} stripe pixels on the sensor{pct}{note}"
    )


def run(args) -> int:
    from ..io._calibration import read_calibration_document
    from ..io._pointcloud import points_extension
    from ..reconstruct._scan import REASONS, ScanError, reconstruct_scan
    from ._common import progress

    points_extension(args.out)
    if args.chunk_frames < 1:
        raise CLIError(f"--chunk-frames must be >= 1, got {args.chunk_frames}")
    out = check_output(args.out, overwrite=args.overwrite)
    loaded = read_calibration_document(args.calibration)
    if loaded.plane is None:
        raise CLIError(
            f"{args.calibration} is a camera-only calibration (no laser_plane): reconstruct "
            "needs a laser plane (calibrate with the laser line on the board views)"
        )
    if args.frame == "measurement" and loaded.stage is None:
        raise CLIError(
            f"--frame measurement needs a calibrated rotary stage; {args.calibration} has "
            "none (calibrate with a gauge scan in the observations, or use --frame camera)"
        )
    import os

    frames = width = tally = None
    if os.path.isdir(args.stripes):
        frames, width, tally = _folder_source(args)
    try:
        s = reconstruct_scan(
            loaded,
            args.stripes,
            out,
            frame=args.frame,
            chunk_frames=args.chunk_frames,
            overwrite=args.overwrite,
            progress=lambda it: progress(it, "reconstruct", f"x{args.chunk_frames} frames"),
            frames=frames,
            width=width,
        )
    except ScanError as err:
        raise CLIError(str(err)) from None

    print(f"reconstructed {s.frames} frames, {s.pixels} stripe pixels ({s.model}, {s.frame} frame)")
    if tally is not None:
        print(
            f"  stripes extracted from the images of {args.stripes}: {tally['skipped']} "
            f"unusable, {tally['empty']} without a line (kept as empty frames)"
        )
    print(f"  valid points  : {s.valid}")
    print(f"  invalid points: {s.pixels - s.valid}")
    for c, reason in REASONS.items():
        if s.counts[c]:
            print(f"    {s.counts[c]:>8}  {reason}")
    if not s.sensor_checked:
        print("  (the calibration records no sensor size: pixels were not range-checked)")
    print(_coverage_line(loaded, s))
    box = ", ".join(f"{a:.3f}..{b:.3f}" for a, b in zip(s.lo, s.hi))
    print(f"  extent (x, y, z): {box} mm")
    print(f"wrote {out}")
    return 0
