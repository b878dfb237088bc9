"""The calibration's parameter pytree, its data, and the residual functions.

Everything that is calibrated lives in ONE `eqx.Module`, `SystemParams`: the camera, the
board poses, the laser plane, the rotary stage and the gauge's eccentricity. Residual
functions take `(params, data)` and return one flat, noise-weighted (unitless) vector, so
separate and joint calibrations are the same solver on different residual blocks.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ...camera._base import AbstractCamera
from ...geometry._plane import LaserPlane
from ...geometry._stage import RotaryStage
from ...geometry._transforms import Pose
from ._blocks import (
    _pad,
    _robustify,
    circle_outlines,
    circle_ring,
    laser_points,
    outline_centroids,
    padded_length,
)
from ._table_block import TableTargetData, table_target_data, table_target_residuals


class SystemParams(eqx.Module):
    """Camera, board poses `T_c_b` (stacked, one per view), laser plane, stage, gauge offset.

    `plane`, `stage` and `eccentricity` are None when not (yet) calibrated.
    `eccentricity` is the gauge axis's offset from the table axis, in the measurement
    frame (mm, shape (2,)). `table_pose` is the pose `T_t_b` of a target fixed to the
    rotary table (None without one; `_stage_table`).
    """

    camera: AbstractCamera
    board_poses: Pose
    plane: LaserPlane | None = None
    stage: RotaryStage | None = None
    eccentricity: Float[Array, "2"] | None = None
    table_pose: Pose | None = None


class CalibrationData(eqx.Module):
    """Observations as padded arrays with weights (0 where missing).

    Missing pixels are replaced by a finite placeholder so no NaN reaches a residual.
    """

    board: Float[Array, "M 3"]
    corners: Float[Array, "V M 2"]
    corner_w: Float[Array, "V M"]
    stripe: Float[Array, "V K 2"]
    stripe_w: Float[Array, "V K"]
    gauge: Float[Array, "F L 2"]
    gauge_w: Float[Array, "F L"]
    frame_index: Float[Array, " F"]
    gauge_radius: Float[Array, ""]
    sigma_corner_px: Float[Array, ""]
    sigma_stripe_mm: Float[Array, ""]
    # per view: its stripe points' σ in units of `sigma_stripe_mm` (>= 1; above 1 where
    # the view's own measured scatter is larger, `view_stripe_scale`)
    stripe_scale: Float[Array, " V"]
    # per view: how far off its board a pixel's error across the line moves a stripe
    # point, in pixel footprints (`_plane.stripe_gain`; 1 where not computed): the
    # stripe σ of the distances is sigma_stripe_mm · stripe_scale · stripe_gain, which
    # the stripe gates judge by (the weights keep the footprint's σ: docs/calibration-trust.md)
    stripe_gain: Float[Array, " V"]
    robust: float | None = eqx.field(static=True, default=None)
    table: TableTargetData | None = None  # a target fixed to the rotary table
    # circle targets: the outline's vertices about each board point (board frame, mm);
    # None: the points are imaged as points
    circle_ring: Float[Array, "R 3"] | None = None


def view_stripe_scale(obs, sigma_stripe_px: float) -> np.ndarray:
    """Per view, its stripe points' σ in units of the stated `sigma_stripe_px`: the
    view's own measured scatter (`View.stripe_sigma_px`, a speckled line's, written by
    `detect`) over the stated σ where it is larger, else 1 (the stated σ is a floor:
    a view measured cleaner than it is not trusted beyond it)."""
    out = np.ones(len(obs.views))
    for i, v in enumerate(obs.views):
        if v.stripe_sigma_px is not None and v.stripe_sigma_px > sigma_stripe_px:
            out[i] = float(v.stripe_sigma_px) / float(sigma_stripe_px)
    return out


def make_data(
    obs,
    *,
    sigma_corner_px: float = 0.03,
    sigma_stripe_mm: float = 1e-3,
    stripe_scale=None,
    stripe_gain=None,
    robust: float | None = None,
) -> CalibrationData:
    """Arrays for the residual functions from an `Observations` record; `stripe_scale`
    `(V,)`: each view's stripe σ in units of `sigma_stripe_mm` ([`view_stripe_scale`][]),
    `stripe_gain` `(V,)`: the field `stripe_gain` (None: 1 for every view)."""
    centre = np.array([(obs.width - 1) / 2, (obs.height - 1) / 2])
    corners, mask = obs.corners()
    corners = np.where(mask[..., None], corners, centre)
    stripe, stripe_w = _pad([v.stripe_px for v in obs.views], centre)
    if obs.stage is not None:
        frames = list(obs.stage.frames)  # padded with empty frames (weight 0) like the points
        frames += [np.zeros((0, 2))] * (padded_length(len(frames)) - len(frames))
        gauge, gauge_w = _pad(frames, centre)
        radius = obs.stage.gauge_radius_mm
    else:
        gauge, gauge_w, radius = np.broadcast_to(centre, (1, 1, 2)).copy(), np.zeros((1, 1)), 1.0

    # `jax.device_put` of NumPy arrays: no device program (`jnp.asarray` of a NumPy
    # array compiles one per shape)
    def put(a):
        return jax.device_put(np.asarray(a, dtype=np.float64))

    return CalibrationData(
        board=put(obs.board_points_mm),
        corners=put(corners),
        corner_w=put(mask),
        stripe=put(stripe),
        stripe_w=put(stripe_w),
        gauge=put(gauge),
        gauge_w=put(gauge_w),
        frame_index=put(np.arange(gauge.shape[0])),
        gauge_radius=put(radius),
        sigma_corner_px=put(sigma_corner_px),
        sigma_stripe_mm=put(sigma_stripe_mm),
        stripe_scale=put(_per_view(stripe_scale, len(obs.views), "stripe_scale")),
        stripe_gain=put(_per_view(stripe_gain, len(obs.views), "stripe_gain")),
        robust=robust,
        table=None if obs.stage_target is None else table_target_data(obs.stage_target, centre),
        circle_ring=None
        if obs.circle_diameter_mm is None
        else put(circle_ring(obs.circle_diameter_mm)),
    )


def _per_view(factors, n_views: int, name: str) -> np.ndarray:
    if factors is None:
        return np.ones(n_views)
    factors = np.asarray(factors, dtype=np.float64).reshape(-1)
    if factors.shape != (n_views,) or not np.all(np.isfinite(factors) & (factors > 0)):
        raise ValueError(
            f"{name} must hold one positive factor per view ({n_views}), got {factors}"
        )
    return factors


def board_images_px(camera, pose: Pose, board, ring=None) -> Float[Array, "M 2"]:
    """Where a detector sees each board point of one view, `(M, 2)` px.

    `ring` None: the point's image. `ring` `(K, 3)` (`CalibrationData.circle_ring`; K
    even): the point is the centre of a circle, and a blob detector measures the centroid
    of the circle's image, which under perspective and distortion is not the image of its
    centre (by up to ~0.1 px for sub-millimetre dots under a short lens). The circle's
    outline is projected at the K vertices and the area centroid of that polygon and of
    the polygon of every other vertex are combined by Richardson extrapolation,
    `(4 c_K - c_K/2) / 3`: the inscribed polygon's error falls as K⁻², the combination's
    as K⁻⁴ (K = 16 on a 0.15 mm dot under an 8 mm lens: 2.7e-3 px alone, 1.3e-4 px
    combined, against 512 vertices).
    """
    if ring is None:
        uv, _ = jax.vmap(camera.project_one)(pose.apply(board))
        return uv
    uv, _ = jax.vmap(camera.project_one)(pose.apply(circle_outlines(board, ring)))
    return outline_centroids(uv, ring.shape[0])


def corner_errors_px(params: SystemParams, data: CalibrationData) -> Float[Array, "V M 2"]:
    """Reprojection errors (px) of every corner; 0 where the corner was not detected."""

    def one_view(pose, uv_obs, w):
        uv = board_images_px(params.camera, pose, data.board, data.circle_ring)
        return (uv - uv_obs) * w[:, None]

    return jax.vmap(one_view)(params.board_poses, data.corners, data.corner_w)


def corner_residuals(params: SystemParams, data: CalibrationData) -> Float[Array, " n"]:
    """Reprojection errors of the board corners / σ (u and v of every corner)."""
    r = corner_errors_px(params, data)
    return _robustify(r.reshape(-1) / data.sigma_corner_px, data.robust)


def stripe_point_residuals(poses, X, w, data: CalibrationData) -> Float[Array, " n"]:
    """[`stripe_residuals`][] from the stripe pixels' laser-plane points `X` `(V, K, 3)`
    (camera frame), with weights `w` `(V, K)`."""

    def one_view(pose, X, w, scale):
        n_b = pose.R[:, 2]  # board normal in the camera frame
        d = X @ n_b - jnp.dot(n_b, pose.translation)
        return d * (w / scale)

    r = jax.vmap(one_view)(poses, X, w, data.stripe_scale)
    return _robustify(r.reshape(-1) / data.sigma_stripe_mm, data.robust)


def stripe_residuals(params: SystemParams, data: CalibrationData) -> Float[Array, " n"]:
    """Distance (mm / σ) of each board stripe point's laser-plane point from its board."""
    (X,) = laser_points(params.camera, params.plane, data.stripe)
    return stripe_point_residuals(params.board_poses, X, data.stripe_w, data)


