"""Geometric fits for measured point clouds: plane, 3-D circle, cylinder, step height.

Plain NumPy in float64 (no JAX, no SciPy): these run once per measurement on a few
thousand points. Every fit minimises *orthogonal* (geometric) distances, reports the
signed residuals of every point and their RMS, and raises `ValueError` with a clear
message on too few, non-finite or degenerate points.

- [`fit_plane`][]: total least squares (SVD of the centred points).
- [`fit_circle_3d`][]: the plane, then the circle in it (algebraic fit, then Gauss–Newton
  on the geometric distances).
- [`fit_cylinder`][]: grid search over axis directions with an algebraic circle fit in the
  plane perpendicular to each, then Levenberg–Marquardt on the geometric distances
  (radius free or known).
- [`step_height`][]: base plane by TLS; the height is the mean distance of the top points
  from it (the two faces are taken as parallel), with its scatter and standard error.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

__all__ = [
    "CircleFit",
    "CylinderFit",
    "PlaneFitResult",
    "StepHeightResult",
    "fit_circle_3d",
    "fit_cylinder",
    "fit_plane",
    "step_height",
]

# Relative size of the second singular value below which points count as collinear, and
# of the third below which (for a cylinder) they are taken as exactly planar.
_DEGENERATE = 1e-9


class PlaneFitResult(NamedTuple):
    """Least-squares plane `normal · (x − point) = 0`.

    **Fields:** `normal` (unit, sign chosen so its largest component is positive),
    `point` (the centroid of the points, on the plane), `rms` (RMS orthogonal distance,
    mm), `residuals` (signed orthogonal distances `normal · (x_i − point)`, shape `(N,)`).
    """

    normal: np.ndarray
    point: np.ndarray
    rms: float
    residuals: np.ndarray


class CircleFit(NamedTuple):
    """A circle in 3-D: `centre`, `radius`, plane `normal` (unit).

    `rms` and `residuals` are the in-plane radial deviations `ρ_i − radius` (the
    out-of-plane deviations are `plane_residuals`, with RMS `plane_rms`).
    """

    centre: np.ndarray
    radius: float
    normal: np.ndarray
    rms: float
    residuals: np.ndarray
    plane_rms: float
    plane_residuals: np.ndarray


class CylinderFit(NamedTuple):
    """A cylinder: axis through `point` along unit `direction`, `radius`.

    `point` is the axis point closest to the centroid of the data; `direction` has its
    largest component positive (or points along `axis_guess` when one was given).
    `residuals` are the signed orthogonal distances `dist(x_i, axis) − radius`, `rms` their
    RMS; `iterations` is the number of Levenberg–Marquardt steps taken.
    """

    point: np.ndarray
    direction: np.ndarray
    radius: float
    rms: float
    residuals: np.ndarray
    iterations: int


class StepHeightResult(NamedTuple):
    """Height of a step between two parallel faces.

    **Fields:**
    - `height`: mean distance of the top points from the base plane (mm, positive).
    - `sigma`: standard deviation of the top points' distances (their scatter, mm).
    - `stderr`: standard error of `height` (top scatter and base-plane uncertainty at the
      top points' centroid, mm).
    - `base`: the base plane's [`PlaneFitResult`][], normal pointing towards the top.
    - `top_residuals`: distances of the top points from the base plane minus `height`.
    - `tilt`: angle (rad) between the base normal and a plane fitted to the top points
      alone (NaN if the top points are collinear): a check of the parallel-faces model.
    """

    height: float
    sigma: float
    stderr: float
    base: PlaneFitResult
    top_residuals: np.ndarray
    tilt: float


# ----------------------------------------------------------------------------- helpers


def _as_points(points, name: str = "points", min_count: int = 1) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name} contains non-finite values (drop invalid points first)")
    if p.shape[0] < min_count:
        raise ValueError(f"{name}: need at least {min_count} points, got {p.shape[0]}")
    return p


def _canonical_sign(v: np.ndarray) -> np.ndarray:
    return v if v[np.argmax(np.abs(v))] >= 0 else -v


def _basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing `normal` to a right-handed orthonormal basis."""
    helper = np.eye(3)[np.argmin(np.abs(normal))]
    e1 = np.cross(normal, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(normal, e1)


def _rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(r**2)))


