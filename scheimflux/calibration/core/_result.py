"""The result of a calibration: the one parameter pytree and how it was obtained."""

from __future__ import annotations

import dataclasses

import numpy as np

from ...geometry._plane import LaserPlane
from ...geometry._stage import RotaryStage
from ._model import CalibrationData, SystemParams


class MissingObservations:
    """Stands in for `Calibration.data` when a file was read without its observations.

    Any use says what to do instead of failing somewhere deep in a solver.
    """

    def __init__(self, source: str):
        self.source = source

    def __getattr__(self, name):
        if name.startswith("__"):
            raise AttributeError(name)
        raise ValueError(
            f"{self.source} was read without its observations: residuals, diagnostics and "
            "refinement need them (read_calibration(path, observations=OBS))"
        )

    def __repr__(self) -> str:
        # shown by type checkers that stop it before use: say what to do there too
        return (
            f"MissingObservations({self.source!r}: read without its observations; use "
            "read_calibration(path, observations=OBS))"
        )


@dataclasses.dataclass(frozen=True)
class Calibration:
    """A complete calibration: the one parameter pytree and how it was obtained.

    **Fields:**
    - `params`: `SystemParams` (camera, board poses, laser plane, stage, eccentricity).
    - `model`: `"thick-lens"`, `"pinhole"` or `"opencv"`; `init`: how the camera was
      initialised.
    - `fits`: the LM solves by stage (`"camera"`, `"stage"`, `"joint"`).
    - `freeze`: the parameter paths held fixed.
    - `reprojection_rms_px`, `plane_rms_mm` (None for a camera-only calibration),
      `gauge_rms_mm` (None without a stage scan).
    - `data`: the arrays the residuals were computed from; for a calibration read from a
      file without its observations, a `MissingObservations` that says so when used.
    - `sensor_size`: `(width, height)` in px; None for a file that does not record it.
    - `coverage`: the sensor region the calibration data covered (`Coverage`), None
      when unknown (no sensor size, or a file written before coverage was recorded).
    - `axis_profile`: with `gauge="profile"`, where the profile of the cost placed the
      axis point (`_gauge.AxisProfile`: value, σ, converged, at_bound); else None.

    - `diagnostics`: read from a file, the file's diagnostics (σ, warnings, gates, … as
      written); `{}` for a calibration computed in this process.
    - `raw`: read from a file, the whole decoded document; else None.

    A camera-only calibration (no stripe pixels on the boards) has `plane = None`
    (`camera_only` is True): it serves OpenCV export and camera studies, not
    reconstruction.
    """

    params: SystemParams
    model: str
    distortion: str
    init: str
    joint: bool
    fits: dict
    freeze: tuple
    reprojection_rms_px: float
    plane_rms_mm: float | None
    gauge_rms_mm: float | None
    data: CalibrationData | MissingObservations
    sensor_size: tuple[int, int] | None = (0, 0)  # (width, height) px
    # gates, rejected observations, warnings: a `trust.Quality` (set by the quality gates)
    quality: object | None = None
    # observations left out by the rejection pass: index arrays (view, corner),
    # (view, stripe point), (frame, gauge point) into the screened observations
    left_out: dict | None = None
    # sensor region covered by calibration data: a `trust.Coverage`
    coverage: object | None = None
    # `gauge="profile"`: where the profile placed the axis point (`_gauge.AxisProfile`)
    axis_profile: object | None = None
    diagnostics: dict = dataclasses.field(default_factory=dict)  # a file's, as read
    raw: dict | None = None  # the decoded file it was read from

    @property
    def converged(self) -> bool:
        """Whether every solve converged (for a calibration read from a file: as the file
        records it)."""
        return all(bool(f.converged) for f in self.fits.values()) and bool(
            self.diagnostics.get("converged", True)
        )

    @property
    def eccentricity_mm(self) -> np.ndarray | None:
        """The gauge axis's offset from the table axis `(2,)` mm, or None."""
        e = self.params.eccentricity
        return None if e is None else np.asarray(e, dtype=np.float64)

    @property
    def camera_only(self) -> bool:
        """True when there is no laser plane (no stripe pixels on the boards)."""
        return self.params.plane is None

    @property
    def camera(self):
        return self.params.camera

    @property
    def plane(self) -> LaserPlane | None:
        return self.params.plane

    @property
    def stage(self) -> RotaryStage | None:
        return self.params.stage
