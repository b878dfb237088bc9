"""Camera calibration from the checkerboard corners (paper §2.4 steps 1–2): the models,
their default frozen parameters, the start values and the Levenberg–Marquardt solves."""

from __future__ import annotations

import contextlib
import dataclasses
import math
from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..._export import exported_jit
from ...camera._distortion import Division, NoDistortion, OpenCVDistortion, RadialTangential
from ...camera._noncentral import ThickLensNonCentral
from ...camera._opencv import OpenCVCamera
from ...camera._pinhole import Pinhole
from ...camera._thick_lens import ThickLensScheimpflug
from ...geometry._transforms import Pose
from ...io._observations import Observations
from ._gauge import (
    AXIS_POINT,
    GAUGE_HELD,
    GAUGES,
    IDEAL_GAUGE,
    AxisProfile,
    distorted_freeze,
    ideal_freeze,
    profile_axis_point,
)
from ._init import (
    _directions,
    closed_form_pinhole,
    nominal_thick_lens,
    poses_for_central_camera,
    require_pixel_pitch,
    thick_lens_from_pinhole,
)
from ._model import CalibrationData, SystemParams, camera_residuals, corner_errors_px, make_data
from ._nested import nested_f_test
from ._opencv import OPENCV_COEFFICIENTS, opencv_from_pinhole, opencv_frozen, parse_opencv_flags
from ._solve import ONE_SHOT, Fit, NotConvergedError, RankDeficientError, least_squares

MODELS = ("thick-lens", "thick-lens-noncentral", "pinhole", "opencv")
# the models built on the thick lens (nominal start, pixel pitch, distortion first)
THICK_LENS_MODELS = ("thick-lens", "thick-lens-noncentral")
DISTORTIONS = ("none", "radial-tangential", "division", "opencv")


def make_distortion(name: str):
    """A zero-initialised distortion model by name."""
    if name == "none":
        return NoDistortion()
    if name == "radial-tangential":
        return RadialTangential()
    if name == "division":
        return Division()
    if name == "opencv":
        return OpenCVDistortion()
    raise ValueError(f"distortion must be one of {DISTORTIONS}, got {name!r}")


# What image data cannot determine is held at its datasheet / nominal value by default.
# The pixel rays of the thick-lens model are a 3x3 projective map K_f, observable only up
# to a rotation (absorbed by the board poses) and a scale: 5 numbers for the 9 lens
# parameters. With e = 0 the model is exactly a zero-skew pinhole (3 numbers once the
# pixel pitch is known), so the sensor tilt is not observable from geometry alone. The
# defaults fix the pixel pitch (datasheet), f (lens datasheet) and a gauge for the
# tilt: the nominal adapter tilt when it is known, else the axis through the sensor
# centre. `diagnostics()` reports the singular values that show this. With distortion
# the tilt is no longer an exact gauge (`_gauge`, docs/noncentral.md: measured, not yet
# solved; `freeze=("camera.dx", "camera.dy", "camera.f")` frees it).
DEFAULT_FREEZE = {
    ("thick-lens", "nominal"): ideal_freeze("nominal"),
    ("thick-lens", "closed-form"): ideal_freeze("closed-form"),
    ("thick-lens-noncentral", "nominal"): ideal_freeze("nominal"),
    ("thick-lens-noncentral", "closed-form"): ideal_freeze("closed-form"),
    ("pinhole", "closed-form"): (),
    # OpenCV's model: the coefficients its flags leave out are added (`opencv_frozen`)
    ("opencv", "closed-form"): (),
}


def _check_observations(obs: Observations, *, min_views: int = 3, min_corners: int = 6):
    if not obs.views:
        raise ValueError("the observations hold no views")
    _, mask = obs.corners()
    good = mask.sum(axis=1) >= min_corners
    if good.sum() < min_views:
        raise ValueError(
            f"calibration needs at least {min_views} views with {min_corners}+ detected "
            f"corners; {int(good.sum())} of {len(obs.views)} views have them"
        )
    bad = [i for i in range(len(obs.views)) if not good[i]]
    if bad:
        raise ValueError(f"views {bad} have fewer than {min_corners} detected corners; remove them")


