"""Metrology: geometric fits of measured point clouds (plane, circle, cylinder, step)."""

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