def _svd_centred(p: np.ndarray, name: str):
    c = p.mean(axis=0)
    _, s, vt = np.linalg.svd(p - c, full_matrices=False)
    if s[0] == 0.0 or s[1] <= _DEGENERATE * s[0]:
        raise ValueError(f"{name}: the points are (nearly) collinear or coincident")
    return c, s, vt


def _kasa(xy: np.ndarray) -> tuple[np.ndarray, float]:
    """Algebraic (Kåsa) circle fit in 2-D: centre, radius."""
    a = np.column_stack([2.0 * xy, np.ones(len(xy))])
    b = np.sum(xy**2, axis=1)
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)
    centre = sol[:2]
    return centre, math.sqrt(max(sol[2] + centre @ centre, 0.0))


def _circle_2d(xy: np.ndarray, iterations: int = 50) -> tuple[np.ndarray, float]:
    """Geometric circle fit in 2-D: Kåsa start, then Gauss–Newton on ρ_i − r."""
    centre, r = _kasa(xy)
    for _ in range(iterations):
        d = xy - centre
        rho = np.linalg.norm(d, axis=1)
        if np.any(rho == 0.0):
            break
        u = d / rho[:, None]
        jac = np.column_stack([-u, -np.ones(len(xy))])
        step, *_ = np.linalg.lstsq(jac, -(rho - r), rcond=None)
        centre = centre + step[:2]
        r += step[2]
        if np.linalg.norm(step) <= 1e-15 * max(1.0, abs(r)):
            break
    return centre, abs(r)


# ----------------------------------------------------------------------------- fits


def fit_plane(points) -> PlaneFitResult:
    """Total-least-squares plane through `points` `(N, 3)`, N ≥ 3, not collinear."""
    p = _as_points(points, min_count=3)
    c, _, vt = _svd_centred(p, "fit_plane")
    normal = _canonical_sign(vt[2])
    r = (p - c) @ normal
    return PlaneFitResult(normal, c, _rms(r), r)


def fit_circle_3d(points) -> CircleFit:
    """Circle through 3-D points `(N, 3)`, N ≥ 3, not collinear.

    Fits the plane (TLS), projects the points into it and fits the circle there by
    geometric least squares (Kåsa's algebraic fit, refined by Gauss–Newton).
    """
    p = _as_points(points, min_count=3)
    plane = fit_plane(p)
    e1, e2 = _basis(plane.normal)
    d = p - plane.point
    xy = np.column_stack([d @ e1, d @ e2])
    c2, r = _circle_2d(xy)
    centre = plane.point + c2[0] * e1 + c2[1] * e2
    res = np.linalg.norm(xy - c2, axis=1) - r
    return CircleFit(centre, float(r), plane.normal, _rms(res), res, plane.rms, plane.residuals)


def _hemisphere(n: int) -> np.ndarray:
    """`n` unit vectors spread evenly over the hemisphere z ≥ 0 (Fibonacci), (n, 3)."""
    k = np.arange(n) + 0.5
    z = k / n
    a = k * math.pi * (3.0 - math.sqrt(5.0))
    s = np.sqrt(1.0 - z**2)
    return np.column_stack([s * np.cos(a), s * np.sin(a), z])


def _cone(axis: np.ndarray, half_angle: float, n: int) -> np.ndarray:
    """`n` unit vectors spread evenly within `half_angle` of `axis`."""
    k = np.arange(n) + 0.5
    cos_t = 1.0 - (k / n) * (1.0 - math.cos(half_angle))
    sin_t = np.sqrt(1.0 - cos_t**2)
    a = k * math.pi * (3.0 - math.sqrt(5.0))
    e1, e2 = _basis(axis)
    return (
        cos_t[:, None] * axis
        + (sin_t * np.cos(a))[:, None] * e1
        + (sin_t * np.sin(a))[:, None] * e2
    )


