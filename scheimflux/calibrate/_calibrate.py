"""Calibration of the camera, the laser plane and the rotary stage — separately as in the
paper (§2.4) and jointly as one parameter pytree."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..camera._distortion import Division, NoDistortion, RadialTangential
from ..camera._pinhole import Pinhole
from ..camera._thick_lens import ThickLensScheimpflug
from ..geometry._plane import LaserPlane
from ..geometry._stage import RotaryStage
from ..geometry._transforms import Pose
from ..io._observations import Observations
from ._init import (
    closed_form_pinhole,
    nominal_thick_lens,
    poses_for_central_camera,
    thick_lens_from_pinhole,
)
from ._model import (
    CalibrationData,
    SystemParams,
    _laser_points_safe,
    camera_plane_residuals,
    camera_residuals,
    corner_errors_px,
    gauge_residuals,
    joint_residuals,
    make_data,
    stripe_residuals,
)
from ._solve import Fit, least_squares

MODELS = ("thick-lens", "pinhole")
DISTORTIONS = ("none", "radial-tangential", "division")


def make_distortion(name: str):
    """A zero-initialised distortion model by name."""
    if name == "none":
        return NoDistortion()
    if name == "radial-tangential":
        return RadialTangential()
    if name == "division":
        return Division()
    raise ValueError(f"distortion must be one of {DISTORTIONS}, got {name!r}")


# What image data cannot determine is held at its datasheet / nominal value by default.
# The pixel rays of the thick-lens model are a 3x3 projective map K_f, observable only up
# to a rotation (absorbed by the board poses) and a scale: 5 numbers for the 9 lens
# parameters. With e = 0 the model is exactly a zero-skew pinhole (3 numbers once the
# pixel pitch is known), so the sensor tilt is not observable from geometry alone. The
# defaults fix the pixel pitch (datasheet), f (lens datasheet) and a gauge for the
# tilt: the nominal adapter tilt when it is known, else the axis through the sensor
# centre. `diagnostics()` reports the singular values that show this.
DEFAULT_FREEZE = {
    ("thick-lens", "nominal"): (
        "camera.dx",
        "camera.dy",
        "camera.f",
        "camera.phi",
        "camera.theta",
    ),
    ("thick-lens", "closed-form"): (
        "camera.dx",
        "camera.dy",
        "camera.f",
        "camera.x0",
        "camera.y0",
    ),
    ("pinhole", "closed-form"): (),
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

    camera: ThickLensScheimpflug | Pinhole
    poses: Pose
    fit: Fit
    reprojection_rms_px: float
    init: str


def _initial(obs, model, init):
    if init not in ("auto", "nominal", "closed-form"):
        raise ValueError(f"init must be 'auto', 'nominal' or 'closed-form', got {init!r}")
    if model == "pinhole":
        return (*closed_form_pinhole(obs), "closed-form")
    nom = obs.nominal
    has_nominal = nom is not None and nom.focal_length_mm and nom.magnification
    if init == "nominal" or (init == "auto" and has_nominal and nom.tilt_deg is not None):
        cam = nominal_thick_lens(obs)
        return cam, poses_for_central_camera(cam, obs), "nominal"
    pin, poses = closed_form_pinhole(obs)
    f = nom.focal_length_mm if nom is not None else None
    cam, poses = thick_lens_from_pinhole(pin, poses, obs, f=f)
    return cam, poses, "closed-form"


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
) -> CameraCalibration:
    """Calibrate the camera from checkerboard corners (Levenberg–Marquardt).

    **Arguments:**
    - `obs`: observations (corners per view, board geometry, sensor).
    - `model`: `"thick-lens"` (paper eq. 12) or `"pinhole"` (eq. 14).
    - `distortion`: `"radial-tangential"` (k1, k2, k3, p1, p2), `"division"` or
      `"none"`, applied in the untilted image plane (thick lens only).
    - `init`: `"nominal"` (paper step 2: nominal f, magnification, tilt, e = 0),
      `"closed-form"` (homographies, no nominal tilt needed) or `"auto"`.
    - `freeze`: parameter paths held fixed (default `DEFAULT_FREEZE[model]`).
    - `robust`: Huber threshold in units of σ (e.g. 3) for outlier corners.
    - `throw`: raise `NotConvergedError` if LM does not converge.
    """
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    _check_observations(obs)
    if distortion is None:
        distortion = "radial-tangential" if model == "thick-lens" else "none"
    dist = make_distortion(distortion)
    if model == "pinhole" and distortion != "none":
        raise ValueError(
            "the pinhole model (paper eq. 14) has no distortion; use "
            "distortion='none' or the thick-lens model"
        )
    camera, poses, how = _initial(obs, model, init)
    if model == "thick-lens" and distortion != "none":
        # the ideal camera first, then with distortion from zero
        first = least_squares(
            camera_residuals,
            SystemParams(camera, poses),
            make_data(obs, sigma_corner_px=sigma_corner_px, robust=robust),
            freeze=DEFAULT_FREEZE[(model, how)] if freeze is None else freeze,
            max_steps=max_steps,
            throw=False,
        )
        camera, poses = first.params.camera, first.params.board_poses
        camera = eqx.tree_at(lambda c: c.distortion, camera, dist)
    data = make_data(obs, sigma_corner_px=sigma_corner_px, robust=robust)
    params = SystemParams(camera, poses)
    freeze = DEFAULT_FREEZE[(model, how)] if freeze is None else tuple(freeze)
    fit = least_squares(
        camera_residuals, params, data, freeze=freeze, max_steps=max_steps, throw=throw
    )
    rms = _rms_px(fit.params, data)
    return CameraCalibration(fit.params.camera, fit.params.board_poses, fit, rms, how)


def _rms_px(params, data: CalibrationData) -> float:
    r = np.asarray(corner_errors_px(params, data))
    n = float(np.sum(np.asarray(data.corner_w)))
    return float(np.sqrt(np.sum(r**2) / (2 * n)))


@dataclasses.dataclass(frozen=True)
class PlaneFit:
    """Laser plane by total least squares through the stripe points on the boards."""

    plane: LaserPlane
    points: np.ndarray  # (N, 3) camera frame, mm
    residuals_mm: np.ndarray  # signed distances from the plane

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(np.mean(self.residuals_mm**2)))


def board_stripe_points(camera, poses: Pose, obs: Observations) -> np.ndarray:
    """Stripe pixels on each board → 3-D points where their rays meet the board plane."""
    pts = []
    for i, view in enumerate(obs.views):
        uv = np.asarray(view.stripe_px).reshape(-1, 2)
        uv = uv[np.all(np.isfinite(uv), axis=1)]
        if len(uv) == 0:
            continue
        R = np.asarray(Pose(poses.rotvec[i], poses.translation[i]).R)
        t = np.asarray(poses.translation[i])
        board_plane = LaserPlane(R[:, 2] / np.dot(R[:, 2], t))
        X = np.asarray(_laser_points_safe(camera, board_plane, jnp.asarray(uv)))
        pts.append(X)
    if not pts:
        raise ValueError("no stripe pixels on any board view: cannot calibrate the laser plane")
    return np.concatenate(pts)


def fit_plane_tls(points: np.ndarray) -> LaserPlane:
    """Total-least-squares plane through 3-D points (SVD of the centred points)."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) < 3:
        raise ValueError(f"a plane needs at least 3 points, got {len(points)}")
    c = points.mean(axis=0)
    _, s, Vt = np.linalg.svd(points - c, full_matrices=False)
    if s[1] < 1e-9 * max(s[0], 1e-300):
        raise ValueError(
            "stripe points are collinear: the laser plane is not determined "
            "(use board poses at different depths or tilts)"
        )
    normal = Vt[2]
    d = float(normal @ c)
    if abs(d) < 1e-9:
        raise ValueError("the fitted laser plane passes through the camera origin")
    return LaserPlane(normal / d)