@dataclasses.dataclass(frozen=True)
class CameraCalibration:
    """Camera and board poses from the checkerboard corners."""

    camera: ThickLensScheimpflug | ThickLensNonCentral | Pinhole | OpenCVCamera
    poses: Pose
    fit: Fit
    reprojection_rms_px: float
    init: str
    freeze: tuple = ()  # the parameter paths held fixed
    # `gauge="profile"`: where the profile placed the axis point (held at that value in
    # the solves, free in `fit`'s covariance); None for the held gauge
    axis_profile: AxisProfile | None = None
    hold: tuple = ()  # paths held at run time in the solves after this one (the axis point)
    notes: tuple[str, ...] = ()  # decisions of the solve (e.g. the pupil terms' test)


def _initial(obs, model, init):
    if init not in ("auto", "nominal", "closed-form"):
        raise ValueError(f"init must be 'auto', 'nominal' or 'closed-form', got {init!r}")
    if model == "pinhole":
        return (*closed_form_pinhole(obs), "closed-form")
    if model == "opencv":
        pin, poses = closed_form_pinhole(obs)
        return opencv_from_pinhole(pin), poses, "closed-form"
    nom = obs.nominal
    has_nominal = nom is not None and nom.focal_length_mm and nom.magnification
    if init == "nominal" or (init == "auto" and has_nominal and nom.tilt_deg is not None):
        cam = nominal_thick_lens(obs)
        return cam, poses_for_central_camera(cam, obs), "nominal"
    pin, poses = closed_form_pinhole(obs)
    f = nom.focal_length_mm if nom is not None else None
    cam, poses = thick_lens_from_pinhole(pin, poses, obs, f=f)
    return cam, poses, "closed-form"


def _focal_length_note(obs, model, how, camera, freeze) -> tuple[str, ...]:
    """A note when the thick lens's f is held at the closed-form start's thin-lens
    estimate (no focal length given): the value printed `(fixed)` is then no data-sheet
    value and may be far from the lens's (35 % on a 100 mm double Gauss at ×2)."""
    if model not in THICK_LENS_MODELS or how != "closed-form" or "camera.f" not in freeze:
        return ()
    nom = obs.nominal
    if nom is not None and nom.focal_length_mm:
        return ()
    return (
        f"f was not given: held at {float(camera.f):.4g} mm, a thin-lens estimate from the "
        "boards' distance, not the lens's focal length (the images do not determine f: "
        "e, z0 and the tilt take it up, the pixel rays stay the same); give "
        "--focal-length-mm to hold the data-sheet value",
    )


def _default_distortion(model: str, distortion: str | None) -> str:
    """The most accurate default: radial-tangential for the thick lens; the pinhole
    (paper eq. 14) has none; OpenCV's model has its own (set by its flags)."""
    if model == "opencv":
        if distortion not in (None, "opencv"):
            raise ValueError(
                "the OpenCV model has OpenCV's distortion (choose its terms with "
                f"opencv_flags), not distortion={distortion!r}"
            )
        return "opencv"
    if distortion == "opencv":
        raise ValueError("distortion='opencv' belongs to model='opencv'")
    if distortion is not None:
        return distortion
    return "radial-tangential" if model in THICK_LENS_MODELS else "none"


def _model_freeze(model: str, how: str, freeze, opencv_flags) -> tuple[str, ...]:
    """The frozen set: the user's (or the default), plus the OpenCV terms not in the model."""
    base = DEFAULT_FREEZE[(model, how)] if freeze is None else tuple(freeze)
    if model != "opencv":
        return tuple(base)
    return tuple(dict.fromkeys(tuple(base) + opencv_frozen(opencv_flags)))


