"""Export calibrations to other tools' formats (OpenCV's camera YAML)."""

from ._opencv import (
    OpenCVFit as OpenCVFit,
    export_opencv as export_opencv,
    opencv_equivalent as opencv_equivalent,
)

__all__ = [
    "export_opencv",
    "opencv_equivalent",
    "OpenCVFit",
]