def fit_laser_plane(camera, poses: Pose, obs: Observations) -> PlaneFit:
    """Paper §2.4 step 3: stripe points on the calibrated boards → TLS plane."""
    pts = board_stripe_points(camera, poses, obs)
    plane = fit_plane_tls(pts)
    res = np.asarray(plane.signed_distance(jnp.asarray(pts)))
    return PlaneFit(plane, pts, res)


@dataclasses.dataclass(frozen=True)
class StageCalibration:
    stage: RotaryStage
    eccentricity_mm: np.ndarray
    fit: Fit
    radius_rms_mm: float


def _fit_cylinder_axis(points: np.ndarray, radius: float):
    """Axis (point, direction) of a cylinder of known radius through points (grid + LS)."""
    c = points.mean(axis=0)
    P = points - c
    best = None
    # directions on a hemisphere
    for el in np.linspace(0.0, np.pi / 2, 19):
        for az in np.linspace(0.0, 2 * np.pi, max(1, int(72 * np.sin(el)) + 1), endpoint=False):
            d = np.array([np.cos(az) * np.sin(el), np.sin(az) * np.sin(el), np.cos(el)])
            a = np.cross(d, [1.0, 0, 0] if abs(d[0]) < 0.9 else [0, 1.0, 0])
            a /= np.linalg.norm(a)
            b = np.cross(d, a)
            x, y = P @ a, P @ b
            # Kasa circle fit
            A = np.stack([x, y, np.ones_like(x)], 1)
            rhs = x**2 + y**2
            sol, *_ = np.linalg.lstsq(A, rhs, rcond=None)
            cx, cy = sol[0] / 2, sol[1] / 2
            rr = np.sqrt(max(sol[2] + cx**2 + cy**2, 0.0))
            resid = np.sqrt(np.mean((np.hypot(x - cx, y - cy) - rr) ** 2))
            score = resid + abs(rr - radius) * 0.01
            if best is None or score < best[0]:
                best = (score, c + cx * a + cy * b, d)
    return best[1], best[2]


