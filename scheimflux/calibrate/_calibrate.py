"""Calibration of the camera, the laser plane and the rotary stage — separately as in the
paper (§2.4) and jointly as one parameter pytree."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..camera._distortion import Division, NoDistortion, OpenCVDistortion, RadialTangential
from ..camera._opencv import OpenCVCamera
from ..camera._pinhole import Pinhole
from ..camera._thick_lens import ThickLensScheimpflug
from ..geometry._plane import LaserPlane
from ..geometry._stage import RotaryStage
from ..geometry._transforms import Pose
from ..io._observations import Observations
from ._gates import (
    REJECT_SIGMA,
    Quality,
    QualityError,
    axis_point_gate,
    board_plane_angles_deg,
    fraction_gate,
    outlier_masks,
    plane_conditioning,
    rms_gate,
    screen_observations,
    tails_gate,
)
from ._init import (
    closed_form_pinhole,
    nominal_thick_lens,
    poses_for_central_camera,
    require_pixel_pitch,
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
from ._opencv import OPENCV_COEFFICIENTS, opencv_from_pinhole, opencv_frozen, parse_opencv_flags
from ._solve import Fit, least_squares

MODELS = ("thick-lens", "pinhole", "opencv")
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

    camera: ThickLensScheimpflug | Pinhole | OpenCVCamera
    poses: Pose
    fit: Fit
    reprojection_rms_px: float
    init: str
    freeze: tuple = ()  # the parameter paths held fixed


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
    return "radial-tangential" if model == "thick-lens" else "none"


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
    - `opencv_flags`: for `model="opencv"` (OpenCV's camera, equal to
      `cv2.projectPoints`): the terms beyond k1, k2, p1, p2, k3 —
      `"rational"`, `"thin-prism"`, `"tilted"` — and `"zero-tangent"`, `"fix-k3"`
      (see `scheimflux.calibrate._opencv`); a list or `"rational,tilted"`.

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
    if model == "thick-lens":
        require_pixel_pitch(obs)
    distortion = _default_distortion(model, distortion)
    dist = make_distortion(distortion)
    if model == "pinhole" and distortion != "none":
        raise ValueError(
            "the pinhole model (paper eq. 14) has no distortion; use "
            "distortion='none' or the thick-lens model"
        )
    camera, poses, how = _initial(obs, model, init)
    freeze = _model_freeze(model, how, freeze, opencv_flags)
    if model == "opencv":
        # the ideal pinhole first (every coefficient at zero), then the model's terms
        first = least_squares(
            camera_residuals,
            SystemParams(camera, poses),
            make_data(obs, sigma_corner_px=sigma_corner_px, robust=robust),
            freeze=tuple(dict.fromkeys(freeze + OPENCV_COEFFICIENTS)),
            max_steps=max_steps,
            throw=False,
        )
        camera, poses = first.params.camera, first.params.board_poses
    if model == "thick-lens" and distortion != "none":
        # the ideal camera first, then with distortion from zero
        first = least_squares(
            camera_residuals,
            SystemParams(camera, poses),
            make_data(obs, sigma_corner_px=sigma_corner_px, robust=robust),
            freeze=freeze,
            max_steps=max_steps,
            throw=False,
        )
        camera, poses = first.params.camera, first.params.board_poses
        camera = eqx.tree_at(lambda c: c.distortion, camera, dist)
    data = make_data(obs, sigma_corner_px=sigma_corner_px, robust=robust)
    params = SystemParams(camera, poses)
    fit = least_squares(
        camera_residuals, params, data, freeze=freeze, max_steps=max_steps, throw=throw
    )
    rms = _rms_px(fit.params, data)
    return CameraCalibration(
        fit.params.camera, fit.params.board_poses, fit, rms, how, tuple(freeze)
    )


# Compiled residual evaluations for the summaries (eager evaluation would dispatch every
# operation of the distortion's fixed point separately).
_corner_errors_jit = eqx.filter_jit(corner_errors_px)
_stripe_residuals_jit = eqx.filter_jit(stripe_residuals)
_gauge_residuals_jit = eqx.filter_jit(gauge_residuals)


def _rms_px(params, data: CalibrationData) -> float:
    r = np.asarray(_corner_errors_jit(params, data))
    n = float(np.sum(np.asarray(data.corner_w)))
    return float(np.sqrt(np.sum(r**2) / (2 * n)))


@dataclasses.dataclass(frozen=True)
class PlaneFit:
    """Laser plane by total least squares through the stripe points on the boards."""

    plane: LaserPlane
    points: np.ndarray  # (N, 3) camera frame, mm
    residuals_mm: np.ndarray  # signed distances from the plane
    conditioning: dict | None = None  # see `_gates.plane_conditioning`

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(np.mean(self.residuals_mm**2)))


@eqx.filter_jit
def _onto_planes(camera, normals, uv):
    """Each pixel's ray meets its own plane `n · X = 1` (rows of `normals`)."""

    def one(p, n):
        ray = camera.backproject_one(p)
        t = (1.0 - jnp.dot(n, ray.origin)) / jnp.dot(n, ray.direction)
        return ray.origin + t * ray.direction

    return jax.vmap(one)(uv, normals)


def _pad_pow2(x: np.ndarray, minimum: int = 256) -> np.ndarray:
    """Pad rows (repeating the first) to a power of two, so compiled shapes recur."""
    m = max(minimum, 1 << (len(x) - 1).bit_length())
    return np.concatenate([x, np.repeat(x[:1], m - len(x), axis=0)])


