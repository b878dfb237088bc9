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