def calibrate_camera(
    obs: Observations,
    *,
    model: str = "thick-lens",
    distortion: str | None = None,
    init: str = "auto",
    freeze: Sequence[str] | None = None,
    sigma_corner_px: float = 0.03,
    robust: float | None = None,
    max_steps: int = 200,
    throw: bool = True,
    opencv_flags: Sequence[str] | str | None = None,
    gauge: str = "held",
) -> CameraCalibration:
    """Calibrate the camera from checkerboard corners (Levenberg–Marquardt).

    **Arguments:**
    - `obs`: observations (corners per view, board geometry, sensor); at least 3 views,
      each with 6 or more detected corners.
    - `model`: `"thick-lens"` (paper eq. 12), `"thick-lens-noncentral"` (the thick
      lens with the entrance pupil moving along the axis with the field and its
      projection centre offset across it, `ThickLensNonCentral`; solved from the
      central optimum, its terms kept only where F-tests find them significant;
      where they are kept and `freeze` is None the held gauge, the nominal tilt or the
      axis point, is then released, since it would bias the result:
      `_nominal_gauge_released`), `"pinhole"` (eq. 14) or
      `"opencv"`
      (OpenCV's camera, see `opencv_flags`).
    - `distortion`: `"radial-tangential"` (k1, k2, k3, p1, p2), `"division"` or
      `"none"`, applied in the untilted image plane (thick lens only); None: the
      model's default (radial-tangential for the thick lens, none for the pinhole,
      OpenCV's own for `"opencv"`).
    - `init`: `"nominal"` (paper step 2: nominal f, magnification, tilt, e = 0),
      `"closed-form"` (homographies, no nominal tilt needed) or `"auto"` (nominal when
      the observations give focal length, magnification and tilt).
    - `freeze`: parameter paths held fixed, e.g. `("camera.dx", "camera.dy")`; None:
      `DEFAULT_FREEZE[(model, how it was initialised)]` (pixel pitch, f and a tilt
      gauge for the thick lens); with `"opencv"` the terms outside `opencv_flags` are
      always added.
    - `sigma_corner_px`: the corners' noise σ (px per coordinate): the residuals'
      weight.
    - `robust`: Huber threshold in units of σ (e.g. 3) for outlier corners; None: plain
      least squares.
    - `max_steps`: Levenberg–Marquardt steps per solve.
    - `throw`: raise `NotConvergedError` if the final solve does not converge (the
      first, ideal-camera solve never raises).
    - `opencv_flags`: for `model="opencv"` (OpenCV's camera, equal to
      `cv2.projectPoints`): the terms beyond k1, k2, p1, p2, k3 —
      `"rational"`, `"thin-prism"`, `"tilted"` — and `"zero-tangent"`, `"fix-k3"`
      (`OPENCV_FLAGS`); a list or `"rational,tilted"`.
    - `gauge`: the thick lens with distortion and `freeze=None`: `"held"` (the
      default: the nominal tilt, or for a closed-form start the axis point, held in every
      solve, except the non-central model's last solve where its terms were kept) or
      `"profile"` (only the pixel pitch and f held; the tilt free and the axis
      point placed at the minimum of the cost profile, `_gauge.profile_axis_point`;
      docs/noncentral.md). `"profile"` with another model, without distortion or with
      an explicit `freeze` is refused (`ValueError`).

    **Returns:** a [`CameraCalibration`][]: the camera, the board poses, the final
    solve's `Fit`, the reprojection RMS (px per coordinate), how it was initialised and
    the frozen paths.

    The thick-lens model needs the pixel pitch (`obs.pixel_pitch_mm`, from the sensor's
    datasheet): without it a `ValueError` says so (`with_nominal(obs, pixel_pitch_mm=...)`
    or `calibrate --pixel-pitch-mm` provide it).
    """
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    if model != "opencv" and opencv_flags:
        raise ValueError(f"opencv_flags apply to model='opencv', not {model!r}")
    if model == "opencv" and init == "nominal":
        raise ValueError("init='nominal' is the thick lens's; the OpenCV model starts closed-form")
    opencv_flags = parse_opencv_flags(opencv_flags)
    _check_observations(obs)
    if model in THICK_LENS_MODELS:
        require_pixel_pitch(obs)
    distortion = _default_distortion(model, distortion)
    dist = make_distortion(distortion)
    if model == "pinhole" and distortion != "none":
        raise ValueError(
            "the pinhole model (paper eq. 14) has no distortion; use "
            "distortion='none' or the thick-lens model"
        )
    _check_gauge(gauge, model, distortion, freeze)
    camera, poses, how = _initial(obs, model, init)
    frozen: list[str] = []  # the solve's frozen set, for the failure's hint
    with _nominal_tilt_checked(obs, camera, how, frozen):
        data = make_data(obs, sigma_corner_px=sigma_corner_px, robust=robust)
        if gauge == "profile":
            camera = eqx.tree_at(lambda c: c.distortion, camera, dist)
            cc = _profiled(SystemParams(camera, poses), data, how, obs, model, max_steps, throw)
            f_note = _focal_length_note(obs, model, how, camera, cc.freeze)
            return dataclasses.replace(cc, notes=f_note + cc.notes)
        defaulted = freeze is None
        freeze = _model_freeze(model, how, freeze, opencv_flags)
        frozen[:] = freeze
        f_note = _focal_length_note(obs, model, how, camera, freeze)
        # The ideal camera first (the distortion at zero, held), then with the distortion
        # free. The distortion is held at run time (`hold`), not frozen: both solves have
        # the same state vector and run the same compiled program.
        hold = ()
        if model == "opencv":
            hold = tuple(c for c in OPENCV_COEFFICIENTS if c not in freeze)
        elif model in THICK_LENS_MODELS and distortion != "none":
            camera = eqx.tree_at(lambda c: c.distortion, camera, dist)
            hold = ("camera.distortion",)
        starts = [(camera, poses)]
        if how == "closed-form" and model in THICK_LENS_MODELS:
            try:
                starts.append(_mirrored_tilt(camera, obs))
            except ValueError:  # its poses not found (corners behind it): no start
                pass
        if hold or len(starts) > 1:
            # the ideal camera (distortion held at zero) from each start; the lower cost
            # is kept (a closed-form start's tilt and its mirror: `_mirrored_tilt`)
            firsts = [
                least_squares(
                    camera_residuals,
                    SystemParams(cam, ps),
                    data,
                    freeze=freeze,
                    hold=hold,
                    max_steps=max_steps,
                    throw=False,
                )
                for cam, ps in starts
            ]
            first = min(firsts, key=_solve_rank)
            camera, poses = first.params.camera, first.params.board_poses
        params = SystemParams(camera, poses)
        central_first = model == "thick-lens-noncentral"

        fit = least_squares(
            camera_residuals,
            params,
            data,
            freeze=freeze,
            max_steps=max_steps,
            throw=throw and not central_first,
        )
        notes = ()
        if central_first:
            # the central thick lens's optimum is the start, the pupil's shift from zero
            central = fit
            start = SystemParams(
                ThickLensNonCentral.from_central(central.params.camera), central.params.board_poses
            )

            # With the default frozen set the held gauge (tilt or axis point) is held at
            # run time, so that its release (`_nominal_gauge_released`) runs the same
            # compiled program as the tested stages.
            released = freeze
            if defaulted and distortion != "none":
                released = distorted_freeze(tuple(freeze))
            gauge = tuple(p for p in freeze if p not in released)

            def run(p, hold, throw=throw):
                return least_squares(camera_residuals, p, data, freeze=released, hold=hold,
                                     max_steps=max_steps, throw=throw)  # fmt: skip

            def solve(p, hold, throw=throw):
                return run(p, gauge + tuple(hold), throw)

            fit, freeze, notes = _noncentral_terms_tested(central, start, freeze, solve)
            if gauge and "camera.pupil" not in freeze:
                kept = tuple(p for p in freeze if p not in gauge)
                held = tuple(p for p in kept if p not in released)  # terms the tests held
                fit, freeze, note = _nominal_gauge_released(
                    fit, freeze, kept, lambda p: run(p, held, throw=False)
                )
                notes += (note,)
        rms = _rms_px(fit.params, data)
        notes = f_note + notes
        return CameraCalibration(
            fit.params.camera, fit.params.board_poses, fit, rms, how, tuple(freeze), notes=notes
        )


