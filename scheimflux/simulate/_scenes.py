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
- [`default_stage`][], [`gauge_scan`][]: a ring gauge (cylinder) on a rotary table.
- [`step_gauge`][]: stepped gauge-block profiles.

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
from jaxtyping import ArrayLike

from ..camera._thick_lens import ThickLensScheimpflug
from ..geometry._stage import RotaryStage
from ..geometry._transforms import Pose
from ..targets._target import Target
from ._lens import paraxial
from ._rig import Rig

__all__ = [
    "BEARING_RADII_MM",
    "BoardView",
    "GaugeScan",
    "ScanFrame",
    "StepProfile",
    "StripeProfile",
    "board_poses",
    "default_stage",
    "gauge_scan",
    "step_gauge",
    "stripe_on_board",
]

#: Inner-ring radii (mm) of the two bearings measured in the paper (same scene as the
#: ring gauge, another radius).
BEARING_RADII_MM = (18.646, 17.545)
#: The paper's ring gauge radius (mm).
RING_GAUGE_RADIUS_MM = 17.5

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
) -> list[Pose]:
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
    centres = np.asarray(rig.laser_points(jnp.asarray(centres_px)))
    poses = []
    for k in range(n):
        psi = rng.uniform(0.0, 2 * math.pi)
        tilt = math.radians(rng.uniform(min_tilt_deg, max_tilt_deg))
        spin = math.radians(rng.uniform(-max_spin_deg, max_spin_deg))
        R_tilt = _rodrigues(tilt * np.array([math.cos(psi), math.sin(psi), 0.0]))
        R = R_align @ R_tilt @ _rot_z(math.pi + spin)
        # Keep the laser line within `stripe_offset_mm` of the board centre: a board
        # centre δ off the laser plane puts the line δ / sin(tilt) from the centre.
        depth = min(depth_mm, stripe_offset_mm * math.sin(tilt))
        centre = centres[k] + field.normal * rng.uniform(-depth, depth)
        t = centre - R @ board.centre_mm
        poses.append(Pose.from_matrix(R, t))
    return poses


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

    **Returns:** a list of [`BoardView`][] (corners visible if the trace succeeds and lands
    `margin_px` inside the sensor; `px` carries Gaussian noise `noise_px` per coordinate).
    """
    if n < 1:
        raise ValueError(f"need at least one board view, got {n}")
    poses = _board_pose_list(
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
    X = np.stack([pts_b @ _pose_np(T)[0].T + _pose_np(T)[1] for T in poses])  # (n, M, 3)
    uv, ok = trace_points(rig, X.reshape(-1, 3))
    uv = uv.reshape(n, -1, 2)
    vis = ok.reshape(n, -1) & _inside(rig, uv, margin_px)
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


# ----------------------------------------------------------------------------- ring gauge


def default_stage(
    rig: Rig,
    radius: Real = RING_GAUGE_RADIUS_MM,
    delta_omega: Real = math.radians(10.0),
    *,
    axis_tilt_deg: Real = 30.0,
    view_angle_deg: Real = 40.0,
    stripe_angle_deg: Real = 15.0,
) -> RotaryStage:
    """A rotary-table pose that puts a cylinder of `radius` through the focus point F0.

    Construction (camera frame; n̂ the laser plane's unit normal, away from the camera):

    - T, the stripe's direction at F0: the camera x axis projected into the laser plane,
      turned by `stripe_angle_deg` about n̂ (so the stripe crosses the image, not exactly
      along the rows); T⊥ = n̂ × T.
    - The gauge's outward surface normal at F0, `x_m = −cos ν n̂ + sin ν T⊥`, makes
      ν = `view_angle_deg` with the direction back to the camera: the lit surface faces
      the camera (viewed 40° off its normal) and the laser, which travels in its plane,
      meets it at 90° − ν off its normal.
    - The table axis `z_m` is perpendicular to `x_m` and tilted `axis_tilt_deg` (α) out of
      the laser plane: `z_m = cos ζ T + sin ζ (x_m × T)` with sin ζ = sin α / sin ν.
    - The axis passes through `C = F0 − r x_m`, the measurement-frame origin (so F0 is
      `(r, 0, 0)` in the measurement frame); `y_m = z_m × x_m`.

    `R_m_c` has rows `x_m, y_m, z_m` and `t_m_c = −R_m_c C`.

    Why this geometry: if the axis lay in the laser plane, the plane would cut the
    cylinder along straight generators whose surface normal lies in the plane — seen at
    grazing incidence by a camera looking almost along n̂ — and every frame would show
    the same straight line, which carries no curvature to fix the axis. Tilted out of the
    plane by α, the plane cuts an ellipse (semi-axes r and r / sin α); near F0 the stripe
    is an arc of curvature about sin²ζ / (r sin ν) (radius ≈ 19 mm for r = 17.5 mm: a
    sagitta of ~50 px across the field) whose curvature also varies along it because F0
    is not at a vertex of the ellipse.

    What the scan determines (stage calibration with known r, points reconstructed in
    the camera frame): each point X_c of frame i must satisfy
    dist(R_i (R_m_c X_c + t_m_c), gauge axis) = r. Two combinations are gauge freedoms for
    *any* cylinder scan and must be fixed by convention: the translation along z_m (a
    cylinder has no height datum; here C is the foot of the perpendicular from F0) and a
    rotation of the measurement frame about z_m together with the same rotation of the
    eccentricity vector. The remaining six — the table axis as a line (4) and the
    eccentricity (2) — are observable: the arc's position, direction and curvature with the
    known r fix the cylinder, and the eccentricity makes the cylinder move by R_iᵀ e from
    frame to frame, so the stripe shifts sinusoidally with i·Δω (amplitude and phase give
    e; with e = 0 every frame shows the same arc, the azimuth about z_m is then a pure
    gauge and the axis is fixed by the arc shape alone, which is weaker). Use a table
    rotation spanning a full turn (n_frames · Δω = 360°) so the sinusoid is sampled evenly.

    Numbers (paper rig, r = 17.5 mm, e = (0.05, −0.03) mm, noise 0.05 px ≈ 0.15 µm on the
    laser plane; `calibrate_stage` with the exact camera and plane, gauge fixed by
    t_y = t_z = 0; Monte Carlo RMS over 12–40 seeds): 36 frames × 10° (~190 points each)
    give the table axis direction to 0.40 mrad, the axis line to 4 µm at the gauge (the
    weakest combination, because the arc is short: ~5 mm of a 17.5 mm radius) and |e| to
    0.03 µm; 12 frames × 30° give 0.48 mrad, 5 µm, 0.03 µm. A centred gauge (e = 0) gives
    3× worse axes (1.6 mrad, 16 µm); an axis tilted only 10° out of the plane 1.3 mrad and
    70 µm. Ray-traced pixels read through the paraxial model camera add a bias of about
    0.35 mrad, 3 µm and −0.06 µm in |e| (the real lens against the model).

    The radial (3-D) distance from the cylinder also has a spurious local minimum: an
    axis parallel to the laser plane at distance ≈ r, a cylinder nearly tangent to the
    plane, comes within ~0.2 µm RMS of every stripe point of this scene — the noise
    level. The calibration must therefore start from residuals measured within the laser
    plane (what `initial_stage` does); started there, Levenberg–Marquardt converged from
    axes up to ~3° off the truth in our tests.
    """
    if radius <= 0:
        raise ValueError(f"gauge radius must be positive, got {radius}")
    alpha, nu = math.radians(axis_tilt_deg), math.radians(view_angle_deg)
    if not 0.0 < alpha <= nu < math.pi / 2:
        raise ValueError("need 0 < axis_tilt_deg <= view_angle_deg < 90")
    field = _field(rig)
    nh = field.normal
    ex = np.array([1.0, 0.0, 0.0])
    T0 = _unit(ex - (ex @ nh) * nh)
    sig = math.radians(stripe_angle_deg)
    T = math.cos(sig) * T0 + math.sin(sig) * np.cross(nh, T0)
    T_perp = np.cross(nh, T)
    x_m = -math.cos(nu) * nh + math.sin(nu) * T_perp
    b = np.cross(x_m, T)
    zeta = math.asin(math.sin(alpha) / math.sin(nu))
    z_m = _unit(math.cos(zeta) * T + math.sin(zeta) * b)
    y_m = np.cross(z_m, x_m)
    R_m_c = np.stack([x_m, y_m, z_m])
    C = field.F0 - radius * x_m
    return RotaryStage(R_m_c, -R_m_c @ C, delta_omega)


@dataclasses.dataclass(frozen=True)
class ScanFrame:
    """One frame of a rotary scan.

    **Fields:** `index` (frame i: table turned by i·Δω), `points_c` `(K, 3)` exact stripe
    points (camera frame), `points_m` `(K, 3)` the same in the measurement frame
    (`X_m = R_i (R_m_c X_c + t_m_c)`), `px_true` `(K, 2)` ray-traced pixels, `px` noisy.
    """

    index: int
    points_c: np.ndarray
    points_m: np.ndarray
    px_true: np.ndarray
    px: np.ndarray


@dataclasses.dataclass(frozen=True)
class GaugeScan:
    """A rotary scan of a cylinder of known radius.

    **Fields:** `stage` (the true [`RotaryStage`][]), `radius` (mm), `eccentricity_mm`
    (the gauge axis's offset from the table axis, measurement frame (x, y)), `wobble_rad`
    (tilt of the gauge axis from z_m towards x_m), `frames` (list of [`ScanFrame`][]).
    The gauge axis in the measurement frame is the line through `(e_x, e_y, 0)` along
    `(sin w, 0, cos w)`.
    """

    stage: RotaryStage
    radius: float
    eccentricity_mm: tuple[float, float]
    wobble_rad: float
    frames: list[ScanFrame]

    def axis_m(self) -> tuple[np.ndarray, np.ndarray]:
        """The gauge axis in the measurement frame: (point, unit direction)."""
        ex, ey = self.eccentricity_mm
        w = self.wobble_rad
        return np.array([ex, ey, 0.0]), np.array([math.sin(w), 0.0, math.cos(w)])


def _rot_z_np(a: Real) -> np.ndarray:
    return _rot_z(a)


def _cylinder_section(
    C: np.ndarray, a: np.ndarray, r: Real, n: np.ndarray, phi: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Points of the cylinder (axis C + s a, radius r) on the plane n · X = 1 at azimuths
    `phi`, and the outward surface normals there."""
    u1 = _unit(np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0]))
    u2 = np.cross(a, u1)
    radial = np.cos(phi)[:, None] * u1 + np.sin(phi)[:, None] * u2
    na = float(n @ a)
    if abs(na) < 1e-12 * np.linalg.norm(n):
        raise ValueError("the gauge axis is parallel to the laser plane")
    s = (1.0 - n @ C - r * (radial @ n)) / na
    return C + r * radial + s[:, None] * a, radial