def gauge_residuals(params: SystemParams, data: CalibrationData) -> Float[Array, " n"]:
    """Distance (mm / σ), within the laser plane, of each reconstructed gauge point from
    the gauge's section by the plane.

    A radial error δr of a point on the cylinder is a displacement of δr / sin β along
    the stripe's normal in the laser plane, β the angle between the gauge's surface
    normal and the plane's normal: that is the direction the stripe pixels' noise moves
    the points, so σ (the in-plane stripe noise) weights it correctly. (Measured in 3-D
    instead, a cylinder nearly tangent to the laser plane fits any stripe in the plane
    to a fraction of a µm: a false minimum.)
    """
    (X_c,) = laser_points(params.camera, params.plane, data.gauge)
    return gauge_point_residuals(
        params.stage, params.eccentricity, params.plane.n, X_c, data.gauge_w, data
    )


def gauge_point_residuals(stage, eccentricity, plane_n, X_c, w, data) -> Float[Array, " n"]:
    """[`gauge_residuals`][] from the gauge pixels' laser-plane points `X_c` `(F, L, 3)`
    (camera frame), with weights `w` `(F, L)`; `data` gives the frame indices, the
    gauge radius, σ and the robust threshold. The stage solve (camera and plane held)
    computes `X_c` once and minimises this, with no camera in its compiled program."""
    n_c = plane_n / jnp.linalg.norm(plane_n)

    def one_frame(X_c, w, i):
        X_m = jax.vmap(stage.to_measurement, in_axes=(0, None))(X_c, i)
        d = X_m[:, :2] - eccentricity
        r = jnp.linalg.norm(d, axis=-1)
        n_m = stage.frame_rotation(i) @ (stage.R_m_c @ n_c)
        cos = (d @ n_m[:2]) / r
        sin = jnp.sqrt(jnp.maximum(1.0 - cos**2, 1e-6))
        return (r - data.gauge_radius) / sin * w

    r = jax.vmap(one_frame)(X_c, w, data.frame_index)
    r = _robustify(r.reshape(-1) / data.sigma_stripe_mm, data.robust)
    # A cylinder fixes the table axis as a line, not the origin along it nor the turn of
    # the measurement frame about it. Fix both gauges: the camera origin lies on the
    # x_m axis (t_m_c = (d, 0, 0)), i.e. the measurement origin is the foot of the
    # perpendicular from the camera to the table axis.
    gauge_fix = stage.t_m_c[1:] / STAGE_GAUGE_MM
    return jnp.concatenate([r, gauge_fix])


