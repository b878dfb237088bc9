"""Measure from stripe pixels with a calibration: the whole chain pixel → 3-D → fit → value,
differentiated end to end (see `_gum.py` for the propagation)."""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from ..calibration import diagnostics as calibration_diagnostics, residual_function
from ._chain import FRAMES, _reconstruct_one
from ._gum import (
    Measurement,
    _check_labels,
    _checked_fit,
    _fit_stats,
    _measurement,
    banded_sum,
    correlation_note,
    lag_correlation,
    point_lines,
)
from ._own_gauge import (
    few_gauge_frames_message,
    frames_on_calibration_gauge,
    is_own_gauge_scan,
    own_gauge_message,
)
from ._shapes import AbstractShape

__all__ = ["measure_stripes"]

@eqx.filter_jit
def _chain_terms(shape, free, static, idx, uv, fi, labels, frame):
    x0, unravel = ravel_pytree(free)
    prm0 = eqx.combine(free, static)

    def points(theta, uv):
        prm = eqx.combine(unravel(x0.at[idx].set(theta)), static)
        return jax.vmap(lambda p, i: _reconstruct_one(prm, p, i, frame)[0])(uv, fi)

    from ._lsq import fit_shape

    def values(theta, uv):
        return fit_shape(shape, points(theta, uv), labels).values

    theta = x0[idx]
    G_theta, G_uv = jax.jacrev(values, argnums=(0, 1))(theta, uv)
    X, status = jax.vmap(lambda p, i: _reconstruct_one(prm0, p, i, frame))(uv, fi)
    J_uv = jax.vmap(jax.jacfwd(lambda p, i: _reconstruct_one(prm0, p, i, frame)[0]))(uv, fi)
    return X, status, G_theta, G_uv, J_uv


@eqx.filter_jit
def _status(params, uv, fi, frame):
    return jax.vmap(lambda p, i: _reconstruct_one(params, p, i, frame))(uv, fi)


@dataclasses.dataclass(frozen=True)
class _JointLabels:
    """The joint problem's free-parameter labels, standing in for its diagnostics where
    the group covariance gives Σ (what `diagnostics` would add, a Jacobian of every
    residual, is then not needed)."""

    labels: list
    block: str = "joint"

    def select(self, prefix) -> np.ndarray:
        return np.array([i for i, lab in enumerate(self.labels) if lab.startswith(prefix)], int)


def _joint_covariance(cal, diag, source, how="groups"):
    from ..calibration.core._model import CalibrationData

    if (
        diag is None and isinstance(how, str) and how == "groups" and "joint" in cal.fits
        and isinstance(getattr(cal, "data", None), CalibrationData)
    ):  # fmt: skip
        from ..calibration.core._solve import parameter_labels

        _, params, spec = residual_function(cal, "joint")
        return _JointLabels(parameter_labels(params, spec))
    if diag is None:
        try:
            diag = calibration_diagnostics(cal, block="joint")
        except ValueError as err:
            raise ValueError(
                f"{source} has no parameter covariance ({err}); the calibration term needs it"
            ) from None
    elif diag.block != "joint":
        raise ValueError("measure_stripes needs the joint diagnostics (diagnostics(cal, "
                         "block='joint'))")
    return diag


def _calibration_covariance(cal, diag, how):
    """`(Σ (p, p) in diag's labels, a note)` for the calibration term."""
    from ..calibration.trust._calcov import GroupCovariance, group_covariance

    if isinstance(how, str) and how == "pooled":
        return diag.covariance, f"variance factor {diag.variance_factor:.3g} pooled"
    if isinstance(how, str) and how == "groups":
        if "joint" not in cal.fits:
            # a sequential estimate is not the joint optimum: its residuals per group are
            # no noise estimate; diagnostics scales by the camera solve's s² instead
            return diag.covariance, (
                f"variance factor {diag.variance_factor:.3g} of the camera solve "
                "(sequential calibration)"
            )
        try:
            how = group_covariance(cal)
        except ValueError as err:  # residual groups not known for this solve
            if isinstance(diag, _JointLabels):
                diag = _joint_covariance(cal, None, "the calibration", "pooled")
            return diag.covariance, (
                f"variance factor {diag.variance_factor:.3g} pooled ({err})"
            )
    if not isinstance(how, GroupCovariance):
        raise ValueError(
            "calibration_covariance must be 'groups', 'pooled' or a GroupCovariance, got "
            f"{how!r}"
        )
    if how.covariance.shape != (len(diag.labels),) * 2:
        raise ValueError("calibration_covariance does not match the calibration's parameters")
    if how.weighting == "pixels":
        noise = ", ".join(f"{g} {np.sqrt(v):.3g} px" for g, v in how.variance_factors.items())
        tau = getattr(how, "correlation_time", {}) or {}
        corr = ", ".join(f"{g} x{t:.3g}" for g, t in tau.items())
        return how.covariance, f"pixel noise from the residuals: {noise}" + (
            f"; neighbouring centres correlate, variance {corr}" if corr else ""
        )
    factors = ", ".join(f"{g} {v:.3g}" for g, v in how.variance_factors.items())
    return how.covariance, f"variance factors {factors}"


