"""Metrology: differentiable geometric fits (plane, circle, cylinder, sphere, steps,
distance) of reconstructed points, and measured values with their GUM uncertainty."""

from ..calibration.trust._calcov import (
    GroupCovariance as GroupCovariance,
    group_covariance as group_covariance,
    sandwich_covariance as sandwich_covariance,
)
from ._chain import chain_function as chain_function
from ._fits import (
    CircleFit as CircleFit,
    CylinderFit as CylinderFit,
    PlaneFitResult as PlaneFitResult,
    StepHeightResult as StepHeightResult,
    fit_circle_3d as fit_circle_3d,
    fit_cylinder as fit_cylinder,
    fit_plane as fit_plane,
    step_height as step_height,
)
from ._gum import (
    COVERAGE_FACTOR as COVERAGE_FACTOR,
    SOURCES as SOURCES,
    Measurement as Measurement,
    measure_points as measure_points,
)
from ._labels import label_steps as label_steps
from ._lsq import (
    ShapeFit as ShapeFit,
    fit_shape as fit_shape,
    residual_normals as residual_normals,
)
from ._shapes import (
    AbstractShape as AbstractShape,
    Circle as Circle,
    Cylinder as Cylinder,
    Distance as Distance,
    Plane as Plane,
    Sphere as Sphere,
    Steps as Steps,
)
from ._stripes import measure_stripes as measure_stripes

__all__ = [
    "AbstractShape",
    "chain_function",
    "Circle",
    "CircleFit",
    "COVERAGE_FACTOR",
    "Cylinder",
    "CylinderFit",
    "Distance",
    "fit_circle_3d",
    "fit_cylinder",
    "fit_plane",
    "fit_shape",
    "group_covariance",
    "GroupCovariance",
    "label_steps",
    "measure_points",
    "measure_stripes",
    "Measurement",
    "Plane",
    "PlaneFitResult",
    "residual_normals",
    "sandwich_covariance",
    "ShapeFit",
    "SOURCES",
    "Sphere",
    "step_height",
    "StepHeightResult",
    "Steps",
]
