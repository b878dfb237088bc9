"""The parameter sets published by Guo, Cui & Wu (Sensors 2024), Tables 1–2 and §3.

Table values are printed in degrees and mm; the models take radians.
"""

from __future__ import annotations

import math

import numpy as np

from .camera._pinhole import Pinhole
from .camera._thick_lens import ThickLensScheimpflug
from .geometry._plane import LaserPlane
from .geometry._stage import RotaryStage

# Table 1: f, x0, y0, phi (deg), theta (deg), e, z0, dx, dy
_TABLE1 = {
    "scheimpflug-1.25": (
        100.01,
        807.88,
        598.82,
        -0.34243,
        13.749,
        -0.97048,
        256.31,
        0.0049,
        0.0051,
    ),
    "scheimpflug-1.5": (97.004, 796.21, 593.99, 2.8718, 13.307, -2.4125, 249.47, 0.0049, 0.0048),
    "regular-1.25": (99.749, 801.78, 596.79, -5.7397, 5.8230, -2.1826, 248.92, 0.0049, 0.0049),
    "regular-1.5": (86.920, 799.64, 601.90, 0.46466, 0.43254, -2.6541, 250.85, 0.0049, 0.0049),
}

# Table 2: alpha, beta, gamma, x0, y0 (px)
_TABLE2 = {
    "scheimpflug-1.25": (36803.0, 32676.0, 1411.3, -4042.5, -490.96),
    "scheimpflug-1.5": (39326.0, 36572.0, 256.63, -1818.3, 504.58),
    "regular-1.25": (38821.0, 38792.0, -37.424, 481.41, 649.06),
    "regular-1.5": (37285.0, 37241.0, -18.943, 557.03, 587.87),
}

SYSTEMS = tuple(_TABLE1)


def _check(system: str) -> None:
    if system not in _TABLE1:
        raise ValueError(f"unknown system {system!r}; choose one of {', '.join(SYSTEMS)}")


def paper_thick_lens(system: str = "scheimpflug-1.5") -> ThickLensScheimpflug:
    """The calibrated thick-lens camera of Table 1."""
    _check(system)
    f, x0, y0, phi, theta, e, z0, dx, dy = _TABLE1[system]
    return ThickLensScheimpflug(
        f=f,
        e=e,
        z0=z0,
        phi=math.radians(phi),
        theta=math.radians(theta),
        x0=x0,
        y0=y0,
        dx=dx,
        dy=dy,
    )


def paper_pinhole(system: str = "scheimpflug-1.5") -> Pinhole:
    """The calibrated pinhole camera of Table 2."""
    _check(system)
    return Pinhole(*_TABLE2[system])


def paper_laser_plane() -> LaserPlane:
    """The ×1.5 Scheimpflug system's laser plane, `[A, B, C] = 1e-4 [8.6089, 3.6205, 31.749]`.

    Signs as printed; the extraction may have dropped some (see `paper_stage`).
    """
    return LaserPlane(1e-4 * np.array([8.6089, 3.6205, 31.749]))


# As printed, the rows of R_c2m are not orthogonal: minus signs were lost. Three
# patterns with two minus signs make it a proper rotation: on (R11, R22), on (R13, R32)
# or on (R23, R31). (R11, R22) is a half-turn (178°) that flips the camera's x and y
# axes, an odd way to describe a mount; the other two are mirror images of the same
# 66° oblique view. We take (R13, R32): the camera's optical axis then points towards
# -x_m, the side of the gauge on which the table's published t_c2m x is small and
# positive. The plane's and t's signs stay uncertain.
_R_C2M_PRINTED = np.array(
    [[0.41199, 0.036022, 0.91047], [0.082152, 0.99368, 0.076488], [0.90748, 0.10631, 0.40643]]
)
R_C2M_SIGNS = np.array([[1, 1, -1], [1, 1, 1], [1, -1, 1]])


def paper_stage(delta_omega_deg: float = 1.0) -> RotaryStage:
    """The ×1.5 system's camera-to-measurement transform with the chosen sign pattern.

    The printed matrix is orthogonal only to about 1e-5; it is projected onto SO(3).
    """
    R = _R_C2M_PRINTED * R_C2M_SIGNS
    U, _, Vt = np.linalg.svd(R)
    R = U @ Vt
    return RotaryStage(R, np.array([10.023, 300.06, 11.231]), math.radians(delta_omega_deg))
