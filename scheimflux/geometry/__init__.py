"""Rigid transforms, the laser plane and the rotary stage."""

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
