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
import os
import time
from numbers import Integral, Real

import numpy as np

from ..geometry._stage import RotaryStage
from ..geometry._transforms import Pose
from ..targets._target import Target
from ._rig import Rig
from ._scenes import (
    BoardView,
    StripeProfile,
    _board_stripe_points,
    _field,
    _inside,
    _near_field,
    _noisy,
    _pose_np,
    _rng,
    _rodrigues,
    _rot_z,
    _trace_stripes,
    trace_points,
)

__all__ = [
    "StageTargetScan",
    "lying_target_pose",
    "stage_target_lines",
    "stage_target_scan",
    "write_stage_target_images",
]


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


def lying_target_pose(
    rig: Rig, stage: RotaryStage, board: Target, *, offset_mm=(0.0, 0.0), face_camera=True
):
    """The table pose of a board lying flat on the table, centred on the axis.

    The board's plane is perpendicular to the table axis at the height of the focus
    point F0 (so the camera sees it where it sees the laser line), its centre on the axis
    plus `offset_mm` (table x, y). A board this way covers the field at every table angle
    when it reaches beyond the field's distance from the axis — check `visible`.

    `face_camera`: the printed side towards the camera (the board's +z, into the board,
    points away from it), as a board lying on a table is seen; False puts the board's +z
    along the table's +z whichever way the camera looks (a pattern seen from the back is
    mirrored: a ChArUco board is then not found, a checkerboard is, its corners numbered
    the other way round, as through a glass target).

    **Returns:** the [`Pose`][] `T_t_b` (board → table).
    """
    R_m_c, t_m_c = _axis_frame(stage)
    F0_m = R_m_c @ _field(rig).F0 + t_m_c
    centre = np.array([float(offset_mm[0]), float(offset_mm[1]), F0_m[2]])
    # the board's +z in the camera frame is ±R_m_c[2] (table rotations keep z_m): its
    # camera z component R_m_c[2, 2] must be positive for the front to face the camera
    flip = face_camera and R_m_c[2, 2] < 0.0
    R = np.diag([1.0, -1.0, -1.0]) if flip else np.eye(3)
    return Pose.from_matrix(R, centre - R @ np.asarray(board.centre_mm, dtype=np.float64))


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


def stage_target_lines(
    rig: Rig, scan: StageTargetScan, *, step_px: Real = 2.0, noise_px: Real = 0.0,
    seed: Integral = 0, margin_px: Real = 5.0,
) -> list[StripeProfile]:  # fmt: skip
    """The laser line on the table target at each step: laser plane ∩ target plane,
    within the target's squares, ray-traced (as [`stripe_on_board`][] for a board view).

    **Returns:** one [`StripeProfile`][] per view of `scan` (exact 3-D points, noise-free
    pixels `px_true` and pixels `px` with Gaussian noise `noise_px`).
    """
    field = _field(rig)
    sets = [_board_stripe_points(rig, field, v.T_c_b, scan.board, float(step_px))
            for v in scan.views]  # fmt: skip
    return _trace_stripes(rig, sets, float(noise_px), int(seed), float(margin_px))


def write_stage_target_images(
    out_dir: str | os.PathLike,
    rig: Rig,
    scan: StageTargetScan,
    *,
    laser_off: bool = True,
    ext: str = "png",
    ambient_level: float = 0.55,
    laser_peak: float = 0.6,
    stripe_width_px: float = 5.0,
    noise_sigma: float = 0.004,
    blur_sigma_px: float = 0.8,
    seed: Integral = 0,
    verbose: bool = False,
) -> list[str]:
    """Render the table-target folder of `detect --stage-target` (docs/stage.md):
    `step_<k>.<ext>`, the target at table step k with the laser line on it (one grey
    image, `albedo × (ambient + laser)` as `write_scene_images`' single layout), and with
    `laser_off` beside it `step_<k>_off.<ext>`, the same step with the laser off.

    The target (checkerboard, ChArUco board or circle grid) is rendered through the ray
    tracer in each view's true pose (wobble and runout included); the line's exact
    centres are [`stage_target_lines`][] (noise-free). Every image gets its own noise
    stream from `seed`. Existing files are replaced.

    **Returns:** the paths written, in step order (each step before its laser-off image).
    """
    from ._images import _EXTS, _board_to_pixel, _quantise, _stripe_image, _write
    from ._render_target import render_target

    ext = str(ext).lower().lstrip(".")
    if ext not in _EXTS:
        raise ValueError(f"ext must be one of {', '.join(_EXTS)}, got {ext!r}")
    out = os.fspath(out_dir)
    os.makedirs(out, exist_ok=True)
    w, h = (int(s) for s in rig.sensor_size)
    lines = stage_target_lines(rig, scan)
    written = []
    for k, (view, line) in enumerate(zip(scan.views, lines)):
        t0 = time.perf_counter()
        s = int(seed) * 100003 + 2 * k
        albedo = render_target(
            scan.board, _board_to_pixel(rig, view.T_c_b), shape=(h, w),
            blur_sigma_px=float(blur_sigma_px), bit_depth=16,
        ) / 65535.0  # fmt: skip
        laser = _stripe_image(
            (h, w), line.px_true, width_px=float(stripe_width_px), peak=1.0, ambient=0.0,
            noise_sigma=0.0, saturate=False, bit_depth=8, seed=s,
        ) / 255.0  # fmt: skip
        lit = albedo * float(ambient_level)
        jobs = [(f"step_{k}.{ext}", lit + albedo * float(laser_peak) * laser, s)]
        if laser_off:
            jobs.append((f"step_{k}_off.{ext}", lit, s + 1))
        for name, img, si in jobs:
            rng = np.random.default_rng(si)
            path = os.path.join(out, name)
            _write(path, _quantise(img + rng.normal(0, noise_sigma, img.shape), 8), ext, 95)
            written.append(path)
        if verbose:
            print(f"  step {k}: {time.perf_counter() - t0:.2f} s")
    return written