def initial_stage(camera, plane, obs: Observations):
    """Table axis from a cylinder fit to the gauge points of all frames (camera frame)."""
    pts = []
    for f in obs.stage.frames:
        uv = np.asarray(f).reshape(-1, 2)
        uv = uv[np.all(np.isfinite(uv), axis=1)]
        if len(uv):
            pts.append(np.asarray(_laser_points_safe(camera, plane, jnp.asarray(uv))))
    if not pts:
        raise ValueError("the stage scan holds no stripe pixels")
    pts = np.concatenate(pts)
    p, d = _fit_cylinder_axis(pts, obs.stage.gauge_radius_mm)
    # measurement frame: z_m along the axis (towards image "up", −y_c), origin at the
    # foot of the perpendicular from the camera, x_m towards the camera
    if d @ np.array([0.0, -1.0, 0.0]) < 0:
        d = -d
    origin = p - (p @ d) * d
    if np.linalg.norm(origin) < 1e-6:
        raise ValueError("the table axis passes through the camera: degenerate stage scan")
    x_m = -origin / np.linalg.norm(origin)
    y_m = np.cross(d, x_m)
    R_c_m = np.stack([x_m, y_m, d], axis=1)
    return RotaryStage(R_c_m.T, -R_c_m.T @ origin, math.radians(obs.stage.delta_omega_deg))


def calibrate_stage(
    camera,
    plane: LaserPlane,
    obs: Observations,
    *,
    sigma_stripe_mm: float = 1e-3,
    max_steps: int = 200,
    throw: bool = True,
) -> StageCalibration:
    """Paper §2.4 step 4: R_m_c, t_m_c (and the gauge eccentricity) from a gauge scan."""
    if obs.stage is None:
        raise ValueError('the observations hold no rotary-stage scan ("stage")')
    stage = initial_stage(camera, plane, obs)
    data = make_data(obs, sigma_stripe_mm=sigma_stripe_mm)
    poses = Pose(jnp.zeros((1, 3)), jnp.zeros((1, 3)))
    params = SystemParams(camera, poses, plane, stage, jnp.zeros(2))
    fit = least_squares(
        gauge_residuals,
        params,
        data,
        freeze=("camera", "board_poses", "plane", "stage.delta_omega"),
        max_steps=max_steps,
        throw=throw,
    )
    r = np.asarray(gauge_residuals(fit.params, data)) * sigma_stripe_mm
    n = float(np.sum(np.asarray(data.gauge_w)))
    return StageCalibration(
        fit.params.stage, np.asarray(fit.params.eccentricity), fit, float(np.sqrt(np.sum(r**2) / n))
    )


@dataclasses.dataclass(frozen=True)
class Calibration:
    """A complete calibration: the one parameter pytree and how it was obtained.

    **Fields:**
    - `params`: `SystemParams` (camera, board poses, laser plane, stage, eccentricity).
    - `model`: `"thick-lens"` or `"pinhole"`; `init`: how the camera was initialised.
    - `fits`: the LM solves by stage (`"camera"`, `"stage"`, `"joint"`).
    - `freeze`: the parameter paths held fixed.
    - `reprojection_rms_px`, `plane_rms_mm`, `gauge_rms_mm` (None without a stage scan).
    - `data`: the arrays the residuals were computed from.
    """

    params: SystemParams
    model: str
    distortion: str
    init: str
    joint: bool
    fits: dict
    freeze: tuple
    reprojection_rms_px: float
    plane_rms_mm: float
    gauge_rms_mm: float | None
    data: CalibrationData
    sensor_size: tuple[int, int] = (0, 0)  # (width, height) px

    @property
    def camera(self):
        return self.params.camera

    @property
    def plane(self) -> LaserPlane:
        return self.params.plane

    @property
    def stage(self) -> RotaryStage | None:
        return self.params.stage


