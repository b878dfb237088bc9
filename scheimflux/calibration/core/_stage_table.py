"""A target fixed to the rotary table: its start and its block's covariance (the residual
block itself: `_table_block`).

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

from ...geometry._stage import RotaryStage
from ...geometry._transforms import Pose
from ...io._observations import Observations, View
from ._stage_target import axis_from_poses, stage_from_axis
from ._table_block import table_target_residuals

__all__ = [
    "TableTargetInit",
    "initial_table_target",
    "mean_table_pose",
    "stage_extra_freeze",
    "table_block_covariance",
    "table_target_start",
]


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
        stage_target=None, dropped=[], circle_diameter_mm=t.circle_diameter_mm,
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


# ----------------------------------------------------------------------------- uncertainty


def _table_block(params, data):
    """The table block's residuals alone (a module-level function: one compiled Jacobian)."""
    return table_target_residuals(params, data)


def _table_block_moved(q, params, data):
    """The table block's residuals (as `table_target_residuals`, no Huber) when the
    target at step i is moved by a small rotation `(q_i0, q_i1, 0)` and a translation
    `(q_i2, q_i3, 0)` in table coordinates, `X_t → X_t + ω × X_t + ε` (the wobble and
    runout of the simulator, `simulate._stage_target`); `q` `(F, 4)`."""
    from ._blocks import circle_outlines, laser_points, outline_centroids

    t, st, T = data.table, params.stage, params.table_pose
    z = jnp.zeros(q.shape[:1])
    om = jnp.stack([q[:, 0], q[:, 1], z], axis=1)
    eps = jnp.stack([q[:, 2], q[:, 3], z], axis=1)
    ring = t.circle_ring
    board = t.board if ring is None else circle_outlines(t.board, ring)

    def corners(step, uv_obs, w, om, eps):
        X_t = T.apply(board)
        X_t = X_t + jnp.cross(om, X_t) + eps
        X = (X_t @ st.frame_rotation(step) - st.t_m_c) @ st.R_m_c
        uv, _ = jax.vmap(params.camera.project_one)(X)
        if ring is not None:  # a circle grid: the centroids of the circles' images
            uv = outline_centroids(uv, ring.shape[0])
        return (uv - uv_obs) * w[:, None]

    (X,) = laser_points(params.camera, params.plane, t.stripe)

    def line(step, X, w, om, eps):
        Ri = st.frame_rotation(step)
        n_t = T.R[:, 2] + jnp.cross(om, T.R[:, 2])
        o_t = T.translation + jnp.cross(om, T.translation) + eps
        n_c = st.R_m_c.T @ (Ri.T @ n_t)
        o_c = st.R_m_c.T @ (Ri.T @ o_t - st.t_m_c)
        return (X @ n_c - jnp.dot(n_c, o_c)) * w

    rc = jax.vmap(corners)(t.steps, t.corners, t.w, om, eps).reshape(-1) / data.sigma_corner_px
    rs = jax.vmap(line)(t.steps, X, t.stripe_w, om, eps).reshape(-1) / data.sigma_stripe_mm
    return jnp.concatenate([rc, rs])


@eqx.filter_jit
def _motion_jacobian(params, data):
    """`∂r_t / ∂q` `(n_t, F, 4)` of [`_table_block_moved`][] at q = 0."""
    q0 = jnp.zeros((data.table.steps.shape[0], 4))
    return jax.jacfwd(_table_block_moved)(q0, params, data)


