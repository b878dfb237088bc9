"""Metrology: differentiable geometric fits (plane, circle, cylinder, sphere, steps,
distance) of reconstructed points, and measured values with their GUM uncertainty."""

from ._calcov import (
    GroupCovariance as GroupCovariance,
    group_covariance as group_covariance,
    sandwich_covariance as sandwich_covariance,
)
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
from ._stripes import chain_function as chain_function, measure_stripes as measure_stripes
