"""A calibration target fixed to the rotary table, imaged at several table angles.

The usual way to find a turntable's axis: put a board on the table, turn the table in
known steps and photograph the board at each step. Every photograph gives a board pose;
the poses share one rotation, about the table axis, and that determines the axis's
direction and position directly (a ring gauge only does so through its eccentricity).

Frame convention (as [`gauge_scan`][]): a point fixed to the table with table
coordinates `X_t` is, in frame i (the table turned by i · Δω), at
`X_c = R_m_cᵀ (R_iᵀ X_t − t_m_c)`, the inverse of paper eq. 13. So the board pose in
frame i is `T_c_b(i) = T_c_m · R_z(−i Δω) · T_t_b` with `T_t_b` the board's pose on the
table. A real table also wobbles and runs out: frame i may carry a small extra rotation
`W_i` about an axis perpendicular to z_m (`wobble_mrad`) and a translation `ε_i` in the
table plane (`runout_um`), applied as `X_t → W_i X_t + ε_i` before `R_iᵀ` — the part a
rigid-axis model cannot follow.
"""

from __future__ import annotations

import dataclasses
import math
from numbers import Integral, Real

import numpy as np

from ..geometry._stage import RotaryStage
from ..geometry._transforms import Pose
from ..targets._target import Target
from ._rig import Rig
from ._scenes import (
    BoardView,
    _field,
    _inside,
    _near_field,
    _noisy,
    _pose_np,
    _rng,
    _rodrigues,
    _rot_z,
    trace_points,
)

__all__ = ["StageTargetScan", "lying_target_pose", "stage_target_scan"]


@dataclasses.dataclass(frozen=True)
class StageTargetScan:
    """Ray-traced views of a board fixed to the rotary table.

    **Fields:**
    - `stage`: the true [`RotaryStage`][] (its `delta_omega` is the step between frames).
    - `board`: the target.
    - `T_t_b`: the board's pose on the table (table coordinates at frame 0).
    - `frame_index`: `(F,)` table step i of each view (angle i · Δω).
    - `views`: one [`BoardView`][] per frame (true camera-from-board pose and corners).
    - `wobble`: `(F, 3, 3)` the extra rotation `W_i` of each frame (identity if none).
    - `runout_mm`: `(F, 3)` the extra translation `ε_i` of each frame.
    """

    stage: RotaryStage
    board: Target
    T_t_b: Pose
    frame_index: np.ndarray
    views: list[BoardView]
    wobble: np.ndarray
    runout_mm: np.ndarray

    def corners(self) -> tuple[np.ndarray, np.ndarray]:
        """Noisy corner pixels `(F, M, 2)` (NaN where not visible) and the mask `(F, M)`."""
        px = np.stack([v.px for v in self.views])
        return px, np.isfinite(px).all(axis=-1)


def _axis_frame(stage: RotaryStage) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(stage.R_m_c, dtype=np.float64), np.asarray(stage.t_m_c, dtype=np.float64)


def lying_target_pose(rig: Rig, stage: RotaryStage, board: Target, *, offset_mm=(0.0, 0.0)):
    """The table pose of a board lying flat on the table, centred on the axis.

    The board's plane is perpendicular to the table axis at the height of the focus
    point F0 (so the camera sees it where it sees the laser line), its centre on the axis
    plus `offset_mm` (table x, y). A board this way covers the field at every table angle
    when it reaches beyond the field's distance from the axis — check `visible`.

    **Returns:** the [`Pose`][] `T_t_b` (board → table).
    """
    R_m_c, t_m_c = _axis_frame(stage)
    F0_m = R_m_c @ _field(rig).F0 + t_m_c
    centre = np.array([float(offset_mm[0]), float(offset_mm[1]), F0_m[2]])
    return Pose.from_matrix(np.eye(3), centre - np.asarray(board.centre_mm, dtype=np.float64))


def _small_rotations(rng: np.random.Generator, n: int, sigma: float) -> np.ndarray:
    """`n` rotations by N(0, σ²) angles about random axes perpendicular to z."""
    if sigma == 0.0:
        return np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    xy = rng.normal(0.0, sigma, (n, 2))
    return np.stack([_rodrigues(np.array([a, b, 0.0])) for a, b in xy])


