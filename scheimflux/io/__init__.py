"""Files users exchange: observations, calibrations, stripes, point clouds."""

from ._observations import (
    Nominal as Nominal,
    Observations as Observations,
    ObservationsError as ObservationsError,
    StageScan as StageScan,
    View as View,
    read_observations as read_observations,
    write_observations as write_observations,
)
from ._opencv_yaml import (
    read_opencv_yaml as read_opencv_yaml,
    write_opencv_yaml as write_opencv_yaml,
)
from ._stripes import read_stripes as read_stripes, write_stripes as write_stripes