def _mirrored_tilt(camera, obs):
    """The closed-form start with its tilt negated, `(-phi, -theta)`, and the board poses
    seen through it.

    Zhang's closed form reads the sensor tilt from the boards' homographies, and where
    the boards show little perspective (a long lens, |beta| <= 0.5) it returns the tilt
    or its mirror image at random: an achromat at x0.5, 10 boards, laser at 45 deg, read
    (-12.7, -23.0) deg for the true (12.9, 23.4), and (-0.1, 15.9) for (0.0, -16.1) (a
    third seed and x1 read the right sign); from the mirror the solve stopped after 200
    steps at (-32.6, -50.7) deg, 2x the corner noise (a rendered ChArUco capture of
    that rig: 300 steps, 5.5x). Both are solved for the ideal camera and the lower cost
    is kept."""
    mirror = eqx.tree_at(lambda c: (c.phi, c.theta), camera, (-camera.phi, -camera.theta))
    return mirror, poses_for_central_camera(mirror, obs)


def _closed_form_camera(obs):
    """The ideal thick lens solved from the closed-form start and from its mirrored
    tilt (`_mirrored_tilt`), the lower cost kept: the tilt the boards show."""
    cam, poses, _ = _initial(obs, "thick-lens", "closed-form")
    data = make_data(obs)
    freeze = DEFAULT_FREEZE[("thick-lens", "closed-form")]
    fits = [
        least_squares(camera_residuals, SystemParams(c, p), data, freeze=freeze, throw=False)
        for c, p in ((cam, poses), _mirrored_tilt(cam, obs))
    ]
    return min(fits, key=_solve_rank).params.camera


