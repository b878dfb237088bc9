"""Simulated scenes with exact ground truth, imaged by the real ray trace.

Every scene builds exact 3-D points in the scheimflux camera frame (analytic geometry,
float64, NumPy) and images them with `Rig.project`, the chief ray traced by Snell's law
through the lens prescription onto the tilted sensor. No camera model computes a pixel:
the paraxial thick-lens model is used only to pick *which* points are worth tracing
(those near the field of view); visibility is decided on the traced pixels.

Each scene returns noise-free pixels (`px_true`) and pixels with independent Gaussian
noise of the requested standard deviation on each coordinate (`px`, seeded), plus the
3-D truth. Points whose trace fails or that land within `margin_px` of the sensor edge
are dropped (corners: kept as NaN rows, so that indices follow the board).

Scenes:
- [`board_poses`][]: checkerboard poses around the laser plane and their corners.
- [`stripe_on_board`][]: the laser line on a posed board.

The gauges (ring gauge on a rotary table, stepped gauge blocks) are in `_gauges.py`, built
on the helpers below.

The laser plane is `rig.laser_plane` (n · X = 1, camera frame); its unit normal n̂ points
away from the camera. The *focus point* F0 is the laser-plane point imaged at the
principal pixel (x0, y0) — the centre of the measuring field.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from numbers import Integral, Real

import jax.numpy as jnp
import numpy as np

from ..camera._thick_lens import ThickLensScheimpflug
from ..geometry._transforms import Pose
from ..targets._target import Target
from ._lens import paraxial
from ._rig import Rig

__all__ = [
    "BoardView",
    "StripeProfile",
    "board_poses",
    "stripe_on_board",
]

_CHUNK = 512  # fixed batch for Rig.project: one compilation serves every scene


# ----------------------------------------------------------------------------- helpers


def _rng(seed: Integral, stream: Integral) -> np.random.Generator:
    return np.random.default_rng([int(seed), int(stream)])


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _rodrigues(rotvec: np.ndarray) -> np.ndarray:
    rotvec = np.asarray(rotvec, dtype=np.float64)
    angle = float(np.linalg.norm(rotvec))
    if angle < 1e-15:
        return np.eye(3)
    k = rotvec / angle
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def _rot_z(a: Real) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _pose_np(T: Pose) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(T.R, dtype=np.float64), np.asarray(T.translation, dtype=np.float64)


def trace_points(rig: Rig, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray-trace camera-frame points `(N, 3)`: pixels `(N, 2)` and validity `(N,)`.

    Calls `rig.project` in fixed-size chunks (one compilation for any N). Valid means the
    chief ray passed the lens and landed on the sensor.
    """
    X = np.asarray(X, dtype=np.float64).reshape(-1, 3)
    n = len(X)
    uv = np.full((n, 2), np.nan)
    ok = np.zeros(n, dtype=bool)
    if n == 0:
        return uv, ok
    pad = (-n) % _CHUNK
    Xp = np.concatenate([X, np.repeat(X[-1:], pad, axis=0)]) if pad else X
    for k in range(0, len(Xp), _CHUNK):
        u, v = rig.project(jnp.asarray(Xp[k : k + _CHUNK]))
        m = min(_CHUNK, n - k)
        uv[k : k + m] = np.asarray(u)[:m]
        ok[k : k + m] = np.asarray(v)[:m]
    uv[~ok] = np.nan
    return uv, ok


def _inside(rig: Rig, uv: np.ndarray, margin_px: Real) -> np.ndarray:
    w, h = rig.sensor_size
    with np.errstate(invalid="ignore"):
        return (
            np.isfinite(uv).all(axis=-1)
            & (uv[..., 0] >= margin_px - 0.5)
            & (uv[..., 0] <= w - 0.5 - margin_px)
            & (uv[..., 1] >= margin_px - 0.5)
            & (uv[..., 1] <= h - 0.5 - margin_px)
        )


def _noisy(px: np.ndarray, sigma: Real, rng: np.random.Generator) -> np.ndarray:
    if sigma < 0 or not math.isfinite(sigma):
        raise ValueError(f"pixel noise must be a finite number >= 0, got {sigma}")
    noise = rng.normal(0.0, 1.0, px.shape) * sigma
    return px + noise  # NaN rows stay NaN


@dataclasses.dataclass(frozen=True)
class _Field:
    """Laser-plane geometry of a rig (NumPy, camera frame)."""

    n: np.ndarray  # plane n · X = 1
    normal: np.ndarray  # unit, away from the camera
    F0: np.ndarray  # laser-plane point imaged at the principal pixel
    pupil: np.ndarray  # entrance-pupil centre (camera frame): where chief rays aim
    mm_per_px: float  # laser-plane length of one pixel near F0
    K_inv: np.ndarray  # inverse paraxial K_f: coarse point → pixel, for pre-selection


