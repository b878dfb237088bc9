"""Gauges with exact ground truth, imaged by the real ray trace: a ring gauge (cylinder)
on a rotary table ([`default_stage`][], [`gauge_scan`][]) and stepped gauge-block profiles
([`step_gauge`][]).

Same conventions as `_scenes.py` (whose helpers these scenes use): exact 3-D points in the
scheimflux camera frame, imaged by `Rig.project` (the chief ray traced through the lens
prescription), noise-free and seeded noisy pixels, points near the sensor edge dropped.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from numbers import Integral, Real

import numpy as np
from jaxtyping import ArrayLike

from ..geometry._stage import RotaryStage
from ..geometry._transforms import Pose
from ._rig import Rig
from ._scenes import (
    _field,
    _near_field,
    _noisy,
    _pose_np,
    _rng,
    _rot_z,
    _trace_sets,
    _trace_stripes,
    _unit,
)

__all__ = [
    "BEARING_RADII_MM",
    "GaugeScan",
    "RING_GAUGE_RADIUS_MM",
    "ScanFrame",
    "StepProfile",
    "default_stage",
    "gauge_scan",
    "step_gauge",
]

#: Inner-ring radii (mm) of the two bearings measured in the paper (same scene as the
#: ring gauge, another radius).
BEARING_RADII_MM = (18.646, 17.545)
#: The paper's ring gauge radius (mm).
RING_GAUGE_RADIUS_MM = 17.5


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