def _plane_rms(params, data) -> float:
    r = np.asarray(stripe_residuals(params, data)) * float(data.sigma_stripe_mm)
    n = float(np.sum(np.asarray(data.stripe_w)))
    return float(np.sqrt(np.sum(r**2) / max(n, 1.0)))


def _gauge_rms(params, data) -> float:
    r = np.asarray(gauge_residuals(params, data)) * float(data.sigma_stripe_mm)
    n = float(np.sum(np.asarray(data.gauge_w)))
    return float(np.sqrt(np.sum(r**2) / max(n, 1.0)))


def calibrate(
    obs: Observations,
    *,
    model: str = "thick-lens",
    distortion: str | None = None,
    init: str = "auto",
    joint: bool = True,
    freeze: Sequence[str] | None = None,
    sigma_corner_px: float = 0.03,
    sigma_stripe_px: float = 0.05,
    robust: float | None = None,
    max_steps: int = 300,
    throw: bool = True,
) -> Calibration:
    """Calibrate camera, laser plane and (if scanned) the rotary stage.

    The separate steps of the paper (§2.4) run first: camera from corners, laser plane by
    TLS through the board stripe points, stage from the gauge scan. With `joint=True`
    (the default) one Levenberg–Marquardt solve then refines every block of the single
    parameter pytree together, each residual weighted by its noise: corners by
    `sigma_corner_px`, stripe and gauge points by `sigma_stripe_px` converted to mm at
    the camera's pixel footprint.
    """
    if distortion is None:
        distortion = "radial-tangential" if model == "thick-lens" else "none"
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
    )
    plane_fit = fit_laser_plane(cam_cal.camera, cam_cal.poses, obs)
    footprint = pixel_footprint_mm(cam_cal.camera, cam_cal.poses, obs)
    sigma_mm = sigma_stripe_px * footprint
    fits = {"camera": cam_cal.fit}
    stage = ecc = None
    if obs.stage is not None:
        st = calibrate_stage(
            cam_cal.camera,
            plane_fit.plane,
            obs,
            sigma_stripe_mm=sigma_mm,
            max_steps=max_steps,
            throw=throw,
        )
        stage, ecc = st.stage, jnp.asarray(st.eccentricity_mm)
        fits["stage"] = st.fit
    params = SystemParams(cam_cal.camera, cam_cal.poses, plane_fit.plane, stage, ecc)
    data = make_data(obs, sigma_corner_px=sigma_corner_px, sigma_stripe_mm=sigma_mm, robust=robust)
    freeze = tuple(DEFAULT_FREEZE[(model, cam_cal.init)] if freeze is None else freeze)
    if joint:
        fn = joint_residuals if stage is not None else camera_plane_residuals
        extra = ("stage.delta_omega",) if stage is not None else ()
        fit = least_squares(
            fn, params, data, freeze=freeze + extra, max_steps=max_steps, throw=throw
        )
        params = fit.params
        fits["joint"] = fit
    return Calibration(
        params=params,
        model=model,
        distortion=distortion,
        init=cam_cal.init,
        joint=joint,
        fits=fits,
        freeze=freeze,
        reprojection_rms_px=_rms_px(params, data),
        plane_rms_mm=_plane_rms(params, data),
        gauge_rms_mm=None if stage is None else _gauge_rms(params, data),
        data=data,
        sensor_size=(int(obs.width), int(obs.height)),
    )


def pixel_footprint_mm(camera, poses: Pose, obs: Observations) -> float:
    """Size (mm) of one pixel at the boards' distance, at the sensor centre."""
    c = jnp.array([(obs.width - 1) / 2, (obs.height - 1) / 2])
    r0 = camera.backproject(c).direction
    r1 = camera.backproject(c + jnp.array([1.0, 0.0])).direction
    angle = float(jnp.linalg.norm(jnp.cross(r0, r1)))
    return angle * float(np.median(np.linalg.norm(np.asarray(poses.translation), axis=1)))
