"""Camera models: the thick-lens Scheimpflug camera, the pinhole and their interface."""

from ._base import AbstractCamera as AbstractCamera, Ray as Ray
from ._pinhole import Pinhole as Pinhole
from ._thick_lens import ThickLensScheimpflug as ThickLensScheimpflug
