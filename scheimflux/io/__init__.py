"""Files users exchange: observations, calibrations, stripes, point clouds."""

from ._calibration import (
    CalibrationFileError as CalibrationFileError,
    UnconvergedCalibrationWarning as UnconvergedCalibrationWarning,
    calibration_to_dict as calibration_to_dict,
    parse_calibration as parse_calibration,
    read_calibration as read_calibration,
    write_calibration as write_calibration,
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


def __getattr__(name):
    # `LoadedCalibration` subclasses `scheimflux.calibrate.Calibration` (which imports
    # this package): resolved on first use.
    if name == "LoadedCalibration":
        from ..calibrate._loaded import LoadedCalibration

        return LoadedCalibration
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