def board_stripe_points(camera, poses: Pose, obs: Observations) -> np.ndarray:
    """Stripe pixels on each board → 3-D points where their rays meet the board plane
    (all views in one compiled call)."""
    R = np.asarray(jax.vmap(lambda p: p.R)(poses))
    t = np.asarray(poses.translation)
    uv, normals = [], []
    for i, view in enumerate(obs.views):
        px = np.asarray(view.stripe_px, dtype=np.float64).reshape(-1, 2)
        px = px[np.all(np.isfinite(px), axis=1)]
        n = R[i, :, 2] / np.dot(R[i, :, 2], t[i])
        uv.append(px)
        normals.append(np.broadcast_to(n, px.shape[:1] + (3,)))
    uv, normals = np.concatenate(uv), np.concatenate(normals)
    if len(uv) == 0:
        raise ValueError("no stripe pixels on any board view: cannot calibrate the laser plane")
    X = _onto_planes(camera, jnp.asarray(_pad_pow2(normals)), jnp.asarray(_pad_pow2(uv)))
    return np.asarray(X)[: len(uv)]


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


def _stripe_views(obs: Observations) -> np.ndarray:
    """The view index of each finite board stripe pixel, in `board_stripe_points` order."""
    idx = []
    for i, view in enumerate(obs.views):
        px = np.asarray(view.stripe_px, dtype=np.float64).reshape(-1, 2)
        idx.append(np.full(int(np.all(np.isfinite(px), axis=1).sum()), i))
    return np.concatenate(idx) if idx else np.zeros(0, int)


def fit_laser_plane(
    camera, poses: Pose, obs: Observations, *, sigma_mm: float | None = None
) -> PlaneFit:
    """Paper §2.4 step 3: stripe points on the calibrated boards → TLS plane.

    With the stripe points' noise `sigma_mm`, the plane's conditioning is checked first
    (`_gates.plane_conditioning`): stripes on fewer than 2 board poses, or on poses whose
    lines are collinear, raise `ValueError` instead of returning an undetermined plane.
    """
    pts = board_stripe_points(camera, poses, obs)
    cond = None
    if sigma_mm is not None:
        cond = plane_conditioning(pts, _stripe_views(obs), sigma_mm)
    plane = fit_plane_tls(pts)
    res = np.asarray(plane.signed_distance(jnp.asarray(pts)))
    return PlaneFit(plane, pts, res, cond)


@dataclasses.dataclass(frozen=True)
class StageInit:
    """Closed-form start of the stage calibration (see [`initial_stage`][]).

    **Fields:**
    - `stage`: the table axis as a gauge-fixed `RotaryStage` (`t_m_c = (d, 0, 0)`).
    - `eccentricity_mm`: the gauge axis's offset from the table axis (measurement frame).
    - `rms_mm`: RMS in-plane distance of the gauge points from the fitted sections.
    - `sense_from_data`: whether the table's turning sense (the sign of `z_m`) came from
      the eccentric motion of the gauge; False: the convention (`z_m` towards image up).
    """

    stage: RotaryStage
    eccentricity_mm: np.ndarray
    rms_mm: float
    sense_from_data: bool


@dataclasses.dataclass(frozen=True)
class StageCalibration:
    """Rotary-stage calibration from a gauge scan (paper §2.4 step 4).

    **Fields:**
    - `stage`: `R_m_c`, `t_m_c` (gauge-fixed: `t_m_c = (d, 0, 0)`) and Δω.
    - `eccentricity_mm`: the gauge axis's offset from the table axis, measurement frame.
    - `fit`: the Levenberg–Marquardt solve.
    - `radius_rms_mm`: RMS in-plane distance of the gauge points from the gauge's section
      by the laser plane (the residual of `gauge_residuals`, in mm).
    - `initial`: the closed-form start ([`StageInit`][]).
    """

    stage: RotaryStage
    eccentricity_mm: np.ndarray
    fit: Fit
    radius_rms_mm: float
    initial: StageInit | None = None


# Backprojection onto the laser plane, compiled once per (padded) number of pixels.
_laser_points_jit = eqx.filter_jit(_laser_points_safe)


def _gauge_points(camera, plane: LaserPlane, frames) -> tuple[np.ndarray, np.ndarray]:
    """All frames' stripe pixels → laser-plane points `(N, 3)` and frame indices `(N,)`,
    in ONE compiled call (pixels concatenated and padded to a power of two)."""
    uv, idx = [], []
    for i, f in enumerate(frames):
        f = np.asarray(f, dtype=np.float64).reshape(-1, 2)
        f = f[np.all(np.isfinite(f), axis=1)]
        uv.append(f)
        idx.append(np.full(len(f), i))
    uv, idx = np.concatenate(uv), np.concatenate(idx)
    n = len(uv)
    if n == 0:
        raise ValueError("the stage scan holds no stripe pixels")
    X = np.asarray(_laser_points_jit(camera, plane, jnp.asarray(_pad_pow2(uv))))[:n]
    ok = np.all(np.isfinite(X), axis=1)
    return X[ok], idx[ok]


