"""`scheimflux report`: one self-contained HTML page about a calibration.

The camera parameters ± σ, their correlation matrix, identifiability warnings, corner
residuals over the sensor and per view (with --observations), the laser plane and the
stage, and views of a point cloud (--points). Images are embedded as base64 PNG; with
--png-dir they are also written as PNG files. Needs matplotlib (pip install
'scheimflux[plot]').
"""

from __future__ import annotations

import argparse
import os

from ._common import CLIError, check_output


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "report",
        help="an HTML report of a calibration (parameters, correlations, residual maps)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("calibration", metavar="CAL.json", help="calibration file")
    p.add_argument("--observations", metavar="OBS.json", help="for the residual maps")
    p.add_argument("--points", metavar="POINTS", help="a point cloud to show")
    p.add_argument("--out", required=True, metavar="REPORT.html", help="the HTML page")
    p.add_argument("--png-dir", metavar="DIR", help="also write the images as PNG files")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.set_defaults(func=run)


def output_paths(args) -> dict[str, list[str]]:
    """The files this command writes (checked against its inputs by `_main`); the PNG
    folder is an output, not an input."""
    return {"out": [args.out], "png_dir": []}


def run(args) -> int:
    from ..report import build_report, write_report

    out = check_output(args.out, overwrite=args.overwrite)
    if args.png_dir is not None and not os.path.isdir(args.png_dir):
        raise CLIError(f"--png-dir {args.png_dir} is not a folder")
    try:
        rep = build_report(args.calibration, observations=args.observations,
                           points=args.points)
    except ImportError as err:
        raise CLIError(str(err)) from None
    written = write_report(rep, out, png_dir=args.png_dir, overwrite=args.overwrite)
    print(f"report: {len(rep.sections)} sections, {len(rep.images)} images")
    for path in written:
        print(f"wrote {path}")
    return 0
