"""Geometric models for differentiable fits: plane, sphere, circle, cylinder, steps, distance.

Each shape is a small `eqx.Module` (its configuration static) with four pure JAX methods:

- `start(X, labels) -> (y0, frame)`: a closed-form start (SVD, algebraic fits, a grid of
  axis directions for the cylinder), under `stop_gradient`: the fit's derivatives come
  from the implicit function theorem at the optimum, not from the start.
- `residual(y, frame, x, label) -> (m,)`: the orthogonal (geometric) residual of one point
  in local, non-redundant parameters `y` around the start (directions tilted in their
  tangent plane, so `JᵀJ` has no gauge freedom and the implicit derivative exists).
- `values(y, frame, X, labels) -> (K,)`: the measured values (`names`).
- `check(X, labels)`: NumPy, before any tracing: too few points or degenerate geometry
  raise `ValueError` with a one-line reason.

The fit itself (optimistix Levenberg–Marquardt with its implicit adjoint) is in `_solve.py`.
"""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["Circle", "Cylinder", "Distance", "Plane", "Sphere", "Steps"]

# Relative singular value below which points count as collinear / coplanar. Camera-frame
# stripe points lie in the laser plane to rounding (relative 1e-16), real surfaces far
# above this.
DEGENERATE_RTOL = 1e-9


def _unit(v):
    return v / jnp.sqrt(jnp.sum(v * v))


def _safe_norm(v):
    s = jnp.sum(v * v)
    ok = s > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, s, 1.0)), 0.0)


def _perp_basis(u):
    """Two unit vectors completing `u` to an orthonormal basis (for starts only)."""
    helper = jnp.eye(3, dtype=u.dtype)[jnp.argmin(jnp.abs(u))]
    e1 = _unit(jnp.cross(u, helper))
    return e1, jnp.cross(u, e1)


def _tilt(u0, e1, e2, a, b):
    return _unit(u0 + a * e1 + b * e2)


def _kasa(xy):
    """Algebraic (Kåsa) circle in 2-D by its 3×3 normal equations: centre, radius, cost."""
    A = jnp.concatenate([2.0 * xy, jnp.ones_like(xy[:, :1])], axis=1)
    b = jnp.sum(xy * xy, axis=1)
    sol = jnp.linalg.solve(A.T @ A, A.T @ b)
    c = sol[:2]
    r = jnp.sqrt(jnp.maximum(sol[2] + c @ c, 0.0))
    rho = jnp.sqrt(jnp.sum((xy - c) ** 2, axis=1))
    return c, r, jnp.mean((rho - r) ** 2)


def _svd_frame(X):
    c = jnp.mean(X, axis=0)
    _, _, vt = jnp.linalg.svd(X - c, full_matrices=False)
    return c, vt


def _np_points(X, name, min_count):
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"{name}: points must have shape (N, 3), got {X.shape}")
    if not np.all(np.isfinite(X)):
        raise ValueError(f"{name}: points contain NaN or inf (drop invalid points first)")
    if X.shape[0] < min_count:
        raise ValueError(f"{name}: need at least {min_count} points, got {X.shape[0]}")
    return X


def _singular(X):
    s = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
    return s / s[0] if s[0] > 0 else np.zeros(3)


def _check_spread(X, name, *, need_3d: bool):
    s = _singular(X)
    if s[1] <= DEGENERATE_RTOL:
        raise ValueError(f"{name}: the points are collinear or coincident (degenerate geometry)")
    if need_3d and s[2] <= DEGENERATE_RTOL:
        raise ValueError(
            f"{name}: the points are coplanar (camera-frame stripe points all lie in the "
            "laser plane): a surface fit needs points spread over it, e.g. a rotary scan "
            "in the measurement frame"
        )


class AbstractShape(eqx.Module):
    """A geometric model fitted by orthogonal least squares (see module docstring)."""

    kind: ClassVar[str] = ""
    n_residuals: ClassVar[int] = 1  # residual components per point

    @property
    def names(self) -> tuple[str, ...]:
        raise NotImplementedError

    def n_params(self) -> int:
        raise NotImplementedError

    def check(self, X, labels) -> None:
        raise NotImplementedError

    def start(self, X, labels):
        raise NotImplementedError

    def residual(self, y, frame, x, label):
        raise NotImplementedError

    def values(self, y, frame, X, labels):
        raise NotImplementedError

    def describe(self, y, frame) -> dict:
        """The fitted geometry as plain numbers (axis, centre, normal, ...)."""
        return {}