def measure_stripes(
    cal,
    uv,
    shape: AbstractShape,
    *,
    frame: str = "camera",
    frame_index=None,
    labels=None,
    sigma_px: float | None = None,
    diag=None,
    frozen_sigma: dict | str | None = "nominal",
    calibration_covariance="groups",
    source: str = "the calibration",
) -> Measurement:
    """Measure a shape from stripe pixels with the full GUM budget.

    Reconstructs the pixels with the calibration (camera frame, or the measurement frame
    through the rotary stage), fits `shape`, and propagates the calibration's covariance,
    the pixels' noise and the fit residual to the values (see `_gum.py`), with the
    covariance between all points.

    **Arguments:**
    - `cal`: a `Calibration` with a laser plane, and its observations (a calibration read
      from a file needs `read_calibration(path, observations=OBS)`: the covariance is
      computed from them).
    - `uv`: stripe pixels `(N, 2)`; pixels that give no point (NaN, ray misses the plane)
      are left out, with their labels.
    - `frame`, `frame_index`: `"measurement"` needs a stage and the frame number of each
      pixel (`(N,)` or a scalar).
    - `labels`: `(N,)` face per pixel for [`Steps`][].
    - `sigma_px`: the stripe centres' noise (px per coordinate); None: not evaluated (the
      fit residual term then carries it).
    - `diag`: precomputed `diagnostics(cal, block="joint")`.
    - `frozen_sigma`: standard uncertainty (mm, rad, px) of parameters the calibration
      held fixed, `{"camera.f": 0.3, ...}`, propagated with the calibration re-solved to
      first order (`_frozen.py`); `"nominal"` (default): `nominal_tolerances(cal)`, the
      rounding of the nominal f (1 mm) and tilt (1°); None: not evaluated.
    - `calibration_covariance`: `"groups"` (default): the calibration parameters'
      covariance with one variance factor per kind of residual (corners, board stripes,
      gauge scan; [`group_covariance`][], `_calcov.py`), or a precomputed
      [`GroupCovariance`][] of `cal` (to measure many times with one calibration);
      `"pooled"`: `diag.covariance`, one variance factor for all residuals (understates
      what the corners determine when the stripe residuals scatter less than their σ).

    **Returns:** a [`Measurement`][] with `sensitivity` (∂values/∂θ). **Raises:**
    `ValueError` (one line) for a calibration without laser plane, stage or covariance,
    too few valid points, degenerate geometry or a fit that did not converge.
    """
    if frame not in FRAMES:
        raise ValueError(f"frame must be 'camera' or 'measurement', got {frame!r}")
    if sigma_px is not None and not (math.isfinite(sigma_px) and sigma_px >= 0):
        raise ValueError(f"sigma_px must be a number >= 0, got {sigma_px}")
    if cal.params.plane is None:
        raise ValueError(f"{source} has no laser plane: nothing to reconstruct")
    if frame == "measurement" and cal.params.stage is None:
        raise ValueError(f"{source} has no rotary stage: no measurement frame")
    uv = np.asarray(uv, dtype=np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"uv must have shape (N, 2), got {uv.shape}")
    n = len(uv)
    lab = _check_labels(shape, n, labels)
    if frame_index is None:
        if frame == "measurement":
            raise ValueError("frame='measurement' needs frame_index (the frame of each pixel)")
        frame_index = 0
    fi = np.broadcast_to(np.asarray(frame_index, dtype=np.float64), (n,)).copy()
    own = frames_on_calibration_gauge(cal, uv, fi)
    diag = _joint_covariance(cal, diag, source, calibration_covariance)
    _, params, spec = residual_function(cal, "joint")
    prefixes = ("camera.", "plane.") + (("stage.",) if frame == "measurement" else ())
    idx = diag.select(prefixes)
    free, static = eqx.partition(params, spec)
    if ravel_pytree(free)[0].size != len(diag.labels):
        raise ValueError("the diagnostics do not match the calibration's free parameters")

    _, status = _status(params, jnp.asarray(uv), jnp.asarray(fi), frame)
    keep = np.asarray(status) == 0
    if not keep.any():
        raise ValueError(f"no stripe pixel of {n} gives a point with {source}")
    uv, fi, lab = uv[keep], fi[keep], lab[keep]
    X, _, G_theta, G_uv, J_uv = _chain_terms(
        shape, free, static, jnp.asarray(idx, jnp.int32), jnp.asarray(uv), jnp.asarray(fi),
        jnp.asarray(lab), frame,
    )
    X = np.asarray(X)
    shape.check(X, lab)
    fit, gX, normals = _checked_fit(shape, X, lab)

    G_theta, G_uv, J_uv = np.asarray(G_theta), np.asarray(G_uv), np.asarray(J_uv)
    S_all, cov_note = _calibration_covariance(cal, diag, calibration_covariance)
    S = S_all[np.ix_(idx, idx)]
    terms = {"calibration": G_theta @ S @ G_theta.T}
    notes = []
    held = [p for p in tuple(cal.freeze) if p.split(".")[0] in ("camera", "plane", "stage")]
    if isinstance(frozen_sigma, str):
        if frozen_sigma != "nominal":
            raise ValueError(
                f"frozen_sigma must be a dict, 'nominal' or None, got {frozen_sigma!r}"
            )
        from ._frozen import nominal_tolerances

        frozen_sigma = nominal_tolerances(cal)
    if frozen_sigma is None:
        notes.append(f"held parameters ({', '.join(held) or 'none'}) count as exact "
                     "(frozen_sigma not given)")
    else:
        from ._frozen import frozen_derivatives

        sig = {p: float(s) for p, s in frozen_sigma.items()}
        bad = [p for p, s in sig.items() if not (math.isfinite(s) and s >= 0)]
        if bad:
            raise ValueError(f"frozen_sigma[{bad[0]!r}] must be a number >= 0")
        paths = [p for p, s in sig.items() if s > 0]
        if paths:
            D = frozen_derivatives(cal, shape, uv, fi, lab, frame, paths, source)
            Ds = D * np.array([sig[p] for p in paths])[None, :]
            terms["frozen_parameters"] = Ds @ Ds.T
        else:
            terms["frozen_parameters"] = np.zeros((len(shape.names),) * 2)
        exact = [p for p in held if sig.get(p, 0.0) == 0.0]
        notes.append(
            "held parameters: "
            + ", ".join(f"{p} σ {sig[p]:.3g}" for p in paths)
            + (f"; counted exact: {', '.join(exact)}" if exact else "")
        )
    s2_px = 0.0
    lines = point_lines(X, fi, lab)
    rho = lag_correlation(fit.residuals, lines) if shape.n_params() else np.zeros(0)
    if sigma_px is not None:
        terms["stripe_noise"] = sigma_px**2 * banded_sum(G_uv, rho, lines)
        if shape.n_params():
            rj = np.einsum("nmj,nji->nmi", normals, J_uv)  # ∂r/∂uv per point
            s2_px = sigma_px**2 * float(np.mean(np.sum(rj * rj, axis=2)))
    else:
        notes.append("stripe noise not evaluated (no sigma_px): the fit residual carries it")
    C_fit, stats = _fit_stats(shape, fit, normals, gX, s2_px, rho, lines)
    terms["fit_residual"] = C_fit
    if (note := correlation_note(rho)) is not None:
        notes.append(note)
    if n - int(keep.sum()):
        notes.append(f"{n - int(keep.sum())} of {n} pixels gave no point and were left out")
    cov = getattr(cal, "coverage", None)
    if cov is None:
        notes.append("coverage of the sensor by calibration data unknown")
    else:
        n_out = int(np.sum(~np.asarray(cov.contains(uv))))
        if n_out:
            notes.append(
                f"{n_out} of {len(uv)} pixels lie outside the calibration's coverage: the "
                "model extrapolates there, and its error is not in the budget"
            )
    n_frames = len(np.unique(fi))
    if is_own_gauge_scan(own, n_frames):  # first: it says what the value means
        notes.insert(0, own_gauge_message(cal, own, n_frames))
    elif own:
        notes.append(few_gauge_frames_message(own, n_frames))
    notes.append(
        f"calibration: covariance of {len(idx)} {'/'.join(p.rstrip('.') for p in prefixes)} "
        f"parameters ({diag.block} solve, {cov_note})"
    )
    sens = {"labels": [diag.labels[i] for i in idx], "d_values": G_theta}
    return _measurement(shape, fit, terms, stats, sens, notes)