# Scale of the stage gauge-fixing residuals (mm): far below any measurement noise.
STAGE_GAUGE_MM = 1e-7


def camera_residuals(params, data):
    return corner_residuals(params, data)


def laser_residuals(params: SystemParams, data: CalibrationData):
    """`(stripe_residuals, gauge_residuals)` through one back-projection of the stripe and
    gauge pixels ([`laser_points`][], as in [`joint_residuals`][]); the gauge's is None
    without a stage. The residual summaries (rejection pass, plane and gauge RMS) are
    this one compiled program."""
    if params.stage is None:
        return stripe_residuals(params, data), None
    X_s, X_g = laser_points(params.camera, params.plane, data.stripe, data.gauge)
    stripe = stripe_point_residuals(params.board_poses, X_s, data.stripe_w, data)
    gauge = gauge_point_residuals(
        params.stage, params.eccentricity, params.plane.n, X_g, data.gauge_w, data
    )
    return stripe, gauge


def camera_plane_residuals(params, data):
    return jnp.concatenate([corner_residuals(params, data), stripe_residuals(params, data)])


def joint_residuals(params, data):
    """Corner, board-stripe and gauge residuals, in that order, then the table target's
    when the observations hold one (`_stage_table`). The stripe, gauge and table-target
    line pixels are back-projected together ([`laser_points`][]): the largest compiled
    program of a calibration holds the camera's back-projection once."""
    table = params.table_pose is not None  # a target on the table
    pixels = (data.stripe, data.gauge) + ((data.table.stripe,) if table else ())
    X_s, X_g, *X_t = laser_points(params.camera, params.plane, *pixels)
    blocks = [
        corner_residuals(params, data),
        stripe_point_residuals(params.board_poses, X_s, data.stripe_w, data),
        gauge_point_residuals(
            params.stage, params.eccentricity, params.plane.n, X_g, data.gauge_w, data
        ),
    ]
    if table:
        blocks.append(table_target_residuals(params, data, X_t[0]))
    return jnp.concatenate(blocks)
