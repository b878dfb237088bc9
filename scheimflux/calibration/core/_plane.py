"""The laser plane from the stripe on the calibrated boards (paper §2.4 step 3): stripe
pixels → points on their board planes → total-least-squares plane."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ..._export import exported_jit
from ...geometry._fitting import fit_plane_svd
from ...geometry._plane import LaserPlane
from ...geometry._transforms import Pose
from ...io._observations import Observations
from ._blocks import laser_points
from ._model import laser_residuals
from ._screen import plane_conditioning
from ._solve import ONE_SHOT

# Compiled residual evaluation for the summaries (see `_camera._corner_errors_jit`):
# the stripe and gauge residuals in one program (one back-projection of their pixels).
_laser_residuals_jit = exported_jit(laser_residuals, compiler_options=ONE_SHOT)


@dataclasses.dataclass(frozen=True)
class PlaneFit:
    """Laser plane by total least squares through the stripe points on the boards."""

    plane: LaserPlane
    points: np.ndarray  # (N, 3) camera frame, mm
    residuals_mm: np.ndarray  # signed distances from the plane
    conditioning: dict | None = None  # see `_screen.plane_conditioning`

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(np.mean(self.residuals_mm**2)))


@exported_jit(compiler_options=ONE_SHOT)
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


# The least distance off its board (in pixel footprints) that a stripe pixel's error
# across the line is taken to cause: for a board nearly parallel to the laser plane the
# stripe gate's σ would otherwise vanish (5 % is a board ~3° from the plane; the
# weak-geometry warning names boards within 5°).
MIN_STRIPE_GAIN = 0.05


@exported_jit(compiler_options=ONE_SHOT)
def _stripe_gains(camera, plane, poses, stripe):
    """`‖∂d/∂u‖` (mm per px) of each stripe pixel `(V, K, 2)`: d the distance of its
    laser-plane point from its view's board (`stripe_point_residuals` without weights).
    Each d depends on its own pixel only, so one reverse pass gives them all."""

    def distances(uv):
        (X,) = laser_points(camera, plane, uv)

        def one(pose, X):
            n_b = pose.R[:, 2]
            return X @ n_b - jnp.dot(n_b, pose.translation)

        return jax.vmap(one)(poses, X)

    g = jax.grad(lambda uv: jnp.sum(distances(uv)))(stripe)
    return jnp.linalg.norm(g, axis=-1)


def stripe_gain(camera, plane, poses: Pose, data, footprint_mm: float) -> np.ndarray:
    """Per view `(V,)`: how far off its board a stripe pixel's error across the line moves
    its point, in pixel footprints (the median over the view's pixels of weight > 0 in
    `data` of `‖∂d/∂u‖` over `footprint_mm`; 1 for a view without stripe pixels; at
    least `MIN_STRIPE_GAIN`).

    The stripe σ in mm is the pixel σ times the footprint; the distance off the board
    is less: the footprint times the sine of the board's angle with the laser plane over
    the sine of the ray's angle with it (0.17-0.46 over the views of an achromat at
    x0.5, within +-3 % along each view's line): the stripe gates judge the distances by
    the σ it gives (`CalibrationData.stripe_gain`)."""
    g = np.asarray(_stripe_gains(camera, plane, poses, data.stripe))
    w = np.asarray(data.stripe_w)
    out = np.ones(len(w))
    for i in range(len(out)):
        used = (w[i] > 0) & np.isfinite(g[i])
        if used.any():
            out[i] = max(float(np.median(g[i][used])) / footprint_mm, MIN_STRIPE_GAIN)
    return out


def fit_plane_tls(points: np.ndarray, weights: np.ndarray | None = None) -> LaserPlane:
    """Total-least-squares plane through 3-D points (SVD of the centred points; with
    `weights` `(N,)`, of the points about their weighted centroid, each row scaled by
    √w: the plane minimising Σ w d²)."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) < 3:
        raise ValueError(f"a plane needs at least 3 points, got {len(points)}")
    if weights is None:
        c, normal, s = fit_plane_svd(points)
    else:
        w = np.asarray(weights, dtype=np.float64)
        c = (w[:, None] * points).sum(axis=0) / w.sum()
        _, s, Vt = np.linalg.svd(np.sqrt(w / w.mean())[:, None] * (points - c), full_matrices=False)
        normal = Vt[2]
    if s[1] < 1e-9 * max(s[0], 1e-300):
        raise ValueError(
            "stripe points are collinear: the laser plane is not determined "
            "(use board poses at different depths or tilts)"
        )
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