class Plane(AbstractShape):
    """Plane `n · (x − c) = d`; values: flatness (peak-to-valley of the orthogonal
    residuals, mm) and the RMS form deviation (mm).

    Peak-to-valley grows with the noise of the points (≈ 4–6 σ for a few hundred points):
    compare it with the stripe-noise part of the budget before reading it as form error.
    """

    kind: ClassVar[str] = "plane"

    @property
    def names(self):
        return ("flatness", "rms")

    def n_params(self):
        return 3

    def check(self, X, labels):
        X = _np_points(X, "plane", 4)
        _check_spread(X, "plane", need_3d=False)

    def start(self, X, labels):
        c, vt = _svd_frame(jax.lax.stop_gradient(X))
        return jnp.zeros(3, X.dtype), (c, vt[2], vt[0], vt[1])

    def _normal(self, y, frame):
        _, n0, e1, e2 = frame
        return _tilt(n0, e1, e2, y[0], y[1])

    def residual(self, y, frame, x, label):
        return jnp.reshape(self._normal(y, frame) @ (x - frame[0]) - y[2], (1,))

    def values(self, y, frame, X, labels):
        r = (X - frame[0]) @ self._normal(y, frame) - y[2]
        return jnp.stack([jnp.max(r) - jnp.min(r), jnp.sqrt(jnp.mean(r * r))])

    def describe(self, y, frame):
        n = self._normal(y, frame)
        return {"normal": n, "point": frame[0] + y[2] * n}


class Sphere(AbstractShape):
    """Sphere `|x − c| = R`; value: the radius (mm)."""

    kind: ClassVar[str] = "sphere"

    @property
    def names(self):
        return ("radius",)

    def n_params(self):
        return 4

    def check(self, X, labels):
        X = _np_points(X, "sphere", 5)
        _check_spread(X, "sphere", need_3d=True)

    def start(self, X, labels):
        X = jax.lax.stop_gradient(X)
        m = jnp.mean(X, axis=0)
        d = X - m
        A = jnp.concatenate([2.0 * d, jnp.ones_like(d[:, :1])], axis=1)
        sol = jnp.linalg.solve(A.T @ A, A.T @ jnp.sum(d * d, axis=1))
        c0 = m + sol[:3]
        r0 = jnp.sqrt(jnp.maximum(sol[3] + sol[:3] @ sol[:3], 0.0))
        return jnp.zeros(4, X.dtype), (c0, r0)

    def residual(self, y, frame, x, label):
        c0, r0 = frame
        return jnp.reshape(_safe_norm(x - c0 - y[:3]) - (r0 + y[3]), (1,))

    def values(self, y, frame, X, labels):
        return jnp.reshape(frame[1] + y[3], (1,))

    def describe(self, y, frame):
        return {"centre": frame[0] + y[:3]}


class Circle(AbstractShape):
    """Circle in 3-D (centre `c`, plane normal `n`, radius `r`); two residuals per point:
    the out-of-plane distance `n · (x − c)` and the in-plane radial deviation. Value: the
    radius (mm)."""

    kind: ClassVar[str] = "circle"
    n_residuals: ClassVar[int] = 2

    @property
    def names(self):
        return ("radius",)

    def n_params(self):
        return 6

    def check(self, X, labels):
        X = _np_points(X, "circle", 4)
        _check_spread(X, "circle", need_3d=False)

    def start(self, X, labels):
        X = jax.lax.stop_gradient(X)
        c, vt = _svd_frame(X)
        e1, e2, n0 = vt[0], vt[1], vt[2]
        d = X - c
        c2, r0, _ = _kasa(jnp.stack([d @ e1, d @ e2], axis=1))
        centre = c + c2[0] * e1 + c2[1] * e2
        return jnp.zeros(6, X.dtype), (centre, n0, e1, e2, r0)

    def residual(self, y, frame, x, label):
        centre, n0, e1, e2, r0 = frame
        n = _tilt(n0, e1, e2, y[0], y[1])
        w = x - centre - y[2:5]
        h = n @ w
        return jnp.stack([h, _safe_norm(w - h * n) - (r0 + y[5])])

    def values(self, y, frame, X, labels):
        return jnp.reshape(frame[4] + y[5], (1,))

    def describe(self, y, frame):
        centre, n0, e1, e2, _ = frame
        return {"centre": centre + y[2:5], "normal": _tilt(n0, e1, e2, y[0], y[1])}


