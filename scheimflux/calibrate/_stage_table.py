"""The table-target block of the joint calibration: a target fixed to the rotary table.

A board lying or standing on the table is imaged at table steps i (angle i · Δω). Its
corners are camera observations like any board's, but the views do not get a pose each:
every view's pose is

    T_c_b(i) = T_c_m · R_z(−i Δω) · T_t_b,

the stage (`T_m_c`, Δω) and ONE table pose `T_t_b` of the board (`SystemParams.
table_pose`, table coordinates at step 0), all in the one parameter pytree. So the
residuals (reprojection errors of the table target's corners / σ_corner) tie the stage
directly to the images, and, since the target reaches depths off the laser plane that the
calibration boards do not, they also constrain the camera there (a camera calibrated
from boards near the laser plane alone misplaced such points by several pixels; the
table-target views then gave an axis 5–20 µm off: docs/stage.md).

The start comes from the closed form: per-view poses with the board-calibrated camera
held, [`axis_from_poses`][], [`stage_from_axis`][] (the gauge `t_m_c = (t_x, 0, 0)` that
`gauge_residuals` also fixes) and the mean of the per-view table poses.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..geometry._stage import RotaryStage
from ..geometry._transforms import Pose
from ..io._observations import Observations, StageTargetViews, View
from ._solve import ONE_SHOT
from ._stage_target import axis_from_poses, stage_from_axis

__all__ = [
    "TableTargetData",
    "TableTargetInit",
    "initial_table_target",
    "table_target_data",
    "table_target_errors_px",
    "table_target_residuals",
]


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


def table_target_data(target: StageTargetViews, centre) -> TableTargetData:
    """[`TableTargetData`][] of an observations file's `stage_target`."""
    from ._model import _pad

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
    )


def table_points_c(stage: RotaryStage, table_pose: Pose, board, step):
    """The board points `(M, 3)` in the camera frame at table step `step`:
    `X_c = R_m_cᵀ (R_iᵀ (R_t_b X_b + t_t_b) − t_m_c)`."""
    X_t = table_pose.apply(board)
    X_m = X_t @ stage.frame_rotation(step)  # rows: (R_iᵀ X)ᵀ = Xᵀ R_i
    return (X_m - stage.t_m_c) @ stage.R_m_c


def table_target_errors_px(params, data) -> Float[Array, "F M 2"]:
    """Reprojection errors (px) of the table target's corners; 0 where not detected."""
    t = data.table

    def one(step, uv_obs, w):
        X = table_points_c(params.stage, params.table_pose, t.board, step)
        uv, _ = jax.vmap(params.camera.project_one)(X)
        return (uv - uv_obs) * w[:, None]

    return jax.vmap(one)(t.steps, t.corners, t.w)


def table_target_residuals(params, data, X=None) -> Float[Array, " n"]:
    """Reprojection errors of the table target's corners / σ_corner (u and v of each),
    then [`table_stripe_residuals`][]; `X` `(F, K, 3)`: the laser-plane points of the
    line's pixels when the caller back-projected them already (`joint_residuals` does,
    with the other blocks' pixels, in one `laser_points` call)."""
    from ._model import _robustify

    r = table_target_errors_px(params, data).reshape(-1) / data.sigma_corner_px
    return jnp.concatenate([_robustify(r, data.robust), table_stripe_residuals(params, data, X)])


def table_stripe_residuals(params, data, X=None) -> Float[Array, " n"]:
    """Distance (mm / σ_stripe) of each laser-line point on the table target (the
    pixel's ray meeting the laser plane; `X` `(F, K, 3)` if already computed) from the
    target's plane at its table step: the line ties the laser plane to the table target,
    hence to the axis."""
    from ._model import _robustify, laser_points

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
_errors_jit = eqx.filter_jit(table_target_errors_px, compiler_options=ONE_SHOT)


def table_target_rms_px(params, data) -> float:
    """RMS reprojection error (px per coordinate) of the table target's corners."""
    r = np.asarray(_errors_jit(params, data))
    n = float(np.sum(np.asarray(data.table.w)))
    return float(np.sqrt(np.sum(r**2) / max(2.0 * n, 1.0)))


# ----------------------------------------------------------------------------- start


@dataclasses.dataclass(frozen=True)
class TableTargetInit:
    """The closed-form start of the table-target block.

    **Fields:** `stage` (gauge-fixed, Δω the stated step); `table_pose` `T_t_b`;
    `view_poses` the per-view camera-from-board poses (camera held); `step_deg` the
    table step measured from them; `pose_rms_px` their reprojection RMS.
    """

    stage: RotaryStage
    table_pose: Pose
    view_poses: Pose
    step_deg: float
    pose_rms_px: float


