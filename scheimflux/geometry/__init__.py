"""Rigid transforms, the laser plane, the rotary stage, small geometric fits, and the
sensor region a calibration's data covered."""

from ._coverage import Coverage as Coverage, coverage_of as coverage_of
from ._fitting import (
    aligned_distances as aligned_distances,
    fit_plane_svd as fit_plane_svd,
    perpendicular_basis as perpendicular_basis,
    rigid_fit as rigid_fit,
    unit_rows as unit_rows,
)
from ._plane import LaserPlane as LaserPlane
from ._stage import RotaryStage as RotaryStage
from ._transforms import (
    Pose as Pose,
    rot_x as rot_x,
    rot_y as rot_y,
    rot_z as rot_z,
    rotation_matrix as rotation_matrix,
    rotation_vector as rotation_vector,
)

__all__ = [
    "aligned_distances",
    "Coverage",
    "coverage_of",
    "fit_plane_svd",
    "LaserPlane",
    "perpendicular_basis",
    "Pose",
    "rigid_fit",
    "rot_x",
    "rot_y",
    "rot_z",
    "RotaryStage",
    "rotation_matrix",
    "rotation_vector",
    "unit_rows",
]