def _hemisphere(n: int) -> np.ndarray:
    k = np.arange(n) + 0.5
    z = k / n
    a = k * math.pi * (3.0 - math.sqrt(5.0))
    s = np.sqrt(1.0 - z**2)
    return np.column_stack([s * np.cos(a), s * np.sin(a), z])


class Cylinder(AbstractShape):
    """Cylinder: axis through `p` along unit `u`, radius `r`; value: the radius (mm).

    Start: `n_directions` axis directions over the hemisphere, an algebraic circle in the
    plane perpendicular to each, the best kept (vectorised, no Python loop); then
    Levenberg–Marquardt on `dist(x, axis) − r` over the axis (4 parameters) and `r`.
    """

    kind: ClassVar[str] = "cylinder"
    n_directions: int = eqx.field(static=True, default=400)

    @property
    def names(self):
        return ("radius",)

    def n_params(self):
        return 5

    def check(self, X, labels):
        X = _np_points(X, "cylinder", 6)
        _check_spread(X, "cylinder", need_3d=True)

    def start(self, X, labels):
        X = jax.lax.stop_gradient(X)
        c = jnp.mean(X, axis=0)
        d = X - c
        dirs = jnp.asarray(_hemisphere(self.n_directions), X.dtype)

        def cost(u):
            e1, e2 = _perp_basis(u)
            return _kasa(jnp.stack([d @ e1, d @ e2], axis=1))[2]

        u0 = dirs[jnp.argmin(jax.vmap(cost)(dirs))]
        e1, e2 = _perp_basis(u0)
        c2, r0, _ = _kasa(jnp.stack([d @ e1, d @ e2], axis=1))
        p0 = c + c2[0] * e1 + c2[1] * e2
        return jnp.zeros(5, X.dtype), (p0, u0, e1, e2, r0)

    def _axis(self, y, frame):
        p0, u0, e1, e2, _ = frame
        return p0 + y[0] * e1 + y[1] * e2, _tilt(u0, e1, e2, y[2], y[3])

    def residual(self, y, frame, x, label):
        p, u = self._axis(y, frame)
        w = x - p
        return jnp.reshape(_safe_norm(w - (w @ u) * u) - (frame[4] + y[4]), (1,))

    def values(self, y, frame, X, labels):
        return jnp.reshape(frame[4] + y[4], (1,))

    def describe(self, y, frame):
        p, u = self._axis(y, frame)
        return {"axis_point": p, "axis_direction": u}


