"""Uncertainty of the calibration's parameters and of what users measure with it.

The parameters' covariance comes from `JᵀJ` at the final solve's optimum, which the
solver already assembles ([`Fit`][]`.normal_matrix`: no extra compilation):

    Σ = s² (JᵀJ)⁺,   s² = |r|² / (n − p)

on the column-scaled matrix, with s² floored at 1 (see [`fit_diagnostics`][]). Where the
stripe centres along a laser line share their errors (the lag correlations of the board-
stripe, gauge or table-stripe residuals, `metrology._calcov.residual_lag_correlation`),
that covariance counts them as independent; the stated one is then raised to the sandwich
covariance that counts the correlation ([`metrology.group_covariance`][], as `measure`
and `verify` use it) wherever that is larger ([`raise_covariance`][]). A
reconstructed point's own σ is relative to the camera
frame, whose placement (above all its depth along the optical axis, which e and z0
share) the data determine poorly; but that placement moves every point alike and cancels
in what users measure: distances, lengths, heights. [`length_uncertainty`][] propagates
the full covariance between points (and the stripe pixels' own noise) to the distance
between two reconstructed points.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ...reconstruct._reconstruct import intersect_ray_plane
from ..core._model import CalibrationData
from ..core._result import Calibration
from ..core._solve import RANK_RTOL, Fit, linearised, parameter_labels, split
from ._calcov import correlated_groups, joint_linearisation, raise_covariance
from ._covariance import (
    Diagnostics,
    correlation_warnings,
    dominant_parameters,
    residual_function,
    std_and_correlation,
)
from ._diagnostics import diagnostics

__all__ = ["fit_diagnostics", "length_uncertainty", "point_uncertainty"]


def _final_fit(cal: Calibration) -> tuple[str, Fit]:
    for name in ("joint", "camera"):
        if name in cal.fits:
            return name, cal.fits[name]
    raise ValueError("the calibration holds no camera or joint solve")


def _normal_equations(cal: Calibration, block: str, fit: Fit):
    """`JᵀJ` of a solve over its free parameters (physical units), their labels and the
    number of observations (residuals of non-zero weight).

    The solver's own, kept at its optimum; a solve read back from a file keeps none, and
    there it is assembled from the Jacobian of the residuals at the stored optimum (the
    same matrix to rounding: the file holds the optimum, the free set and the weights)."""
    if fit.normal_matrix is not None:
        H = np.asarray(fit.normal_matrix, dtype=np.float64)
        return H, list(fit.labels), int(fit.n_observations)
    if not isinstance(getattr(cal, "data", None), CalibrationData):
        raise ValueError(
            f"the {block} solve kept no normal matrix and the calibration holds no "
            "observations: read it with read_calibration(path, observations=OBS)"
        )
    fn, params, spec = residual_function(cal, block)
    if block == "joint":
        _, J, _ = joint_linearisation(cal)
    else:
        _, J, _ = linearised(fn, params, cal.data, spec)
    n = int(np.count_nonzero(np.asarray(fit.residuals)))
    return J.T @ J, parameter_labels(params, spec), n


def fit_diagnostics(cal: Calibration, *, top: int = 4) -> Diagnostics:
    """σ, correlations and identifiability of the final solve, from its `JᵀJ`.

    The same statistics as [`diagnostics`][] (which differentiates the residuals anew),
    computed from the normal matrix the solver kept at its optimum (for a calibration
    read back from its file with its observations, which keeps none, from the residuals'
    Jacobian at the stored optimum). A direction whose
    eigenvalue of the column-scaled `JᵀJ` is below `RANK_RTOL` × the largest is reported
    (with the `top` parameters in it) and left out of Σ.

    The covariance is `max(1, s²) (JᵀJ)⁺`: the stated noise σ, scaled up where the
    residuals show more (s² > 1), never down (`variance_factor` reports s² itself).
    Where the stripe centres along a laser line share their errors ([`correlated_groups`][]),
    it is raised ([`raise_covariance`][]) to the sandwich covariance that counts that
    correlation (`metrology.group_covariance`: each group's own pixel noise, a banded
    residual covariance along the lines) wherever that is larger, never lowered;
    `correlation_time` then holds each correlated group's `τ = 1 + 2 Σ ρ_k`.

    **Returns:** a [`Diagnostics`][] (`covariance` in physical units; `singular_values`
    are the square roots of the scaled eigenvalues).
    """
    block, fit = _final_fit(cal)
    H, labels, n = _normal_equations(cal, block, fit)
    d = np.sqrt(np.clip(np.diag(H), 0.0, None))
    d = np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 1.0)
    lam, V = np.linalg.eigh(H * np.outer(d, d))
    lam, V = lam[::-1], V[:, ::-1]  # descending
    big = max(float(lam[0]), 1e-300) if lam.size else 1.0
    keep = lam > RANK_RTOL * big
    inv = np.where(keep, 1.0 / np.where(keep, lam, 1.0), 0.0)
    p = len(labels)
    s2 = 2.0 * fit.cost / (n - p) if n > p else math.nan
    # Σ = max(1, s²) (JᵀJ)⁺: the stated σ unless the residuals show more noise. s² < 1
    # says only that some block's σ was stated too large, not that every parameter is
    # better determined: on ray-traced data the board-stripe residuals (distance from
    # the board) scatter 4× less than the stated in-plane stripe σ, s² = 0.17, and Σ
    # scaled by it understated the spread of re-solved lengths 2.2× (Monte Carlo).
    cov = max(1.0, s2) * (d[:, None] * ((V * inv) @ V.T) * d[None, :])
    tau = {}
    groups = correlated_groups(cal) if block == "joint" else None
    if groups is not None and groups.covariance.shape == cov.shape:
        # neighbouring stripe centres share their errors: (JᵀJ)⁺ counts them as
        # independent (up to √τ too small for what the lines determine); raise Σ to the
        # sandwich with their banded covariance wherever that is larger. Σ = T Tᵀ with
        # T = d V_k (max(1, s²) / λ_k)^½ on the identifiable directions.
        T = d[:, None] * V[:, keep] * np.sqrt(max(1.0, s2) / lam[keep])[None, :]
        cov = raise_covariance(T, groups.covariance)
        tau = dict(groups.correlation_time)
    std, corr = std_and_correlation(cov)
    warnings, nulls = [], []
    for k in np.flatnonzero(~keep):
        comps = dominant_parameters(labels, V[:, k], top)
        nulls.append((float(lam[k] / big), comps))
        names = ", ".join(f"{lab} ({c:+.2f})" for lab, c in comps)
        warnings.append(f"non-identifiable direction: {names}; freeze one of these parameters")
    warnings.extend(correlation_warnings(labels, corr))
    x0, _, _ = split(fit.params, fit.free_mask)
    sv = np.sqrt(np.clip(lam, 0.0, None))
    return Diagnostics(
        block=block,
        labels=labels,
        values=np.asarray(x0),
        std=std,
        covariance=cov,
        correlation=corr,
        variance_factor=s2,
        n_residuals=n,
        n_params=p,
        singular_values=sv,
        condition_number=float(sv[0] / sv[-1]) if sv.size and sv[-1] > 0 else math.inf,
        null_directions=nulls,
        warnings=warnings,
        frozen=tuple(cal.freeze),
        coverage=getattr(getattr(cal, "coverage", None), "fraction", None),
        correlation_time=tau,
    )


# ----------------------------------------------------------------------------- points


def _point_fn(frame: str):
    def one(params, uv, i):
        X, _ = intersect_ray_plane(params.camera.backproject_one(uv), params.plane)
        if frame == "measurement":
            X = params.stage.to_measurement(X, i)
        return X

    return one


@eqx.filter_jit
def _points_and_jacobian(params, spec, idx, uv, fi, frame):
    one = _point_fn(frame)
    x0, unravel, static = split(params, spec)
    x_sub = x0[idx]

    def f(xs, p, i):
        params = eqx.combine(unravel(x0.at[idx].set(xs)), static)
        return one(params, p, i)

    X = jax.vmap(f, in_axes=(None, 0, 0))(x_sub, uv, fi)
    JX = jax.vmap(jax.jacfwd(f), in_axes=(None, 0, 0))(x_sub, uv, fi)
    return X, JX


def point_uncertainty(
    cal: Calibration,
    uv,
    *,
    frame: str = "camera",
    frame_index=None,
    diag: Diagnostics | None = None,
):
    """Propagate the calibration's covariance to reconstructed stripe points.

    The points are `X(θ, uv)` (ray of each pixel ∩ laser plane, then the stage for
    `frame="measurement"`); θ are the free camera and plane parameters (and the stage
    and eccentricity for the measurement frame). With `Σ_θ` their marginal covariance
    from the joint problem (board poses' uncertainty included) and `J_X = ∂X/∂θ`
    (autodiff), `cov = J_X Σ_θ J_Xᵀ`. This is the calibration error of each point,
    common to every scan; pixel noise of the measured stripe itself adds on top.

    `Σ_θ` is by default the calibration's stated covariance, the one its file, summary
    and [`length_uncertainty`][] use: [`fit_diagnostics`][] of the joint solve
    (`max(1, s²)(JᵀJ)⁺`, raised where the stripe centres along a line share their
    errors). A sequential calibration (`joint=False`) has no joint solve: there it is
    [`diagnostics`][]`(cal, block="joint")`, the joint problem linearised at the
    sequential estimate with the camera solve's s², floored at 1 as the stated
    covariance is.

    The σ is relative to the **camera frame** (its origin at the image-side principal
    point): it is dominated by the frame's poorly determined placement along the optical
    axis (the camera datum that e and z0 share), which moves every point alike and
    cancels in distances and lengths. For what users measure, use
    [`length_uncertainty`][] (covariance between points).

    **Arguments:**
    - `uv`: stripe pixels `(N, 2)`.
    - `frame`: `"camera"` or `"measurement"` (needs a stage and `frame_index`: an
      integer or `(N,)`).
    - `diag`: precomputed diagnostics of the joint problem (`fit_diagnostics(cal)` of a
      joint calibration, or `diagnostics(cal, block="joint")`).

    **Returns:** `(points (N, 3), sigma (N, 3), cov (N, 3, 3))` in mm.
    """
    if frame not in ("camera", "measurement"):
        raise ValueError(f"frame must be 'camera' or 'measurement', got {frame!r}")
    uv = jnp.asarray(np.asarray(uv, dtype=np.float64).reshape(-1, 2))
    fn, params, spec = residual_function(cal, "joint")
    if frame == "measurement":
        if params.stage is None:
            raise ValueError("frame='measurement' needs a calibrated rotary stage")
        if frame_index is None:
            raise ValueError("frame='measurement' needs frame_index")
        fi = jnp.broadcast_to(jnp.asarray(frame_index, dtype=jnp.float64), uv.shape[:1])
        prefixes = ("camera.", "plane.", "stage.", "eccentricity")
    else:
        fi = jnp.zeros(uv.shape[:1], dtype=jnp.float64)
        prefixes = ("camera.", "plane.")
    if diag is None:
        if "joint" in cal.fits:
            diag = fit_diagnostics(cal)
        else:
            # the linearised joint problem with the camera solve's s², floored at 1 as
            # the stated covariance is: residuals that scatter less than the stated σ
            # do not make every parameter better known
            diag = diagnostics(cal, block="joint")
            s2 = diag.variance_factor
            if math.isfinite(s2) and 0 < s2 < 1:
                diag = dataclasses.replace(
                    diag, covariance=diag.covariance / s2, std=diag.std / math.sqrt(s2)
                )
    if diag.block != "joint" or list(diag.labels) != parameter_labels(params, spec):
        raise ValueError(
            "point_uncertainty needs the diagnostics of this calibration's joint problem "
            "(fit_diagnostics(cal) or diagnostics(cal, block='joint'))"
        )
    idx = diag.select(prefixes)
    X, JX = _points_and_jacobian(params, spec, jnp.asarray(idx), uv, fi, frame)
    JX = np.asarray(JX)
    S = diag.covariance[np.ix_(idx, idx)]
    cov = np.einsum("nij,jk,nlk->nil", JX, S, JX)
    sigma = np.sqrt(np.clip(np.einsum("nii->ni", cov), 0.0, None))
    return np.asarray(X), sigma, cov


# ----------------------------------------------------------------------------- lengths


@eqx.filter_jit
def _points_with_jacobians(params, spec, idx, uv):
    """Points `(N, 3)`, `∂X/∂θ` `(N, 3, q)` for the free parameters `idx`, and
    `∂X/∂uv` `(N, 3, 2)` (camera frame)."""
    x0, unravel, static = split(params, spec)

    def point(xs, p):
        prm = eqx.combine(unravel(x0.at[idx].set(xs)), static)
        X, _ = intersect_ray_plane(prm.camera.backproject_one(p), prm.plane)
        return X

    xs = x0[idx]
    X = jax.vmap(point, in_axes=(None, 0))(xs, uv)
    J_theta = jax.vmap(jax.jacfwd(point), in_axes=(None, 0))(xs, uv)
    J_uv = jax.vmap(jax.jacfwd(point, argnums=1), in_axes=(None, 0))(xs, uv)
    return X, J_theta, J_uv


def length_uncertainty(
    cal: Calibration,
    uv_a,
    uv_b,
    *,
    sigma_px: float = 0.0,
    diag: Diagnostics | None = None,
) -> dict:
    """σ of the distance between pairs of reconstructed stripe points (camera frame).

    With θ the free camera and laser-plane parameters, `Σ_θ` their covariance (joint
    solve, board poses marginalised), and `X_a = X(θ, p_a)`, `X_b = X(θ, p_b)`:

        L = |X_a − X_b|,   u = (X_a − X_b) / L,
        σ²_L = uᵀ (J_a − J_b) Σ_θ (J_a − J_b)ᵀ u          (calibration, shared by both)
             + σ²_px (|uᵀ ∂X_a/∂p_a|² + |uᵀ ∂X_b/∂p_b|²)   (each pixel's own noise)

    The calibration term holds the covariance between the two points: what moves both
    alike (the camera datum) cancels. Per-point σ (from [`point_uncertainty`][]) are
    relative to the camera frame and include that datum.

    **Arguments:**
    - `uv_a`, `uv_b`: stripe pixels `(N, 2)` of the two ends of each length.
    - `sigma_px`: the measured stripe pixels' noise (px per coordinate; 0: the
      calibration's part only).
    - `diag`: the parameters' diagnostics (default [`fit_diagnostics`][] of the joint
      solve).

    **Returns:** a dict of `(N,)` arrays (mm): `length`, `sigma` (total),
    `sigma_calibration`, `sigma_pixels`, and the per-point camera-frame σ of each end,
    `point_sigma_a`, `point_sigma_b` `(N, 3)`.
    """
    if cal.params.plane is None:
        raise ValueError("the calibration has no laser plane: nothing to reconstruct")
    uv_a = np.asarray(uv_a, dtype=np.float64).reshape(-1, 2)
    uv_b = np.asarray(uv_b, dtype=np.float64).reshape(-1, 2)
    if uv_a.shape != uv_b.shape:
        raise ValueError(f"uv_a {uv_a.shape} and uv_b {uv_b.shape} must have the same shape")
    if "joint" not in cal.fits:
        raise ValueError("length_uncertainty needs a joint calibration (calibrate(joint=True))")
    if diag is None:
        diag = fit_diagnostics(cal)
    fit = cal.fits["joint"]
    params, spec = fit.params, fit.free_mask
    idx = diag.select(("camera.", "plane."))
    if len(idx) == 0:
        raise ValueError("no free camera or laser-plane parameters: no calibration σ")
    if not (math.isfinite(sigma_px) and sigma_px >= 0):
        raise ValueError(f"sigma_px must be >= 0, got {sigma_px}")
    uv = jnp.asarray(np.concatenate([uv_a, uv_b]))
    X, Jt, Ju = (np.asarray(a) for a in _points_with_jacobians(params, spec, jnp.asarray(idx), uv))
    n = len(uv_a)
    Xa, Xb, Ja, Jb, Ua, Ub = X[:n], X[n:], Jt[:n], Jt[n:], Ju[:n], Ju[n:]
    delta = Xa - Xb
    L = np.linalg.norm(delta, axis=1)
    u = delta / np.where(L > 0, L, 1.0)[:, None]
    S = diag.covariance[np.ix_(idx, idx)]
    g = np.einsum("ni,niq->nq", u, Ja - Jb)
    var_cal = np.einsum("nq,qr,nr->n", g, S, g)
    ga, gb = np.einsum("ni,nik->nk", u, Ua), np.einsum("ni,nik->nk", u, Ub)
    var_px = sigma_px**2 * (np.sum(ga**2, axis=1) + np.sum(gb**2, axis=1))
    pa = np.sqrt(np.clip(np.einsum("niq,qr,nir->ni", Ja, S, Ja), 0.0, None))
    pb = np.sqrt(np.clip(np.einsum("niq,qr,nir->ni", Jb, S, Jb), 0.0, None))
    var_cal = np.clip(var_cal, 0.0, None)
    return {
        "length": L,
        "sigma": np.sqrt(var_cal + var_px),
        "sigma_calibration": np.sqrt(var_cal),
        "sigma_pixels": np.sqrt(var_px),
        "point_sigma_a": pa,
        "point_sigma_b": pb,
    }
