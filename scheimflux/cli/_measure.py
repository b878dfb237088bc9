"""`scheimflux measure`: a radius, flatness, step or distance with its uncertainty.

From a points file written by `reconstruct` (POINTS.json / .ply / .npy: the budget then
holds the fit residual only), or from a calibration and stripe centres
(--calibration CAL.json --stripes STRIPES.json --observations OBS.json: the calibration's
covariance, the stripe noise (--sigma-px) and the fit residual, propagated by autodiff
through reconstruction and the fit, with the correlations between points). Prints each
value ± U (k = 2) with its budget and residual statistics; --out writes them as JSON
(scheimflux.measurement/1).
"""

from __future__ import annotations

import argparse

from ._common import CLIError, check_output


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "measure",
        help="fit a cylinder, plane, sphere, circle, steps or a distance, with uncertainty",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("points", nargs="?", metavar="POINTS", help="points from reconstruct")
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--cylinder", action="store_true", help="cylinder radius")
    what.add_argument("--plane", action="store_true", help="flatness (peak-to-valley, RMS)")
    what.add_argument("--sphere", action="store_true", help="sphere radius")
    what.add_argument("--circle", action="store_true", help="circle radius")
    what.add_argument(
        "--steps", type=int, nargs="?", const=2, metavar="FACES",
        help="step heights of FACES parallel faces (default 2), face 0 the base",
    )
    what.add_argument(
        "--distance", type=int, nargs=2, metavar=("I", "J"),
        help="distance between valid points I and J",
    )
    p.add_argument("--calibration", metavar="CAL.json", help="calibration file")
    p.add_argument("--stripes", metavar="STRIPES.json", help="stripe centres per frame")
    p.add_argument(
        "--observations", metavar="OBS.json",
        help="the observations CAL was computed from (its covariance needs them)",
    )
    p.add_argument(
        "--frame", choices=("camera", "measurement"),
        help="with POINTS: the frame it must be in; with stripes: the frame to reconstruct "
        "in (default camera)",
    )
    p.add_argument("--labels", metavar="LABELS", help="face per point (.json or .npy), steps")
    p.add_argument("--sigma-px", type=float, metavar="PX", help="stripe noise, px")
    p.add_argument(
        "--frozen-sigma", default="nominal", metavar="nominal|none|PATH=SIGMA,...",
        help="standard uncertainty of the parameters the calibration held fixed (mm, rad), "
        "e.g. camera.f=0.3,camera.phi=0.002; nominal: the rounding of the nominal f (1 mm) "
        "and tilt (1 deg); none: held parameters count as exact (default: %(default)s)",
    )
    p.add_argument("--out", metavar="RESULT.json", help="write the result as JSON")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    p.set_defaults(func=run)


def _kind(args) -> str:
    for k in ("cylinder", "plane", "sphere", "circle"):
        if getattr(args, k):
            return k
    return "steps" if args.steps is not None else "distance"


def _frozen_sigma(text: str):
    """`--frozen-sigma`: "nominal", "none" or PATH=SIGMA pairs."""
    if text in ("nominal", "none"):
        return None if text == "none" else "nominal"
    out = {}
    for item in text.split(","):
        path, eq, value = item.partition("=")
        try:
            out[path.strip()] = float(value)
        except ValueError:
            raise CLIError(f"--frozen-sigma: {item!r} is not PATH=SIGMA") from None
        if not eq or not path.strip():
            raise CLIError(f"--frozen-sigma: {item!r} is not PATH=SIGMA")
    return out


def run(args) -> int:
    from ..io._files import write_json
    from ..metrology._workflow import measure_files

    if args.points is not None and (args.calibration or args.stripes):
        raise CLIError("give either POINTS or --calibration with --stripes, not both")
    if args.steps is not None and args.steps < 2:
        raise CLIError(f"--steps needs at least 2 faces, got {args.steps}")
    out = check_output(args.out, overwrite=args.overwrite) if args.out else None
    m = measure_files(
        _kind(args),
        points=args.points,
        calibration=args.calibration,
        stripes=args.stripes,
        observations=args.observations,
        frame=args.frame,
        labels=args.labels,
        n_faces=args.steps or 2,
        distance=tuple(args.distance) if args.distance else (0, 1),
        sigma_px=args.sigma_px,
        frozen_sigma=_frozen_sigma(args.frozen_sigma),
    )
    print(m.summary())
    if out:
        write_json(out, m.to_dict(), overwrite=args.overwrite)
        print(f"wrote {out}")
    return 0