def _unit_rows(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _perp_basis(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors a, b with (a, b, d) right-handed, for directions `d` `(D, 3)`."""
    h = np.where(np.abs(d[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    a = _unit_rows(np.cross(d, h))
    return a, np.cross(d, a)


def _direction_grid(normal: np.ndarray, step: float, min_elevation: float) -> np.ndarray:
    """Directions `d` with `d · n̂ ≥ sin(min_elevation)`, about `step` rad apart (a
    hemisphere of axis directions about the laser normal; ±d are the same axis)."""
    u, v = _perp_basis(normal[None])
    u, v = u[0], v[0]
    out = []
    for el in np.arange(min_elevation, np.pi / 2 + 1e-9, step):
        k = max(1, int(round(2 * np.pi * np.cos(el) / step)))
        az = (np.arange(k) + 0.5 * (len(out) % 2)) * 2 * np.pi / k
        ring = np.cos(az)[:, None] * u + np.sin(az)[:, None] * v
        out.append(np.cos(el) * ring + np.sin(el) * normal)
    return np.concatenate(out)


@dataclasses.dataclass(frozen=True)
class _Sections:
    """Gauge points grouped by frame, for the section fits (NumPy, camera frame).

    `P` `(N, 3)`: the points minus their mean `mean`, sorted by frame; `starts` `(K,)`:
    where each of the K frames with points begins in `P`; `seg` `(N,)`: the group of each
    point (0 … K−1); `frames` `(K,)`: the frame indices i of the groups; `normal`: unit
    laser-plane normal; `radius`: the gauge radius (mm).
    """

    P: np.ndarray
    mean: np.ndarray
    starts: np.ndarray
    seg: np.ndarray
    frames: np.ndarray
    normal: np.ndarray
    radius: float

    @classmethod
    def of(cls, X, frame, normal, radius) -> _Sections:
        order = np.argsort(frame, kind="stable")
        X, frame = np.asarray(X, dtype=np.float64)[order], np.asarray(frame)[order]
        frames, starts, seg = np.unique(frame, return_index=True, return_inverse=True)
        mean = X.mean(axis=0)
        normal = np.asarray(normal, dtype=np.float64)
        return cls(X - mean, mean, starts, seg, frames, normal / np.linalg.norm(normal), radius)

    def subsample(self, per_frame: int) -> _Sections:
        """At most `per_frame` points per frame, evenly along each arc."""
        ends = np.append(self.starts[1:], len(self.P))
        keep = np.concatenate(
            [
                np.unique(np.linspace(s, e - 1, min(e - s, per_frame)).round().astype(int))
                for s, e in zip(self.starts, ends)
            ]
        )
        return _Sections(
            self.P[keep], self.mean, np.searchsorted(keep, self.starts), self.seg[keep],
            self.frames, self.normal, self.radius,
        )  # fmt: skip


def _section_fits(sec: _Sections, dirs: np.ndarray, iterations: int = 5):
    """For each candidate axis direction, a circle of the known radius per frame.

    The gauge points of frame i lie on a cylinder of radius r: projected along the true
    axis direction they lie on a circle of radius r (its centre moves from frame to frame
    with the eccentricity). For each direction `d` `(D, 3)` the points are projected onto
    the plane ⟂ d and a circle of radius r is fitted to each frame (Kåsa start, then
    Gauss–Newton on the centre). A point's residual, its distance from the cylinder along
    the surface normal, is divided by that normal's length within the laser plane
    (√(1 − (ρ̂·n̂)²)): the distance *within the laser plane*, where the pixel noise acts.
    The plain 3-D distance would favour cylinders nearly tangent to the laser plane,
    which come within a fraction of a micrometre of a whole band of the plane.

    Per-frame sums use `np.add.reduceat` (no BLAS threads: fast on a busy machine).

    **Returns:** `(score, resid, centres, H, (a, b))`: `score` `(D,)` the mean squared
    in-plane residual (mm²; inf where most of the lit surface would face away from the
    camera or a fit failed), `resid` `(D, N)` the in-plane residuals, the centres `(D, K,
    2)` in the basis `a, b` of each direction (about `sec.mean`), and their normal
    matrices `H` `(D, K, 2, 2)`.
    """
    P, seg, r = sec.P, sec.seg, sec.radius

    def ssum(v):  # (D, N) → per-frame sums (D, K)
        return np.add.reduceat(v, sec.starts, axis=1)

    def dot(u, V):  # (D, 3), (N, 3) → (D, N), without BLAS
        return u[:, :1] * V[:, 0] + u[:, 1:2] * V[:, 1] + u[:, 2:] * V[:, 2]

    a, b = _perp_basis(dirs)
    x, y = dot(a, P), dot(b, P)  # (D, N)
    cnt = np.diff(np.append(sec.starts, len(P)))
    # Kåsa fit per frame, in coordinates centred on the frame's centroid
    mx, my = ssum(x) / cnt, ssum(y) / cnt  # (D, K)
    xc, yc = x - mx[:, seg], y - my[:, seg]
    z = xc**2 + yc**2
    sxx, sxy, syy = ssum(xc * xc), ssum(xc * yc), ssum(yc * yc)
    sxz, syz = ssum(xc * z), ssum(yc * z)
    with np.errstate(divide="ignore", invalid="ignore"):
        det = sxx * syy - sxy**2
        kx = (syy * sxz - sxy * syz) / det
        ky = (sxx * syz - sxy * sxz) / det
        k = np.hypot(kx, ky)
        # the circle of radius r through the arc, on the side of the Kåsa centre
        cx, cy = mx + r * kx / k, my + r * ky / k
    ok = np.isfinite(cx) & np.isfinite(cy)
    cx, cy = np.where(ok, cx, mx), np.where(ok, cy, my)
    an, bn = (a @ sec.normal)[:, None], (b @ sec.normal)[:, None]
    for it in range(iterations + 1):
        dx, dy = x - cx[:, seg], y - cy[:, seg]
        rho = np.hypot(dx, dy)
        ux, uy = dx / rho, dy / rho
        res = rho - r
        w = 1.0 / np.maximum(1.0 - (ux * an + uy * bn) ** 2, 1e-12)
        wx, wy = w * ux, w * uy
        hxx, hxy, hyy = ssum(wx * ux), ssum(wx * uy), ssum(wy * uy)
        if it == iterations:
            break
        gx, gy = ssum(wx * res), ssum(wy * res)
        with np.errstate(divide="ignore", invalid="ignore"):
            det = hxx * hyy - hxy**2
            sx, sy = (hyy * gx - hxy * gy) / det, (hxx * gy - hxy * gx) / det
        good = np.isfinite(sx) & np.isfinite(sy)
        cx, cy = cx + np.where(good, sx, 0.0), cy + np.where(good, sy, 0.0)
    resid = np.sqrt(w) * res
    score = np.mean(resid**2, axis=1)
    # the lit surface faces the camera (at −mean): outward normal towards it
    cam = -sec.mean - P  # (N, 3)
    facing = np.mean(ux * dot(a, cam) + uy * dot(b, cam) > 0, axis=1)
    valid = (facing > 0.5) & np.all(ok, axis=1) & np.isfinite(score)
    score = np.where(valid, score, np.inf)
    centres = np.stack([cx, cy], axis=-1)
    H = np.stack([np.stack([hxx, hxy], -1), np.stack([hxy, hyy], -1)], -2)
    return score, resid, centres, H, (a, b)


def _refine_direction(sec: _Sections, d: np.ndarray, *, tol: float, max_iter: int = 50):
    """Levenberg–Marquardt on the axis direction alone (the per-frame circle centres are
    solved for each direction: variable projection), finite-difference Jacobian."""
    h = 1e-6
    score, res = _section_fits(sec, d[None])[:2]
    cost, res = float(score[0]), res[0]
    lam = 1e-3
    for _ in range(max_iter):
        a, b = _perp_basis(d[None])
        trial = _unit_rows(np.stack([d + h * a[0], d + h * b[0]]))
        J = (_section_fits(sec, trial)[1] - res).T / h  # (N, 2)
        JtJ, g = J.T @ J, J.T @ res
        while True:
            step = -np.linalg.solve(JtJ + lam * np.diag(np.diag(JtJ)), g)
            new = _unit_rows(d + step[0] * a[0] + step[1] * b[0])
            s_new, r_new = _section_fits(sec, new[None])[:2]
            if float(s_new[0]) <= cost:
                d, cost, res = new, float(s_new[0]), r_new[0]
                lam = max(lam / 5.0, 1e-9)
                break
            lam *= 8.0
            if lam > 1e8:
                return d, cost
        if np.hypot(*step) < tol:
            break
    return d, cost


def _fit_cylinder_axis(
    sec: _Sections,
    *,
    coarse_step: float = math.radians(4.0),
    min_elevation: float = math.radians(2.0),
    candidates: int = 2,
    tol: float = 1e-7,
):
    """The axis direction of a cylinder of known radius from its sections by one plane.

    The points (`sec`, camera frame) lie on the laser plane and on the cylinder, which may
    move from frame to frame (an eccentric gauge on a turning table) but keeps its
    direction. A coarse grid of directions (`coarse_step` apart, at least `min_elevation`
    out of the plane; a subsample of the points) scores every direction by the in-plane
    residual of per-frame fixed-radius circle fits ([`_section_fits`][]), vectorised over
    directions; the best `candidates` separated minima are refined on all points
    ([`_refine_direction`][], to `tol` rad).

    **Returns:** `(direction, score)`, the unit direction with `direction · n̂ > 0` and
    its mean squared in-plane residual (mm²).
    """
    coarse = sec.subsample(12)
    dirs = _direction_grid(sec.normal, coarse_step, min_elevation)
    score = np.concatenate(
        [_section_fits(coarse, dirs[k : k + 256], 3)[0] for k in range(0, len(dirs), 256)]
    )
    picked = []
    for j in np.argsort(score):
        if not np.isfinite(score[j]) or len(picked) == candidates:
            break
        if all(abs(dirs[j] @ dirs[p]) < math.cos(3 * coarse_step) for p in picked):
            picked.append(j)
    if not picked:
        raise ValueError(
            "no cylinder of the gauge radius fits the scan with its lit side facing the "
            "camera: check the gauge radius, the laser plane and the camera"
        )
    best = min((_refine_direction(sec, dirs[j], tol=tol) for j in picked), key=lambda t: t[1])
    d = best[0] if best[0] @ sec.normal > 0 else -best[0]
    return d, best[1]


def _straight_line_ms(sec: _Sections) -> float:
    """Mean squared distance of the points from a straight line fitted to each frame."""
    P = sec.P
    cnt = np.diff(np.append(sec.starts, len(P)))
    m = np.add.reduceat(P, sec.starts, axis=0) / cnt[:, None]  # (K, 3) frame centroids
    outer = np.add.reduceat(P[:, :, None] * P[:, None, :], sec.starts, axis=0)
    cov = outer / cnt[:, None, None] - m[:, :, None] * m[:, None, :]
    ev = np.linalg.eigvalsh(cov)  # ascending: off the plane, across the line, along it
    # eigenvalues of an exactly straight stripe round to ±1e-20: never below 0
    return max(float(np.sum(cnt * (ev[:, 0] + ev[:, 1])) / len(P)), 0.0)


def _usable_gauge_points(X, frame, radius, min_points=5):
    """The points of frames with `min_points` or more; `ValueError` if too few remain."""
    if not (radius > 0 and np.isfinite(radius)):
        raise ValueError(f"the gauge radius must be positive, got {radius}")
    n_per = np.bincount(frame)
    keep = n_per[frame] >= min_points
    if np.count_nonzero(keep) < 2 * min_points:
        raise ValueError(
            f"the stage scan holds too few stripe points ({len(X)}; need frames with "
            f"{min_points} or more, {2 * min_points} in all) to fit the gauge"
        )
    return X[keep], frame[keep]


def _stage_from_sections(sec: _Sections, d: np.ndarray, delta_omega: float):
    """Table axis and eccentricity from the per-frame section circles along `d`.

    Along the table axis z_m (= ±d), frame i's gauge centre sits at c + rot(−i Δω) e:
    the eccentric gauge circles the table axis against the table's turn. Both senses of
    z_m are tried; the one that fits the centres' motion wins when it fits clearly
    better (an eccentric gauge), else z_m points towards image up (−y_c).
    """
    score, _, centres, H, (a, b) = _section_fits(sec, d[None])
    centres, H, a, b = centres[0], H[0], a[0], b[0]
    # whitened rows Lᵀ (c_f − c − R_f e), H_f = L Lᵀ
    eps = 1e-12 * np.trace(H, axis1=1, axis2=2)[:, None, None] * np.eye(2)
    L = np.linalg.cholesky(H + eps)
    ang = -sec.frames * delta_omega
    Rf = np.stack(
        [np.stack([np.cos(ang), -np.sin(ang)], -1), np.stack([np.sin(ang), np.cos(ang)], -1)], -2
    )  # (K, 2, 2)
    fits = {}
    for sense in (1.0, -1.0):
        # coordinates in the basis (a, s b) of z_m = s d: (c_a, s c_b), H → F H F
        F = np.diag([1.0, sense])
        Lt = np.swapaxes(F @ L, 1, 2)
        A = np.concatenate([Lt, Lt @ Rf], axis=2).reshape(-1, 4)
        rhs = np.einsum("kij,kj->ki", Lt, centres @ F).reshape(-1)
        if len(sec.frames) >= 3:
            sol = np.linalg.lstsq(A, rhs, rcond=1e-12)[0]
        else:  # too few frames for the eccentricity
            sol = np.append(np.linalg.lstsq(A[:, :2], rhs, rcond=1e-12)[0], [0.0, 0.0])
        fits[sense] = (float(np.sum((A @ sol - rhs) ** 2)), sol)
    ss = {s: f[0] for s, f in fits.items()}
    from_data = min(ss.values()) < 0.25 * max(ss.values())
    if from_data:
        sense = min(ss, key=ss.get)
    else:
        sense = 1.0 if d @ np.array([0.0, -1.0, 0.0]) >= 0 else -1.0
    sol = fits[sense][1]
    z, bb = sense * d, sense * b
    p = sec.mean + sol[0] * a + sol[1] * bb  # a point on the table axis
    e3 = sol[2] * a + sol[3] * bb
    # measurement frame: origin at the foot of the perpendicular from the camera, x_m
    # towards the camera (the gauge fixing of `gauge_residuals`: t_m_c = (d, 0, 0))
    origin = p - (p @ z) * z
    dist = float(np.linalg.norm(origin))
    if dist < 1e-6:
        raise ValueError("the table axis passes through the camera: degenerate stage scan")
    x_m = -origin / dist
    R_m_c = np.stack([x_m, np.cross(z, x_m), z])
    stage = RotaryStage(R_m_c, np.array([dist, 0.0, 0.0]), delta_omega)
    ecc = np.array([e3 @ R_m_c[0], e3 @ R_m_c[1]])
    return stage, ecc, float(np.sqrt(score[0])), bool(from_data)


def initial_stage(camera, plane: LaserPlane, obs: Observations) -> StageInit:
    """Closed-form start for the stage calibration: table axis and gauge eccentricity.

    The stripe pixels of all frames are back-projected onto the laser plane (one compiled
    call). The table axis direction is searched over a hemisphere about the laser normal
    (coarse grid, then Levenberg–Marquardt on the direction): along the right direction
    every frame's points project onto a circle of the gauge radius, with the lit side
    facing the camera ([`_section_fits`][]). The per-frame circle centres then give the
    axis position, the eccentricity (the gauge circles the table axis as it turns) and
    the turning sense.

    **Returns:** a [`StageInit`][]. Raises `ValueError` for a scan that cannot determine
    the axis (too few points, a straight stripe, no fitting cylinder facing the camera).
    """
    if obs.stage is None:
        raise ValueError('the observations hold no rotary-stage scan ("stage")')
    radius = float(obs.stage.gauge_radius_mm)
    X, frame = _gauge_points(camera, plane, obs.stage.frames)
    X, frame = _usable_gauge_points(X, frame, radius)
    sec = _Sections.of(X, frame, np.asarray(plane.n, dtype=np.float64), radius)
    min_elevation = math.radians(2.0)
    d, score = _fit_cylinder_axis(sec, min_elevation=min_elevation)
    # The axis comes from the stripe's curvature: it must stand out of the noise, i.e. a
    # straight line per frame must fit far worse than the sections.
    line_ms = _straight_line_ms(sec)
    if d @ sec.normal < math.sin(min_elevation) or line_ms < 100.0 * score:
        raise ValueError(
            "the gauge scan does not determine the table axis: the stripe is straight "
            f"(RMS {1e3 * math.sqrt(max(line_ms, 0.0)):.3g} µm from a straight line per "
            f"frame, {1e3 * math.sqrt(max(score, 0.0)):.3g} µm from the fitted cylinder; "
            "the best axis "
            f"lies {math.degrees(math.asin(min(1.0, abs(d @ sec.normal)))):.3g}° out of "
            "the laser plane). Tilt the table axis out of the laser plane."
        )
    stage, ecc, rms, from_data = _stage_from_sections(
        sec, d, math.radians(obs.stage.delta_omega_deg)
    )
    return StageInit(stage, ecc, rms, from_data)


def calibrate_stage(
    camera,
    plane: LaserPlane,
    obs: Observations,
    *,
    sigma_stripe_mm: float = 1e-3,
    freeze: Sequence[str] = (),
    max_steps: int = 200,
    throw: bool = True,
) -> StageCalibration:
    """Paper §2.4 step 4: R_m_c, t_m_c (and the gauge eccentricity) from a gauge scan.

    Starts from [`initial_stage`][] and refines the table axis and the eccentricity by
    Levenberg–Marquardt on `gauge_residuals` (camera, laser plane and Δω held fixed,
    and the stage or eccentricity paths in `freeze`, e.g. `"stage.T_m_c.rotvec"`).
    """
    if obs.stage is None:
        raise ValueError('the observations hold no rotary-stage scan ("stage")')
    init = initial_stage(camera, plane, obs)
    if not obs.views:  # the stage block needs no boards; make_data wants one view
        from ..io._observations import View

        blank = View(np.full((len(obs.board_points_mm), 2), np.nan), np.zeros((0, 2)))
        obs = dataclasses.replace(obs, views=[blank])
    data = make_data(obs, sigma_stripe_mm=sigma_stripe_mm)
    poses = Pose(jnp.zeros((1, 3)), jnp.zeros((1, 3)))
    params = SystemParams(camera, poses, plane, init.stage, jnp.asarray(init.eccentricity_mm))
    fit = least_squares(
        gauge_residuals,
        params,
        data,
        freeze=("camera", "board_poses", "plane", "stage.delta_omega", *freeze),
        max_steps=max_steps,
        throw=throw,
    )
    return StageCalibration(
        fit.params.stage,
        np.asarray(fit.params.eccentricity),
        fit,
        _gauge_rms(fit.params, data),
        init,
    )


@dataclasses.dataclass(frozen=True)
class Calibration:
    """A complete calibration: the one parameter pytree and how it was obtained.

    **Fields:**
    - `params`: `SystemParams` (camera, board poses, laser plane, stage, eccentricity).
    - `model`: `"thick-lens"`, `"pinhole"` or `"opencv"`; `init`: how the camera was
      initialised.
    - `fits`: the LM solves by stage (`"camera"`, `"stage"`, `"joint"`).
    - `freeze`: the parameter paths held fixed.
    - `reprojection_rms_px`, `plane_rms_mm` (None for a camera-only calibration),
      `gauge_rms_mm` (None without a stage scan).
    - `data`: the arrays the residuals were computed from.
    - `sensor_size`: `(width, height)` in px.

    A camera-only calibration (no stripe pixels on the boards) has `plane = None`
    (`camera_only` is True): it serves OpenCV export and camera studies, not
    reconstruction.
    """

    params: SystemParams
    model: str
    distortion: str
    init: str
    joint: bool
    fits: dict
    freeze: tuple
    reprojection_rms_px: float
    plane_rms_mm: float | None
    gauge_rms_mm: float | None
    data: CalibrationData
    sensor_size: tuple[int, int] = (0, 0)  # (width, height) px
    quality: Quality | None = None  # gates, rejected observations, warnings
    # observations left out by the rejection pass: index arrays (view, corner),
    # (view, stripe point), (frame, gauge point) into the screened observations
    left_out: dict | None = None

    @property
    def camera_only(self) -> bool:
        """True when there is no laser plane (no stripe pixels on the boards)."""
        return self.params.plane is None

    @property
    def camera(self):
        return self.params.camera

    @property
    def plane(self) -> LaserPlane | None:
        return self.params.plane

    @property
    def stage(self) -> RotaryStage | None:
        return self.params.stage


def _plane_rms(params, data) -> float:
    r = np.asarray(_stripe_residuals_jit(params, data)) * float(data.sigma_stripe_mm)
    n = float(np.sum(np.asarray(data.stripe_w)))
    return float(np.sqrt(np.sum(r**2) / max(n, 1.0)))


def _gauge_rms(params, data) -> float:
    r = np.asarray(_gauge_residuals_jit(params, data)) * float(data.sigma_stripe_mm)
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
    reject: float | None = REJECT_SIGMA,
    max_steps: int = 300,
    throw: bool = True,
    opencv_flags: Sequence[str] | str | None = None,
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
    `cal.quality` holds the gates, counts and warnings (`scheimflux.calibrate._gates`).

    **Raises:** with `throw`, `NotConvergedError` when a solve fails and `QualityError`
    when a quality gate fails (both carry the result); `ValueError` for data that cannot
    determine the laser plane or that leave parameters undetermined.
    """
    obs, outside = screen_observations(obs)
    stage_freeze = _stage_freeze(freeze, obs)
    distortion = _default_distortion(model, distortion)
    camera_only = not _has_board_stripes(obs)
    if camera_only and obs.stage is not None:
        raise ValueError(
            "the observations hold a rotary-stage scan but no stripe pixels on any board "
            "view: the stage needs the laser plane, which needs the laser line on the boards"
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
    )
    if camera_only:
        cal = _camera_only(cam_cal, obs, model, distortion, sigma_corner_px, robust)
        rejected = {"threshold_sigma": reject}
        if reject is not None:
            rejected["corner_outliers"] = int(_outliers(cal.params, cal.data, reject)[0].sum())
        return _gated(cal, {**outside, **rejected}, None, throw)
    footprint = pixel_footprint_mm(cam_cal.camera, cam_cal.poses, obs)
    sigma_mm = sigma_stripe_px * footprint
    plane_fit = fit_laser_plane(cam_cal.camera, cam_cal.poses, obs, sigma_mm=sigma_mm)
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
    params = SystemParams(cam_cal.camera, cam_cal.poses, plane_fit.plane, stage, ecc)
    data = make_data(obs, sigma_corner_px=sigma_corner_px, sigma_stripe_mm=sigma_mm, robust=robust)
    freeze = cam_cal.freeze
    start = params
    if joint:
        fn = joint_residuals if stage is not None else camera_plane_residuals
        extra = ("stage.delta_omega",) if stage is not None else ()
        fit = least_squares(
            fn, params, data, freeze=freeze + extra, max_steps=max_steps, throw=throw
        )
        params = fit.params
        fits["joint"] = fit
    outliers = {"threshold_sigma": reject}
    left_out = None  # set where the rejection pass re-solved without them
    if reject is not None:
        fit, applied, passes = _rejection_passes(
            fn if joint else None,
            start,
            params,
            data,
            freeze + (extra if joint else ()),
            reject,
            max_steps,
            throw,
        )
        if fit is not None:
            params, data = fit.params, _without(data, applied)
            fits["joint"] = fit
            left_out = _left_out_indices(applied)
        outliers.update(
            corner_outliers=int(applied[0].sum()),
            stripe_outliers=int(applied[1].sum()),
            gauge_outliers=int(applied[2].sum()),
            rejection_passes=passes,
        )
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
        gauge_rms_mm=None if stage is None else _gauge_rms(params, data),
        data=data,
        sensor_size=(int(obs.width), int(obs.height)),
        left_out=left_out,
    )
    return _gated(cal, {**outside, **outliers}, plane_fit.conditioning, throw)


LEFT_OUT_BLOCKS = ("corners", "stripe", "gauge")


def _left_out_indices(masks) -> dict:
    """The rejection masks as `{block: (n, 2) int array}` (row, index) per block."""
    return {k: np.argwhere(np.asarray(m)) for k, m in zip(LEFT_OUT_BLOCKS, masks)}


def apply_left_out(data: CalibrationData, left_out: dict) -> CalibrationData:
    """`data` with the observations of `left_out` (see `Calibration.left_out`) at weight
    0; `ValueError` when an index does not fit the data."""
    masks = []
    for k, w in zip(LEFT_OUT_BLOCKS, (data.corner_w, data.stripe_w, data.gauge_w)):
        m = np.zeros(w.shape, bool)
        idx = np.asarray(left_out.get(k, ()), dtype=int).reshape(-1, 2)
        if len(idx) and (np.any(idx < 0) or np.any(idx >= np.array(w.shape))):
            raise ValueError(f"left-out {k} index out of range for these observations")
        m[idx[:, 0], idx[:, 1]] = True
        masks.append(m)
    return _without(data, masks)


def _gated(cal: Calibration, rejected: dict, conditioning, throw: bool) -> Calibration:
    """`cal` with its quality gates assessed; `QualityError` (with `throw`) if one fails."""
    quality = assess_quality(cal, rejected, conditioning)
    cal = dataclasses.replace(cal, quality=quality)
    if throw and not quality.passed:
        raise QualityError(
            "calibration failed its quality gates: "
            + "; ".join(g.message for g in quality.failures),
            cal,
        )
    return cal


def _stage_freeze(freeze, obs: Observations) -> tuple[str, ...]:
    """The stage and eccentricity paths of a user's `freeze` (for the stage solve)."""
    paths = tuple(p for p in (freeze or ()) if p.split(".")[0] in ("stage", "eccentricity"))
    if paths and obs.stage is None:
        raise ValueError(
            f"cannot freeze {', '.join(paths)}: the observations hold no rotary-stage scan"
        )
    return paths


# At most this many rejection passes (re-solves) after the joint solve.
MAX_REJECTION_PASSES = 3


def _without(data: CalibrationData, masks) -> CalibrationData:
    """`data` with the observations under `masks` (True: left out) at weight 0."""
    return eqx.tree_at(
        lambda d: (d.corner_w, d.stripe_w, d.gauge_w),
        data,
        tuple(
            jnp.where(jnp.asarray(m), 0.0, w)
            for m, w in zip(masks, (data.corner_w, data.stripe_w, data.gauge_w))
        ),
    )


def _rejection_passes(fn, start, params, data, freeze, reject, max_steps, throw):
    """The rejection pass: leave out what lies beyond `reject` robust σ, solve again.

    A few gross outliers pull a least-squares solution so far that good neighbours (the
    other corners of their view) look like outliers too. So the masks are recomputed from
    every observation at each new solution, and the joint problem is re-solved (from the
    separate steps' `start`: from the contaminated optimum LM crept along the weak
    depth valley without converging) until the masks stop changing, at most
    `MAX_REJECTION_PASSES` times. Same shapes (weights 0): the compiled solver is reused.
    With `fn` None (no joint solve) the outliers are only counted.

    **Returns:** `(fit or None, masks applied, number of passes)`.
    """
    masks = _outliers(params, data, reject)
    fit, applied, passes = None, tuple(np.zeros_like(m) for m in masks), 0
    if fn is not None:
        while passes < MAX_REJECTION_PASSES:
            same = all(np.array_equal(a, m) for a, m in zip(applied, masks))
            if same:
                break
            fit = least_squares(
                fn, start, _without(data, masks), freeze=freeze, max_steps=max_steps, throw=throw
            )
            applied, passes = masks, passes + 1
            masks = _outliers(fit.params, data, reject)
    else:
        applied = masks
    return fit, applied, passes


# ----------------------------------------------------------------------------- quality


def _unrobust(r: np.ndarray, k: float | None) -> np.ndarray:
    """Invert `_model._robustify` (Huber's square-root trick) to the plain residual."""
    if k is None:
        return r
    a = np.abs(r)
    return np.where(a <= k, r, np.sign(r) * (a**2 + k * k) / (2 * k))


def _block_residuals(params, data):
    """Corner errors `(V, M, 2)` px and the plain stripe `(V, K)` and gauge `(F, L)`
    residuals (units of their σ; zeros where the block is absent)."""
    err = np.asarray(_corner_errors_jit(params, data))
    if params.plane is None:
        stripe = np.zeros(data.stripe_w.shape)
    else:
        stripe = np.asarray(_stripe_residuals_jit(params, data)).reshape(data.stripe_w.shape)
        stripe = _unrobust(stripe, data.robust)
    if params.stage is None:
        gauge = np.zeros(data.gauge_w.shape)
    else:
        gauge = np.asarray(_gauge_residuals_jit(params, data))[:-2].reshape(data.gauge_w.shape)
        gauge = _unrobust(gauge, data.robust)
    return err, stripe, gauge


def _outliers(params, data, threshold: float):
    err, stripe, gauge = _block_residuals(params, data)
    return outlier_masks(
        err,
        np.asarray(data.corner_w),
        stripe,
        np.asarray(data.stripe_w),
        gauge,
        np.asarray(data.gauge_w),
        threshold=threshold,
        corner_sigma=float(data.sigma_corner_px),
        sigma=1.0,  # stripe and gauge residuals are in units of their σ
    )


# A board within this angle of the laser plane carries a poorly determined stripe line.
WEAK_BOARD_ANGLE_DEG = 5.0


def assess_quality(cal: Calibration, rejected: dict, plane_info: dict | None) -> Quality:
    """The quality gates of a calibration (see `scheimflux.calibrate._gates`)."""
    params, data = cal.params, cal.data
    W, H = cal.sensor_size
    sigma_c = float(data.sigma_corner_px)
    sigma_s = float(data.sigma_stripe_mm)
    gates = [
        rms_gate(
            "reprojection",
            cal.reprojection_rms_px,
            sigma_c,
            "px",
            "the camera model does not fit the corners (a bad start converged to a wrong "
            "camera, a missing distortion model, or a wrong --sigma-corner-px); try "
            "--init closed-form",
        )
    ]
    warnings = []
    err, stripe, gauge = _block_residuals(params, data)
    cw, sw, gw = (np.asarray(w) > 0 for w in (data.corner_w, data.stripe_w, data.gauge_w))
    gates.append(tails_gate("corner", (err / sigma_c)[cw].reshape(-1)))
    n_out = int(rejected.get("corner_outliers", 0) or 0)
    gates.append(fraction_gate("corners", n_out, int(cw.sum()) + n_out))
    if params.plane is not None and sw.any():
        gates.append(
            rms_gate(
                "stripe",
                cal.plane_rms_mm,
                sigma_s,
                "mm",
                "the board stripe points do not lie on one laser plane (stripes from the "
                "wrong views, reflections, or a wrong --sigma-stripe-px)",
            )
        )
        gates.append(tails_gate("stripe", stripe[sw]))
        n_out = int(rejected.get("stripe_outliers", 0) or 0)
        gates.append(fraction_gate("stripe points", n_out, int(sw.sum()) + n_out))
        views = np.flatnonzero(sw.any(axis=1))
        R = np.asarray(jax.vmap(lambda p: p.R)(params.board_poses))
        angles = board_plane_angles_deg(R[views, :, 2], np.asarray(params.plane.n))
        weak = views[angles < WEAK_BOARD_ANGLE_DEG]
        if len(weak):
            warnings.append(
                f"weak geometry: boards of views {weak.tolist()} lie within "
                f"{WEAK_BOARD_ANGLE_DEG:g}° of the laser plane (smallest "
                f"{float(angles.min()):.2g}°): their stripe lines are poorly determined; "
                "tilt the boards against the laser plane"
            )
    if cal.gauge_rms_mm is not None:
        gates.append(
            rms_gate(
                "gauge",
                cal.gauge_rms_mm,
                sigma_s,
                "mm",
                "the gauge scan does not fit a cylinder of the gauge radius about the table "
                "axis (wrong gauge radius, or Δω)",
            )
        )
    cam = params.camera
    if isinstance(cam, ThickLensScheimpflug):
        gates.append(axis_point_gate(float(cam.x0), float(cam.y0), W, H))
    elif isinstance(cam, Pinhole):
        g = axis_point_gate(float(cam.x0), float(cam.y0), W, H)
        if not g.passed:
            warnings.append(
                f"the pinhole's principal point ({float(cam.x0):.1f}, {float(cam.y0):.1f}) "
                "px lies off the sensor: expected for a tilted sensor, which the pinhole "
                "(paper eq. 14) absorbs into skew and principal point; the thick-lens "
                "model describes it"
            )
    for name, fit in cal.fits.items():
        if not fit.converged:
            warnings.append(f"the {name} solve did not converge ({fit.message})")
    if not cal.joint and rejected.get("threshold_sigma") is not None:
        warnings.append("outliers are counted but not left out without the joint solve")
    return Quality(tuple(gates), dict(rejected), tuple(warnings), plane_info)


def _has_board_stripes(obs: Observations) -> bool:
    """Whether any board view holds a finite stripe pixel."""
    for view in obs.views:
        px = np.asarray(view.stripe_px, dtype=np.float64).reshape(-1, 2)
        if np.any(np.all(np.isfinite(px), axis=1)):
            return True
    return False


def _camera_only(cam_cal: CameraCalibration, obs, model, distortion, sigma_corner_px, robust):
    """The `Calibration` of the camera solve alone (no laser plane, no stage)."""
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


@eqx.filter_jit
def _directions(camera, uv):
    return camera.backproject(uv).direction


def pixel_footprint_mm(camera, poses: Pose, obs: Observations) -> float:
    """Size (mm) of one pixel at the boards' distance, at the sensor centre."""
    c = np.array([(obs.width - 1) / 2, (obs.height - 1) / 2])
    r0, r1 = _directions(camera, jnp.asarray(np.stack([c, c + [1.0, 0.0]])))
    angle = float(jnp.linalg.norm(jnp.cross(r0, r1)))
    return angle * float(np.median(np.linalg.norm(np.asarray(poses.translation), axis=1)))
