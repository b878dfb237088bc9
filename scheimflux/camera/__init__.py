"""Camera models: the thick-lens Scheimpflug camera, the pinhole, an OpenCV-compatible
tilted camera, and lens distortion models."""

from ._base import AbstractCamera as AbstractCamera, Ray as Ray
from ._distortion import (
    AbstractDistortion as AbstractDistortion,
    Division as Division,
    NoDistortion as NoDistortion,
    OpenCVDistortion as OpenCVDistortion,
    RadialTangential as RadialTangential,
)
from ._noncentral import ThickLensNonCentral as ThickLensNonCentral
from ._opencv import OpenCVCamera as OpenCVCamera
from ._pinhole import Pinhole as Pinhole
from ._thick_lens import ThickLensScheimpflug as ThickLensScheimpflug

__all__ = [
    "AbstractCamera",
    "AbstractDistortion",
    "Division",
    "NoDistortion",
    "OpenCVCamera",
    "OpenCVDistortion",
    "Pinhole",
    "RadialTangential",
    "Ray",
    "ThickLensNonCentral",
    "ThickLensScheimpflug",
]