class Steps(AbstractShape):
    """Parallel faces of a stepped gauge: face 0 is the base, faces 1 … K−1 the steps.

    - `model="lines"`: one laser profile (the faces' points are collinear, as on a single
      stripe): parallel lines with a common direction, two residuals per point (the
      distance vector ⊥ the direction). Value k: the distance between line k and line 0
      (in the laser plane: the height divided by the sine of the angle between the laser
      plane and the faces; ratios of steps measured alike cancel that factor).
    - `model="planes"`: parallel planes with a common normal (a scan over the faces).
      Value k: the height of face k above face 0 along the normal.
    """

    n_faces: int = eqx.field(static=True, default=2)
    model: str = eqx.field(static=True, default="lines")

    def __check_init__(self):
        if self.model not in ("lines", "planes"):
            raise ValueError(f"Steps model must be 'lines' or 'planes', got {self.model!r}")
        if self.n_faces < 2:
            raise ValueError(f"Steps needs at least 2 faces, got {self.n_faces}")

    kind: ClassVar[str] = "steps"

    @property
    def n_residuals(self):
        return 2 if self.model == "lines" else 1

    @property
    def names(self):
        return tuple(f"step_{k}" for k in range(1, self.n_faces))

    def n_params(self):
        return 2 + (2 if self.model == "lines" else 1) * self.n_faces

    def check(self, X, labels):
        X = _np_points(X, "steps", 3)
        lab = np.asarray(labels)
        if lab.shape != (X.shape[0],):
            raise ValueError(f"steps: labels must have shape ({X.shape[0]},), got {lab.shape}")
        need = 2 if self.model == "lines" else 3
        for k in range(self.n_faces):
            face = X[lab == k]
            if len(face) < need:
                raise ValueError(
                    f"steps: face {k} has {len(face)} points, a {self.model[:-1]} needs {need}"
                )
            if self.model == "planes":
                _check_spread(face, f"steps (face {k})", need_3d=False)
            elif _singular(face)[0] == 0:
                raise ValueError(f"steps: the points of face {k} coincide")
        if self.model == "lines" and _singular(X[lab < self.n_faces])[1] <= DEGENERATE_RTOL:
            raise ValueError("steps: all faces lie on one line: there is no step")

    def _pooled(self, X, labels):
        onehot = jax.nn.one_hot(labels, self.n_faces, dtype=X.dtype)  # (N, K)
        C = (onehot.T @ X) / jnp.maximum(jnp.sum(onehot, axis=0), 1.0)[:, None]
        D = X - C[labels]
        return C, D.T @ D

    def start(self, X, labels):
        X = jax.lax.stop_gradient(X)
        C, S = self._pooled(X, labels)
        _, V = jnp.linalg.eigh(S)  # ascending
        if self.model == "lines":
            frame = (C, V[:, 2], V[:, 1], V[:, 0])  # direction = largest scatter
        else:
            frame = (C, V[:, 0], V[:, 2], V[:, 1])  # normal = smallest scatter
        return jnp.zeros(self.n_params(), X.dtype), frame

    def _direction(self, y, frame):
        _, u0, e1, e2 = frame
        return _tilt(u0, e1, e2, y[0], y[1])

    def _line_points(self, y, frame):
        C, _, e1, e2 = frame
        s = y[2:].reshape(self.n_faces, 2)
        return C + s[:, :1] * e1 + s[:, 1:] * e2

    def residual(self, y, frame, x, label):
        u = self._direction(y, frame)
        if self.model == "planes":
            return jnp.reshape(u @ (x - frame[0][label]) - y[2 + label], (1,))
        e1 = frame[2]
        f1 = _unit(e1 - (e1 @ u) * u)
        f2 = jnp.cross(u, f1)
        w = x - self._line_points(y, frame)[label]
        return jnp.stack([w @ f1, w @ f2])

    def values(self, y, frame, X, labels):
        u = self._direction(y, frame)
        if self.model == "planes":
            off = u @ frame[0].T + y[2:]  # (K,) offsets along the common normal
            return jnp.abs(off[1:] - off[0])
        q = self._line_points(y, frame)
        d = q[1:] - q[0]
        return jax.vmap(lambda v: _safe_norm(v - (v @ u) * u))(d)

    def describe(self, y, frame):
        key = "normal" if self.model == "planes" else "direction"
        return {key: self._direction(y, frame)}


class Distance(AbstractShape):
    """Distance between two points, `|x_i − x_j|` (mm): no fit, no residuals.

    `i`, `j` index the points given to the measurement.
    """

    kind: ClassVar[str] = "distance"
    n_residuals: ClassVar[int] = 0
    i: int = eqx.field(static=True, default=0)
    j: int = eqx.field(static=True, default=1)

    @property
    def names(self):
        return ("distance",)

    def n_params(self):
        return 0

    def check(self, X, labels):
        X = _np_points(X, "distance", 2)
        n = X.shape[0]
        for v in (self.i, self.j):
            if not -n <= v < n:
                raise ValueError(f"distance: point index {v} out of range for {n} points")
        if self.i % n == self.j % n:
            raise ValueError("distance: the two point indices are the same point")

    def start(self, X, labels):
        return jnp.zeros(0, X.dtype), ()

    def residual(self, y, frame, x, label):
        return jnp.zeros(0, x.dtype)

    def values(self, y, frame, X, labels):
        return jnp.reshape(_safe_norm(X[self.i] - X[self.j]), (1,))
