"""[`diagnostics`][]: what the data determine of a calibration's parameters (σ,
correlations, null directions) and the warnings about them, including the rotary axis's
conditioning (`_stage_warning`)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ...io._observations import Observations
from ..core._camera import CameraCalibration
from ..core._model import camera_residuals, make_data
from ..core._result import Calibration
from ..core._solve import free_spec, jacobian, parameter_labels, split
from ._covariance import (
    NULL_RTOL,
    Diagnostics,
    correlation_warnings,
    covariance_from_jacobian,
    dominant_parameters,
    residual_function,
    std_and_correlation,
)
from ._stage_warning import axis_conditioning, axis_warning, reference_pixels

__all__ = ["diagnostics"]


def diagnostics(
    cal: Calibration | CameraCalibration,
    obs: Observations | None = None,
    *,
    block: str = "auto",
    freeze: Sequence[str] | None = None,
    top: int = 4,
) -> Diagnostics:
    """Standard deviations, correlations and identifiability of a calibration.

    Uses the Jacobian of the final solve's residuals (see [`residual_function`][]) at
    its optimum. A direction whose singular value (column-normalised J) is below
    1e-8 × the largest is reported with the `top` parameters that dominate it.

    **Arguments:**
    - `cal`: a `Calibration`, or a `CameraCalibration` together with the `obs` it was
      computed from (the covariance does not depend on the σ assumed for the corners:
      s² rescales it; a Huber `robust` setting is not known here and is ignored).
    - `obs`: the observations of a `CameraCalibration` (ignored for a `Calibration`,
      which keeps its data).
    - `block`: see [`residual_function`][].
    - `freeze`: analyse the same optimum with these parameter paths held fixed instead
      of the solve's own (e.g. `("camera.dx", "camera.dy")` to see what freeing f and
      the tilt would cost); the paths are relative to `SystemParams`.
    - `top`: how many parameters to name per non-identifiable direction.

    **Returns:** a [`Diagnostics`][] (σ, covariance, correlation, variance factor,
    singular values, null directions and warnings of the free parameters).
    """
    fn, params, spec = residual_function(cal, block)
    if freeze is not None:
        spec = free_spec(params, tuple(freeze))
    if isinstance(cal, CameraCalibration):
        if obs is None:
            raise ValueError("diagnostics of a CameraCalibration need its observations (obs)")
        data = make_data(obs)
        frozen = ()
    else:
        data, frozen = cal.data, tuple(cal.freeze)
    if freeze is not None:
        frozen = tuple(freeze)
    J = jacobian(fn, params, data, spec)
    r = fn(params, data)
    cov, s2, n, s, V = covariance_from_jacobian(J, r)
    if (
        isinstance(cal, Calibration)
        and fn is not camera_residuals
        and "joint" not in cal.fits
        and "camera" in cal.fits
    ):
        # A sequential calibration is not the optimum of the joint problem: its misfit
        # there is no noise estimate. Take the variance factor of the camera solve.
        _, s2_cam, *_ = covariance_from_jacobian(
            jacobian(
                camera_residuals, cal.fits["camera"].params, data, cal.fits["camera"].free_mask
            ),
            cal.fits["camera"].residuals,
        )
        cov, s2 = cov * (s2_cam / s2), s2_cam
    labels = parameter_labels(params, spec)
    x0, _, _ = split(params, spec)
    std, corr = std_and_correlation(cov)
    warnings, nulls = [], []
    smax = s[0] if s.size else 0.0
    for k in np.flatnonzero(s < NULL_RTOL * smax):
        comps = dominant_parameters(labels, V[:, k], top)
        nulls.append((float(s[k] / smax), comps))
        names = ", ".join(f"{lab} ({c:+.2f})" for lab, c in comps)
        warnings.append(
            f"non-identifiable direction (singular value {s[k] / smax:.1e} × max): {names}; "
            "freeze one of these parameters"
        )
    warnings.extend(correlation_warnings(labels, corr))
    if (
        isinstance(cal, Calibration)
        and fn is not camera_residuals
        and getattr(params, "stage", None) is not None
    ):
        if all(cal.sensor_size):
            note = axis_warning(
                axis_conditioning(params, spec, cov, reference_pixels(*cal.sensor_size))
            )
            if note is not None:
                warnings.append(note)
    cond = float(smax / s[-1]) if s.size and s[-1] > 0 else math.inf
    return Diagnostics(
        block="joint" if fn is not camera_residuals else "camera",
        labels=labels,
        values=np.asarray(x0),
        std=std,
        covariance=cov,
        correlation=corr,
        variance_factor=s2,
        n_residuals=n,
        n_params=len(labels),
        singular_values=s,
        condition_number=cond,
        null_directions=nulls,
        warnings=warnings,
        frozen=frozen,
        coverage=getattr(getattr(cal, "coverage", None), "fraction", None),
    )