def stripe_conditioning(points: np.ndarray, obs: Observations, sigma_mm) -> dict:
    """`_screen.plane_conditioning` of the board stripe points `(N, 3)` (in
    `board_stripe_points` order) with their σ given per view `(V,)` or for all: the
    RMS over the points of their σ."""
    view = _stripe_views(obs)
    sigma = np.broadcast_to(np.asarray(sigma_mm, dtype=np.float64), (len(obs.views),))
    rms = float(np.sqrt(np.mean(sigma[view] ** 2))) if len(view) else float(sigma.max())
    return plane_conditioning(points, view, rms)


def fit_laser_plane(camera, poses: Pose, obs: Observations, *, sigma_mm=None) -> PlaneFit:
    """Paper §2.4 step 3: stripe points on the calibrated boards → TLS plane.

    With the stripe points' noise `sigma_mm`, the plane's conditioning is checked first
    (`_screen.plane_conditioning`): stripes on fewer than 2 board poses, or on poses whose
    lines are collinear, raise `ValueError` instead of returning an undetermined plane.
    Given per view (`(V,)`: views of unequal noise, e.g. speckled lines), each view's
    points are weighted by 1/σ² in the plane fit and the conditioning uses their RMS σ.

    **Arguments:**
    - `camera`: the calibrated camera (e.g. `calibrate_camera(obs).camera`).
    - `poses`: the board poses `T_c_b` of the views, batched `(V,)` (its `.poses`).
    - `obs`: the observations whose views' `stripe_px` lie on the boards.
    - `sigma_mm`: the stripe points' noise (mm), one for all or `(V,)` per view; None:
      no conditioning check, every point weighted alike.

    **Returns:** a [`PlaneFit`][]: the plane, the stripe points `(N, 3)` (camera frame,
    mm), their signed distances from the plane (mm) and the conditioning (None without
    `sigma_mm`).
    """
    pts = board_stripe_points(camera, poses, obs)
    cond, weights = None, None
    if sigma_mm is not None:
        cond = stripe_conditioning(pts, obs, sigma_mm)
        sigma = np.broadcast_to(np.asarray(sigma_mm, dtype=np.float64), (len(obs.views),))
        if np.ptp(sigma) > 0:
            weights = 1.0 / sigma[_stripe_views(obs)] ** 2
    plane = fit_plane_tls(pts, weights)
    res = np.asarray(plane.signed_distance(jnp.asarray(pts)))
    return PlaneFit(plane, pts, res, cond)


def _plane_rms(params, data) -> float:
    """RMS (mm) of the board stripe points' distances from their boards (each view's
    residuals back from units of its own σ)."""
    w = np.asarray(data.stripe_w)
    r = np.asarray(_laser_residuals_jit(params, data)[0]).reshape(w.shape)
    r = r * float(data.sigma_stripe_mm) * np.asarray(data.stripe_scale)[:, None]
    n = float(np.sum(w))
    return float(np.sqrt(np.sum(r**2) / max(n, 1.0)))


def stripe_sigma_rms_mm(data) -> float:
    """The RMS of the board stripe points' σ (mm) off their boards (each view's pixel
    σ, `data.stripe_scale`, moved off its board, `data.stripe_gain`): what `_plane_rms`
    is for pixel noise of exactly those σ."""
    w = np.asarray(data.stripe_w) > 0
    n = w.sum(axis=1)
    scale2 = (np.asarray(data.stripe_scale) * np.asarray(data.stripe_gain)) ** 2
    mean2 = float(np.sum(n * scale2) / n.sum()) if n.sum() else 1.0
    return float(data.sigma_stripe_mm) * float(np.sqrt(mean2))


def _has_board_stripes(obs: Observations) -> bool:
    """Whether any board view holds a finite stripe pixel."""
    for view in obs.views:
        px = np.asarray(view.stripe_px, dtype=np.float64).reshape(-1, 2)
        if np.any(np.all(np.isfinite(px), axis=1)):
            return True
    return False
