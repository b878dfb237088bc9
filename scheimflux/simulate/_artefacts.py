"""Verification artefacts: objects measured to check a calibration, never to make one.

Three scenes, each ray-traced through the rig like the calibration data:

- **a second ring** (`"cylinder"`): a cylinder of another radius on the rotary table, set
  off its axis ([`gauge_scan`][] with that radius and eccentricity);
- **two spheres** (`"sphere-pair"`): balls fixed to the table at the same height, turned
  through the laser plane one after the other; their centre distance spans a large
  table angle, so it tests what a ring cannot: distances between points seen in
  different frames;
- **a stepped gauge** (`"steps"`): one laser profile across faces at heights
  `H1, H2, …` above a base face, the faces perpendicular to the laser plane (as under a
  laser that falls perpendicular onto the reference surface), so the distance between
  the profile's lines is the height itself.

Each returns an [`ArtefactScan`][]: per frame the noisy stripe pixels, the exact
points, the nominal value(s), and in which frame (camera or measurement) to measure.
Occlusion by the artefact itself is not modelled (only surfaces facing the entrance
pupil are sampled).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from numbers import Integral, Real

import numpy as np

from ..geometry._stage import RotaryStage
from ._gauges import gauge_scan
from ._rig import Rig
from ._scenes import (
    _coarse_pixels,
    _field,
    _near_field,
    _noisy,
    _rng,
    _rot_z,
    _trace_sets,
    _unit,
)

__all__ = ["ArtefactScan", "ring_artefact", "sphere_pair_artefact", "stepped_gauge_artefact"]


@dataclasses.dataclass(frozen=True)
class ArtefactScan:
    """A ray-traced scan of a verification artefact.

    **Fields:**
    - `kind`: `"cylinder"`, `"sphere-pair"` or `"steps"`.
    - `nominal_mm`: the true value(s): `(R,)`, `(D,)` or `(H1, H2, …)`.
    - `frame`: `"measurement"` (a rotary scan) or `"camera"` (one profile).
    - `delta_omega`: the table step of the scan (rad; 0 for a profile).
    - `px`: per frame the noisy stripe pixels `(K_i, 2)`; `px_true` noise-free.
    - `points_c`: per frame the exact camera-frame points; `labels`: per frame the part
      of the artefact each point lies on (sphere 0/1, face 0 … K), or None (ring).
    """

    kind: str
    nominal_mm: tuple[float, ...]
    frame: str
    delta_omega: float
    px: list[np.ndarray]
    px_true: list[np.ndarray]
    points_c: list[np.ndarray]
    labels: list[np.ndarray] | None = None


def _stage_np(stage: RotaryStage):
    return np.asarray(stage.R_m_c, np.float64), np.asarray(stage.t_m_c, np.float64)


def ring_artefact(
    rig: Rig,
    stage: RotaryStage,
    radius_mm: Real,
    *,
    n_frames: Integral = 24,
    eccentricity_mm: Sequence[float] = (0.25, -0.15),
    noise_px: Real = 0.0,
    seed: Integral = 0,
) -> ArtefactScan:
    """A second ring of `radius_mm`, off the table axis by `eccentricity_mm`, scanned at
    the stage's Δω (the stage must put a cylinder of about that radius into the field:
    [`default_stage`][] for the calibration gauge's radius takes rings within ~1 mm)."""
    scan = gauge_scan(
        rig, stage, float(radius_mm), int(n_frames), eccentricity_mm=eccentricity_mm,
        noise_px=float(noise_px), seed=int(seed),
    )  # fmt: skip
    return ArtefactScan(
        "cylinder",
        (float(radius_mm),),
        "measurement",
        float(stage.delta_omega),
        [f.px for f in scan.frames],
        [f.px_true for f in scan.frames],
        [f.points_c for f in scan.frames],
    )


