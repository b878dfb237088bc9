"""Lens distortion models on the normalised image plane, one point at a time.

A distortion maps an ideal (undistorted) point `xy` of a normalised image plane to the
point `xy_d` where the lens actually images it. The coordinates are dimensionless; the
camera decides the plane and the normalisation (OpenCV: `x = X / Z`, `y = Y / Z`).

Every model has a closed-form direction and an inverse that reports whether it
succeeded: `undistort(xy_d) -> (xy, converged)`. Where the inverse does not exist or was
not found (beyond a fold of the model, a diverged Newton iteration), `xy` is NaN and
`converged` is False — never a silently wrong value.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

NEWTON_STEPS = 20
"""Newton steps taken by the iterative inverses (quadratic convergence: ample)."""

FOLD_SAMPLES = 16
"""Points on the segment centre → solution where the Jacobian must be orientation-kept."""


def _tolerance(dtype) -> float:
    """Residual tolerance of the inverses, relative to `max(1, |xy_d|)`."""
    return 1e-12 if jnp.dtype(dtype) == jnp.float64 else 1e-5


def _as_point(xy, name: str) -> Float[Array, "2"]:
    xy = jnp.asarray(xy)
    if xy.shape != (2,):
        raise ValueError(f"{name} must have shape (2,) (one point), got {xy.shape}")
    if not jnp.issubdtype(xy.dtype, jnp.floating):
        xy = xy.astype(float)
    return xy


def _scalar(v):
    return jnp.asarray(v, dtype=float)


def _check_scalars(obj, names):
    for name in names:
        if jnp.shape(getattr(obj, name)) != ():
            raise ValueError(f"{type(obj).__name__}.{name} must be a scalar")


def _det2(J):
    return J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]


def _solve2(J, r):
    """`J⁻¹ r` for a 2×2 `J` by Cramer's rule, with a safe (unit) determinant if singular."""
    det = _det2(J)
    det = jnp.where(jnp.abs(det) > 1e-300, det, jnp.ones_like(det))
    return jnp.stack([J[1, 1] * r[0] - J[0, 1] * r[1], J[0, 0] * r[1] - J[1, 0] * r[0]]) / det


@eqx.filter_jit
def newton_inverse(
    distortion: AbstractDistortion, xy_d: Float[Array, "2"], *, steps: int = NEWTON_STEPS
) -> tuple[Float[Array, "2"], Bool[Array, ""]]:
    """Invert `distortion.distort` at `xy_d` by a fixed number of Newton steps.

    Starts at `xy_d`, takes `steps` Newton steps with the 2×2 Jacobian from
    `jax.jacfwd`, then checks the result: it is accepted when it is finite, its residual
    `|distort(xy) − xy_d|` is below `1e-12 · max(1, |xy_d|)` (float64; `1e-5` in
    float32), and the Jacobian determinant is positive at `FOLD_SAMPLES` points evenly
    spaced on the segment from the centre to the solution — that is, the point lies on
    the same sheet of the map as the image centre, not beyond a fold (where a strong
    or rational radial term turns the image back on itself, another solution far
    out can reproduce `xy_d` exactly but is not the lens's ray).
    Rejected points give NaN and `converged = False`.

    Derivatives (with respect to `xy_d` and the distortion parameters) come from one
    final Newton step taken outside the loop, which gives the implicit-function
    derivative `J⁻¹` at the solution without differentiating through the iterations.

    Compiled with `eqx.filter_jit`, so eager calls (one point at a time) stay fast.
    """
    nondiff = jax.lax.stop_gradient(distortion)
    target = jax.lax.stop_gradient(xy_d)
    jac = jax.jacfwd(nondiff.distort)

    def step(_, x):
        return x - _solve2(jac(x), nondiff.distort(x) - target)

    x = jax.lax.fori_loop(0, steps, step, target)
    x = jnp.where(jnp.all(jnp.isfinite(x)), x, target)  # keep the last step NaN-free
    # One differentiable Newton step: value unchanged at convergence, derivative J⁻¹.
    x = x - _solve2(jac(x), distortion.distort(x) - xy_d)
    xs = jax.lax.stop_gradient(x)
    residual = jnp.linalg.norm(nondiff.distort(xs) - target)
    # Main sheet: no fold (det J ≤ 0) on the segment from the centre to the solution.
    t = jnp.linspace(1.0 / FOLD_SAMPLES, 1.0, FOLD_SAMPLES, dtype=xs.dtype)
    dets = jax.vmap(lambda ti: _det2(jac(ti * xs)))(t)
    scale = jnp.maximum(1.0, jnp.linalg.norm(target))
    converged = (
        jnp.all(jnp.isfinite(xs)) & (residual <= _tolerance(xy_d.dtype) * scale) & jnp.all(dets > 0)
    )
    return jnp.where(converged, x, jnp.nan), converged