def _solve_rank(fit):
    """Order of solves from several starts: the lowest cost, a NaN cost last."""
    return (not math.isfinite(fit.cost), fit.cost)


# A tilt the boards show (`_closed_form_camera`) this far (degrees, either angle) from
# the nominal one that a failed solve started from is named in its error: the
# closed-form start's tilt was within 0.5° of the truth on the rigs tried once its sign
# was resolved (achromat ×0.5: 15.05° against 15.53°, (12.86, 23.22)° against (12.92,
# 23.41)°; the paper's rig (2.97, 13.36)° against (2.87, 13.31)°), and a nominal tilt
# is rounded to whole degrees.
TILT_HINT_DEG = 2.0


@contextlib.contextmanager
def _nominal_tilt_checked(obs, camera, how: str, frozen: list[str]):
    """Amend a solve's failure from a nominal start with the tilt the boards show, where
    that disagrees with the nominal tilt (a sign, the order of the two angles or a value
    mistyped: the solve then stops as rank-deficient or unconverged, naming parameters
    that are not the cause). A null direction made of the principal point and the
    boards' positions is named as that, after the tilt hint where there is one (a
    swapped nominal tilt leaves that direction too; so does a long lens's weak
    perspective, which also pulls the closed-form tilt off); `frozen`: the solve's
    frozen set."""
    try:
        yield
    except (RankDeficientError, NotConvergedError) as err:
        hint = _tilt_disagreement(obs, camera) if how == "nominal" else None
        pp = isinstance(err, RankDeficientError) and _principal_point_null(err)
        if pp and hint is None:
            raise RankDeficientError(_principal_point_hint(err, frozen), err.nulls) from None
        if hint is None:
            raise
        if pp:  # a wrong tilt leaves this direction too; so does weak perspective
            message = f"{hint}; if the nominal tilt is right, {_principal_point_hint(err, frozen)}"
            raise RankDeficientError(message, err.nulls) from None
        message = f"{hint} (the solve from it stopped: {err})"
        if isinstance(err, NotConvergedError):
            raise NotConvergedError(message, err.fit) from None
        raise RankDeficientError(message, err.nulls) from None


def _principal_point_null(err: RankDeficientError) -> bool:
    """Whether the first null direction is the principal point against the boards'
    positions: its largest component camera.x0 or camera.y0, every other one a board
    pose's translation or the principal point: the weak perspective of a long lens (the
    boards' images almost affine), or a nominal tilt far off."""
    if not err.nulls:
        return False
    comps = err.nulls[0][1]
    pp = ("camera.x0", "camera.y0")
    return (
        bool(comps)
        and comps[0][0] in pp
        and all(lab in pp or lab.startswith("board_poses.translation") for lab, _ in comps)
    )


