"""The budget term of parameters the calibration held fixed (GUM type B).

A parameter held at a nominal value (a datasheet focal length, an adapter tilt rounded to
a degree) is not exact: were it `δq` off, the calibration would have converged elsewhere
— the free parameters absorb what they can — and the measured value would move by
`(dv/dq) δq` with the *total* derivative

    dv/dq = ∂v/∂q + ∂v/∂θ · dθ*/dq,    dθ*/dq = −(J_θᵀ J_θ)⁻¹ J_θᵀ J_q

(implicit function theorem at the optimum: `J_θ`, `J_q` the calibration residuals'
Jacobians with respect to the free parameters θ and the held one q). A pure gauge
freedom (one the data cannot see) gives `dv/dq = 0` for a length: holding it costs
nothing; a held value that biases the result gives `dv/dq ≠ 0`. With a standard
uncertainty `σ_q` per held scalar (independent), the term is `Σ_q (dv/dq σ_q)²`.

`nominal_tolerances(cal)` is the documented default: the nominal values a user types
are rounded (focal length to 1 mm, tilt to 1°, `simulate.nominal_of`): uniform within
half a unit, σ = 0.5 / √3 of the unit; the pixel pitch (datasheet, lithographic) and any
other held parameter count as exact (σ = 0).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["frozen_derivatives", "nominal_tolerances"]

_HALF_UNIFORM = 0.5 / math.sqrt(3.0)
# σ of a held value rounded to one unit: f to 1 mm, the tilt angles to 1 deg (in rad)
NOMINAL_SIGMA = {
    "camera.f": _HALF_UNIFORM,
    "camera.phi": math.radians(_HALF_UNIFORM),
    "camera.theta": math.radians(_HALF_UNIFORM),
}


def nominal_tolerances(cal) -> dict[str, float]:
    """The default σ (mm, rad) of the held parameters of `cal` (see the module text):
    the ones in `NOMINAL_SIGMA` that `cal.freeze` holds; the others count as exact."""
    return {p: s for p, s in NOMINAL_SIGMA.items() if p in tuple(cal.freeze)}


def frozen_derivatives(cal, shape, uv, fi, lab, frame, paths, source="the calibration"):
    """Total derivatives `dv/dq` `(K, len(paths))` of the values with respect to held
    scalar parameters `paths`, re-solving the calibration to first order.

    **Raises:** `ValueError` for a path the calibration does not hold fixed or that is
    not a scalar.
    """
    import jax
    import jax.numpy as jnp

    from ..calibration import residual_function
    from ..calibration.core._solve import free_spec, jacobian, parameter_labels
    from ._chain import chain_function

    frozen = tuple(cal.freeze)
    for p in paths:
        if p not in frozen:
            raise ValueError(
                f"frozen_sigma names {p!r}, which {source} does not hold fixed "
                f"(held: {', '.join(frozen) or 'none'})"
            )
    fn, params, spec0 = residual_function(cal, "joint")
    labels0 = parameter_labels(params, spec0)
    extra = tuple(p for p in ("stage.delta_omega",) if params.stage is not None)
    spec = free_spec(params, tuple(p for p in frozen if p not in paths) + extra)
    labels = parameter_labels(params, spec)
    q_cols = [labels.index(p) if p in labels else -1 for p in paths]
    for p, c in zip(paths, q_cols):
        if c < 0:
            raise ValueError(f"frozen_sigma: {p!r} is not a scalar parameter")
    th_cols = [i for i in range(len(labels)) if i not in q_cols]
    if [labels[i] for i in th_cols] != labels0:
        raise ValueError("frozen_sigma: the free parameters do not match the joint solve's")
    J = np.asarray(jacobian(fn, params, cal.data, spec))
    dtheta, *_ = np.linalg.lstsq(J[:, th_cols], -J[:, q_cols], rcond=None)
    prefixes = ("camera.", "plane.") + (("stage.",) if frame == "measurement" else ())
    used = [i for i, lab in enumerate(labels) if lab.startswith(prefixes)]
    f, theta0 = chain_function(shape, params, spec, used, frame)
    G = np.asarray(
        jax.jit(jax.jacrev(f))(theta0, jnp.asarray(uv), jnp.asarray(fi), jnp.asarray(lab))
    )  # (K, len(used)); one compiled program (op by op it dispatched ~700 small ones)
    pos = {c: k for k, c in enumerate(used)}
    d_total = np.stack([G[:, pos[c]] for c in q_cols], axis=1)
    th_pos = {c: k for k, c in enumerate(th_cols)}
    for c in used:
        if c in th_pos:
            d_total += G[:, [pos[c]]] * dtheta[th_pos[c]][None, :]
    return d_total