class AbstractDistortion(eqx.Module):
    """A lens distortion of one point on a normalised image plane.

    Subclasses implement `distort` (closed form) and `undistort` (its inverse, with a
    convergence flag). Both take and return one point of shape `(2,)`; batch with
    `jax.vmap` (the cameras do).
    """

    @abc.abstractmethod
    def distort(self, xy: ArrayLike) -> Float[Array, "2"]:
        """The distorted point `xy_d` of an ideal point `xy`."""

    @abc.abstractmethod
    def undistort(self, xy_d: ArrayLike) -> tuple[Float[Array, "2"], Bool[Array, ""]]:
        """The ideal point `xy` with `distort(xy) = xy_d`, and whether it was found.

        Where it was not (`converged = False`), `xy` is NaN.
        """


class NoDistortion(AbstractDistortion):
    """The identity: `xy_d = xy`."""

    def distort(self, xy: ArrayLike) -> Float[Array, "2"]:
        return _as_point(xy, "xy")

    def undistort(self, xy_d: ArrayLike) -> tuple[Float[Array, "2"], Bool[Array, ""]]:
        xy_d = _as_point(xy_d, "xy_d")
        return xy_d, jnp.all(jnp.isfinite(xy_d))


def _rational_prism(x, y, k1, k2, k3, k4, k5, k6, p1, p2, s1, s2, s3, s4):
    """OpenCV's distortion (`cvProjectPoints2Internal`), term for term."""
    r2 = x * x + y * y
    r4 = r2 * r2
    r6 = r4 * r2
    a1 = 2 * x * y
    a2 = r2 + 2 * x * x
    a3 = r2 + 2 * y * y
    cdist = 1 + k1 * r2 + k2 * r4 + k3 * r6
    icdist2 = 1 / (1 + k4 * r2 + k5 * r4 + k6 * r6)
    xd = x * cdist * icdist2 + p1 * a1 + p2 * a2 + s1 * r2 + s2 * r4
    yd = y * cdist * icdist2 + p1 * a3 + p2 * a1 + s3 * r2 + s4 * r4
    return jnp.stack([xd, yd])


def _radial_tangential(x, y, k1, k2, k3, p1, p2):
    """[`_rational_prism`][] with k4 = k5 = k6 = 0 and no thin prism: the same operations
    in the same order less those on the zero terms (×1 and +0, exact), so the compiled
    programs of the default camera hold no arithmetic on constant zeros (XLA keeps
    `x · 0`, which is not 0 for every float). The numbers agree to 1 ulp (XLA's fused
    multiply-adds pair the remaining operations differently)."""
    r2 = x * x + y * y
    r4 = r2 * r2
    r6 = r4 * r2
    a1 = 2 * x * y
    a2 = r2 + 2 * x * x
    a3 = r2 + 2 * y * y
    cdist = 1 + k1 * r2 + k2 * r4 + k3 * r6
    xd = x * cdist + p1 * a1 + p2 * a2
    yd = y * cdist + p1 * a3 + p2 * a1
    return jnp.stack([xd, yd])


class RadialTangential(AbstractDistortion):
    """Brown–Conrady radial + tangential distortion, as OpenCV's 5 coefficients.

    With `r² = x² + y²`:
    `x_d = x (1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2x²)`,
    `y_d = y (1 + k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2y²) + 2 p2 x y`.
    """

    k1: Float[Array, ""]
    k2: Float[Array, ""]
    k3: Float[Array, ""]
    p1: Float[Array, ""]
    p2: Float[Array, ""]

    def __init__(self, k1=0.0, k2=0.0, k3=0.0, p1=0.0, p2=0.0):
        self.k1, self.k2, self.k3 = _scalar(k1), _scalar(k2), _scalar(k3)
        self.p1, self.p2 = _scalar(p1), _scalar(p2)

    def __check_init__(self):
        _check_scalars(self, ("k1", "k2", "k3", "p1", "p2"))

    def distort(self, xy: ArrayLike) -> Float[Array, "2"]:
        xy = _as_point(xy, "xy")
        return _radial_tangential(xy[0], xy[1], self.k1, self.k2, self.k3, self.p1, self.p2)

    def undistort(self, xy_d: ArrayLike) -> tuple[Float[Array, "2"], Bool[Array, ""]]:
        return newton_inverse(self, _as_point(xy_d, "xy_d"))


_OPENCV_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4")