def _principal_point_hint(err: RankDeficientError, frozen) -> str:
    """The failure of `_principal_point_null`, with what to do."""
    held = [p for p in frozen if p not in ("camera.x0", "camera.y0")]
    option = " ".join([*held, "camera.x0", "camera.y0"])
    return (
        "the views do not determine the principal point: camera.x0, camera.y0 trade off "
        "with the boards' positions (a long lens sees the boards with too little "
        "perspective); hold it at the sensor's centre by freezing it too "
        f"(--freeze {option}; freeze=(...)), or take views with the boards tilted more "
        f"steeply ({err})"
    )


def _tilt_disagreement(obs, camera) -> str | None:
    """The hint naming the nominal tilt and the closed-form start's, or None where they
    agree within `TILT_HINT_DEG` (or no closed-form start exists)."""
    try:
        seen = _closed_form_camera(obs)
    except Exception:  # a diagnosis of another failure: it must not replace that error
        return None
    nominal = [math.degrees(float(camera.phi)), math.degrees(float(camera.theta))]
    data = [math.degrees(float(seen.phi)), math.degrees(float(seen.theta))]
    if not all(map(math.isfinite, data)):
        return None
    if max(abs(a - b) for a, b in zip(nominal, data)) <= TILT_HINT_DEG:
        return None
    return (
        f"the nominal tilt (phi, theta) = ({nominal[0]:.3g}, {nominal[1]:.3g}) deg disagrees "
        f"with the tilt the boards show, ({data[0]:.1f}, {data[1]:.1f}) deg (the ideal camera "
        "solved from the boards' homographies): check the nominal tilt's value, signs and "
        "order (--tilt-deg PHI THETA: phi turns the sensor about its u axis, theta about "
        "its v axis; docs/conventions.md), or start from the data (--init closed-form, "
        "init='closed-form')"
    )


def _check_gauge(gauge, model, distortion, freeze) -> None:
    """Refuse a `gauge` the calibration would not apply (never ignore it silently)."""
    if gauge not in GAUGES:
        raise ValueError(f"gauge must be one of {GAUGES}, got {gauge!r}")
    if gauge == "held":
        return
    if model not in THICK_LENS_MODELS:
        raise ValueError(f"gauge='profile' is the thick lens's (with distortion), not {model!r}'s")
    if distortion == "none":
        raise ValueError(
            "gauge='profile' needs distortion: without it the tilt and the axis point are an "
            "exact gauge (use gauge='held')"
        )
    if freeze is not None:
        raise ValueError(
            "gauge='profile' sets its own frozen set (pixel pitch and f); drop freeze "
            "(--freeze) or use gauge='held'"
        )


#: The non-central camera's terms beyond the central thick lens, in the order they are
#: tested: the ray's slide along the axis (c1, c2) with the origin's lateral offset
#: (ax, ay), then the pivot shift (b1, b2) on top of them.
NONCENTRAL_STAGES = (("camera.pupil", "camera.lateral"), ("camera.pivot",))


