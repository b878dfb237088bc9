"""Calibration of camera, laser plane and rotary stage — separately and jointly, as one
parameter pytree solved by optimistix Levenberg–Marquardt with autodiff Jacobians."""

from ._calibrate import calibrate as calibrate
from ._camera import (
    DEFAULT_FREEZE as DEFAULT_FREEZE,
    DISTORTIONS as DISTORTIONS,
    MODELS as MODELS,
    CameraCalibration as CameraCalibration,
    calibrate_camera as calibrate_camera,
    pixel_footprint_mm as pixel_footprint_mm,
)
from ._compare import (
    compare_with_opencv as compare_with_opencv,
    opencv_calibrate as opencv_calibrate,
)
from ._covariance import (
    Diagnostics as Diagnostics,
    diagnostics as diagnostics,
    residual_function as residual_function,
)
from ._cross_validate import CrossValidation as CrossValidation, cross_validate as cross_validate
from ._gates import (
    Gate as Gate,
    Quality as Quality,
    QualityError as QualityError,
    screen_field as screen_field,
    screen_observations as screen_observations,
)
from ._init import with_nominal as with_nominal
from ._loaded import LoadedCalibration as LoadedCalibration
from ._model import (
    CalibrationData as CalibrationData,
    SystemParams as SystemParams,
    camera_plane_residuals as camera_plane_residuals,
    camera_residuals as camera_residuals,
    corner_residuals as corner_residuals,
    gauge_residuals as gauge_residuals,
    joint_residuals as joint_residuals,
    make_data as make_data,
    stripe_residuals as stripe_residuals,
)
from ._opencv import (
    OPENCV_FLAGS as OPENCV_FLAGS,
    cv2_calibration_flags as cv2_calibration_flags,
    opencv_frozen as opencv_frozen,
)
from ._plane import (
    PlaneFit as PlaneFit,
    board_stripe_points as board_stripe_points,
    fit_laser_plane as fit_laser_plane,
    fit_plane_tls as fit_plane_tls,
)
from ._plots import plot_residuals as plot_residuals, residual_map as residual_map
from ._result import Calibration as Calibration
from ._solve import (
    Fit as Fit,
    NotConvergedError as NotConvergedError,
    RankDeficientError as RankDeficientError,
    free_spec as free_spec,
    jacobian as jacobian,
    least_squares as least_squares,
    parameter_labels as parameter_labels,
    refine as refine,
)
from ._stage import (
    StageCalibration as StageCalibration,
    StageInit as StageInit,
    calibrate_stage as calibrate_stage,
    initial_stage as initial_stage,
)
from ._stage_target import (
    axis_from_poses as axis_from_poses,
    stage_from_axis as stage_from_axis,
)
from ._summary import (
    calibration_summary as calibration_summary,
    format_summary as format_summary,
    format_trust as format_trust,
    trust_entries as trust_entries,
)
from ._uncertainty import (
    fit_diagnostics as fit_diagnostics,
    length_uncertainty as length_uncertainty,
    point_uncertainty as point_uncertainty,
)
