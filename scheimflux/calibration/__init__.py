"""Calibration of camera, laser plane and rotary stage — separately and jointly, as one
parameter pytree solved by optimistix Levenberg–Marquardt with autodiff Jacobians.

Two subpackages and the workflow above them: `core` solves (residual blocks, the
parameter pytree, the LM solver and its linear algebra, initialisation, the camera,
plane and stage steps), `trust` judges what was solved (quality gates, covariance,
uncertainty, warnings, summaries); `calibrate`, `cross_validate` and the calibration
file (`read_calibration`, `write_calibration`) use both. See docs/architecture.md.
"""

from ._calibrate import calibrate as calibrate
from ._cross_validate import CrossValidation as CrossValidation, cross_validate as cross_validate
from ._file import (
    calibration_to_dict as calibration_to_dict,
    parse_calibration as parse_calibration,
    read_calibration as read_calibration,
    write_calibration as write_calibration,
)
from ._summary import calibration_summary as calibration_summary
from .core._camera import (
    DEFAULT_FREEZE as DEFAULT_FREEZE,
    DISTORTIONS as DISTORTIONS,
    MODELS as MODELS,
    CameraCalibration as CameraCalibration,
    calibrate_camera as calibrate_camera,
    pixel_footprint_mm as pixel_footprint_mm,
)
from .core._compare import (
    compare_with_opencv as compare_with_opencv,
    opencv_calibrate as opencv_calibrate,
)
from .core._init import with_nominal as with_nominal
from .core._model import (
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
from .core._opencv import (
    OPENCV_FLAGS as OPENCV_FLAGS,
    cv2_calibration_flags as cv2_calibration_flags,
    opencv_frozen as opencv_frozen,
)
from .core._plane import (
    PlaneFit as PlaneFit,
    board_stripe_points as board_stripe_points,
    fit_laser_plane as fit_laser_plane,
    fit_plane_tls as fit_plane_tls,
)
from .core._result import (
    Calibration as Calibration,
    MissingObservations as MissingObservations,
)
from .core._screen import screen_field as screen_field, screen_observations as screen_observations
from .core._solve import (
    Fit as Fit,
    NotConvergedError as NotConvergedError,
    RankDeficientError as RankDeficientError,
    free_spec as free_spec,
    jacobian as jacobian,
    least_squares as least_squares,
    parameter_labels as parameter_labels,
    refine as refine,
)
from .core._stage import (
    StageCalibration as StageCalibration,
    StageInit as StageInit,
    calibrate_stage as calibrate_stage,
    initial_stage as initial_stage,
)
from .core._stage_target import (
    axis_from_poses as axis_from_poses,
    stage_from_axis as stage_from_axis,
)
from .trust._covariance import (
    Diagnostics as Diagnostics,
    residual_function as residual_function,
)
from .trust._diagnostics import diagnostics as diagnostics
from .trust._gates import (
    Gate as Gate,
    Quality as Quality,
    QualityError as QualityError,
)
from .trust._plots import plot_residuals as plot_residuals, residual_map as residual_map
from .trust._summary import (
    format_summary as format_summary,
    format_trust as format_trust,
    trust_entries as trust_entries,
)
from .trust._uncertainty import (
    fit_diagnostics as fit_diagnostics,
    length_uncertainty as length_uncertainty,
    point_uncertainty as point_uncertainty,
)

__all__ = [
    "axis_from_poses",
    "board_stripe_points",
    "calibrate",
    "calibrate_camera",
    "calibrate_stage",
    "Calibration",
    "calibration_summary",
    "calibration_to_dict",
    "CalibrationData",
    "camera_plane_residuals",
    "camera_residuals",
    "CameraCalibration",
    "compare_with_opencv",
    "corner_residuals",
    "cross_validate",
    "CrossValidation",
    "cv2_calibration_flags",
    "DEFAULT_FREEZE",
    "Diagnostics",
    "diagnostics",
    "DISTORTIONS",
    "Fit",
    "fit_diagnostics",
    "fit_laser_plane",
    "fit_plane_tls",
    "format_summary",
    "format_trust",
    "free_spec",
    "Gate",
    "gauge_residuals",
    "initial_stage",
    "jacobian",
    "joint_residuals",
    "least_squares",
    "length_uncertainty",
    "make_data",
    "MissingObservations",
    "MODELS",
    "NotConvergedError",
    "opencv_calibrate",
    "OPENCV_FLAGS",
    "opencv_frozen",
    "parameter_labels",
    "parse_calibration",
    "pixel_footprint_mm",
    "PlaneFit",
    "plot_residuals",
    "point_uncertainty",
    "Quality",
    "QualityError",
    "RankDeficientError",
    "read_calibration",
    "refine",
    "residual_function",
    "residual_map",
    "screen_field",
    "screen_observations",
    "stage_from_axis",
    "StageCalibration",
    "StageInit",
    "stripe_residuals",
    "SystemParams",
    "trust_entries",
    "with_nominal",
    "write_calibration",
]