def _field(rig: Rig) -> _Field:
    n = np.asarray(rig.laser_plane, dtype=np.float64)
    x0, y0 = float(rig.x0), float(rig.y0)
    pts = np.asarray(rig.laser_points(jnp.asarray([[x0, y0], [x0 + 10.0, y0]])))
    par = paraxial(rig.lens)
    pupil = np.array([0.0, 0.0, float(par.z_principal_image - par.z_entrance_pupil)])
    K = np.asarray(ThickLensScheimpflug(**rig.nominal_thick_lens_params()).K_f)
    return _Field(
        n,
        n / np.linalg.norm(n),
        pts[0],
        pupil,
        float(np.linalg.norm(pts[1] - pts[0])) / 10.0,
        np.linalg.inv(K),
    )


def _coarse_pixels(field: _Field, X: np.ndarray) -> np.ndarray:
    """Paraxial-model pixels of points near the laser plane (selection only)."""
    p = X @ field.K_inv.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return p[..., :2] / p[..., 2:3]


def _near_field(rig: Rig, field: _Field, X: np.ndarray, slack_px: Real = 40.0) -> np.ndarray:
    return _inside(rig, _coarse_pixels(field, X), -slack_px)


# ----------------------------------------------------------------------------- boards


@dataclasses.dataclass(frozen=True)
class BoardView:
    """One checkerboard pose and its corners.

    **Fields:**
    - `T_c_b`: camera-from-board pose.
    - `points_c`: every corner in the camera frame, `(M, 3)` mm.
    - `visible`: `(M,)` whether the corner traced onto the sensor (inside the margin).
    - `px_true`: noise-free ray-traced pixels `(M, 2)`, NaN where not visible.
    - `px`: `px_true` plus Gaussian noise, NaN where not visible.
    """

    T_c_b: Pose
    points_c: np.ndarray
    visible: np.ndarray
    px_true: np.ndarray
    px: np.ndarray


def _board_pose_list(
    rig: Rig,
    board: Target,
    n: Integral,
    seed: Integral,
    max_tilt_deg: Real,
    min_tilt_deg: Real,
    max_spin_deg: Real,
    depth_mm: Real,
    stripe_offset_mm: Real,
    spread: Real,
):
    """The poses, and `pose_at(k, centre_px)`: view k's orientation and depth offset with
    its centre moved to the laser-plane point imaged (paraxially) at `centre_px`."""
    field = _field(rig)
    rng = _rng(seed, 1)
    w, h = rig.sensor_size
    # Align board z with the laser normal (board in focus), then rotate a half turn about
    # z so that the lens's inversion shows the board upright (corner 0 top-left).
    ez = np.array([0.0, 0.0, 1.0])
    axis = np.cross(ez, field.normal)
    R_align = _rodrigues(axis / np.linalg.norm(axis) * math.asin(np.linalg.norm(axis)))
    # Stratified centre pixels (a Latin square with jitter) so that the corners of all
    # views cover the sensor.
    lo, hi = 0.5 - spread / 2, 0.5 + spread / 2
    cu = (rng.permutation(n) + rng.uniform(0.0, 1.0, n)) / n
    cv = (rng.permutation(n) + rng.uniform(0.0, 1.0, n)) / n
    centres_px = np.stack([(lo + (hi - lo) * cu) * (w - 1), (lo + (hi - lo) * cv) * (h - 1)], -1)
    rotations, offsets = [], []
    for _ in range(n):
        psi = rng.uniform(0.0, 2 * math.pi)
        tilt = math.radians(rng.uniform(min_tilt_deg, max_tilt_deg))
        spin = math.radians(rng.uniform(-max_spin_deg, max_spin_deg))
        R_tilt = _rodrigues(tilt * np.array([math.cos(psi), math.sin(psi), 0.0]))
        rotations.append(R_align @ R_tilt @ _rot_z(math.pi + spin))
        # Keep the laser line within `stripe_offset_mm` of the board centre: a board
        # centre δ off the laser plane puts the line δ / sin(tilt) from the centre.
        depth = min(depth_mm, stripe_offset_mm * math.sin(tilt))
        offsets.append(rng.uniform(-depth, depth))

    def pose_at(k: int, centre_px: np.ndarray) -> Pose:
        centre = np.asarray(rig.laser_points(jnp.asarray(centre_px[None])))[0]
        centre = centre + field.normal * offsets[k]
        return Pose.from_matrix(rotations[k], centre - rotations[k] @ board.centre_mm)

    centres = np.asarray(rig.laser_points(jnp.asarray(centres_px)))
    poses = [
        Pose.from_matrix(R, c + field.normal * o - R @ board.centre_mm)
        for R, c, o in zip(rotations, centres, offsets)
    ]
    return poses, centres_px, pose_at