def _kasa_cost(d: np.ndarray, dirs: np.ndarray, radius: float | None) -> np.ndarray:
    """Geometric cost of the algebraic circle fit in the plane ⊥ each direction."""
    costs = np.empty(len(dirs))
    for i, u in enumerate(dirs):
        e1, e2 = _basis(u)
        xy = np.column_stack([d @ e1, d @ e2])
        c, r = _kasa(xy)
        rho = np.linalg.norm(xy - c, axis=1)
        costs[i] = np.mean((rho - (r if radius is None else radius)) ** 2)
    return costs


def _cylinder_lm(p, point, direction, radius, fixed_radius, max_iter=200):
    """Levenberg–Marquardt on the orthogonal distances, relinearised around the current
    axis each step: parameters (s1, s2) move the axis point in the plane ⊥ axis, (a, b)
    tilt the axis, and r (unless fixed)."""

    def residuals(pt, u, r):
        w = p - pt
        t = w @ u
        q = w - t[:, None] * u
        rho = np.linalg.norm(q, axis=1)
        return rho - r, q, rho, t

    r = radius
    res, q, rho, t = residuals(point, direction, r)
    cost = res @ res
    lam = 1e-3
    it = 0
    for it in range(1, max_iter + 1):
        e1, e2 = _basis(direction)
        nh = q / np.where(rho > 0, rho, 1.0)[:, None]
        n1, n2 = nh @ e1, nh @ e2
        cols = [-n1, -n2, -t * n1, -t * n2]
        if not fixed_radius:
            cols.append(-np.ones_like(n1))
        jac = np.column_stack(cols)
        jtj = jac.T @ jac
        g = jac.T @ res
        improved = False
        for _ in range(30):
            a = jtj + lam * np.diag(np.diag(jtj) + 1e-30)
            step = np.linalg.solve(a, -g)
            new_point = point + step[0] * e1 + step[1] * e2
            new_dir = direction + step[2] * e1 + step[3] * e2
            new_dir /= np.linalg.norm(new_dir)
            new_r = r if fixed_radius else r + step[4]
            new_res, new_q, new_rho, new_t = residuals(new_point, new_dir, new_r)
            new_cost = new_res @ new_res
            if new_cost <= cost:
                improved = True
                break
            lam *= 10.0
        if not improved:
            break
        small = (
            np.max(np.abs(step[:2])) <= 1e-14 * max(1.0, abs(r))
            and np.max(np.abs(step[2:4])) <= 1e-15
        )
        point, direction, r = new_point, new_dir, new_r
        res, q, rho, t, cost = new_res, new_q, new_rho, new_t, new_cost
        lam = max(lam / 10.0, 1e-12)
        if small or cost == 0.0:
            break
    return point, direction, r, res, it