def _noncentral_terms_tested(central, start, freeze, solve):
    """The non-central solve with each stage of terms (`NONCENTRAL_STAGES`) kept only if it
    reduces the corners' residuals by more than noise would (`nested_f_test`, q = 2 per
    free pair, against the model without it).

    `solve(params, hold, throw=...)` runs the camera solve with the non-central terms in
    `hold` held at their values in `params` (at run time: one compiled program).
    `central` is the central optimum, `start` the non-central camera at it (every term 0).
    First the slide and the lateral offset (the pivot held at 0) against the central
    optimum: not significant, every term is held at 0 (the central optimum, re-solved
    with them held). Then the pivot terms from that optimum, against it: not
    significant, or their solve does not converge in its step limit (where the lens is
    nearly central they are nearly collinear with the slide), they are held at 0 and
    the first stage's fit stands.

    **Returns:** `(fit, freeze, notes)`; `notes` says what was decided and why.
    """
    first = tuple(t for t in NONCENTRAL_STAGES[0] if t not in freeze)
    pivot = tuple(t for t in NONCENTRAL_STAGES[1] if t not in freeze)
    fit = solve(start, pivot)
    notes = ()
    if first:
        test = nested_f_test(2.0 * central.cost, 2.0 * fit.cost, fit.n_observations,
                             len(fit.labels), 2 * len(first))  # fmt: skip
        stat = f"F = {test.f:.3g}, p = {test.p_value:.2g}"
        if not test.significant:
            held = solve(start, first + pivot)
            note = (
                f"pupil terms held at 0: the non-central fit of the corners is not "
                f"significantly better than the central one ({stat}, level {test.alpha:g}); "
                "the lens is central to the data's precision"
            )
            return held, tuple(freeze) + first + pivot, (note,)
        notes = (f"pupil terms kept: they reduce the corners' residuals significantly "
                 f"({stat})",)  # fmt: skip
    if not pivot:
        return fit, tuple(freeze), notes
    turned = _continued(lambda p: solve(p, (), throw=False), fit.params)
    if not turned.converged:
        return fit, tuple(freeze) + pivot, notes + (
            "pivot terms held at 0: their solve did not converge in its step limit",)
    test = nested_f_test(2.0 * fit.cost, 2.0 * turned.cost, turned.n_observations,
                         len(turned.labels), 2 * len(pivot))  # fmt: skip
    stat = f"F = {test.f:.3g}, p = {test.p_value:.2g}"
    if test.significant:
        return turned, tuple(freeze), notes + (
            f"pivot terms kept: they reduce the corners' residuals significantly ({stat})",)
    return fit, tuple(freeze) + pivot, notes + (
        f"pivot terms held at 0: not significant ({stat}, level {test.alpha:g})",)


#: How many times a non-central solve that stopped at its step limit is continued from
#: where it stopped (the same compiled program). Measured on the noise-free Tessar ×0.5
#: with a nominal tilt 1° off: the pivot solve needed 241 steps and the released one
#: 306 (200 per solve) and both then reached the optimum found from a closer start.
CONTINUATIONS = 2


def _continued(solve, params):
    """`solve(params)`, continued from its last iterate up to `CONTINUATIONS` times while
    it stops at its step limit and still lowers the cost (the `Fit`'s steps and initial
    cost are those of the whole run)."""
    fit = solve(params)
    for _ in range(CONTINUATIONS):
        if fit.converged:
            break
        more = solve(fit.params)
        if not more.cost < fit.cost:
            break
        fit = dataclasses.replace(more, steps=fit.steps + more.steps,
                                  initial_cost=fit.initial_cost)  # fmt: skip
    return fit


def _nominal_gauge_released(fit, freeze, released, solve):
    """The non-central solve with the nominal gauge (the tilt held at its nominal value,
    or the axis point at the sensor centre) released.

    With distortion the tilt and the axis point are determined (weakly, `_gauge`), and
    where the lens is far from central the rounded nominal tilt biases what is measured.
    Measured on the benchmark's pupil-integrated 8 mm Tessar at ×0.5 (docs/noncentral.md):
    noise-free, a nominal tilt off by ±1° moved pairwise distances by 0.06–0.07 µm with
    it held and by 4e-12 µm released (the error 0.044 → 0.031 µm; 0.045 → 0.008 µm with
    the lens's vignetting removed); with 0.03/0.05 px noise (7 seeds) released was
    better on 5 seeds, RMS over them 0.056 against 0.057 µm. Called only where the
    non-central terms were kept; for a lens the F-tests find central the held gauge's
    smaller variance wins (section 1 of docs/noncentral.md). The released solve starts
    at the held optimum with the tilt and the axis point free and the pixel pitch and f
    held (`distorted_freeze`); if it is refused or does not converge, the held fit stays.

    `freeze` is the held fit's frozen set, `released` that set without the gauge, and
    `solve(params)` the solve with `released` frozen and nothing held (the program the
    held fit ran with the gauge held at run time).

    **Returns:** `(fit, freeze, note)`; the note carries the F statistic of the release
    against the held gauge (how strongly the data reject the nominal value).
    """
    names = [p.split(".")[-1] for p in freeze if p not in released]
    what = ", ".join(names)
    try:
        free = _continued(solve, fit.params)
    except RankDeficientError as err:
        return fit, freeze, f"{what} held at the nominal value: with them released {err}"
    if not free.converged:
        return fit, freeze, (f"{what} held at the nominal value: the solve with them "
                             "released did not converge in its step limit")  # fmt: skip
    test = nested_f_test(2.0 * fit.cost, 2.0 * free.cost, free.n_observations,
                         len(free.labels), len(names))  # fmt: skip
    return free, released, (
        f"{what} released with the non-central terms (the nominal value would bias the "
        f"result; the data against it: F = {test.f:.3g}, p = {test.p_value:.2g})")