def gauge_scan(
    rig: Rig,
    stage: RotaryStage,
    radius: Real = RING_GAUGE_RADIUS_MM,
    n_frames: Integral = 36,
    *,
    eccentricity_mm: ArrayLike | Sequence = (0.0, 0.0),
    wobble_rad: Real = 0.0,
    points_per_frame: Integral = 200,
    noise_px: Real = 0.0,
    seed: Integral = 0,
    margin_px: Real = 5.0,
) -> GaugeScan:
    """Scan a cylinder (ring gauge, bearing ring) standing on the rotary table.

    The gauge axis in the measurement frame passes through `(e_x, e_y, 0)`
    (`eccentricity_mm`) along `(sin w, 0, cos w)` (`wobble_rad`), fixed to the table. In
    frame i (`i = 0 … n_frames − 1`) the table has turned by i · Δω, so a gauge point X_m
    sits at `X_c = R_m_cᵀ (R_iᵀ X_m − t_m_c)` (the inverse of paper eq. 13). The stripe is
    the laser plane ∩ the cylinder, on the side facing the camera (outward normal towards
    the entrance pupil; the laser is assumed to light that side), traced and kept where it
    lands `margin_px` inside the sensor: `points_per_frame` points evenly spaced in azimuth
    over the visible arc. Truth points are exact (on the plane and the cylinder to
    rounding). Use [`default_stage`][] for a stage pose that suits the rig;
    `BEARING_RADII_MM` holds the paper's bearing radii.

    **Returns:** a [`GaugeScan`][].
    """
    if radius <= 0:
        raise ValueError(f"gauge radius must be positive, got {radius}")
    if n_frames < 1:
        raise ValueError(f"need at least one frame, got {n_frames}")
    field = _field(rig)
    R_m_c = np.asarray(stage.R_m_c, dtype=np.float64)
    t_m_c = np.asarray(stage.t_m_c, dtype=np.float64)
    dw = float(stage.delta_omega)
    ex, ey = (float(v) for v in eccentricity_mm)
    w = float(wobble_rad)
    c_m = np.array([ex, ey, 0.0])
    a_m = np.array([math.sin(w), 0.0, math.cos(w)])
    grid = np.linspace(0.0, 2 * math.pi, 7200, endpoint=False)
    step = grid[1] - grid[0]
    point_sets = []
    for i in range(n_frames):
        Ri = _rot_z_np(i * dw)
        C = R_m_c.T @ (Ri.T @ c_m - t_m_c)
        a = R_m_c.T @ (Ri.T @ a_m)
        X, radial = _cylinder_section(C, a, radius, field.n, grid)
        facing = np.einsum("ij,ij->i", radial, field.pupil - X) > 0
        sel = facing & _near_field(rig, field, X)
        if not sel.any():
            point_sets.append((C, a, np.zeros(0)))
            continue
        # Largest contiguous run of selected azimuths (circular).
        if sel.all():
            lo, hi = 0.0, 2 * math.pi
        else:
            start = int(np.flatnonzero(~sel)[0])
            rolled = np.roll(sel, -start)
            edges = np.diff(np.concatenate([[0], rolled.astype(int), [0]]))
            starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
            j = int(np.argmax(ends - starts))
            lo = grid[(starts[j] + start) % len(grid)] - step
            hi = lo + (ends[j] - starts[j] + 1) * step
        phi = np.linspace(lo, hi, points_per_frame)
        point_sets.append((C, a, phi))
    sets = []
    for C, a, phi in point_sets:
        if len(phi) == 0:
            sets.append(np.zeros((0, 3)))
            continue
        X, radial = _cylinder_section(C, a, radius, field.n, phi)
        facing = np.einsum("ij,ij->i", radial, field.pupil - X) > 0
        sets.append(X[facing])
    profiles = _trace_stripes(rig, sets, noise_px, seed, margin_px)
    frames = []
    for i, prof in enumerate(profiles):
        Ri = _rot_z_np(i * dw)
        X_m = (prof.points_c @ R_m_c.T + t_m_c) @ Ri.T
        frames.append(ScanFrame(i, prof.points_c, X_m, prof.px_true, prof.px))
    return GaugeScan(stage, float(radius), (ex, ey), w, frames)


