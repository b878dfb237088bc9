"""scheimflux: thick-lens Scheimpflug camera calibration and laser-line 3-D measurement.

Importing scheimflux switches JAX to 64-bit floats (metrology needs them; set the
environment variable `SCHEIMFLUX_NO_X64=1` before importing to keep JAX's default) and
switches JAX's persistent compilation cache on (`scheimflux._cache`: the folder is
`~/.cache/scheimflux/jax`, `SCHEIMFLUX_CACHE_DIR` overrides it, `SCHEIMFLUX_CACHE_DIR=off`
switches it off).
"""

import importlib.metadata

from . import _cache

_cache.enable_x64()
_cache.enable_compilation_cache()

from . import (
    camera as camera,
    geometry as geometry,
    io as io,
    reconstruct as reconstruct,
    stripe as stripe,
    targets as targets,
)
from ._presets import (
    paper_laser_plane as paper_laser_plane,
    paper_pinhole as paper_pinhole,
    paper_stage as paper_stage,
    paper_thick_lens as paper_thick_lens,
)

# `sf.calibrate` is the function (bound after the subpackage is imported, so it stays the
# function whatever is imported later); the subpackage stays `scheimflux.calibrate` for
# `from scheimflux.calibrate import X`. See docs/api.md.
from .calibrate import (
    Calibration as Calibration,
    calibrate as calibrate,
    calibrate_camera as calibrate_camera,
    calibrate_stage as calibrate_stage,
    cross_validate as cross_validate,
    diagnostics as diagnostics,
    fit_laser_plane as fit_laser_plane,
)
from .camera import (
    AbstractCamera as AbstractCamera,
    Pinhole as Pinhole,
    Ray as Ray,
    ThickLensScheimpflug as ThickLensScheimpflug,
)
from .geometry import LaserPlane as LaserPlane, Pose as Pose, RotaryStage as RotaryStage
from .io import (
    Observations as Observations,
    read_calibration as read_calibration,
    read_observations as read_observations,
    write_calibration as write_calibration,
    write_observations as write_observations,
    write_points as write_points,
)
from .reconstruct import (
    Reconstruction as Reconstruction,
    Status as Status,
    stripe_to_camera as stripe_to_camera,
    stripe_to_measurement as stripe_to_measurement,
)
from .stripe import (
    StripeResult as StripeResult,
    extract_stripe as extract_stripe,
    extract_stripes as extract_stripes,
)
from .targets import Checkerboard as Checkerboard, detect_checkerboard as detect_checkerboard

__version__ = importlib.metadata.version("scheimflux")

# Imported on first use (import time, issue 14): these subpackages pull in SciPy, the
# renderer and optimistix's solvers, which `import scheimflux` does not need.
_LAZY_MODULES = ("capture", "export", "metrology", "simulate")
_LAZY_NAMES = {"fit_cylinder": "metrology", "fit_plane": "metrology", "step_height": "metrology"}


def __getattr__(name: str):
    import importlib

    if name in _LAZY_MODULES:
        return importlib.import_module(f".{name}", __name__)
    if name in _LAZY_NAMES:
        return getattr(importlib.import_module(f".{_LAZY_NAMES[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY_MODULES) | set(_LAZY_NAMES))
