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
when STRIPES has no frames or no pixel gives a valid point.
"""

from __future__ import annotations

import argparse

import numpy as np

from ._common import CLIError, check_output

_REASONS = {
    1: "invalid pixel (not finite, or undistortion failed)",
    2: "ray parallel to the laser plane",
    3: "intersection behind the camera",
    4: "degenerate laser plane (not finite, or through the camera centre)",
    5: "outside the sensor",
}


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "reconstruct",
        help="reconstruct stripe pixels as 3-D points with a calibration",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("calibration", metavar="CAL.json", help="calibration file")
    p.add_argument("stripes", metavar="STRIPES.json", help="stripe centres per frame")
    p.add_argument(
        "--out", required=True, metavar="POINTS", help="output: POINTS.json, .ply or .npy"
    )
    p.add_argument(
        "--frame",
        choices=("camera", "measurement"),
        default="camera",
        help="camera frame, or the rotary table's measurement frame (needs a calibrated "
        "stage; frame i of STRIPES is turned by i x delta omega) (default: %(default)s)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.set_defaults(func=run)


def reconstruct_frames(
    loaded, frames: list[np.ndarray], frame: str = "camera", *, sensor_size=None
):
    """Reconstruct stripe frames: `(points per frame (N_i, 3) NaN where invalid,
    status per frame (N_i,))`. All frames are padded into one batch (one compilation);
    frame i of a measurement-frame scan is turned by `i · delta_omega`. `sensor_size`
    `(w, h)` gives pixels outside the sensor the OUTSIDE_SENSOR status."""
    import jax.numpy as jnp

    from ..reconstruct._reconstruct import stripe_to_camera, stripe_to_measurement

    if frame == "measurement" and loaded.stage is None:
        raise CLIError(
            "--frame measurement needs a calibrated rotary stage, and the calibration has "
            "none (calibrate with a gauge scan in the observations, or use --frame camera)"
        )
    lengths = [len(f) for f in frames]
    if not frames or max(lengths) == 0:
        return [np.zeros((n, 3)) for n in lengths], [np.zeros(n, np.int8) for n in lengths]
    n_max = max(lengths)
    uv = np.full((len(frames), n_max, 2), np.nan)
    for i, f in enumerate(frames):
        uv[i, : len(f)] = f
    if frame == "measurement":
        frame_index = np.arange(len(frames))[:, None]  # one index per frame (row of uv)
        rec = stripe_to_measurement(
            loaded.camera,
            loaded.plane,
            loaded.stage,
            jnp.asarray(uv),
            frame_index,
            sensor_size=sensor_size,
        )
    else:
        rec = stripe_to_camera(
            loaded.camera, loaded.plane, jnp.asarray(uv), sensor_size=sensor_size
        )
    pts, status = np.asarray(rec.points), np.asarray(rec.status)
    return [pts[i, :n] for i, n in enumerate(lengths)], [
        status[i, :n] for i, n in enumerate(lengths)
    ]


def run(args) -> int:
    from ..io._calibration import read_calibration
    from ..io._pointcloud import points_extension, write_points
    from ..io._stripes import read_stripes

    points_extension(args.out)
    out = check_output(args.out, overwrite=args.overwrite)
    loaded = read_calibration(args.calibration)
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
    frames = read_stripes(args.stripes)
    if not frames:
        raise CLIError(f"{args.stripes} has no frames: nothing to reconstruct")
    sensor = getattr(loaded, "sensor_size", None)
    points, status = reconstruct_frames(loaded, frames, args.frame, sensor_size=sensor)

    codes = np.concatenate([np.zeros(0, np.int8)] + status)
    n_valid = int(np.sum(codes == 0))
    counts = [(int(np.sum(codes == c)), reason) for c, reason in _REASONS.items()]
    if n_valid == 0:
        why = "; ".join(f"{k} {reason}" for k, reason in counts if k) or "no stripe pixels"
        raise CLIError(
            f"no valid point from {codes.size} stripe pixels in {len(frames)} frames "
            f"({why}); nothing written"
        )
    write_points(out, points, args.frame, overwrite=args.overwrite)

    print(
        f"reconstructed {len(frames)} frames, {codes.size} stripe pixels "
        f"({loaded.model}, {args.frame} frame)"
    )
    print(f"  valid points  : {n_valid}")
    print(f"  invalid points: {codes.size - n_valid}")
    for k, reason in counts:
        if k:
            print(f"    {k:>8}  {reason}")
    if sensor is None:
        print("  (the calibration records no sensor size: pixels were not range-checked)")
    valid = np.concatenate([p[s == 0] for p, s in zip(points, status)])
    lo, hi = valid.min(axis=0), valid.max(axis=0)
    box = ", ".join(f"{a:.3f}..{b:.3f}" for a, b in zip(lo, hi))
    print(f"  extent (x, y, z): {box} mm")
    print(f"wrote {out}")
    return 0
