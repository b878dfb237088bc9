"""What a calibration can be trusted for: quality gates, parameter covariance and
uncertainty of measured points and lengths, identifiability warnings, the calibration
covariance that metrology propagates, residual plots and summaries."""

from ._calcov import (
    GroupCovariance as GroupCovariance,
    correlated_groups as correlated_groups,
    group_covariance as group_covariance,
    raise_covariance as raise_covariance,
    sandwich_covariance as sandwich_covariance,
)
from ._covariance import (
    Diagnostics as Diagnostics,
    residual_function as residual_function,
)
from ._diagnostics import diagnostics as diagnostics
from ._gates import (
    Gate as Gate,
    Quality as Quality,
    QualityError as QualityError,
)
from ._plots import (
    plot_residuals as plot_residuals,
    residual_map as residual_map,
)
from ._quality import assess_quality as assess_quality
from ._stage_warning import (
    AxisConditioning as AxisConditioning,
    axis_conditioning as axis_conditioning,
)
from ._summary import (
    format_summary as format_summary,
    format_trust as format_trust,
    trust_entries as trust_entries,
)
from ._uncertainty import (
    fit_diagnostics as fit_diagnostics,
    length_uncertainty as length_uncertainty,
    point_uncertainty as point_uncertainty,
)

__all__ = [
    "assess_quality",
    "axis_conditioning",
    "AxisConditioning",
    "correlated_groups",
    "Diagnostics",
    "diagnostics",
    "fit_diagnostics",
    "format_summary",
    "format_trust",
    "Gate",
    "group_covariance",
    "GroupCovariance",
    "length_uncertainty",
    "plot_residuals",
    "point_uncertainty",
    "Quality",
    "QualityError",
    "raise_covariance",
    "residual_function",
    "residual_map",
    "sandwich_covariance",
    "trust_entries",
]