def fit_cylinder(
    points,
    *,
    radius: float | None = None,
    axis_guess=None,
    n_directions: int = 400,
) -> CylinderFit:
    """Least-squares cylinder through 3-D points `(N, 3)` (orthogonal distances).

    1. Grid search of the axis direction: `n_directions` directions over the hemisphere
       (or, with `axis_guess`, within 20° of it); for each, the algebraic circle fit in
       the plane perpendicular to it; keep the best.
    2. Levenberg–Marquardt on the orthogonal distances `dist(x_i, axis) − r` over the axis
       (4 parameters) and the radius (unless `radius` is given: then it is held fixed).

    A partial arc (a scan of part of a ring gauge) is fine as long as it spans enough
    angle for the radius to be determined; a very short arc makes the radius poorly
    determined and the result then depends on the data's noise (as for any fit).

    **Raises:** `ValueError` for fewer than 5 points (4 with a known radius), non-finite
    points, collinear points or a non-positive `radius`.
    """
    fixed = radius is not None
    p = _as_points(points, min_count=4 if fixed else 5)
    if fixed and not (np.isfinite(radius) and radius > 0):
        raise ValueError(f"radius must be positive and finite, got {radius}")
    c, _, _ = _svd_centred(p, "fit_cylinder")
    d = p - c
    if axis_guess is not None:
        g = np.asarray(axis_guess, dtype=np.float64)
        if g.shape != (3,) or not np.all(np.isfinite(g)) or np.linalg.norm(g) == 0:
            raise ValueError("axis_guess must be a finite non-zero 3-vector")
        g = g / np.linalg.norm(g)
        dirs = np.vstack([g[None], _cone(g, math.radians(20.0), n_directions)])
    else:
        dirs = _hemisphere(n_directions)
    costs = _kasa_cost(d, dirs, radius)
    best = dirs[int(np.argmin(costs))]
    # start: circle in the plane ⊥ best direction
    e1, e2 = _basis(best)
    xy = np.column_stack([d @ e1, d @ e2])
    c2, r0 = _kasa(xy)
    point0 = c + c2[0] * e1 + c2[1] * e2
    r0 = float(radius) if fixed else r0
    if not r0 > 0:
        raise ValueError("fit_cylinder: could not find a starting circle (degenerate points)")
    point, u, r, res, it = _cylinder_lm(p, point0, best, r0, fixed)
    # canonical axis point and direction
    point = point + ((c - point) @ u) * u
    if axis_guess is not None:
        u = u if u @ g >= 0 else -u
    else:
        u = _canonical_sign(u)
    return CylinderFit(point, u, float(r), _rms(res), res, it)


def step_height(points, labels, *, base_label: int = 0, top_label: int = 1) -> StepHeightResult:
    """Height of a step between two parallel faces (e.g. a gauge-block step).

    The base plane is fitted (TLS) to the points labelled `base_label`; the height is the
    mean orthogonal distance of the points labelled `top_label` from it. Other labels are
    ignored.

    **Arguments:** `points` `(N, 3)`; `labels` `(N,)` integers (or booleans: True = top).

    **Raises:** `ValueError` for mismatched shapes, fewer than 3 base points or 1 top
    point, collinear base points.
    """
    p = _as_points(points)
    lab = np.asarray(labels)
    if lab.shape != (p.shape[0],):
        raise ValueError(f"labels must have shape ({p.shape[0]},), got {lab.shape}")
    lab = lab.astype(np.int64)
    base_pts, top_pts = p[lab == base_label], p[lab == top_label]
    if len(base_pts) < 3:
        raise ValueError(f"step_height: need at least 3 base points, got {len(base_pts)}")
    if len(top_pts) < 1:
        raise ValueError("step_height: no top points")
    base = fit_plane(base_pts)
    dist = (top_pts - base.point) @ base.normal
    if np.mean(dist) < 0:
        base = base._replace(normal=-base.normal, residuals=-base.residuals)
        dist = -dist
    h = float(np.mean(dist))
    n_top, n_base = len(top_pts), len(base_pts)
    sigma = float(np.std(dist, ddof=1)) if n_top > 1 else 0.0
    # base-plane uncertainty at the top centroid: offset σ²/n plus the tilt's lever arm
    s_base2 = float(base.residuals @ base.residuals) / max(n_base - 3, 1)
    e1, e2 = _basis(base.normal)
    db = base_pts - base.point
    xy_b = np.column_stack([db @ e1, db @ e2])
    dt = top_pts.mean(axis=0) - base.point
    lever = np.array([dt @ e1, dt @ e2])
    try:
        slope_var = lever @ np.linalg.solve(xy_b.T @ xy_b, lever)
    except np.linalg.LinAlgError:
        slope_var = np.inf
    stderr = math.sqrt(sigma**2 / n_top + s_base2 * (1.0 / n_base + slope_var))
    tilt = math.nan
    if n_top >= 3:
        try:
            top_plane = fit_plane(top_pts)
            cross = np.linalg.norm(np.cross(top_plane.normal, base.normal))
            tilt = math.atan2(float(cross), abs(float(top_plane.normal @ base.normal)))
        except ValueError:
            pass
    return StepHeightResult(h, sigma, stderr, base, dist - h, tilt)
