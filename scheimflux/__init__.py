"""scheimflux: thick-lens Scheimpflug camera calibration and laser-line 3-D measurement.

Importing scheimflux switches JAX to 64-bit floats (metrology needs them; set the
environment variable `SCHEIMFLUX_NO_X64=1` before importing to keep JAX's default) and
switches JAX's persistent compilation cache on (`scheimflux._cache`: the folder is
`~/.cache/scheimflux/jax`, `SCHEIMFLUX_CACHE_DIR` overrides it, `SCHEIMFLUX_CACHE_DIR=off`
switches it off).

`import scheimflux` itself imports neither JAX nor NumPy (import time, issues 13 and 14):
every public name (`sf.ThickLensScheimpflug`, `sf.stripe_to_camera`, `sf.calibrate`, ...)
is imported from its home module on first use (PEP 562). The two JAX settings above are
applied before that, through JAX's environment variables when JAX is not imported yet
(JAX reads them when it is first imported) and through `jax.config` when it is.
"""

from __future__ import annotations

import importlib
import sys
from typing import TYPE_CHECKING

from . import _cache

_cache.enable_x64()
_cache.enable_compilation_cache()

# Public name → home module (relative to this package). Subpackages map to themselves.
_SUBPACKAGES = (
    "calibration",
    "camera",
    "capture",
    "export",
    "geometry",
    "io",
    "metrology",
    "reconstruct",
    "simulate",
    "stripe",
    "targets",
)
_NAMES = {
    "paper_laser_plane": "_presets",
    "paper_pinhole": "_presets",
    "paper_stage": "_presets",
    "paper_thick_lens": "_presets",
    "Calibration": "calibration",
    "calibrate": "calibration",
    "calibrate_camera": "calibration",
    "calibrate_stage": "calibration",
    "cross_validate": "calibration",
    "diagnostics": "calibration",
    "fit_laser_plane": "calibration",
    "AbstractCamera": "camera",
    "Pinhole": "camera",
    "Ray": "camera",
    "ThickLensScheimpflug": "camera",
    "LaserPlane": "geometry",
    "Pose": "geometry",
    "RotaryStage": "geometry",
    "Observations": "io",
    "read_calibration": "calibration",
    "read_observations": "io",
    "write_calibration": "calibration",
    "write_observations": "io",
    "write_points": "io",
    "Reconstruction": "reconstruct",
    "Status": "reconstruct",
    "stripe_to_camera": "reconstruct",
    "stripe_to_measurement": "reconstruct",
    "StripeResult": "stripe",
    "extract_stripe": "stripe",
    "extract_stripes": "stripe",
    "Checkerboard": "targets",
    "detect_checkerboard": "targets",
    "fit_cylinder": "metrology",
    "fit_plane": "metrology",
    "step_height": "metrology",
}

__all__ = sorted({*_SUBPACKAGES, *_NAMES, "__version__"})


def __getattr__(name: str):
    if name in _SUBPACKAGES:
        return importlib.import_module(f".{name}", __name__)
    if name in _NAMES:
        value = getattr(importlib.import_module(f".{_NAMES[name]}", __name__), name)
        globals()[name] = value  # later look-ups skip this function
        return value
    if name == "__version__":
        from importlib import metadata

        value = metadata.version("scheimflux")
        globals()[name] = value
        return value
    # name= and obj= let Python suggest a close public name ("Did you mean: ...?")
    raise AttributeError(
        f"module {__name__!r} has no attribute {name!r}", name=name, obj=sys.modules[__name__]
    )


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


if TYPE_CHECKING:  # what a type checker and an IDE see; never run
    from . import (
        calibration as calibration,
        camera as camera,
        capture as capture,
        export as export,
        geometry as geometry,
        io as io,
        metrology as metrology,
        reconstruct as reconstruct,
        simulate as simulate,
        stripe as stripe,
        targets as targets,
    )
    from ._presets import (
        paper_laser_plane as paper_laser_plane,
        paper_pinhole as paper_pinhole,
        paper_stage as paper_stage,
        paper_thick_lens as paper_thick_lens,
    )
    from .calibration import (
        Calibration as Calibration,
        calibrate as calibrate,
        calibrate_camera as calibrate_camera,
        calibrate_stage as calibrate_stage,
        cross_validate as cross_validate,
        diagnostics as diagnostics,
        fit_laser_plane as fit_laser_plane,
        read_calibration as read_calibration,
        write_calibration as write_calibration,
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
        read_observations as read_observations,
        write_observations as write_observations,
        write_points as write_points,
    )
    from .metrology import (
        fit_cylinder as fit_cylinder,
        fit_plane as fit_plane,
        step_height as step_height,
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
