"""`scheimflux calibrate`: camera, laser plane and rotary stage from an observations file.

Reads OBS.json (scheimflux.observations/1: checkerboard corners, the laser line on the
boards and optionally a ring-gauge scan on the rotary table), calibrates — the paper's
separate steps, then by default one joint Levenberg-Marquardt solve of every block —
prints a summary and writes CAL.json (scheimflux.calibration/1).

The defaults are the most accurate choice: the thick-lens model with radial-tangential
distortion, solved jointly, then a final rejection pass (--reject) of outliers. An
unconverged solve is an error and writes nothing unless --allow-unconverged is given;
pixels outside the sensor are left out and counted; a calibration that fails a quality
gate (reprojection RMS above 3x the stated corner sigma, stripe or gauge RMS above 3x the
stated stripe sigma, the axis point off the sensor, heavy-tailed residuals, more than
10 % outliers) is an error and writes nothing unless --force is given. The summary and
CAL.json hold the sigma of every free parameter, the warnings, the frozen set, the solve
statistics, the gates and the counts of left-out observations.

--model opencv calibrates OpenCV's camera (equal to cv2.projectPoints: fx, fy, cx, cy,
k1 k2 p1 p2 k3; --opencv-flags rational adds k4-k6, thin-prism s1-s4, tilted the sensor
tilt tau_x tau_y; zero-tangent holds p1 = p2 = 0, fix-k3 holds k3 = 0), jointly with the
laser plane and the stage as for the thick lens. Observations without stripe pixels on
the boards give a camera-only calibration (no laser plane: for export, not reconstruct).

The thick-lens model needs the sensor's pixel pitch (--pixel-pitch-mm, or the
observations file's). Nominal values given here (--pixel-pitch-mm, --focal-length-mm,
--magnification, --tilt-deg) override the observations file's.

A target on the rotary table in the observations (`detect --stage-target`) calibrates the
table axis from its turning: its corners enter the joint solve as camera observations
whose board poses are the stage's (docs/stage.md). --ignore-stage-target leaves it out
(the stage then comes from the gauge scan alone, if there is one).
"""

from __future__ import annotations

import argparse
import dataclasses
import time

from ._common import CLIError, require_positive

_MODELS = ("thick-lens", "thick-lens-noncentral", "pinhole", "opencv")
_DISTORTIONS = ("radial-tangential", "division", "none")
_INITS = ("auto", "nominal", "closed-form")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "calibrate",
        help="calibrate camera, laser plane and rotary stage from observations",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("observations", metavar="OBS.json", help="observations file")
    p.add_argument("--out", required=True, metavar="CAL.json", help="calibration file to write")
    p.add_argument(
        "--model",
        choices=_MODELS,
        default="thick-lens",
        help="camera model (default: %(default)s); thick-lens-noncentral adds the entrance "
        "pupil's shift with the field (short wide lenses, docs/noncentral.md)",
    )
    p.add_argument(
        "--opencv-flags",
        default=None,
        metavar="FLAGS",
        help="--model opencv: comma-separated terms beyond k1 k2 p1 p2 k3: rational (k4-k6), "
        "thin-prism (s1-s4), tilted (tau_x, tau_y), zero-tangent (p1 = p2 = 0), fix-k3 "
        "(k3 = 0); e.g. rational,tilted (cv2.CALIB_RATIONAL_MODEL | CALIB_TILTED_MODEL)",
    )
    add_nominal_arguments(p)
    p.add_argument(
        "--distortion",
        choices=_DISTORTIONS,
        default=None,
        help="lens distortion in the untilted image plane (default: radial-tangential for "
        "the thick lens, none for the pinhole, which has none)",
    )
    p.add_argument(
        "--init",
        choices=_INITS,
        default="auto",
        help="initial values: the observations' nominal values, homographies (closed-form) "
        "or auto: nominal when focal length, magnification and tilt are given "
        "(default: %(default)s)",
    )
    p.add_argument(
        "--gauge",
        choices=("held", "profile"),
        default="held",
        help="thick lens with distortion: hold the nominal tilt (held) or free it and place "
        "the axis point at the minimum of the cost profile (profile: no nominal-tilt bias "
        "noise-free, ~2.4x the time; docs/noncentral.md) (default: %(default)s)",
    )
    p.add_argument(
        "--no-joint",
        dest="joint",
        action="store_false",
        help="stop after the paper's separate steps (no joint refinement)",
    )
    p.add_argument(
        "--freeze",
        nargs="+",
        action="extend",
        metavar="PATH",
        default=None,
        help="parameters held fixed, e.g. camera.dx camera.dy camera.f, stage.R_m_c, "
        "stage.t_m_c, eccentricity; REPLACES the defaults (pixel pitch, f and a tilt "
        "gauge; the summary lists them); with --model opencv the terms outside "
        "--opencv-flags stay fixed as well",
    )
    p.add_argument(
        "--sigma-corner-px",
        type=float,
        default=0.03,
        help="corner noise (px): the start of the estimate, or with --noise stated the "
        "weight of the corners (default: %(default)s)",
    )
    p.add_argument(
        "--sigma-stripe-px",
        type=float,
        default=0.05,  # calibrate._calibrate.SIGMA_STRIPE_PX (not imported: it loads JAX)
        help="stripe-centre noise across the line (px): the start of the estimate, or "
        "with --noise stated the weight of the stripe and gauge points; a view's own "
        "measured noise (stripe_sigma_px) where larger (default: %(default)s)",
    )
    p.add_argument(
        "--noise",
        choices=("estimate", "stated"),
        default="estimate",
        help="estimate: each group's noise (corners, each view's stripe points, the gauge "
        "scan) from the data, the stated sigma as a start; stated: the sigma as given, "
        "and the gates compare the residuals with them (default: %(default)s)",
    )
    p.add_argument(
        "--robust",
        type=float,
        default=None,
        metavar="K",
        help="Huber loss with threshold K sigma against outliers (default: off; the "
        "rejection pass, --reject, leaves outliers out)",
    )
    p.add_argument(
        "--reject",
        type=float,
        default=5.0,
        metavar="K",
        help="after the joint solve, leave out observations beyond K robust sigma and "
        "solve once more; 0: no rejection pass (default: %(default)s)",
    )
    p.add_argument(
        "--max-radius-px",
        type=float,
        default=None,
        metavar="R",
        help="calibrate inside R px of the sensor's centre: corners, stripe and gauge "
        "pixels beyond it are left out and counted (a lens that vignettes the outer field; "
        "docs/noncentral.md); points reconstructed outside the data kept are flagged as "
        "extrapolated (default: the whole sensor)",
    )
    p.add_argument(
        "--max-steps", type=int, default=300, help="LM steps per solve (default: %(default)s)"
    )
    p.add_argument(
        "--allow-unconverged",
        action="store_true",
        help='write CAL.json even if a solve did not converge ("converged": false)',
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="write CAL.json even if the calibration fails a quality gate (the file "
        'records the failed gates; "quality": {"passed": false})',
    )
    p.add_argument(
        "--ignore-stage-target",
        action="store_true",
        help="leave the observations' table target out (stage from the gauge scan alone)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing CAL.json")
    p.set_defaults(func=run)


