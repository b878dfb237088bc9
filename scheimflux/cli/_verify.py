"""`scheimflux verify`: measure an artefact that was not used to calibrate.

Reconstructs the artefact's stripe centres (SCAN: a STRIPES.json, frame i = table step i)
with CAL.json, fits it with the metrology fits (value and U, k = 2, with the calibration's
covariance: give --observations, the file CAL was calibrated from) and prints
measured − nominal ± U with PASS/FAIL against --tolerance-um (default: U). Artefacts:
  cylinder:R          a ring of radius R on the table (measurement frame)
  sphere-pair:D       two spheres on the table, centre distance D (measurement frame)
  steps:H1,H2,...     one profile across a stepped gauge, heights above the base face
                      (faces numbered from the profile's end at smaller pixel u, the
                      faces perpendicular to the laser plane)
Exit status: 0 pass, 3 fail, 1 bad input. --out writes the result as JSON
(scheimflux.verification/1).
"""

from __future__ import annotations

import argparse

from ._common import check_output

FAIL_EXIT = 3


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "verify",
        help="measure an artefact not used in calibration: measured - nominal ± U, pass/fail",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("calibration", metavar="CAL.json", help="calibration file")
    p.add_argument("scan", metavar="SCAN", help="the artefact's stripe centres (STRIPES.json)")
    p.add_argument(
        "--artefact", required=True, metavar="KIND:NOMINAL",
        help="cylinder:R | sphere-pair:D | steps:H1,H2,... (mm)",
    )  # fmt: skip
    p.add_argument(
        "--observations", metavar="OBS.json",
        help="the observations CAL was computed from (its covariance needs them)",
    )  # fmt: skip
    p.add_argument(
        "--tolerance-um", type=float, metavar="UM",
        help="accepted |measured - nominal| (default: U of each value)",
    )  # fmt: skip
    p.add_argument("--sigma-px", type=float, metavar="PX", help="stripe noise, px")
    p.add_argument(
        "--delta-omega-deg", type=float, metavar="DEG",
        help="the scan's table step, where it differs from the calibration's",
    )  # fmt: skip
    p.add_argument("--out", metavar="RESULT.json", help="write the result as JSON")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..io._files import write_json
    from ..metrology._stage_verify import verify_files

    out = check_output(args.out, overwrite=args.overwrite) if args.out else None
    v = verify_files(
        args.calibration, args.scan, args.artefact,
        observations=args.observations, tolerance_um=args.tolerance_um,
        sigma_px=args.sigma_px, delta_omega_deg=args.delta_omega_deg,
    )  # fmt: skip
    print(v.summary())
    if out:
        write_json(out, v.to_dict(), overwrite=args.overwrite)
        print(f"wrote {out}")
    return 0 if v.all_passed else FAIL_EXIT
