"""Calibration targets: checkerboard geometry and detection (OpenCV)."""

from ._board import Checkerboard as Checkerboard, parse_board_size as parse_board_size
from ._detect import DetectionResult as DetectionResult, detect_checkerboard as detect_checkerboard