def _moved_inside(rig: Rig, uv: np.ndarray, coarse: np.ndarray, margin_px: Real):
    """The pixel shift that brings a board's corners `margin_px` inside the sensor, or
    None when they span more than the sensor. `uv`: traced pixels (NaN where the trace
    failed), `coarse`: paraxial ones (stand-ins for the failed)."""
    w, h = rig.sensor_size
    p = np.where(np.isfinite(uv), uv, coarse)
    lo = np.array([margin_px - 0.5, margin_px - 0.5]) + 1.0  # 1 px to spare
    hi = np.array([w - 0.5 - margin_px, h - 0.5 - margin_px]) - 1.0
    pmin, pmax = p.min(axis=0), p.max(axis=0)
    if np.any(pmax - pmin > hi - lo):
        return None
    return np.where(pmin < lo, lo - pmin, 0.0) + np.where(pmax > hi, hi - pmax, 0.0)


def board_poses(
    rig: Rig,
    board: Target,
    n: Integral = 15,
    *,
    seed: Integral = 0,
    noise_px: Real = 0.0,
    max_tilt_deg: Real = 20.0,
    min_tilt_deg: Real = 8.0,
    max_spin_deg: Real = 4.0,
    depth_mm: Real = 0.3,
    stripe_offset_mm: Real = 0.6,
    spread: Real = 0.4,
    margin_px: Real = 10.0,
    whole: bool = False,
) -> list[BoardView]:
    """`n` checkerboard poses around the laser plane, with ray-traced corners.

    Each board starts parallel to the laser plane (in sharp focus), is tilted by
    `min_tilt_deg … max_tilt_deg` about a random in-plane axis (so the laser crosses it in
    a line), turned by up to ± `max_spin_deg` in its plane, and seen upright (corner 0 at
    the top left of the image). Its centre lies within ± `depth_mm` of the laser plane
    (along its normal) — less where needed to keep the laser line within
    `stripe_offset_mm` of the board centre — at a pixel drawn from a Latin square over the
    central `spread` fraction of the sensor, so the corners of all views together cover
    the sensor.

    `whole=True` slides each board that the sensor's border would cut across the laser
    plane (same orientation and depth) until every corner lands `margin_px` inside, as a
    photographer keeps a checkerboard whole in the frame (a checkerboard detector finds
    only whole boards); a board larger than the sensor at its pose stays cut.

    **Returns:** a list of [`BoardView`][] (corners visible if the trace succeeds and lands
    `margin_px` inside the sensor; `px` carries Gaussian noise `noise_px` per coordinate).
    """
    if n < 1:
        raise ValueError(f"need at least one board view, got {n}")
    poses, centres_px, pose_at = _board_pose_list(
        rig,
        board,
        n,
        seed,
        max_tilt_deg,
        min_tilt_deg,
        max_spin_deg,
        depth_mm,
        stripe_offset_mm,
        spread,
    )
    pts_b = board.points_mm

    def corners(T: Pose) -> np.ndarray:
        return pts_b @ _pose_np(T)[0].T + _pose_np(T)[1]

    X = np.stack([corners(T) for T in poses])  # (n, M, 3)
    uv, ok = trace_points(rig, X.reshape(-1, 3))
    uv = uv.reshape(n, -1, 2)
    vis = ok.reshape(n, -1) & _inside(rig, uv, margin_px)
    if whole:
        # Slide each cut board across the laser plane until every corner is inside: the
        # shift from the traced pixels (paraxial ones where the trace failed), a few
        # times, as the lens's distortion makes one step approximate.
        field = _field(rig)
        for _ in range(6):
            cut = [k for k in range(n) if not vis[k].all()]
            if not cut:
                break
            moved = []
            for k in cut:
                shift = _moved_inside(rig, uv[k], _coarse_pixels(field, X[k]), margin_px)
                if shift is None or not np.any(shift):
                    continue  # larger than the sensor at this pose: left as it is
                centres_px[k] = centres_px[k] + shift
                poses[k] = pose_at(k, centres_px[k])
                X[k] = corners(poses[k])
                moved.append(k)
            if not moved:
                break
            uv_m, ok_m = trace_points(rig, X[moved].reshape(-1, 3))
            uv[moved] = uv_m.reshape(len(moved), -1, 2)
            vis[moved] = ok_m.reshape(len(moved), -1) & _inside(rig, uv[moved], margin_px)
    uv = np.where(vis[..., None], uv, np.nan)
    noisy = _noisy(uv, noise_px, _rng(seed, 2))
    return [BoardView(poses[k], X[k], vis[k], uv[k], noisy[k]) for k in range(n)]