def stage_target_scan(
    rig: Rig,
    stage: RotaryStage,
    board: Target,
    n_frames: Integral = 12,
    *,
    T_t_b: Pose | None = None,
    first_index: Integral = 0,
    wobble_mrad: Real = 0.0,
    runout_um: Real = 0.0,
    noise_px: Real = 0.0,
    seed: Integral = 0,
    margin_px: Real = 10.0,
    min_points: Integral = 6,
) -> StageTargetScan:
    """Image a board fixed to the rotary table at `n_frames` table angles.

    Frame k is table step `i = first_index + k` (angle i · `stage.delta_omega`). Corners are
    ray-traced (chief rays through the lens prescription) and kept where they land
    `margin_px` inside the sensor; `px` adds Gaussian noise `noise_px` per coordinate.

    **Arguments:**
    - `rig`, `stage`, `board`: the rig, the true stage and the target.
    - `n_frames`: number of table angles.
    - `T_t_b`: the board's pose on the table; default [`lying_target_pose`][].
    - `wobble_mrad`, `runout_um`: σ of the per-frame wobble rotation and in-plane runout.
    - `min_points`: frames with fewer visible corners raise (choose a larger board).

    **Returns:** a [`StageTargetScan`][].
    """
    if n_frames < 1:
        raise ValueError(f"need at least one table angle, got {n_frames}")
    for name, v in (("wobble_mrad", wobble_mrad), ("runout_um", runout_um)):
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"{name} must be a finite number >= 0, got {v}")
    if T_t_b is None:
        T_t_b = lying_target_pose(rig, stage, board)
    field = _field(rig)
    R_m_c, t_m_c = _axis_frame(stage)
    dw = float(stage.delta_omega)
    rng = _rng(seed, 11)
    idx = np.arange(int(first_index), int(first_index) + int(n_frames))
    W = _small_rotations(rng, len(idx), float(wobble_mrad) * 1e-3)
    eps = np.zeros((len(idx), 3))
    if runout_um:
        eps[:, :2] = rng.normal(0.0, float(runout_um) * 1e-3, (len(idx), 2))
    R_t_b, t_t_b = _pose_np(T_t_b)
    X_t = board.points_mm @ R_t_b.T + t_t_b  # (M, 3) table coordinates
    X = np.stack(
        [
            ((X_t @ W[k].T + eps[k]) @ _rot_z(i * dw) - t_m_c) @ R_m_c  # R_m_cᵀ(R_iᵀ X − t)
            for k, i in enumerate(idx)
        ]
    )  # (F, M, 3) camera frame
    near = _near_field(rig, field, X.reshape(-1, 3)).reshape(X.shape[:2])
    uv = np.full(X.shape[:2] + (2,), np.nan)
    ok = np.zeros(X.shape[:2], dtype=bool)
    if near.any():
        uv_n, ok_n = trace_points(rig, X[near])
        uv[near], ok[near] = uv_n, ok_n
    vis = ok & _inside(rig, uv, margin_px)
    uv = np.where(vis[..., None], uv, np.nan)
    noisy = _noisy(uv, noise_px, _rng(seed, 12))
    counts = vis.sum(axis=1)
    if (counts < min_points).any():
        bad = [int(i) for i, c in zip(idx, counts) if c < min_points]
        raise ValueError(
            f"table steps {bad} see fewer than {min_points} corners; use a larger board or "
            "place it where the camera sees it at every angle"
        )
    views = []
    for k, i in enumerate(idx):
        # Board pose in frame k (wobble and runout included): X_c = R_c_b X_b + t_c_b.
        R_k = R_m_c.T @ _rot_z(i * dw).T @ W[k] @ R_t_b
        t_k = R_m_c.T @ (_rot_z(i * dw).T @ (W[k] @ t_t_b + eps[k]) - t_m_c)
        views.append(BoardView(Pose.from_matrix(R_k, t_k), X[k], vis[k], uv[k], noisy[k]))
    return StageTargetScan(stage, board, T_t_b, idx, views, W, eps)
