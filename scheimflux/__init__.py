"""scheimflux: thick-lens Scheimpflug camera calibration and laser-line 3-D measurement.

Importing scheimflux switches JAX to 64-bit floats (metrology needs them); set the
environment variable `SCHEIMFLUX_NO_X64=1` before importing to keep JAX's default.
"""

import importlib.metadata
import os

import jax

if os.environ.get("SCHEIMFLUX_NO_X64", "") in ("", "0"):
    jax.config.update("jax_enable_x64", True)

from . import camera as camera, geometry as geometry, reconstruct as reconstruct
from ._presets import (
    paper_laser_plane as paper_laser_plane,
    paper_pinhole as paper_pinhole,
    paper_stage as paper_stage,
    paper_thick_lens as paper_thick_lens,
)
from .camera import (
    AbstractCamera as AbstractCamera,
    Pinhole as Pinhole,
    Ray as Ray,
    ThickLensScheimpflug as ThickLensScheimpflug,
)
from .geometry import LaserPlane as LaserPlane, Pose as Pose, RotaryStage as RotaryStage
from .reconstruct import (
    Reconstruction as Reconstruction,
    Status as Status,
    stripe_to_camera as stripe_to_camera,
    stripe_to_measurement as stripe_to_measurement,
)

__version__ = importlib.metadata.version("scheimflux")
