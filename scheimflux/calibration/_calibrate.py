"""Calibration of the camera, the laser plane and the rotary stage — separately as in the
paper (§2.4) and jointly as one parameter pytree: the orchestration of the steps in
`_camera`, `_plane`, `_stage`, then the joint solve, the rejection pass and the gates."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..io._observations import Observations
from .core._camera import (
    CameraCalibration,
    _default_distortion,
    _rms_px,
    _tilt_disagreement,
    calibrate_camera,
    pixel_footprint_mm,
)
from .core._gauge import profile_notes
from .core._init import nominal_thick_lens
from .core._model import (
    SystemParams,
    camera_plane_residuals,
    joint_residuals,
    make_data,
    view_stripe_scale,
)
from .core._plane import (
    _has_board_stripes,
    _plane_rms,
    fit_laser_plane,
    stripe_conditioning,
    stripe_gain,
)
from .core._rejection import (
    _left_out_indices,
    _outliers,
    _rejection_passes,
    _without,
    outlier_counts,
)
from .core._result import Calibration
from .core._screen import REJECT_SIGMA, screen_field, screen_observations
from .core._solve import NotConvergedError, RankDeficientError, free_spec, least_squares
from .core._stage import _gauge_rms, calibrate_stage
from .core._stage_table import stage_extra_freeze, table_target_start
from .trust._quality import _gated, _hint_text
from .trust._shift import camera_shift
from .trust._variance import (
    MAX_ITERATIONS,
    TOLERANCE,
    sigma_change,
    variance_components,
    with_factors,
)

# What the joint solve holds where the laser lines would bend the corners' geometry, and
# how much more the corners may scatter in the joint solve than alone before it does (with
# a camera consistent with its lines they scatter alike: the lines add a few parameters'
# worth of pull).
HELD_GEOMETRY = ("camera", "board_poses")
CORNER_INFLATION = 1.5

# How the residual groups' σ are set: estimated from the data (the stated σ as priors), or
# as stated.
NOISE_MODES = ("estimate", "stated")

# The stripe centres' noise assumed by default (px): a clean line's (`detect` reports a
# speckled line's own scatter, which is several times this).
SIGMA_STRIPE_PX = 0.05


def calibrate(
    obs: Observations,
    *,
    model: str = "thick-lens",
    distortion: str | None = None,
    init: str = "auto",
    joint: bool = True,
    freeze: Sequence[str] | None = None,
    sigma_corner_px: float = 0.03,
    sigma_stripe_px: float = SIGMA_STRIPE_PX,
    robust: float | None = None,
    reject: float | None = REJECT_SIGMA,
    max_steps: int = 300,
    throw: bool = True,
    opencv_flags: Sequence[str] | str | None = None,
    gauge: str = "held",
    max_radius_px: float | None = None,
    noise: str = "estimate",
) -> Calibration:
    """Calibrate camera, laser plane and (if scanned) the rotary stage.

    The separate steps of the paper (§2.4) run first: camera from corners, laser plane by
    TLS through the board stripe points, stage from the gauge scan. With `joint=True`
    (the default) one Levenberg–Marquardt solve then refines every block of the single
    parameter pytree together, each residual weighted by its noise: corners by
    `sigma_corner_px`, stripe and gauge points by `sigma_stripe_px` converted to mm at
    the camera's pixel footprint.

    `model="opencv"` calibrates OpenCV's camera (`cv2.projectPoints`; its terms chosen by
    `opencv_flags`, see [`calibrate_camera`][]) in the same way, jointly with the plane
    and the stage. Observations without any stripe pixel on the boards (and no stage
    scan) give a camera-only calibration (`plane = None`, only the camera solve).

    Observations are screened (pixels outside the sensor are left out); after the joint
    solve a rejection pass leaves out what lies beyond `reject` robust σ and solves again,
    until what is left out stops changing (at most `MAX_REJECTION_PASSES`; None: no
    pass). `robust` (e.g. 3) adds a Huber loss at that many σ to every
    solve; it is off by default because Levenberg–Marquardt with Huber's kink stalls
    (measured on a 4-view ray-traced scene: 300 steps, not converged, against 8 steps
    converged without it), while the rejection pass leaves out the same outliers.
    `cal.quality` holds the gates, counts and warnings (`scheimflux.calibration.trust._gates`).

    With `noise="estimate"` (the default) the stated σ are priors: after the joint solve
    each residual group's σ (the corners; each view's stripe points; the gauge scan) is
    estimated from its residuals over its redundancy and the problem solved again until
    they agree (`trust._variance`); the gates then judge the estimated noise against
    what real data reach and the model's fit (tails, outliers, physical sanity), and the
    summary says where the data's noise differs from the stated. Where the joint solve
    moves the camera beyond what its corners allow (`trust._shift`), the camera is kept
    as the corners determine it and the laser plane (and stage) fitted to it, with a
    warning naming the move.

    **Arguments:**
    - `obs`: observations: board corners per view (at least 3 views with 6+ corners),
      the laser line on the boards (`stripe_px`; none at all: camera-only) and
      optionally a rotary-stage gauge scan (`obs.stage`).
    - `model`: `"thick-lens"` (paper eq. 12; needs the pixel pitch), `"pinhole"`
      (eq. 14) or `"opencv"` (OpenCV's camera).
    - `distortion`: `"radial-tangential"`, `"division"` or `"none"` (thick lens); None:
      the model's default (see [`calibrate_camera`][]).
    - `init`: `"auto"`, `"nominal"` or `"closed-form"` start of the camera (see
      [`calibrate_camera`][]).
    - `joint`: after the separate steps, solve every block together (default); False:
      stop after the paper's sequence (outliers are then only counted).
    - `freeze`: parameter paths held fixed, e.g. `("camera.dx", "camera.dy",
      "camera.f")`, `"stage.R_m_c"`, `"eccentricity"`; None: `DEFAULT_FREEZE`. A given
      list replaces the defaults; Δω of the stage is always held.
    - `sigma_corner_px`: the corners' noise σ (px per coordinate).
    - `sigma_stripe_px`: the stripe centres' noise σ (px, across the line), converted
      to mm at the camera's pixel footprint on the boards for the stripe and gauge
      residuals. A view whose own measured σ is larger (`View.stripe_sigma_px`: `detect`
      measures a speckled line's scatter) has its stripe points weighted by that σ. The
      stripe gate compares the board-stripe RMS with the RMS of the σ used, each moved
      off its board as a pixel's error moves its point (`_plane.stripe_gain`;
      docs/calibration-trust.md).
    - `robust`: Huber threshold (units of σ) on every residual; None: off (see above).
    - `reject`: the rejection pass's threshold (robust σ); None: no rejection pass.
    - `max_steps`: Levenberg–Marquardt steps per solve.
    - `throw`: raise on an unconverged solve or a failed gate (below); False: return
      the result with `fit.converged` and `quality.passed` telling.
    - `opencv_flags`: the OpenCV model's terms (`model="opencv"` only; see
      [`calibrate_camera`][]).
    - `gauge`: `"held"` (default) or `"profile"`: how the thick lens with distortion
      fixes its weak directions (see [`calibrate_camera`][]; docs/noncentral.md). With
      `"profile"` the joint solve holds the axis point at the camera profile's value and
      the covariance has it free.
    - `max_radius_px`: calibrate inside this distance (px) from the sensor's centre
      only: every corner, stripe and gauge pixel beyond it is left out and counted
      ([`screen_field`][]); for a lens that vignettes the outer field, where a spot's
      centroid is not the image of one ray (docs/noncentral.md). The coverage, and so
      `reconstruct`'s flag on extrapolated points, follows the data kept. None: the
      whole sensor.
    - `noise`: `"estimate"` (default): each group's σ from the data (above); `"stated"`:
      the σ as given (the gates then compare the residuals with them).

    **Returns:** a [`Calibration`][]: the parameter pytree (camera, board poses, laser
    plane, stage, eccentricity), every solve's `Fit`, the RMS figures, the data the
    residuals were computed from, the quality gates and what was left out.

    **Raises:** with `throw`, `NotConvergedError` when a solve fails and `QualityError`
    when a quality gate fails (both carry the result); `ValueError` for data that cannot
    determine the laser plane or that leave parameters undetermined.
    """
    _check_arguments(obs, noise, robust)
    stated = {"corner_px": float(sigma_corner_px), "stripe_px": float(sigma_stripe_px)}
    obs, outside = screen_observations(obs)
    if max_radius_px is not None:
        obs, field = _inside_radius(obs, max_radius_px)
        outside.update(field)
    stage_freeze = _stage_freeze(freeze, obs)
    distortion = _default_distortion(model, distortion)
    camera_only = not _has_board_stripes(obs)
    if camera_only and (obs.stage is not None or obs.stage_target is not None):
        raise ValueError(
            "the observations hold a rotary-stage scan or table target but no stripe pixels "
            "on any board view: the stage needs the laser plane, which needs the laser line "
            "on the boards"
        )
    cam_cal = calibrate_camera(
        obs,
        model=model,
        distortion=distortion,
        init=init,
        freeze=freeze,
        sigma_corner_px=sigma_corner_px,
        robust=robust,
        max_steps=max_steps,
        throw=throw,
        opencv_flags=opencv_flags,
        gauge=gauge,
    )
    hold = cam_cal.hold
    notes = cam_cal.notes + profile_notes(cam_cal.axis_profile) + _unchecked_motion(obs)
    notes += board_scale_note(obs, cam_cal.poses) + _duplicate_views_note(obs)
    if camera_only:
        cal = _camera_only(cam_cal, obs, model, distortion, sigma_corner_px, robust, noise)
        rejected = {"threshold_sigma": reject}
        if reject is not None:
            rejected["corner_outliers"] = int(_outliers(cal.params, cal.data, reject)[0].sum())
        cal = dataclasses.replace(cal, axis_profile=cam_cal.axis_profile)
        record = _noise_record(noise, stated, cal.data, None, None)
        hint = _tilt_hint(obs, cam_cal)
        return _gated(cal, {**outside, **rejected}, None, throw, notes, hint, record)
    footprint = pixel_footprint_mm(cam_cal.camera, cam_cal.poses, obs)
    sigma_mm = sigma_stripe_px * footprint
    own = view_stripe_scale(obs, sigma_stripe_px)
    notes += _own_sigma_note(own, sigma_stripe_px)
    plane_fit = fit_laser_plane(cam_cal.camera, cam_cal.poses, obs, sigma_mm=sigma_mm * own)
    data = make_data(
        obs,
        sigma_corner_px=sigma_corner_px,
        sigma_stripe_mm=sigma_mm,
        stripe_scale=own,
        robust=robust,
    )
    # how far a pixel's error moves each view's points off its board (for the gates,
    # again after the solve; the conditioning reported with the σ it gives)
    data = _with_gain(data, cam_cal.camera, plane_fit.plane, cam_cal.poses, footprint)
    gain = np.asarray(data.stripe_gain)
    cond = stripe_conditioning(plane_fit.points, obs, sigma_mm * own * gain)
    plane_fit = dataclasses.replace(plane_fit, conditioning=cond)
    fits = {"camera": cam_cal.fit}
    stage = ecc = None
    if obs.stage is not None:
        st = calibrate_stage(
            cam_cal.camera,
            plane_fit.plane,
            obs,
            sigma_stripe_mm=sigma_mm,
            freeze=stage_freeze,
            max_steps=max_steps,
            throw=throw,
        )
        stage, ecc = st.stage, jnp.asarray(st.eccentricity_mm)
        fits["stage"] = st.fit
    table_pose = None
    if obs.stage_target is not None:  # a target on the table (`_stage_table`)
        stage, ecc, table_pose = table_target_start(cam_cal.camera, obs, stage, ecc)
    params = SystemParams(cam_cal.camera, cam_cal.poses, plane_fit.plane, stage, ecc, table_pose)
    freeze = cam_cal.freeze
    start = params
    hint = None if stage is None else _gauge_start_hint(params, data, obs)
    if joint:
        fn = joint_residuals if stage is not None else camera_plane_residuals
        extra = stage_extra_freeze(obs) if stage is not None else ()
        try:
            fit = least_squares(
                fn,
                params,
                data,
                freeze=freeze + extra,
                hold=hold,
                release=hold,
                max_steps=max_steps,
                throw=throw,
            )
        except (RankDeficientError, NotConvergedError) as err:
            tilt = _hint_text(_tilt_hint(obs, cam_cal))
            if tilt is None and (hint is None or isinstance(err, NotConvergedError)):
                raise
            message = f"{err}" if tilt is None else f"{tilt} (the joint solve stopped: {err})"
            message += "" if hint is None else f"; {hint}"
            if isinstance(err, NotConvergedError):
                raise NotConvergedError(message, err.fit) from None
            raise RankDeficientError(message) from None
        release = hold  # held at run time, reported free (the profiled axis point)
        # The laser lines may refine the camera within what its corners allow. Beyond it
        # (checked after the first solve and after the noise estimate: a collapsing
        # camera shrinks the stripe distances in mm, and the estimate follows it), or
        # where the joint solve's corners scatter far more than the corners-only
        # solve's (the lines bending the board poses), the camera and the board poses
        # are kept as the corners determine them and the laser plane (and stage) fitted
        # to them: held at run time, in the joint solve's compiled program.
        # (a thick lens's tilt and axis point are what the lines determine: its corners
        # alone leave them weak and model-biased, so only the corners' scatter is checked)
        shift = None if model.startswith("thick-lens") else camera_shift(cam_cal.fit, fit)
        weights = data
        stated_data, solves = data, 0  # the stated σ: the noise estimate's floor
        corners_alone = _corners_alone_px(cam_cal.fit, sigma_corner_px)
        for _ in range(2):
            finding = _held_finding(shift, data, corners_alone)
            if finding is not None and "camera" not in hold:
                hold, data = hold + HELD_GEOMETRY, weights  # the weights before it moved
                fit = least_squares(
                    fn, start, data, freeze=freeze + extra, hold=hold, release=release,
                    max_steps=max_steps, throw=throw,
                )  # fmt: skip
                notes += (_held_camera_note(finding, stage is not None),)
            if noise != "estimate":
                break
            fit, data, passes = _estimate_noise(
                fn, fit, data, freeze + extra, hold, release, max_steps, throw, stated_data
            )
            solves += passes
            if "camera" in hold:
                break
            if shift is not None:
                shift = camera_shift(cam_cal.fit, fit)
        params = fit.params
        fits["joint"] = fit
    elif noise == "estimate":  # the paper's sequence: each group's σ at its own optimum
        fn = joint_residuals if stage is not None else camera_plane_residuals
        stated_data, solves = data, 0
        spec = free_spec(params, freeze + (stage_extra_freeze(obs) if stage is not None else ()))
        data = with_factors(data, variance_components(fn, params, data, spec), data)
    outliers = {"threshold_sigma": reject}
    left_out = None  # set where the rejection pass re-solved without them
    if reject is not None:
        fit, applied, passes_r = _rejection_passes(
            fn if joint else None,
            start,
            params,
            data,
            freeze + (extra if joint else ()),
            reject,
            max_steps,
            throw,
            hold,
            release=release if joint else (),
        )
        if fit is not None:
            params, data = fit.params, _without(data, applied)
            left_out = _left_out_indices(applied)
            if noise == "estimate":  # the outliers inflated the first estimate
                fit, data, passes = _estimate_noise(
                    fn, fit, data, freeze + extra, hold, release, max_steps, throw, stated_data
                )
                solves += passes
                params = fit.params
            fits["joint"] = fit
        outliers.update(outlier_counts(applied), rejection_passes=passes_r)
    if joint and "camera" in hold:
        freeze = freeze + HELD_GEOMETRY  # as the file records it: the joint solve held them
    # the gates judge the distances with the solved geometry (the start's gains differ
    # by up to ~7 %; the weights do not use them)
    data = _with_gain(data, params.camera, params.plane, params.board_poses, footprint)
    cal = Calibration(
        params=params,
        model=model,
        distortion=distortion,
        init=cam_cal.init,
        joint=joint,
        fits=fits,
        freeze=freeze,
        reprojection_rms_px=_rms_px(params, data),
        plane_rms_mm=_plane_rms(params, data),
        gauge_rms_mm=None if obs.stage is None else _gauge_rms(params, data),
        data=data,
        sensor_size=(int(obs.width), int(obs.height)),
        left_out=left_out,
        axis_profile=cam_cal.axis_profile,
    )
    hints = (_tilt_hint(obs, cam_cal), hint)
    record = _noise_record(
        noise, stated, data, footprint, shift if joint else None,
        stated_data if noise == "estimate" else None,
    )  # fmt: skip
    if joint:
        record = _with_held(record, hold)
    if noise == "estimate" and joint:
        record["solves"] = int(solves)  # the re-solves the estimate took
    return _gated(
        cal, {**outside, **outliers}, plane_fit.conditioning, throw, notes, hints, record
    )


def _check_arguments(obs, noise: str, robust) -> None:
    """One-line refusals of arguments that cannot be calibrated from, naming them."""
    if not isinstance(obs, Observations):
        raise TypeError(
            f"obs must be Observations (read_observations(path)), got {type(obs).__name__}"
        )
    if noise not in NOISE_MODES:
        raise ValueError(f"noise must be one of {NOISE_MODES}, got {noise!r}")
    if robust is not None and not (isinstance(robust, (int, float)) and 0 < robust < math.inf):
        raise ValueError(f"robust must be a Huber threshold > 0 (σ) or None (off), got {robust!r}")
    for name, scan in (("stage", obs.stage), ("stage_target", obs.stage_target)):
        step = None if scan is None else float(scan.delta_omega_deg)
        if step is not None and not (math.isfinite(step) and step != 0.0):
            raise ValueError(
                f"obs.{name}.delta_omega_deg is {step:g}: the table must turn between "
                "frames (give the table step in degrees)"
            )
    views = [np.asarray(v.corners_px, dtype=np.float64) for v in obs.views]
    if len(views) >= 3 and all(np.array_equal(v, views[0], equal_nan=True) for v in views):
        raise ValueError(
            f"the {len(views)} views hold identical corners: one pose imaged "
            f"{len(views)} times; a calibration needs the board in different poses"
        )


def _duplicate_views_note(obs) -> tuple[str, ...]:
    """A warning naming views whose corners repeat an earlier view's exactly (the same
    image given twice weighs its pose double)."""
    seen, dup = {}, []
    for i, v in enumerate(obs.views):
        key = np.asarray(v.corners_px, dtype=np.float64).tobytes()
        if key in seen:
            dup.append(f"{i} (= {seen[key]})")
        else:
            seen[key] = i
    if not dup:
        return ()
    return (
        f"view(s) {', '.join(dup[:8])}{' ...' if len(dup) > 8 else ''} repeat an earlier "
        "view's corners exactly: the same image given twice counts its pose double",
    )


def _estimate_noise(fn, fit, data, freeze, hold, release, max_steps, throw, floor):
    """Variance-component estimation (`trust._variance`): estimate each group's factor
    at the solve's optimum, scale its σ (never below `floor`'s, the stated σ), solve
    again, until no σ changes by more than half the tolerance (at most `MAX_ITERATIONS`
    solves). A re-solve that fails (rank, convergence) ends it with the last solve.

    **Returns:** `(fit, data, solves)`: the last solve, the data with the estimated σ,
    and how many solves the estimation took (0: the σ already agreed)."""
    for solves in range(MAX_ITERATIONS + 1):
        vc = variance_components(fn, fit.params, data, fit.free_mask)
        new = with_factors(data, vc, floor)
        if sigma_change(data, new) <= 0.5 * TOLERANCE or solves == MAX_ITERATIONS:
            break
        try:
            again = least_squares(
                fn, fit.params, new, freeze=freeze, hold=hold, release=release,
                max_steps=max_steps, throw=throw,
            )  # fmt: skip
        except (RankDeficientError, NotConvergedError):
            break  # the last solve and its weights stand
        fit, data = again, new
    return fit, data, solves


def _corners_alone_px(fit, sigma_corner_px: float) -> float:
    """The corners' σ (px) as the corners-only solve's residuals give it, the stated σ
    its floor (as the noise estimate's)."""
    n, p = int(fit.n_observations), len(fit.labels)
    s2 = 2.0 * float(fit.cost) / (n - p) if n > p else math.nan
    return sigma_corner_px * math.sqrt(max(s2, 1.0))


def _held_finding(shift, data, corners_alone_px: float) -> str | None:
    """Why the joint solve's camera and board poses are not to be trusted, or None: the
    camera moved beyond its corners' covariance ([`camera_shift`][]), or the corners
    scatter more than `CORNER_INFLATION` x as much as in the corners-only solve."""
    if shift is not None and shift.moved:
        return shift.message()
    sigma = float(data.sigma_corner_px)
    if sigma > CORNER_INFLATION * corners_alone_px:
        return (
            f"in the joint solve the corners scatter {sigma:.3g} px, "
            f"{sigma / corners_alone_px:.2g}x their {corners_alone_px:.3g} px in the "
            "corners-only solve: the laser lines bend the board poses"
        )
    return None


def _held_camera_note(finding: str, with_stage: bool) -> str:
    return (
        finding
        + ": the camera and the board poses are kept as the corners determine them and "
        "the laser plane" + (" and stage" if with_stage else "") + " fitted to them (stripe "
        "points off their boards, a bent board, a line from another view or stripe "
        "weights far too high pull them this far; look at the stripe previews)"
    )


def _noise_record(noise: str, stated: dict, data, footprint_mm, shift, floor=None) -> dict:
    """What `Quality.noise` records: the σ the calibration used per group and the stated
    ones, in px. A view's stripe σ raised by the estimate is of its distances off the
    board, in px across the line through the view's gain (`_plane.stripe_gain`); one at
    the stated floor (`floor`: the data with the stated σ) is the stated."""
    out = {"mode": noise, "stated_corner_px": stated["corner_px"]}
    out["corner_px"] = float(data.sigma_corner_px)
    if footprint_mm is not None:
        out["stated_stripe_px"] = stated["stripe_px"]
        scale = np.asarray(data.stripe_scale, dtype=np.float64)
        mm = float(data.sigma_stripe_mm) * scale
        has = np.asarray(data.stripe_w).sum(axis=1) > 0
        gain = np.asarray(data.stripe_gain, dtype=np.float64)
        own = np.asarray((floor if floor is not None else data).stripe_scale, np.float64)
        px = stated["stripe_px"] * own  # the stated (a view's own measured where larger)
        if noise == "estimate" and floor is not None:
            low = float(floor.sigma_stripe_mm) * own
            raised = mm > low * (1.0 + 1e-9)
            est = mm / (footprint_mm * np.where(gain > 0, gain, 1.0))
            px = np.where(raised, est, px)
        out["stripe_px"] = [float(x) if h else None for x, h in zip(px, has)]
        out["stripe_mm"] = [float(x) if h else None for x, h in zip(mm, has)]
        if data.gauge_w.size and float(np.asarray(data.gauge_w).sum()) > 0:
            out["gauge_px"] = float(data.sigma_stripe_mm) / footprint_mm
    if shift is not None:
        out["camera_shift"] = shift.to_dict()
    return out


def _with_held(record: dict, hold) -> dict:
    """The record with whether the joint solve held the corners' camera and poses."""
    if "camera_shift" in record:
        record["held_corners_geometry"] = "camera" in hold
    return record


def _tilt_hint(obs: Observations, cam_cal):
    """For a nominal start: a function giving the nominal-tilt hint (the tilt the boards
    show where it disagrees with the nominal one, `_camera._tilt_disagreement`), for a
    failed gate; None otherwise."""
    if cam_cal.init != "nominal":
        return None
    return lambda: _tilt_disagreement(obs, nominal_thick_lens(obs))


def _gauge_start_hint(params: SystemParams, data, obs: Observations) -> str | None:
    """What to check first when the calibration is refused, if the gauge scan did not fit
    before the joint solve.

    The stage solve fits the table axis and the gauge's eccentricity with the camera and
    the laser plane from the boards alone. Where the gauge's stripes still lie several
    stated σ from a cylinder of the gauge radius there, a wrong `--gauge-radius-mm` or
    `--delta-omega-deg` is the likely cause, yet the joint solve can absorb it by bending
    the camera, and the gate that then fails names the camera (measured: the ×0.5
    achromat's 12 mm gauge given as 12.5 mm, 0.83 µm RMS after the stage solve against
    0.066 µm with the right radius, refused only as "axis point outside the sensor"; Δω
    given as 10° for 15°, 18 µm). A poor start that the joint solve repairs also lands
    here, so this is said only beside a refusal, never as a refusal of its own."""
    from .trust._gates import RMS_FACTOR

    rms, sigma = _gauge_rms(params, data), float(data.sigma_stripe_mm)
    if not rms > RMS_FACTOR * sigma:
        return None
    st = obs.stage
    return (
        f"before the joint solve (camera and laser plane from the boards) the gauge scan "
        f"lay {rms * 1e3:.3g} um RMS from a cylinder of its radius about the table axis, "
        f"{rms / sigma:.3g}x its stated sigma: check the gauge radius ({st.gauge_radius_mm:g}"
        f" mm, --gauge-radius-mm) and the table step ({st.delta_omega_deg:g} deg, "
        "--delta-omega-deg) before the camera"
    )


def board_scale_note(obs: Observations, poses) -> tuple[str, ...]:
    """A warning when the calibrated boards lie far from where the nominal lens images.

    The pixel rays of a central camera do not fix the scene's scale: a board 10x larger
    than its real size (a square size typed 10x off) is placed 10x farther, and every
    gate passes (the x0.5 achromat, 9x6 boards of 0.9 mm given as 9 mm: every gate
    passed, the boards at 2.6 m where the lens focuses at 0.3 m, every length 10x). The
    nominal focal length and magnification say where the object is: f (1 + 1/|β|) from
    the lens. Boards more than 2x farther or nearer than that (rough nominal values and
    a tilted focus plane stay well inside) are named, with what to check.
    """
    nom = obs.nominal
    if nom is None or not nom.focal_length_mm or not nom.magnification or not obs.views:
        return ()
    f, beta = float(nom.focal_length_mm), abs(float(nom.magnification))
    expected = f * (1.0 + 1.0 / beta)
    pts = np.asarray(obs.board_points_mm, np.float64)
    centre = np.zeros(3)
    centre[: pts.shape[-1]] = pts.mean(axis=0)
    R = np.asarray(jax.vmap(lambda p: p.R)(poses))
    z = (R @ centre + np.asarray(poses.translation))[:, 2]
    z = float(np.median(z[np.isfinite(z)])) if np.isfinite(z).any() else math.nan
    ratio = z / expected
    if not (ratio > 2.0 or ratio < 0.5):
        return ()
    return (
        f"the boards lie a median {z:.4g} mm from the lens, {ratio:.2g}x the {expected:.4g} "
        f"mm where a lens of f = {f:g} mm images at |beta| = {beta:g} (the nominal values): "
        "check the board's square size (detect --square-mm: it sets the scale of every "
        "calibrated length) and the nominal focal length and magnification",
    )


def _with_gain(data, camera, plane, poses, footprint_mm: float):
    """`data` with its `stripe_gain` computed for this geometry ([`stripe_gain`][])."""
    gain = stripe_gain(camera, plane, poses, data, footprint_mm)
    return eqx.tree_at(lambda d: d.stripe_gain, data, jax.device_put(gain))


def _own_sigma_note(scale: np.ndarray, sigma_stripe_px: float) -> tuple[str, ...]:
    """A note naming the views whose stripe points are weighted by their own measured
    σ (`View.stripe_sigma_px`, above the stated `sigma_stripe_px`)."""
    own = np.flatnonzero(scale > 1.0)
    if not len(own):
        return ()
    px = scale[own] * sigma_stripe_px
    views = ", ".join(str(int(i)) for i in own[:8]) + (" ..." if len(own) > 8 else "")
    return (
        f"the stripe points of view(s) {views} are weighted by their own measured σ "
        f"({px.min():.2f}-{px.max():.2f} px across the line: a speckled laser line, "
        f"stripe_sigma_px in the observations) instead of {sigma_stripe_px:g} px",
    )


def _unchecked_motion(obs: Observations) -> tuple[str, ...]:
    """A warning naming the views whose laser line is used although `detect` could not
    measure whether the board moved between their laser-off and laser-on images."""
    views = [
        (i, v)
        for i, v in enumerate(obs.views)
        if v.board_motion_px is not None and math.isnan(v.board_motion_px) and len(v.stripe_px)
    ]
    if not views:
        return ()
    names = ", ".join(f"{i} ({v.source[-1]})" if v.source else str(i) for i, v in views[:5])
    more = f" and {len(views) - 5} more" if len(views) > 5 else ""
    return (
        f"the board's motion between the laser-off and laser-on images of view(s) "
        f"{names}{more} could not be measured (the laser-on image shows the board too "
        "faintly): their laser lines are used as if the board had not moved",
    )


def _inside_radius(obs: Observations, radius_px) -> tuple[Observations, dict]:
    """`screen_field`, refusing a radius that leaves too little to calibrate from."""
    had_stripes = _has_board_stripes(obs)
    cut, counts = screen_field(obs, radius_px)
    r = counts["field_radius_px"]
    views = sum(int(v.corner_mask.sum()) >= 6 for v in cut.views)
    if views < 3:
        raise ValueError(
            f"a field radius of {r:g} px (max_radius_px) leaves {views} views with 6 or more "
            "corners within it of the sensor's centre; calibration needs 3"
        )
    if had_stripes and not _has_board_stripes(cut):
        raise ValueError(
            f"a field radius of {r:g} px (max_radius_px) leaves no stripe pixel on the "
            "boards: the laser plane would not be calibrated"
        )
    return cut, counts


def _stage_freeze(freeze, obs: Observations) -> tuple[str, ...]:
    """The stage and eccentricity paths of a user's `freeze` (for the stage solve)."""
    paths = tuple(p for p in (freeze or ()) if p.split(".")[0] in ("stage", "eccentricity"))
    if paths and obs.stage is None:
        raise ValueError(
            f"cannot freeze {', '.join(paths)}: the observations hold no rotary-stage scan"
        )
    return paths


def _camera_only(
    cam_cal: CameraCalibration, obs, model, distortion, sigma_corner_px, robust, noise
):
    """The `Calibration` of the camera solve alone (no laser plane, no stage); with
    `noise="estimate"` the corners weighted by their σ as the solve's residuals give it
    (one group: `s² = |r|² / (n − p)`)."""
    if noise == "estimate":
        fit = cam_cal.fit
        n, p = int(fit.n_observations), len(fit.labels)
        if n > p:
            sigma_corner_px *= math.sqrt(2.0 * float(fit.cost) / (n - p))
    data = make_data(obs, sigma_corner_px=sigma_corner_px, robust=robust)
    params = SystemParams(cam_cal.camera, cam_cal.poses)
    return Calibration(
        params=params,
        model=model,
        distortion=distortion,
        init=cam_cal.init,
        joint=False,
        fits={"camera": cam_cal.fit},
        freeze=cam_cal.freeze,
        reprojection_rms_px=_rms_px(params, data),
        plane_rms_mm=None,
        gauge_rms_mm=None,
        data=data,
        sensor_size=(int(obs.width), int(obs.height)),
    )
