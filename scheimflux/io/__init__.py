"""Files users exchange: observations, calibrations, stripes, point clouds.

This package only serialises: it reads and writes files as values (a calibration file as
a `CalibrationDocument`); `scheimflux.read_calibration` / `write_calibration` turn a
`Calibration` into its file and back."""

from ._calibration import (
    CalibrationDocument as CalibrationDocument,
    CalibrationFileError as CalibrationFileError,
    UnconvergedCalibrationWarning as UnconvergedCalibrationWarning,
    parse_calibration_document as parse_calibration_document,
    read_calibration_document as read_calibration_document,
    write_calibration_document as write_calibration_document,
)
from ._observations import (
    DroppedView as DroppedView,
    Nominal as Nominal,
    Observations as Observations,
    ObservationsError as ObservationsError,
    StageScan as StageScan,
    StageTargetViews as StageTargetViews,
    View as View,
    read_observations as read_observations,
    write_observations as write_observations,
)
from ._opencv_yaml import (
    read_opencv_yaml as read_opencv_yaml,
    write_opencv_yaml as write_opencv_yaml,
)
from ._pointcloud import (
    open_points_writer as open_points_writer,
    read_ply as read_ply,
    read_points_parquet as read_points_parquet,
    write_ply as write_ply,
    write_points as write_points,
)
from ._stripes import (
    iter_stripes as iter_stripes,
    read_stripes as read_stripes,
    write_stripes as write_stripes,
)

__all__ = [
    "CalibrationDocument",
    "CalibrationFileError",
    "DroppedView",
    "iter_stripes",
    "Nominal",
    "Observations",
    "ObservationsError",
    "open_points_writer",
    "parse_calibration_document",
    "read_calibration_document",
    "read_observations",
    "read_opencv_yaml",
    "read_ply",
    "read_points_parquet",
    "read_stripes",
    "StageScan",
    "StageTargetViews",
    "UnconvergedCalibrationWarning",
    "View",
    "write_calibration_document",
    "write_observations",
    "write_opencv_yaml",
    "write_ply",
    "write_points",
    "write_stripes",
]