def _target_observations(obs: Observations) -> Observations:
    """The table target's views as plain board views (for per-view poses)."""
    t = obs.stage_target
    views = [View(c, np.zeros((0, 2))) for c in np.asarray(t.corners_px)]
    return dataclasses.replace(
        obs, board_points_mm=np.asarray(t.board_points_mm), views=views, stage=None,
        stage_target=None, dropped=[],
    )  # fmt: skip


def initial_table_target(camera, obs: Observations, *, min_corners: int = 6) -> TableTargetInit:
    """Stage and table pose from the table target's views with `camera` held.

    Each view's pose is solved (homography start, then Levenberg–Marquardt on its
    corners with the camera fixed); [`axis_from_poses`][] gives the axis and checks the
    stated step and the order; the table pose is the mean over the views of
    `R_z(i Δω) · T_m_c · T_c_b(i)`.

    **Raises:** `ValueError` (one line) for views with fewer than `min_corners` corners,
    fewer than two table steps, or poses that do not turn by the stated step.
    """
    from ._init import poses_for_central_camera
    from ._model import SystemParams, camera_residuals, make_data
    from ._solve import least_squares

    t = obs.stage_target
    dw = math.radians(float(t.delta_omega_deg))
    if not (math.isfinite(dw) and dw != 0.0):
        raise ValueError(f"the table step must be a non-zero angle, got {t.delta_omega_deg}°")
    counts = np.all(np.isfinite(np.asarray(t.corners_px)), axis=-1).sum(axis=1)
    few = [int(s) for s, c in zip(t.table_steps, counts) if c < min_corners]
    if few:
        raise ValueError(
            f"stage-target table steps {few} have fewer than {min_corners} detected corners; "
            "drop those views"
        )
    if len(t.table_steps) < 2:
        raise ValueError("the table axis needs the table target at two or more table steps")
    tobs = _target_observations(obs)
    poses0 = poses_for_central_camera(camera, tobs)
    data = make_data(tobs)
    fit = least_squares(
        camera_residuals,
        SystemParams(camera, poses0),
        data,
        freeze=("camera",),
        max_steps=100,
        throw=False,
    )
    poses = fit.params.board_poses
    R = np.asarray(jax.vmap(lambda p: p.R)(poses))
    steps = np.asarray(t.table_steps, dtype=np.float64)
    d, C, step = axis_from_poses(R, np.asarray(poses.translation), steps, dw)
    stage = stage_from_axis(d, C, dw)
    rms = float(np.sqrt(2.0 * fit.cost / max(fit.n_observations, 1))) * float(
        data.sigma_corner_px
    )  # the residuals are in units of σ_corner
    return TableTargetInit(
        stage, mean_table_pose(stage, poses, steps), poses, math.degrees(step), rms
    )


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def mean_table_pose(stage: RotaryStage, view_poses: Pose, steps) -> Pose:
    """The table pose `T_t_b` of views `T_c_b(i)` for a given stage: the mean of
    `R_z(i Δω) · T_m_c · T_c_b(i)` over the views (rotation: the mean matrix projected
    onto SO(3))."""
    R = np.asarray(jax.vmap(lambda p: p.R)(view_poses))
    tr = np.asarray(view_poses.translation)
    R_m_c, t_m_c = np.asarray(stage.R_m_c), np.asarray(stage.t_m_c)
    dw = float(stage.delta_omega)
    Rs, ts = [], []
    for Rk, tk, i in zip(R, tr, np.asarray(steps, dtype=np.float64)):
        Ri = _rot_z(i * dw)
        Rs.append(Ri @ R_m_c @ Rk)
        ts.append(Ri @ (R_m_c @ tk + t_m_c))
    U, _, Vt = np.linalg.svd(np.mean(Rs, axis=0))
    R_mean = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return Pose.from_matrix(R_mean, np.mean(ts, axis=0))


def stage_extra_freeze(obs: Observations) -> tuple[str, ...]:
    """What the joint solve with a stage holds besides the user's set: Δω always, the
    gauge eccentricity when there is no gauge scan (a table target alone)."""
    return ("stage.delta_omega",) + (("eccentricity",) if obs.stage is None else ())


def table_target_start(camera, obs: Observations, stage=None, ecc=None):
    """`(stage, eccentricity, table_pose)` to start the joint solve with a table target.

    Without a gauge-scan `stage`: the table target's closed form
    ([`initial_table_target`][]) and a zero eccentricity (held by the joint solve).
    With one: that stage and eccentricity, and the table pose of the target's views for
    it (both in the same gauge, `t_m_c = (t_x, 0, 0)`).
    """
    init = initial_table_target(camera, obs)
    if stage is None:
        return init.stage, jnp.zeros(2), init.table_pose
    steps = np.asarray(obs.stage_target.table_steps, dtype=np.float64)
    return stage, ecc, mean_table_pose(stage, init.view_poses, steps)
