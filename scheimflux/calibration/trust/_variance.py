"""Each residual group's noise, estimated from the data (variance-component estimation).

A calibration weights every residual by its noise σ: corners by `sigma_corner_px`, each
view's stripe points by `sigma_stripe_mm · stripe_scale[v]`, the gauge scan by
`sigma_stripe_mm`. Stated σ are guesses (a simulation's 0.03 px corners are 5–10× below
what a real detector reaches on real photographs), and the joint solve's balance between
corners and laser lines rests on them: a line weighted 20× too high pulls the camera off
what its corners say.

After a solve with the current weights, each group `g` has the variance factor

    s²_g = |r_g|² / (n_g − tr H_gg),     H = J (JᵀJ)⁺ Jᵀ,

its weighted residuals' sum of squares over its redundancy (Förstner's estimator; the
redundancies add up to n − p). `s²_g = 1` where the stated σ is the noise; otherwise the
group's σ is multiplied by `s_g` and the problem solved again, until every factor is
within `TOLERANCE` of 1 ([`variance_components`][] gives one step; the workflow,
`calibration._calibrate`, iterates). The stated σ is a floor (as a view's own measured
stripe σ is): the data raise a σ that was stated too small — the usual case on real
photographs — but do not lower one below what the user stated; stripes weighted far
above the pixel footprint's σ also leave the thick lens's depth gauge below the rank
check's resolution. A group with less redundancy than
`MIN_REDUNDANCY` takes the pooled factor of its kind (a view with a handful of stripe
points cannot tell its own noise).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import numpy as np

from ..core._model import gauge_residuals
from ..core._solve import linearised

__all__ = [
    "TOLERANCE",
    "VarianceComponents",
    "sigma_change",
    "variance_components",
    "with_factors",
]

# Factors within this of 1 (σ within about half of it) end the iteration.
TOLERANCE = 0.1
# Iterations of estimate and re-solve at most (the factors converge geometrically; three
# to four suffice where the stated σ were off by 10x).
MAX_ITERATIONS = 6
# Below this redundancy a group's own factor is too uncertain (its relative σ is about
# sqrt(2 / redundancy)): it takes its kind's pooled factor.
MIN_REDUNDANCY = 10.0


@dataclasses.dataclass(frozen=True)
class VarianceComponents:
    """One step of variance-component estimation.

    **Fields:**
    - `corners`: the corners' factor s² (table-target corners included).
    - `stripes` `(V,)`: each view's stripe-point factor (1 for a view without stripes).
    - `gauge`: the gauge scan's factor (table-target stripes included), or None.
    - `redundancy`: `{"corners": …, "stripes": (V,), "gauge": …}`.
    """

    corners: float
    stripes: np.ndarray
    gauge: float | None
    redundancy: dict

    def factors(self) -> list[float]:
        """Every group's factor: corners, each view's stripes, the gauge scan (if any)."""
        return [self.corners, *self.stripes.tolist()] + ([] if self.gauge is None else [self.gauge])

    def converged(self, tolerance: float = TOLERANCE) -> bool:
        """Whether every factor is within `tolerance` of 1."""
        return all(abs(x - 1.0) <= tolerance for x in self.factors())


def _group_bounds(data, params) -> dict:
    """Row ranges of the joint residual vector: corners, each view's stripes, gauge,
    table-target corners and stripes (the order `joint_residuals` concatenates them)."""
    V, M = data.corners.shape[:2]
    K = data.stripe.shape[1]
    out, at = {"corners": [(0, 2 * V * M)], "stripes": []}, 2 * V * M
    if params.plane is not None:
        out["stripes"] = [(at + v * K, at + (v + 1) * K) for v in range(V)]
        at += V * K
    gauge = []
    if params.stage is not None:  # F · L points, then the stage's two gauge-fixing rows
        n = int(np.prod(jax.eval_shape(gauge_residuals, params, data).shape))
        gauge.append((at, at + n))
        at += n
    if params.table_pose is not None and data.table is not None:
        t = data.table
        n_c = 2 * int(np.prod(t.corners.shape[:2]))
        n_s = int(np.prod(t.stripe.shape[:2]))
        out["corners"].append((at, at + n_c))
        gauge.append((at + n_c, at + n_c + n_s))
        at += n_c + n_s
    out["gauge"] = gauge
    out["total"] = at
    return out


def variance_components(fn, params, data, spec) -> VarianceComponents:
    """The variance factor of each residual group at `params` (module text).

    **Arguments:** the residual function (`joint_residuals` or `camera_plane_residuals`),
    the solved parameters, their data and the solve's filter spec.

    **Returns:** a [`VarianceComponents`][]. **Raises:** `ValueError` when the residuals
    do not come in the expected groups or there is no redundancy.
    """
    r, J, _ = linearised(fn, params, data, spec)
    bounds = _group_bounds(data, params)
    if bounds["total"] != len(r):
        raise ValueError(
            f"the residual vector has {len(r)} rows, its groups {bounds['total']}: "
            "variance components need the joint residuals"
        )
    used = np.any(J != 0, axis=1) | (r != 0)  # padding rows are no observations
    col = np.linalg.norm(J, axis=0)
    d = np.where(col > 0, 1.0 / np.where(col > 0, col, 1.0), 1.0)
    U, s, _ = np.linalg.svd(J * d, full_matrices=False)
    U = U[:, s > 1e-10 * s[0]] if s.size else U[:, :0]
    h = np.sum(U * U, axis=1)  # the hat matrix's diagonal: each row's share of p
    n, p = int(used.sum()), U.shape[1]
    if n <= p:
        raise ValueError("no redundancy (residuals <= parameters): the noise is not estimable")

    def group(ranges):
        q = red = 0.0
        for lo, hi in ranges:
            m = used[lo:hi]
            q += float(np.sum(r[lo:hi][m] ** 2))
            red += float(np.sum(1.0 - h[lo:hi][m]))
        return q, red

    pooled = float(np.sum(r[used] ** 2)) / (n - p)

    def factor(q, red, fallback):
        return q / red if red >= MIN_REDUNDANCY else fallback

    qc, rc = group(bounds["corners"])
    corners = factor(qc, rc, pooled)
    per_view = [group([b]) for b in bounds["stripes"]]
    q_all = sum(q for q, _ in per_view)
    r_all = sum(x for _, x in per_view)
    stripes_pooled = factor(q_all, r_all, pooled)
    stripes = np.array([factor(q, x, stripes_pooled) for q, x in per_view])
    # a view without stripe points has no stripe factor
    has = [bool(np.any(used[lo:hi])) for lo, hi in bounds["stripes"]]
    stripes = np.where(has, stripes, 1.0) if len(stripes) else np.ones(data.stripe.shape[0])
    gauge = None
    redundancy = {"corners": rc, "stripes": np.array([x for _, x in per_view])}
    if bounds["gauge"]:
        qg, rg = group(bounds["gauge"])
        gauge = factor(qg, rg, pooled)
        redundancy["gauge"] = rg
    return VarianceComponents(float(corners), stripes, gauge, redundancy)


def _sigmas(data) -> np.ndarray:
    """The groups' σ as the residuals use them: corners (px), each view's stripes and the
    gauge scan (mm)."""
    s = float(data.sigma_stripe_mm)
    scale = np.asarray(data.stripe_scale, dtype=np.float64)
    return np.concatenate([[float(data.sigma_corner_px)], s * scale, [s]])


def with_factors(data, vc: VarianceComponents, floor=None):
    """`data` with each group's σ multiplied by the square root of its factor, and no
    smaller than `floor`'s (the stated σ: a prior that the data may raise, not lower).

    Corners (and table-target corners): `sigma_corner_px`. The gauge scan (and the
    table target's laser line): `sigma_stripe_mm`; each view's stripes keep their own
    factor through `stripe_scale` (relative to `sigma_stripe_mm`)."""
    g = 1.0 if vc.gauge is None else vc.gauge
    f = np.concatenate([[vc.corners], vc.stripes, [g]])
    sigma = _sigmas(data) * np.sqrt(f)
    if floor is not None:
        sigma = np.maximum(sigma, _sigmas(floor))
    sigma_s = sigma[-1]

    def put(a):
        return jax.device_put(np.asarray(a, dtype=np.float64))

    return eqx.tree_at(
        lambda d: (d.sigma_corner_px, d.sigma_stripe_mm, d.stripe_scale),
        data,
        (put(sigma[0]), put(sigma_s), put(sigma[1:-1] / sigma_s)),
    )


def sigma_change(old, new) -> float:
    """The largest |log| ratio of a group's σ between two data (0: unchanged)."""
    return float(np.max(np.abs(np.log(_sigmas(new) / _sigmas(old)))))
