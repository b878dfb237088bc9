"""The result of a calibration: the one parameter pytree and how it was obtained."""

from __future__ import annotations

import dataclasses

from ..geometry._plane import LaserPlane
from ..geometry._stage import RotaryStage
from ._coverage import Coverage
from ._gates import Quality
from ._model import CalibrationData, SystemParams


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
    - `data`: the arrays the residuals were computed from.
    - `sensor_size`: `(width, height)` in px.
    - `coverage`: the sensor region the calibration data covered (`Coverage`), None
      when unknown (no sensor size, or a file written before coverage was recorded).
    - `axis_profile`: with `gauge="profile"`, where the profile of the cost placed the
      axis point (`_gauge.AxisProfile`: value, σ, converged, at_bound); else None.

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
    data: CalibrationData
    sensor_size: tuple[int, int] = (0, 0)  # (width, height) px
    quality: Quality | None = None  # gates, rejected observations, warnings
    # observations left out by the rejection pass: index arrays (view, corner),
    # (view, stripe point), (frame, gauge point) into the screened observations
    left_out: dict | None = None
    coverage: Coverage | None = None  # sensor region covered by calibration data
    # `gauge="profile"`: where the profile placed the axis point (`_gauge.AxisProfile`)
    axis_profile: object | None = None

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