def _profiled(params, data, how, obs, model, max_steps, throw) -> CameraCalibration:
    """`gauge="profile"`: the thick lens with distortion, only the pixel pitch and f held.

    One compiled Levenberg–Marquardt program (one state vector; what is held changes at
    run time): the ideal camera (distortion and the ideal gauge held at their start
    values: the nominal tilt, or the axis point for a closed-form start), the
    distortion freed, then the tilt freed and the axis point placed at the minimum of
    the cost profile by Newton steps (`profile_axis_point`), each inner solve holding it.
    The returned fit reports the axis point free (`release`), so the covariance holds
    its uncertainty.
    """
    ideal = tuple(p for p in IDEAL_GAUGE[how] if p not in GAUGE_HELD)

    def solve(p, hold=AXIS_POINT, release=AXIS_POINT):
        return least_squares(
            camera_residuals, p, data, freeze=GAUGE_HELD, hold=hold, release=release,
            max_steps=max_steps, throw=False,
        )  # fmt: skip

    first = solve(params, ideal + ("camera.distortion",), ())
    second = solve(first.params, ideal, ())
    fit = solve(second.params)
    bounds = ((0.0, obs.width - 1.0), (0.0, obs.height - 1.0))
    fit, profile = profile_axis_point(solve, fit, bounds=bounds)
    freeze, notes = GAUGE_HELD, ()
    if model == "thick-lens-noncentral":
        # the central thick lens's optimum is the start, the pupil's shift from zero;
        # the pupil terms kept only where the F-test finds them (as with the held gauge)
        central = fit
        start = SystemParams(ThickLensNonCentral.from_central(fit.params.camera),
                             fit.params.board_poses)  # fmt: skip
        fit, freeze, notes = _noncentral_terms_tested(
            central, start, freeze, lambda p, hold, throw=False: solve(p, AXIS_POINT + hold)
        )
    if throw and not fit.converged:
        raise NotConvergedError(f"Levenberg–Marquardt did not converge: {fit.message}", fit)
    rms = _rms_px(fit.params, data)
    return CameraCalibration(
        fit.params.camera, fit.params.board_poses, fit, rms, how, freeze,
        axis_profile=profile, hold=AXIS_POINT, notes=notes,
    )  # fmt: skip


# Compiled residual evaluation for the summaries (eager evaluation would dispatch every
# operation of the distortion's fixed point separately).
_corner_errors_jit = exported_jit(corner_errors_px, compiler_options=ONE_SHOT)


def _corner_errors(params, data: CalibrationData) -> np.ndarray:
    """`corner_errors_px` through one compiled program, whichever blocks `params` holds
    (only the camera and the poses enter)."""
    return np.asarray(_corner_errors_jit(SystemParams(params.camera, params.board_poses), data))


def _rms_px(params, data: CalibrationData) -> float:
    r = _corner_errors(params, data)
    n = float(np.sum(np.asarray(data.corner_w)))
    return float(np.sqrt(np.sum(r**2) / (2 * n)))


def pixel_footprint_mm(camera, poses: Pose, obs: Observations) -> float:
    """Size (mm) of one pixel at the boards' distance, at the sensor centre."""
    c = np.array([(obs.width - 1) / 2, (obs.height - 1) / 2])
    r0, r1 = _directions(camera, jnp.asarray(np.stack([c, c + [1.0, 0.0]])))
    angle = float(jnp.linalg.norm(jnp.cross(r0, r1)))
    return angle * float(np.median(np.linalg.norm(np.asarray(poses.translation), axis=1)))
