"""The table-target residual block: a target fixed to the rotary table, seen at table
steps i with the pose `T_c_b(i) = T_c_m · R_z(−i Δω) · T_t_b` (the stage and ONE table
pose in the parameter pytree; `_stage_table` has its start and its covariance)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..._export import exported_jit
from ...geometry._stage import RotaryStage
from ...geometry._transforms import Pose
from ...io._observations import StageTargetViews
from ._blocks import (
    _pad,
    _robustify,
    circle_outlines,
    circle_ring,
    laser_points,
    outline_centroids,
)
from ._solve import ONE_SHOT


class TableTargetData(eqx.Module):
    """The table target's observations as arrays (weight 0 where a corner is missing).

    **Fields:** `board` `(M, 3)` its points; `corners` `(F, M, 2)` pixels (a finite
    placeholder where missing); `w` `(F, M)` weights; `steps` `(F,)` table steps;
    `stripe` `(F, K, 2)`, `stripe_w` `(F, K)`: the laser line on the target (padded,
    weight 0 where there is none).
    """

    board: Float[Array, "M 3"]
    corners: Float[Array, "F M 2"]
    w: Float[Array, "F M"]
    steps: Float[Array, " F"]
    stripe: Float[Array, "F K 2"]
    stripe_w: Float[Array, "F K"]
    circle_ring: Float[Array, "R 3"] | None = None  # a circle grid (`CalibrationData`'s)


def table_target_data(target: StageTargetViews, centre) -> TableTargetData:
    """[`TableTargetData`][] of an observations file's `stage_target`."""
    uv = np.asarray(target.corners_px, dtype=np.float64)
    ok = np.all(np.isfinite(uv), axis=-1)
    uv = np.where(ok[..., None], uv, np.asarray(centre, dtype=np.float64))
    sets = list(target.stripe_px) or [np.zeros((0, 2))] * len(uv)
    stripe, stripe_w = _pad(sets, np.asarray(centre, dtype=np.float64))

    def put(a):  # no device program per shape (as `make_data`)
        return jax.device_put(np.asarray(a, dtype=np.float64))

    return TableTargetData(
        board=put(target.board_points_mm),
        corners=put(uv),
        w=put(ok),
        steps=put(target.table_steps),
        stripe=put(stripe),
        stripe_w=put(stripe_w),
        circle_ring=None
        if target.circle_diameter_mm is None
        else put(circle_ring(target.circle_diameter_mm)),
    )


def table_points_c(stage: RotaryStage, table_pose: Pose, board, step):
    """The board points `(M, 3)` in the camera frame at table step `step`:
    `X_c = R_m_cᵀ (R_iᵀ (R_t_b X_b + t_t_b) − t_m_c)`."""
    X_t = table_pose.apply(board)
    X_m = X_t @ stage.frame_rotation(step)  # rows: (R_iᵀ X)ᵀ = Xᵀ R_i
    return (X_m - stage.t_m_c) @ stage.R_m_c


def table_target_errors_px(params, data) -> Float[Array, "F M 2"]:
    """Reprojection errors (px) of the table target's corners; 0 where not detected."""
    t, ring = data.table, data.table.circle_ring
    board = t.board if ring is None else circle_outlines(t.board, ring)

    def one(step, uv_obs, w):
        X = table_points_c(params.stage, params.table_pose, board, step)
        uv, _ = jax.vmap(params.camera.project_one)(X)
        if ring is not None:  # a circle grid: the centroids of the circles' images
            uv = outline_centroids(uv, ring.shape[0])
        return (uv - uv_obs) * w[:, None]

    return jax.vmap(one)(t.steps, t.corners, t.w)


def table_target_residuals(params, data, X=None) -> Float[Array, " n"]:
    """Reprojection errors of the table target's corners / σ_corner (u and v of each),
    then [`table_stripe_residuals`][]; `X` `(F, K, 3)`: the laser-plane points of the
    line's pixels when the caller back-projected them already (`joint_residuals` does,
    with the other blocks' pixels, in one `laser_points` call)."""
    r = table_target_errors_px(params, data).reshape(-1) / data.sigma_corner_px
    return jnp.concatenate([_robustify(r, data.robust), table_stripe_residuals(params, data, X)])


def table_stripe_residuals(params, data, X=None) -> Float[Array, " n"]:
    """Distance (mm / σ_stripe) of each laser-line point on the table target (the
    pixel's ray meeting the laser plane; `X` `(F, K, 3)` if already computed) from the
    target's plane at its table step: the line ties the laser plane to the table target,
    hence to the axis."""
    t = data.table
    st, T = params.stage, params.table_pose
    if X is None:
        (X,) = laser_points(params.camera, params.plane, t.stripe)

    def one(step, X, w):
        Ri = st.frame_rotation(step)
        n_c = st.R_m_c.T @ (Ri.T @ T.R[:, 2])  # the target's normal in the camera frame
        o_c = st.R_m_c.T @ (Ri.T @ T.translation - st.t_m_c)  # its origin
        return (X @ n_c - jnp.dot(n_c, o_c)) * w

    r = jax.vmap(one)(t.steps, X, t.stripe_w).reshape(-1) / data.sigma_stripe_mm
    return _robustify(r, data.robust)


# run once per calibration (summaries): compiled as the other one-shot programs
_errors_jit = exported_jit(table_target_errors_px, compiler_options=ONE_SHOT)


def table_target_rms_px(params, data) -> float:
    """RMS reprojection error (px per coordinate) of the table target's corners."""
    r = np.asarray(_errors_jit(params, data))
    n = float(np.sum(np.asarray(data.table.w)))
    return float(np.sqrt(np.sum(r**2) / max(2.0 * n, 1.0)))
