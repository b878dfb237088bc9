"""A non-central thick-lens Scheimpflug camera: the entrance pupil moves with the field.

A real lens is a central camera only to first order. Its chief rays pass through the
centre of the aperture stop, but in object space they cross the optical axis at a point
that moves with the field angle (pupil aberration): for a short wide-angle lens at
finite conjugates this spread reaches a tenth of a millimetre, and a central model then
misplaces points off the plane it was calibrated on. This model keeps every part of
`ThickLensScheimpflug` (sensor, tilt, Newton's formula, distortion in the untilted image
plane) for the pixel's in-focus point and lets the ray's *origin* slide along the axis,
and across it:

    origin = (ax, ay, Δz + Δp),   Δz = c1 ρ² + c2 ρ⁴,   Δp = b1 ρ² + b2 ρ⁴,   ρ² = |ξ_u|²,
    direction ∥ P + (0, 0, Δz) − origin,

where `ξ_u` is the pixel's undistorted coordinate in the untilted image plane (the
normalised image-side field, `z0 ξ_u` in mm on the plane `z = −z0`), `P` the pixel's
conjugate point on the plane of sharp focus (Newton's formula, as in the central model)
and `(ax, ay)` (`lateral`, mm) an offset of the projection centre across the axis. The
ray passes through its in-focus point shifted by `Δz` (`pupil`: the whole ray slides
along the axis) and through the origin, which the **pivot** terms `Δp` (`pivot`) move
further along the axis: the ray turns about its (shifted) in-focus point. With every
coefficient 0 it is exactly the paper's model; with `b1 = b2 = 0` the model with the
sliding ray alone, with `ax = ay = 0` too the axial pupil shift alone (the same
arithmetic).

Why two kinds of shift: measured on the pupil-integrated 8 mm Tessar at ×0.5
(noise-free, 15 views; docs/noncentral.md), the sliding ray describes the chief rays'
pupil aberration (the pivot alone: 0.070 against 0.021 µm on chief-ray data), but where
the lens vignettes, a pixel records the centroid of a clipped bundle, which the
bundle's in-focus point anchors (every ray of a bundle meets there) while the clipped
pupil's centroid moves off its centre: a ray turning about its in-focus point. There
the sliding ray alone left 0.105 µm, the pivot alone 0.088 µm, both 0.045 µm, the
same as on the lens with its vignetting removed.

Why a lateral offset: a sensor records the centroid of each point's bundle. Measured
with `simulate._pupil` on the 8 mm Tessar at ×0.5 (`benchmarks/raxels.py`), the object
points that image to one unvignetted pixel lie on a line turned from the chief ray by
56–265 µrad that passes the axis at up to ~4.6 µm instead of meeting it (the chief rays
meet it to rounding), as if the projection centre sat ~4.5 µm off the axis, on the side
of the sensor tilt. (The likely mechanism, not separately measured: a defocused cone
meets the tilted sensor at an obliquity that varies across it, so its centroid moves
with the defocus.) A model whose rays meet the axis can only imitate it
with its tilt and axis point (docs/noncentral.md).

Back-projection (pixel → ray) is closed form given the undistortion. Projection
(point → pixel) solves the fixed point of the two shifts `s = (Δz, Δp) = F(s)`: given
`s`, the pixel of `X` is the one whose in-focus point `P` satisfies
`P − a ∝ X − o`, `o = (ax, ay, Δz + Δp)`, `a = (ax, ay, Δp)`, one 3×3 solve
(`K_a = K_f − a ⊗ w`, `w` the last row of the homogeneous pixel → object map:
`K_a p̃ ∝ P − a`), and `F(s)` the shifts at that pixel's field. The shifts change the
field by about `ρ |s| / Z` (Z the object distance, ~10² mm), so the map contracts by
orders of magnitude per step. A fixed number of steps runs on constants; one Newton
step at the fixed point carries the derivative (the implicit function theorem,
`ds = (I − F′)⁻¹ ∂F`, exact), and a point whose residual is not at rounding level is
reported invalid, never as a silent NaN or a wrong pixel.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ._base import AbstractCamera, Ray
from ._distortion import AbstractDistortion, NoDistortion
from ._thick_lens import ThickLensScheimpflug, _homogeneous, check_thick_lens_values

_SHIFT_STEPS = 6
# max |s − F(s)| after the steps (the shifts, mm), relative to max(1 mm, |s|): float64 rounding
# of the 3×3 solve is ~1e-15 relative; 1e-12 leaves room and still rejects any point
# whose fixed point did not contract (it would be off by ≥ the contraction factor).
_SHIFT_TOL = {jnp.dtype(jnp.float64): 1e-12, jnp.dtype(jnp.float32): 1e-5}



class ThickLensNonCentral(AbstractCamera):
    """Thick lens with a tilted sensor and a field-dependent entrance pupil.

    The ray of a pixel (with `lateral` and `pivot` 0) has the direction of
    `ThickLensScheimpflug`'s ray (same fields, same meaning) and starts on the optical
    axis at `z = c1 ρ² + c2 ρ⁴` (mm), `ρ` the pixel's undistorted normalised radius in
    the untilted image plane; `lateral = [ax, ay]` (mm) moves the start across the axis,
    and the ray then passes through the pixel's in-focus point shifted by the same `Δz`;
    `pivot = [b1, b2]` (mm) moves the start further along the axis by
    `b1 ρ² + b2 ρ⁴`, turning the ray about that point (module docstring).
    `pupil = [c1, c2]` (mm); `pupil`, `lateral` and `pivot` zero give the paper's
    central model.

    **Fields:** those of `ThickLensScheimpflug` (`f`, `e`, `z0`, `phi`, `theta`, `x0`,
    `y0`, `dx`, `dy`, `distortion`), `pupil` (shape (2,), mm), `lateral` (shape (2,),
    mm; default 0) and `pivot` (shape (2,), mm; default 0).
    """

    f: Float[Array, ""]
    e: Float[Array, ""]
    z0: Float[Array, ""]
    phi: Float[Array, ""]
    theta: Float[Array, ""]
    x0: Float[Array, ""]
    y0: Float[Array, ""]
    dx: Float[Array, ""]
    dy: Float[Array, ""]
    distortion: AbstractDistortion
    pupil: Float[Array, "2"]
    lateral: Float[Array, "2"]
    pivot: Float[Array, "2"]

    def __init__(self, f, e, z0, phi, theta, x0, y0, dx, dy, distortion=None, pupil=None,
                 lateral=None, pivot=None):  # fmt: skip
        self.f, self.e, self.z0 = (jnp.asarray(v, dtype=float) for v in (f, e, z0))
        self.phi, self.theta = (jnp.asarray(v, dtype=float) for v in (phi, theta))
        self.x0, self.y0 = (jnp.asarray(v, dtype=float) for v in (x0, y0))
        self.dx, self.dy = (jnp.asarray(v, dtype=float) for v in (dx, dy))
        self.distortion = NoDistortion() if distortion is None else distortion
        self.pupil = jnp.zeros(2) if pupil is None else jnp.asarray(pupil, dtype=float)
        self.lateral = jnp.zeros(2) if lateral is None else jnp.asarray(lateral, dtype=float)
        self.pivot = jnp.zeros(2) if pivot is None else jnp.asarray(pivot, dtype=float)

    def __check_init__(self):
        for name in ("f", "e", "z0", "phi", "theta", "x0", "y0", "dx", "dy"):
            if jnp.shape(getattr(self, name)) != ():
                raise ValueError(f"ThickLensNonCentral.{name} must be a scalar")
        check_thick_lens_values("ThickLensNonCentral", self)
        if jnp.shape(self.pupil) != (2,):
            raise ValueError(
                f"ThickLensNonCentral.pupil must have shape (2,) (c1, c2), "
                f"got {jnp.shape(self.pupil)}"
            )
        if jnp.shape(self.lateral) != (2,):
            raise ValueError(
                f"ThickLensNonCentral.lateral must have shape (2,) (ax, ay), "
                f"got {jnp.shape(self.lateral)}"
            )
        if jnp.shape(self.pivot) != (2,):
            raise ValueError(
                f"ThickLensNonCentral.pivot must have shape (2,) (b1, b2), "
                f"got {jnp.shape(self.pivot)}"
            )

    def parameters_ok(self):
        return super().parameters_ok() & (self.f > 0) & (self.dx > 0) & (self.dy > 0)

    @classmethod
    def from_central(cls, camera: ThickLensScheimpflug, pupil=None, lateral=None,
                     pivot=None) -> ThickLensNonCentral:  # fmt: skip
        """The non-central camera with `camera`'s parameters, `pupil`, `lateral` and
        `pivot` (default 0)."""
        names = ("f", "e", "z0", "phi", "theta", "x0", "y0", "dx", "dy")
        return cls(*(getattr(camera, n) for n in names), camera.distortion, pupil, lateral,
                   pivot)  # fmt: skip

    @property
    def central(self) -> ThickLensScheimpflug:
        """The central part: the same camera with the pupil fixed at the origin."""
        return ThickLensScheimpflug(
            self.f, self.e, self.z0, self.phi, self.theta,
            self.x0, self.y0, self.dx, self.dy, self.distortion,
        )  # fmt: skip

    @property
    def c1(self) -> Float[Array, ""]:
        """The ρ² coefficient of the pupil shift (mm)."""
        return self.pupil[0]

    @property
    def c2(self) -> Float[Array, ""]:
        """The ρ⁴ coefficient of the pupil shift (mm)."""
        return self.pupil[1]

    @property
    def ax(self) -> Float[Array, ""]:
        """The projection centre's offset across the axis, x (mm)."""
        return self.lateral[0]

    @property
    def ay(self) -> Float[Array, ""]:
        """The projection centre's offset across the axis, y (mm)."""
        return self.lateral[1]

    @property
    def b1(self) -> Float[Array, ""]:
        """The ρ² coefficient of the pivot shift (mm)."""
        return self.pivot[0]

    @property
    def b2(self) -> Float[Array, ""]:
        """The ρ⁴ coefficient of the pivot shift (mm)."""
        return self.pivot[1]

    @property
    def is_distorted(self) -> bool:
        return not isinstance(self.distortion, NoDistortion)

    def shifts(self, xi_u: Float[Array, "2"]) -> Float[Array, "2"]:
        """`(Δz, Δp)` (mm): the ray's slide along the axis and the origin's further
        (pivot) shift, at the undistorted untilted coordinate `ξ_u`."""
        r2 = jnp.sum(xi_u * xi_u)
        c = jnp.stack([self.pupil, self.pivot])
        return r2 * (c[:, 0] + c[:, 1] * r2)

    # --- pixel → ray (closed form given the undistortion) -------------------------------
    def backproject_one(self, uv):
        ray, ok = self.backproject_one_with_mask(uv)
        return Ray(jnp.where(ok, ray.origin, jnp.nan), jnp.where(ok, ray.direction, jnp.nan))

    def backproject_one_with_mask(self, uv):
        c = self.central
        ok = jnp.all(jnp.isfinite(uv))
        uv = jnp.where(ok, uv, jnp.stack([self.x0, self.y0]).astype(uv.dtype))
        xi = c._untilted(c.sensor_point(uv))
        if self.is_distorted:
            xi, ok_u = c._undistort(xi)
            uv = c._sensor_pixel(xi)
            ok = ok & ok_u
        Ph = c.pixel_to_object_matrix() @ _homogeneous(uv)
        ok = ok & (Ph[3] != 0) & jnp.all(jnp.isfinite(Ph)) & jnp.all(jnp.isfinite(xi))
        P = Ph[:3] / jnp.where(ok, Ph[3], jnp.ones_like(Ph[3]))
        ok = ok & (jnp.sum(P * P) > 0)
        P = jnp.where(ok, P, jnp.zeros_like(P).at[2].set(1.0))
        xi = jnp.where(ok, xi, jnp.zeros_like(xi))
        dz, dp = self.shifts(xi).astype(P.dtype)
        origin = self._origin(dz + dp, P.dtype)
        D = P - self._origin(dp, P.dtype)  # P + (0, 0, Δz) − origin
        ok = ok & (jnp.sum(D * D) > 0)
        D = jnp.where(ok, D, jnp.zeros_like(D).at[2].set(1.0))
        return Ray(origin, D / jnp.linalg.norm(D)), ok

    # --- point → pixel (convergence-checked fixed point of the two shifts) ---------------
    def _ideal(self, Y: Float[Array, "3"], dp):
        """Undistorted pixel, field `ξ_u` and validity of the point `o + Y`, `o` the ray
        origin, for the pivot shift `dp`: the pixel whose in-focus point `P` satisfies
        `P − a ∝ Y`, `a = (ax, ay, dp)` (module docstring)."""
        c = self.central
        M = c.pixel_to_object_matrix()
        a = self._origin(dp, M.dtype)
        K_a = M[:3] - a[:, None] * M[3][None, :]  # K_a p̃ ∝ P − a
        pix = jnp.linalg.solve(K_a, Y)
        uv = pix[:2] / pix[2]
        w = M[3] @ _homogeneous(uv)
        valid = (pix[2] * w > 0) & jnp.all(jnp.isfinite(uv))
        return uv, c._untilted(c.sensor_point(uv)), valid

    def _origin(self, s, dtype) -> Float[Array, "3"]:
        """The ray origin `(ax, ay, s)` for the axial shift `s`."""
        return jnp.concatenate([self.lateral.astype(dtype), jnp.reshape(s, (1,)).astype(dtype)])

    def _shift_map(self, s, X):
        """`F(s)`: the shifts `(Δz, Δp)` at the field of the pixel that sees `X` when the
        shifts are `s`."""
        _, xi, _ = self._ideal(X - self._origin(s[0] + s[1], X.dtype), s[1])
        return self.shifts(xi).astype(X.dtype)

    def solve_shift(self, X: Float[Array, "3"]) -> tuple[Float[Array, "2"], Bool[Array, ""]]:
        """The shifts `s = (Δz, Δp)` of the ray through `X` and whether the solve converged.

        `_SHIFT_STEPS` fixed-point steps on constants, then one differentiable Newton step
        `s ← s − (I − F′)⁻¹ (s − F(s))` with `F′` held (its derivative is the implicit
        one, `ds = (I − F′)⁻¹ ∂F`), then the residual check.
        """
        const = jax.lax.stop_gradient(self)
        Xc = jax.lax.stop_gradient(X)
        s = jnp.zeros(2, X.dtype)
        for _ in range(_SHIFT_STEPS):
            s = const._shift_map(s, Xc)
        s = jnp.where(jnp.isfinite(s), s, jnp.zeros_like(s))
        dF = jax.lax.stop_gradient(jax.jacfwd(lambda t: const._shift_map(t, Xc))(s))
        # a contraction by at least 2× (∞-norm), so that I − F′ is well conditioned
        ok = jnp.all(jnp.isfinite(dF)) & (jnp.max(jnp.sum(jnp.abs(dF), axis=1)) < 0.5)
        A = jnp.eye(2, dtype=X.dtype) - jnp.where(ok, dF, jnp.zeros_like(dF))
        s_new = s - jnp.linalg.solve(A, s - self._shift_map(s, X))
        done = jax.lax.stop_gradient(s_new)
        err = jnp.max(jnp.abs(done - const._shift_map(done, Xc)))
        tol = _SHIFT_TOL.get(jnp.dtype(X.dtype), 1e-5)
        ok = ok & jnp.isfinite(err) & (err <= tol * jnp.maximum(1.0, jnp.max(jnp.abs(s))))
        return jnp.where(ok, s_new, jnp.zeros_like(s_new)), ok

    def project_one(self, X):
        s, ok = self.solve_shift(X)
        uv, xi, valid = self._ideal(X - self._origin(s[0] + s[1], X.dtype), s[1])
        if self.is_distorted:
            uv = self.central._sensor_pixel(self.distortion.distort(xi))
            valid = valid & jnp.all(jnp.isfinite(uv))
        return uv, valid & ok