def add_nominal_arguments(p) -> None:
    """Nominal device values that override the observations file's."""
    g = p.add_argument_group("nominal values (override the observations file's)")
    g.add_argument(
        "--pixel-pitch-mm",
        type=float,
        nargs="+",
        metavar="MM",
        default=None,
        help="sensor pixel pitch: DX [DY] in mm (the thick-lens model needs it)",
    )
    g.add_argument("--focal-length-mm", type=float, default=None, help="nominal focal length")
    g.add_argument(
        "--magnification", type=float, default=None, help="nominal lateral magnification |beta|"
    )
    g.add_argument(
        "--tilt-deg",
        type=float,
        nargs=2,
        metavar=("PHI", "THETA"),
        default=None,
        help="nominal sensor tilt (phi, theta) in degrees",
    )


def _check_nominal(args) -> None:
    pitch = args.pixel_pitch_mm
    if pitch is not None and (len(pitch) > 2 or not all(p > 0 and p < 1e300 for p in pitch)):
        raise CLIError(f"--pixel-pitch-mm must be one or two positive numbers (mm), got {pitch}")
    require_positive(args, "focal_length_mm", "magnification")
    if args.tilt_deg is not None:
        from .._checks import MAX_TILT_DEG

        if not all(abs(a) <= MAX_TILT_DEG for a in args.tilt_deg):
            raise CLIError(
                f"--tilt-deg angles beyond any Scheimpflug camera's sensor tilt (|tilt| <= "
                f"{MAX_TILT_DEG:g}°), got {args.tilt_deg}"
            )


def _check_opencv(args) -> None:
    from ..calibration.core._opencv import parse_opencv_flags

    if args.opencv_flags is not None and args.model != "opencv":
        raise CLIError("--opencv-flags applies to --model opencv")
    if args.model == "opencv" and args.distortion is not None:
        raise CLIError(
            "--model opencv has OpenCV's distortion: choose its terms with --opencv-flags, "
            "not --distortion"
        )
    try:
        args.opencv_flags = parse_opencv_flags(args.opencv_flags)
    except ValueError as err:
        raise CLIError(f"--opencv-flags: {err}") from None


def _check(args) -> None:
    require_positive(args, "sigma_corner_px", "sigma_stripe_px", "max_radius_px")
    require_positive(args, "robust", "reject", zero_ok=True)
    _check_nominal(args)
    _check_opencv(args)
    if args.max_steps < 1:
        raise CLIError(f"--max-steps must be at least 1, got {args.max_steps}")
    if args.model == "pinhole" and args.distortion not in (None, "none"):
        raise CLIError(
            "the pinhole model (paper eq. 14) has no distortion; use --distortion none "
            "or --model thick-lens"
        )


