"""Calibration targets: checkerboards, ChArUco boards and circle grids (OpenCV detection)."""

from ._board import Checkerboard as Checkerboard, parse_board_size as parse_board_size
from ._charuco import (
    CharucoBoard as CharucoBoard,
    aruco_dictionary_names as aruco_dictionary_names,
    detect_charuco as detect_charuco,
)
from ._circles import (
    CircleGrid as CircleGrid,
    circle_diameters_mm as circle_diameters_mm,
    detect_circles as detect_circles,
)
from ._detect import detect_checkerboard as detect_checkerboard
from ._result import DetectionResult as DetectionResult
from ._target import (
    TARGET_KINDS as TARGET_KINDS,
    Target as Target,
    detect_target as detect_target,
    make_target as make_target,
)

__all__ = [
    "aruco_dictionary_names",
    "CharucoBoard",
    "Checkerboard",
    "circle_diameters_mm",
    "CircleGrid",
    "detect_charuco",
    "detect_checkerboard",
    "detect_circles",
    "detect_target",
    "DetectionResult",
    "make_target",
    "parse_board_size",
    "Target",
    "TARGET_KINDS",
]
