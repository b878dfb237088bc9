"""The rotary-table axis from a target fixed to the table (the usual turntable method).

A board on the table is photographed at table steps i (angles i · Δω). Its pose in frame i
is `T_c_b(i) = T_c_m · R_z(−i Δω) · T_t_b` (the inverse of paper eq. 13 applied to the
board's table pose `T_t_b`), so the relative pose of any two frames is a rotation by
`−(j − i) Δω` about the table axis — which fixes the axis's direction and position
directly, with no gauge radius and no eccentricity needed.

Two combinations are gauge freedoms of any rotary scan (the measurement frame may turn
about z_m and slide along it); they are fixed as in the gauge calibration: the camera
origin lies on the measurement x_m axis, `t_m_c = (t_x, 0, 0)` ([`stage_from_axis`][]).

This module holds the closed form ([`axis_from_poses`][]) and its checks of the stated
table step and frame order: the start of the least-squares block that ties these views
into the joint calibration (`_stage_table`).
"""

from __future__ import annotations

import math

import numpy as np

from ...geometry._stage import RotaryStage

__all__ = ["axis_from_poses", "stage_from_axis"]

#: Largest accepted difference between the measured and the stated table step (fraction).
STEP_TOLERANCE = 0.05


# ----------------------------------------------------------------------------- closed form


def _rotvec(R: np.ndarray) -> np.ndarray:
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s = np.linalg.norm(w) / 2.0
    angle = math.atan2(s, c)
    if angle < math.pi - 1e-3:
        return w / (2.0 * s) * angle if s > 1e-15 else np.zeros(3)
    # Near a half turn the antisymmetric part vanishes: the axis is the dominant column
    # of (R + I) / 2 = d dᵀ − (small), its sign taken from the antisymmetric part.
    B = (R + np.eye(3)) / 2.0
    axis = B[:, int(np.argmax(np.diag(B)))]
    axis = axis / np.linalg.norm(axis)
    return (axis if axis @ w >= 0 else -axis) * angle


def axis_from_poses(R_c_b, t_c_b, frame_index, delta_omega):
    """The table axis from board poses at table steps (closed form, NumPy).

    Every pair of frames (i, j) has the relative pose `R_ij = R_j R_iᵀ`, a rotation by
    `−(j − i) Δω` about the axis direction d, and `t_ij = t_j − R_ij t_i = (I − R_ij) p`
    for any point p on the axis. d is the common null vector of all `R_ij − I`, p the
    least-squares solution of the stacked translation equations.

    **Arguments:** `R_c_b` `(F, 3, 3)`, `t_c_b` `(F, 3)` camera-from-board poses;
    `frame_index` `(F,)`; `delta_omega` (rad, non-zero).

    **Returns:** `(d, C, step)`: the unit axis direction in the camera frame (oriented so
    that the table turns by +Δω about it), the foot `C` of the perpendicular from the
    camera origin onto the axis, and the measured step angle (rad, signed like Δω).
    Raises `ValueError` when the poses do not turn about one axis by the stated steps
    (frames out of order, a wrong or missing Δω).
    """
    R_c_b, t_c_b = np.asarray(R_c_b, float), np.asarray(t_c_b, float)
    idx = np.asarray(frame_index, float)
    dw = float(delta_omega)
    if not math.isfinite(dw) or dw == 0.0:
        raise ValueError(f"the table step delta_omega must be a non-zero angle, got {dw}")
    F = len(R_c_b)
    if F < 2 or len(np.unique(idx)) < 2:
        raise ValueError("the table axis needs the target at two or more table angles")
    pairs = [(i, j) for i in range(F) for j in range(i + 1, F) if idx[j] != idx[i]]
    A, b, rv, steps = [], [], [], []
    for i, j in pairs:
        Rij = R_c_b[j] @ R_c_b[i].T
        A.append(Rij - np.eye(3))
        b.append(t_c_b[j] - Rij @ t_c_b[i])
        rv.append(_rotvec(Rij))
        steps.append(idx[j] - idx[i])
    A, b, rv, steps = np.stack(A), np.stack(b), np.stack(rv), np.asarray(steps)
    d = np.linalg.svd(A.reshape(-1, 3))[2][-1]

    def misfit(d):  # measured minus stated turn of each pair, wrapped to (−π, π]
        return np.angle(np.exp(1j * (rv @ d + steps * dw)))

    # R_ij turns by −(j − i) Δω about d: orient d so that the table turns by +Δω.
    if np.sum(np.abs(misfit(-d))) < np.sum(np.abs(misfit(d))):
        d = -d
    delta = misfit(d)
    step = dw - float(np.median(delta / steps))
    worst = int(np.argmax(np.abs(delta)))
    if abs(step - dw) > STEP_TOLERANCE * abs(dw) or abs(delta[worst]) > 0.25 * abs(dw):
        raise ValueError(
            f"the target turns by {math.degrees(step):.3f}° per table step, not the stated "
            f"{math.degrees(dw):.3f}° (views {pairs[worst]} are {math.degrees(delta[worst]):+.3f}° "
            "off): check delta_omega and that the views are in table order"
        )
    M = -A.reshape(-1, 3)  # (I − R_ij) p = t_ij
    p = np.linalg.lstsq(M, b.reshape(-1), rcond=None)[0]
    C = p - (p @ d) * d
    return d, C, step


def stage_from_axis(d, C, delta_omega: float) -> RotaryStage:
    """The [`RotaryStage`][] of an axis, in the gauge `t_m_c = (t_x, 0, 0)`.

    **Arguments:** `d` the unit axis direction and `C` the foot of the perpendicular from
    the camera origin onto the axis (camera frame, as [`axis_from_poses`][] returns);
    `delta_omega` the table step (rad).

    **Returns:** the stage with `z_m = d`, `x_m` from the axis towards the camera origin,
    the measurement origin at `C`.
    """
    d, C = np.asarray(d, float), np.asarray(C, float)
    dist = float(np.linalg.norm(C))
    if dist < 1e-9:
        raise ValueError("the table axis passes through the camera centre")
    x = -C / dist
    R = np.stack([x, np.cross(d, x), d])
    return RotaryStage(R, np.array([dist, 0.0, 0.0]), delta_omega)