def sphere_pair_artefact(
    rig: Rig,
    stage: RotaryStage,
    *,
    sphere_radius_mm: Real = 1.5,
    separation_deg: Real = 60.0,
    delta_omega_deg: Real = 0.5,
    inset_mm: Real = 0.6,
    points_per_frame: Integral = 120,
    noise_px: Real = 0.0,
    seed: Integral = 0,
) -> ArtefactScan:
    """Two balls of `sphere_radius_mm` fixed to the table `separation_deg` apart.

    Sphere 0's centre sits, at table step 0, at the focus point F0 moved `inset_mm` away
    from the entrance pupil (so the lit cap faces the camera); sphere 1 is the same point
    turned by `separation_deg` about the table axis. The table turns in steps of
    `delta_omega_deg` through both spheres' passes through the laser plane; frame 0 of
    the result is the first step that sees a sphere (a common turn of all frames leaves
    every distance unchanged), the frames between the passes are empty. The nominal
    value is the centre distance `2 ρ sin(separation / 2)`, ρ the centres' distance
    from the table axis.
    """
    field = _field(rig)
    R_m_c, t_m_c = _stage_np(stage)
    dw = math.radians(float(delta_omega_deg))
    if not dw > 0:
        raise ValueError(f"delta_omega_deg must be positive, got {delta_omega_deg}")
    a = float(sphere_radius_mm)
    gap = int(round(math.radians(float(separation_deg)) / dw))
    n_hat = field.normal
    C0_c = field.F0 + float(inset_mm) * _unit(field.F0 - field.pupil)
    c0_t = R_m_c @ C0_c + t_m_c  # sphere 0's centre, table coordinates (table at step 0)
    c1_t = _rot_z(gap * dw) @ c0_t
    rho = float(np.hypot(c0_t[0], c0_t[1]))
    if rho < 2 * a:
        raise ValueError("the spheres sit too close to the table axis")
    if gap * dw * rho <= 2.5 * a:
        raise ValueError("the spheres' frames overlap: raise separation_deg")
    D = float(np.linalg.norm(c1_t - c0_t))
    u1 = _unit(np.cross(n_hat, [1.0, 0.0, 0.0]))
    u2 = np.cross(n_hat, u1)
    phi = np.linspace(0.0, 2 * math.pi, 720, endpoint=False)
    m = int(math.ceil(2.0 * a / (rho * dw))) + 2
    sets, labels = [], []
    for i in range(-m, gap + m + 1):
        Xs, ls = [], []
        for lab, c_t in ((0, c0_t), (1, c1_t)):
            C = R_m_c.T @ (_rot_z(i * dw).T @ c_t - t_m_c)  # centre, camera frame
            delta = float(n_hat @ C - 1.0 / np.linalg.norm(field.n))
            if abs(delta) >= 0.98 * a:
                continue
            P = C - delta * n_hat
            r = math.sqrt(a * a - delta * delta)
            X = P + r * (np.cos(phi)[:, None] * u1 + np.sin(phi)[:, None] * u2)
            facing = np.einsum("ij,ij->i", X - C, field.pupil - X) > 0
            X = X[facing & _near_field(rig, field, X)]
            if len(X) > points_per_frame:
                X = X[np.linspace(0, len(X) - 1, int(points_per_frame)).astype(int)]
            Xs.append(X)
            ls.append(np.full(len(X), lab))
        sets.append(np.concatenate(Xs) if Xs else np.zeros((0, 3)))
        labels.append(np.concatenate(ls).astype(np.int32) if ls else np.zeros(0, np.int32))
    used = [k for k, X in enumerate(sets) if len(X)]
    sets, labels = sets[used[0] : used[-1] + 1], labels[used[0] : used[-1] + 1]
    px, px_true, pts, lab_kept = _traced(rig, sets, labels, noise_px, seed)
    return ArtefactScan(
        "sphere-pair", (D,), "measurement", dw,
        px, px_true, pts, lab_kept,
    )  # fmt: skip


def _traced(rig, sets, labels, noise_px, seed):
    """Trace point sets: per set the noisy and exact pixels, kept points and labels."""
    rng = _rng(int(seed), 5)
    px, px_true, pts, labs = [], [], [], []
    for X, lab, (keep, uv) in zip(sets, labels, _trace_sets(rig, sets, 5.0)):
        px.append(_noisy(uv, float(noise_px), rng))
        px_true.append(uv)
        pts.append(X[keep])
        labs.append(lab[keep])
    return px, px_true, pts, labs


def stepped_gauge_artefact(
    rig: Rig,
    heights_mm: Sequence[float] = (1.0, 1.5, 2.0),
    *,
    step_px: Real = 2.0,
    edge_gap_mm: Real = 0.1,
    stripe_angle_deg: Real = 0.0,
    noise_px: Real = 0.0,
    seed: Integral = 0,
) -> ArtefactScan:
    """One laser profile across a stepped gauge: a base face and faces `heights_mm` above it.

    The faces are perpendicular to the laser plane and parallel to the stripe direction T
    (the camera x axis projected into the plane, turned by `stripe_angle_deg`); in the
    laser plane they are parallel lines at heights 0, H1, H2, … along `U = n̂ × T` (U
    towards the entrance pupil, so the faces face the camera), the middle height at the
    focus point F0. The visible length along T is shared equally by the faces, each
    shortened by `edge_gap_mm` at both ends (edge shadow and blur); the base is at the
    profile's end with the smaller pixel u (the order `verify` numbers the faces in).
    """
    hs = [0.0] + [float(h) for h in heights_mm]
    if len(hs) < 2 or any(not h > 0 for h in hs[1:]):
        raise ValueError(f"step heights must be positive, got {tuple(heights_mm)}")
    field = _field(rig)
    nh = field.normal
    ex = np.array([1.0, 0.0, 0.0])
    T0 = _unit(ex - (ex @ nh) * nh)
    s = math.radians(float(stripe_angle_deg))
    T = math.cos(s) * T0 + math.sin(s) * np.cross(nh, T0)
    if np.diff(_coarse_pixels(field, np.stack([field.F0 - T, field.F0 + T]))[:, 0])[0] < 0:
        T = -T  # face 0 (the base) at the profile's end with the smaller pixel u
    U = np.cross(nh, T)
    if U @ (field.pupil - field.F0) < 0:
        U = -U
    mid = 0.5 * (min(hs) + max(hs))
    step = float(step_px) * field.mm_per_px
    half = 0.75 * max(rig.sensor_size) * field.mm_per_px
    # the visible span along T at F0
    sgrid = np.arange(-half, half, step)
    vis = sgrid[_near_field(rig, field, field.F0 + sgrid[:, None] * T)]
    if len(vis) < 4 * len(hs):
        raise ValueError("the stepped gauge's faces do not fit into the field")
    edges = np.linspace(vis.min(), vis.max(), len(hs) + 1)
    X, lab = [], []
    for k, h in enumerate(hs):
        sk = sgrid[(sgrid > edges[k] + edge_gap_mm) & (sgrid < edges[k + 1] - edge_gap_mm)]
        X.append(field.F0 + (h - mid) * U + sk[:, None] * T)
        lab.append(np.full(len(sk), k, np.int32))
    X, lab = np.concatenate(X), np.concatenate(lab)
    near = _near_field(rig, field, X)
    X, lab = X[near], lab[near]
    px, px_true, pts, labs = _traced(rig, [X], [lab], noise_px, seed)
    return ArtefactScan("steps", tuple(hs[1:]), "camera", 0.0, px, px_true, pts, labs)