class OpenCVDistortion(AbstractDistortion):
    """OpenCV's full distortion: rational radial, tangential and thin prism (12 numbers).

    With `r² = x² + y²`:
    `x_d = x (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶)
    + 2 p1 x y + p2 (r² + 2x²) + s1 r² + s2 r⁴`, and
    `y_d = y (…)/(…) + p1 (r² + 2y²) + 2 p2 x y + s3 r² + s4 r⁴`.

    The sensor tilt `τx, τy` (OpenCV's coefficients 13 and 14) is not a distortion of
    this plane; `OpenCVCamera` holds it.
    """

    k1: Float[Array, ""]
    k2: Float[Array, ""]
    p1: Float[Array, ""]
    p2: Float[Array, ""]
    k3: Float[Array, ""]
    k4: Float[Array, ""]
    k5: Float[Array, ""]
    k6: Float[Array, ""]
    s1: Float[Array, ""]
    s2: Float[Array, ""]
    s3: Float[Array, ""]
    s4: Float[Array, ""]

    def __init__(
        self,
        k1=0.0,
        k2=0.0,
        p1=0.0,
        p2=0.0,
        k3=0.0,
        k4=0.0,
        k5=0.0,
        k6=0.0,
        s1=0.0,
        s2=0.0,
        s3=0.0,
        s4=0.0,
    ):
        self.k1, self.k2, self.p1, self.p2 = (_scalar(v) for v in (k1, k2, p1, p2))
        self.k3, self.k4, self.k5, self.k6 = (_scalar(v) for v in (k3, k4, k5, k6))
        self.s1, self.s2, self.s3, self.s4 = (_scalar(v) for v in (s1, s2, s3, s4))

    def __check_init__(self):
        _check_scalars(self, _OPENCV_NAMES)

    @classmethod
    def from_coefficients(cls, coeffs: ArrayLike) -> OpenCVDistortion:
        """From the 12 numbers `[k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4]`."""
        coeffs = jnp.asarray(coeffs, dtype=float)
        if coeffs.shape != (12,):
            raise ValueError(f"expected 12 coefficients, got shape {coeffs.shape}")
        return cls(*coeffs)

    @property
    def coefficients(self) -> Float[Array, "12"]:
        """`[k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4]` (OpenCV's order)."""
        return jnp.stack([getattr(self, n) for n in _OPENCV_NAMES])

    def distort(self, xy: ArrayLike) -> Float[Array, "2"]:
        xy = _as_point(xy, "xy")
        return _rational_prism(
            xy[0],
            xy[1],
            self.k1,
            self.k2,
            self.k3,
            self.k4,
            self.k5,
            self.k6,
            self.p1,
            self.p2,
            self.s1,
            self.s2,
            self.s3,
            self.s4,
        )

    def undistort(self, xy_d: ArrayLike) -> tuple[Float[Array, "2"], Bool[Array, ""]]:
        return newton_inverse(self, _as_point(xy_d, "xy_d"))


class Division(AbstractDistortion):
    """Steger's division model: `xy = xy_d / (1 + κ |xy_d|²)`.

    Its undistortion is closed form; its distortion is the closed-form inverse
    `xy_d = 2 xy / (1 + √(1 − 4 κ |xy|²))`. The model is one-to-one while
    `|κ| |xy_d|² < 1` (for κ > 0, `|xy|` peaks at `|xy_d| = 1/√κ`); outside that disc
    `undistort` reports `converged = False`, and `distort` gives NaN where
    `4 κ |xy|² > 1` (no distorted point exists).
    """

    kappa: Float[Array, ""]

    def __init__(self, kappa=0.0):
        self.kappa = _scalar(kappa)

    def __check_init__(self):
        _check_scalars(self, ("kappa",))

    def distort(self, xy: ArrayLike) -> Float[Array, "2"]:
        xy = _as_point(xy, "xy")
        disc = 1 - 4 * self.kappa * (xy[0] ** 2 + xy[1] ** 2)
        ok = disc >= 0
        root = jnp.sqrt(jnp.where(ok, disc, jnp.ones_like(disc)))
        return jnp.where(ok, 2 * xy / (1 + root), jnp.nan)

    def undistort(self, xy_d: ArrayLike) -> tuple[Float[Array, "2"], Bool[Array, ""]]:
        xy_d = _as_point(xy_d, "xy_d")
        kr2 = self.kappa * (xy_d[0] ** 2 + xy_d[1] ** 2)
        xy = xy_d / (1 + kr2)
        converged = (jnp.abs(kr2) < 1) & jnp.all(jnp.isfinite(xy))
        return jnp.where(converged, xy, jnp.nan), converged