# ----------------------------------------------------------------------------- run


def _with_nominal(args, obs):
    """The observations with the command line's nominal values in place of the file's."""
    from ..calibration.core._init import with_nominal

    try:
        return with_nominal(
            obs,
            pixel_pitch_mm=args.pixel_pitch_mm,
            focal_length_mm=args.focal_length_mm,
            magnification=args.magnification,
            tilt_deg=args.tilt_deg,
        )
    except ValueError as err:
        raise CLIError(str(err)) from None


def run(args) -> int:
    _check(args)
    from ..calibration import (
        NotConvergedError,
        RankDeficientError,
        calibrate,
        calibration_summary,
        calibration_to_dict,
        trust_entries,
        write_calibration,
    )
    from ..io._files import check_writable
    from ..io._observations import read_observations

    out = check_writable(args.out, overwrite=args.overwrite)  # before the long part
    obs = _with_nominal(args, read_observations(args.observations))
    if args.ignore_stage_target:
        obs = dataclasses.replace(obs, stage_target=None)
    distortion = args.distortion
    if distortion is None:
        rt = "radial-tangential"
        defaults = {"thick-lens": rt, "thick-lens-noncentral": rt, "opencv": "opencv"}
        distortion = defaults.get(args.model, "none")
    if args.model.startswith("thick-lens"):
        from ..calibration.core._init import require_pixel_pitch

        try:
            require_pixel_pitch(obs)
        except ValueError as err:
            raise CLIError(f"{args.observations}: {err}") from None
    print(
        f"calibrating {args.observations}: {len(obs.views)} views"
        + (f", {len(obs.stage.frames)} stage frames" if obs.stage is not None else "")
        + (
            f", table target at {len(obs.stage_target.table_steps)} table steps"
            if obs.stage_target is not None
            else ""
        )
        + f"; model {args.model}, distortion {distortion}"
        + (
            f"; circle centroids modelled (diameter {obs.circle_diameter_mm:g} mm)"
            if obs.circle_diameter_mm is not None
            else ""
        ),
        flush=True,
    )
    t0 = time.perf_counter()
    try:
        cal = calibrate(
            obs,
            model=args.model,
            distortion=distortion,
            init=args.init,
            joint=args.joint,
            freeze=args.freeze,
            gauge=args.gauge,
            sigma_corner_px=args.sigma_corner_px,
            sigma_stripe_px=args.sigma_stripe_px,
            robust=args.robust or None,
            reject=args.reject or None,
            max_steps=args.max_steps,
            max_radius_px=args.max_radius_px,
            noise=args.noise,
            throw=False,
            **({"opencv_flags": args.opencv_flags} if args.model == "opencv" else {}),
        )
    except NotConvergedError as err:  # throw=False should prevent it; be safe
        raise CLIError(f"calibration did not converge: {err}; no file written") from None
    except RankDeficientError as err:
        raise CLIError(f"{err} (--freeze PATH ...); no file written") from None
    total = time.perf_counter() - t0
    extra = {
        "observations": str(args.observations),
        # as stated; the weights used (estimated by default) are the file's own entries
        "stated_sigma_corner_px": args.sigma_corner_px,
        "stated_sigma_stripe_px": args.sigma_stripe_px,
        "robust": args.robust or None,
        "reject_sigma": args.reject or None,
        "total_time_s": total,
        **trust_entries(cal),
    }
    doc = calibration_to_dict(cal, diagnostics=extra)
    print(calibration_summary(cal, doc))
    print(f"total time: {total:.1f} s")
    failed = [
        f"{name} ({fit.message or 'not converged'} after {fit.steps} steps)"
        for name, fit in cal.fits.items()
        if not fit.converged
    ]
    quality = cal.quality
    refusals = []
    if failed and not args.allow_unconverged:
        closed = cal.init == "closed-form"
        other = "the nominal tilt (--init nominal)" if closed else "--init closed-form"
        refusals.append(
            f"calibration did not converge: {', '.join(failed)} (try {other}, "
            "more views, or --allow-unconverged to write it anyway)"
        )
    if quality is not None and not quality.passed and not args.force:
        refusals.append(
            "calibration failed its quality gates: "
            + "; ".join(g.message for g in quality.failures)
            + ("" if quality.hint is None else f"; {quality.hint}")
            + " (--force writes it anyway)"
        )
    if refusals:
        raise CLIError("; ".join(refusals) + "; no file written")
    try:  # what is written must read back (the file's schema)
        write_calibration(out, cal, diagnostics=extra, overwrite=args.overwrite)
    except ValueError as err:
        raise CLIError(f"the calibration cannot be written: {err}; no file written") from None
    if failed:
        print(f"warning: wrote an UNCONVERGED calibration ({', '.join(failed)})")
    if quality is not None and not quality.passed:
        names = ", ".join(g.name for g in quality.failures)
        print(f"warning: wrote a calibration that FAILED its quality gates ({names})")
    print(f"wrote {out}")
    return 0