def table_block_covariance(fit, data) -> np.ndarray | None:
    """Covariance of a joint solve's free parameters when the table wobbles and runs out.

    The pooled factor `s² = |r|² / (n − p)` (`_stage_warning._fit_covariance`) charges
    every block with the worst one's misfit. A table that wobbles or runs out fits its
    target worse than the boards fit theirs (0.14 against 0.03 px for 0.02 mrad and
    0.5 µm per step), and the pooled factor scaled the boards' share of the axis and
    length σ up with it (3.5 µm across half a turn predicted against ≈ 1.3 µm of
    spread). That misfit is not white noise: at each step the whole target moves
    rigidly. So it is modelled as what it is, a random motion per step, `X_t → X_t +
    ω_i × X_t + ε_i` (ω_i ⊥ z: wobble; ε_i in the table plane: runout), of variances
    estimated from the residuals:

    - `A = ∂r_t/∂q` (F × 4 motion components); `q̂ = argmin |r_t − A q|` per step; the
      motions' 4 × 4 covariance `C` from the F estimates q̂ ([`_motion_covariance`][]:
      the solve absorbed their mean into the axis, and the pixel noise's part is taken
      off);
    - the white factors `s_t² = |r_t − A q̂|² / (n_t − 4F)` of the table block and
      `s_o² = |r_o|² / (n_o − p)` of the rest (boards, their stripes, a gauge), each ≥ 1;
    - `Σ = H⁻¹ (s_o² H_o + s_t² H_t + K C Kᵀ) H⁻¹`, `H = H_o + H_t = JᵀJ`, `K = J_tᵀ A`,
      `C` per step: the estimate's first-order response to the motions, whose mean over
      the steps moves the fitted axis.

    The motions count only where they explain the table block's misfit beyond its pixel
    noise (an F test at 0.1 %); without wobble or runout Σ is the pooled covariance (all
    factors ≈ 1, C = 0).
    **Returns:** `(p, p)` in the order of `split(params, spec)`, or None without a kept
    normal matrix or a table block.
    """
    from ._solve import jacobian

    H = getattr(fit, "normal_matrix", None)
    if H is None or getattr(data, "table", None) is None or fit.params.table_pose is None:
        return None
    H = np.asarray(H, dtype=np.float64)
    J_t = np.asarray(jacobian(_table_block, fit.params, data, fit.free_mask), dtype=np.float64)
    A3 = np.asarray(_motion_jacobian(fit.params, data), dtype=np.float64)
    n_rows, F = A3.shape[0], A3.shape[1]
    A = A3.reshape(n_rows, 4 * F)
    r = np.asarray(fit.residuals, dtype=np.float64)
    k = len(r) - J_t.shape[0]  # the table block is the joint residuals' last
    r_t, r_o = r[k:], r[:k]
    # counted as `Fit.n_observations`: the rows with non-zero residual (weight 0 gives 0)
    n_t, n_o, p = np.count_nonzero(r_t), np.count_nonzero(r_o), H.shape[0]
    G = A.T @ A  # block diagonal: one 4 × 4 block per step
    Ginv = np.linalg.pinv(G)
    q = Ginv @ (A.T @ r_t)
    e = r_t - A @ q
    s2_t = max(1.0, float(e @ e) / (n_t - 4 * F)) if n_t > 4 * F else 1.0
    s2_o = max(1.0, float(r_o @ r_o) / (n_o - p)) if n_o > p else 1.0
    # the motions enter only where they explain the misfit beyond the pixel noise (F test
    # at 0.1 %: without wobble or runout, C = 0 and Σ is the pooled covariance)
    from scipy.stats import f as f_dist

    dof = n_t - 4 * F
    moved = dof > 0 and (float(r_t @ r_t) - float(e @ e)) / (4 * F) > f_dist.ppf(
        0.999, 4 * F, dof
    ) * max(float(e @ e) / dof, 1e-300)
    blocks = np.stack([Ginv[4 * i : 4 * i + 4, 4 * i : 4 * i + 4] for i in range(F)])
    C = _motion_covariance(q.reshape(F, 4), s2_t * blocks) if moved else np.zeros((4, 4))
    K = J_t.T @ A
    H_t = J_t.T @ J_t
    d = np.sqrt(np.clip(np.diag(H), 0.0, None))
    d = np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 1.0)
    Hinv = d[:, None] * np.linalg.pinv(H * np.outer(d, d)) * d[None, :]
    KC = sum(K[:, 4 * i : 4 * i + 4] @ C @ K[:, 4 * i : 4 * i + 4].T for i in range(F))
    meat = s2_o * (H - H_t) + s2_t * H_t + KC
    return Hinv @ meat @ Hinv


def _motion_covariance(q: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """The 4 × 4 covariance of the per-step motions from their estimates `q` `(F, 4)`:
    `Σ q_i q_iᵀ / (F − 1)` (the solve absorbed their mean into the axis) less the mean
    of the estimates' own noise covariances `noise` `(F, 4, 4)`,
    clipped to positive semi-definite. Full, not diagonal: in the fitted table frame a
    wobble about a point elsewhere on the axis shows as a runout too, so the two
    correlate (the origin on the axis is the stage's gauge, not the table's pivot)."""
    F = q.shape[0]
    S = q.T @ q / max(F - 1, 1)
    N = np.mean(np.asarray(noise, dtype=np.float64).reshape(-1, 4, 4), axis=0)
    w, V = np.linalg.eigh(0.5 * ((S - N) + (S - N).T))
    return (V * np.clip(w, 0.0, None)) @ V.T
