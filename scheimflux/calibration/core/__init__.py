"""The calibration's core: residual blocks, the one parameter pytree, the
Levenberg–Marquardt solver and its block linear algebra, initialisation, and the camera,
laser-plane and stage steps. Nothing here judges a result (that is `..trust`)."""

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
from ._init import (
    with_nominal as with_nominal,
)
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
from ._result import (
    Calibration as Calibration,
    MissingObservations as MissingObservations,
)
from ._screen import (
    screen_field as screen_field,
    screen_observations as screen_observations,
)
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

__all__ = [
    "axis_from_poses",
    "board_stripe_points",
    "calibrate_camera",
    "calibrate_stage",
    "Calibration",
    "CalibrationData",
    "camera_plane_residuals",
    "camera_residuals",
    "CameraCalibration",
    "compare_with_opencv",
    "corner_residuals",
    "cv2_calibration_flags",
    "DEFAULT_FREEZE",
    "DISTORTIONS",
    "Fit",
    "fit_laser_plane",
    "fit_plane_tls",
    "free_spec",
    "gauge_residuals",
    "initial_stage",
    "jacobian",
    "joint_residuals",
    "least_squares",
    "make_data",
    "MissingObservations",
    "MODELS",
    "NotConvergedError",
    "opencv_calibrate",
    "OPENCV_FLAGS",
    "opencv_frozen",
    "parameter_labels",
    "pixel_footprint_mm",
    "PlaneFit",
    "RankDeficientError",
    "refine",
    "screen_field",
    "screen_observations",
    "stage_from_axis",
    "StageCalibration",
    "StageInit",
    "stripe_residuals",
    "SystemParams",
    "with_nominal",
]