# ----------------------------------------------------------------------------- stripes


@dataclasses.dataclass(frozen=True)
class StripeProfile:
    """Laser-stripe points: exact 3-D truth and ray-traced pixels.

    **Fields:** `points_c` `(K, 3)` camera frame (mm) on the laser plane; `px_true` `(K, 2)`
    noise-free pixels; `px` with Gaussian noise.
    """

    points_c: np.ndarray
    px_true: np.ndarray
    px: np.ndarray


def _plane_line(n: np.ndarray, m: np.ndarray, hm: Real):
    """Line of `n · X = 1` ∩ `m · X = hm`: (point, unit direction), or None if parallel."""
    d = np.cross(n, m)
    if np.linalg.norm(d) < 1e-12 * np.linalg.norm(n) * np.linalg.norm(m):
        return None
    A = np.stack([n, m])
    X0 = A.T @ np.linalg.solve(A @ A.T, np.array([1.0, hm]))
    return X0, _unit(d)


def _board_stripe_points(
    rig: Rig, field: _Field, T_c_b: Pose, board: Target, step_px: Real
) -> np.ndarray:
    R, t = _pose_np(T_c_b)
    m = R[:, 2]
    line = _plane_line(field.n, m, float(m @ t))
    if line is None:
        return np.zeros((0, 3))
    X0, d = line
    xb0, db = R.T @ (X0 - t), R.T @ d  # board coordinates along the line: xb0 + s db
    x_lo, x_hi, y_lo, y_hi = board.extent_mm
    s_lo, s_hi = -math.inf, math.inf
    for a, b, lo, hi in ((xb0[0], db[0], x_lo, x_hi), (xb0[1], db[1], y_lo, y_hi)):
        if abs(b) < 1e-15:
            if not lo <= a <= hi:
                return np.zeros((0, 3))
            continue
        s1, s2 = sorted(((lo - a) / b, (hi - a) / b))
        s_lo, s_hi = max(s_lo, s1), min(s_hi, s2)
    if not s_hi > s_lo:
        return np.zeros((0, 3))
    step = step_px * field.mm_per_px
    k = max(int(math.floor((s_hi - s_lo) / step)), 1)
    s = s_lo + (np.arange(k) + 0.5) * (s_hi - s_lo) / k
    X = X0 + s[:, None] * d
    return X[_near_field(rig, field, X)]


def _trace_sets(
    rig: Rig, point_sets: Sequence[np.ndarray], margin_px: Real
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Trace several point sets at once: per set (kept mask, pixels of the kept points)."""
    sizes = [len(p) for p in point_sets]
    X = np.concatenate([np.reshape(p, (-1, 3)) for p in point_sets]) if sizes else np.zeros((0, 3))
    uv, ok = trace_points(rig, X)
    keep = ok & _inside(rig, uv, margin_px)
    out, start = [], 0
    for size in sizes:
        sl = slice(start, start + size)
        start += size
        out.append((keep[sl], uv[sl][keep[sl]]))
    return out


def _trace_stripes(
    rig: Rig, point_sets: Sequence[np.ndarray], noise_px: Real, seed: Integral, margin_px: Real
) -> list[StripeProfile]:
    rng = _rng(seed, 3)
    return [
        StripeProfile(np.reshape(X, (-1, 3))[k], px, _noisy(px, noise_px, rng))
        for X, (k, px) in zip(point_sets, _trace_sets(rig, point_sets, margin_px))
    ]


def stripe_on_board(
    rig: Rig,
    T_c_b: Pose,
    board: Target,
    *,
    step_px: Real = 2.0,
    noise_px: Real = 0.0,
    seed: Integral = 0,
    margin_px: Real = 5.0,
) -> StripeProfile:
    """The laser line on a posed board: laser plane ∩ board plane, within the squares.

    Points are spaced about `step_px` pixels apart along the stripe (laser-plane scale
    at the field centre), clipped to the board's squares (`board.extent_mm`) and to the
    sensor (traced pixels `margin_px` inside it). The 3-D points are exact: on the laser
    plane and the board plane to rounding. **Returns:** a [`StripeProfile`][] (empty
    arrays when the plane misses the board).
    """
    field = _field(rig)
    X = _board_stripe_points(rig, field, T_c_b, board, step_px)
    return _trace_stripes(rig, [X], noise_px, seed, margin_px)[0]