# ----------------------------------------------------------------------------- step gauge


@dataclasses.dataclass(frozen=True)
class StepProfile:
    """One laser profile across one step of a stepped gauge block.

    **Fields:**
    - `height_mm`: the step height (top − base).
    - `T_c_g`: camera-from-gauge pose; gauge frame: origin on the base plane at the step
      edge, z up out of the base (towards the camera side), x across the edge towards
      the raised part, so the base is `z = 0, x < 0` and the top `z = h, x > 0`.
    - `points_c` `(K, 3)`, `labels` `(K,)` (0 base, 1 top), `px_true`, `px` `(K, 2)`.
    """

    height_mm: float
    T_c_g: Pose
    points_c: np.ndarray
    labels: np.ndarray
    px_true: np.ndarray
    px: np.ndarray

    def heights(self) -> np.ndarray:
        """Exact height of every point above the base plane (mm)."""
        R, t = _pose_np(self.T_c_g)
        return (self.points_c - t) @ R[:, 2]


def step_gauge(
    rig: Rig,
    steps_mm: Sequence[float] = (1.0, 1.5, 2.0),
    *,
    surface_angle_deg: Real = 60.0,
    stripe_angle_deg: Real = 0.0,
    step_px: Real = 2.0,
    edge_gap_mm: Real = 0.05,
    noise_px: Real = 0.0,
    seed: Integral = 0,
    margin_px: Real = 5.0,
) -> list[StepProfile]:
    """Stepped gauge-block profiles, one per step height, each crossing one step edge.

    The field is small (≈ 4.7 × 3.5 mm at |β| = 1.5), so each profile shows one edge: the
    base on one side, the top of height h on the other, the edge at the focus point F0
    and the plane halfway up the step through F0. The block's surface normal makes
    `surface_angle_deg` (ψ) with the direction back to the camera (−n̂); the laser plane
    cuts base and top in parallel lines h / sin ψ apart (2.3 mm for h = 2, ψ = 60°), along
    the camera x axis turned by `stripe_angle_deg` in the laser plane. The riser faces the
    camera, so no base point is hidden behind the step; points within `edge_gap_mm` of the
    edge are left out (edge shadow and blur); the riser itself is not sampled.

    **Returns:** a list of [`StepProfile`][], one per height, in the order given.
    """
    psi = math.radians(surface_angle_deg)
    if not 0.0 < psi < math.pi / 2:
        raise ValueError("surface_angle_deg must be in (0, 90)")
    field = _field(rig)
    nh, n = field.normal, field.n
    ex = np.array([1.0, 0.0, 0.0])
    T0 = _unit(ex - (ex @ nh) * nh)
    sig = math.radians(stripe_angle_deg)
    T = math.cos(sig) * T0 + math.sin(sig) * np.cross(nh, T0)
    z_g = -math.cos(psi) * nh + math.sin(psi) * np.cross(nh, T)
    x_g = T if T @ (field.pupil - field.F0) <= 0 else -T
    y_g = np.cross(z_g, x_g)
    R = np.stack([x_g, y_g, z_g], axis=1)
    step = step_px * field.mm_per_px
    half = 0.75 * max(rig.sensor_size) * field.mm_per_px
    s = np.arange(edge_gap_mm, half, step)
    sets, meta = [], []
    for h in steps_mm:
        h = float(h)
        if not h > 0:
            raise ValueError(f"step heights must be positive, got {h}")
        O = field.F0 - 0.5 * h * z_g
        parts, labels = [], []
        for lab, base, sgn in ((0, O, -1.0), (1, O + h * z_g, 1.0)):
            t_line = (1.0 - n @ base) / (n @ y_g)
            X = base + t_line * y_g + (sgn * s)[:, None] * x_g
            X = X[_near_field(rig, field, X)]
            parts.append(X)
            labels.append(np.full(len(X), lab))
        sets.append(np.concatenate(parts))
        meta.append((h, Pose.from_matrix(R, O), np.concatenate(labels)))
    rng = _rng(seed, 4)
    out = []
    for (h, T_c_g, labels), X, (keep, px) in zip(meta, sets, _trace_sets(rig, sets, margin_px)):
        out.append(StepProfile(h, T_c_g, X[keep], labels[keep], px, _noisy(px, noise_px, rng)))
    return out
