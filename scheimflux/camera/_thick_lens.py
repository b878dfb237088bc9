"""The thick-lens Scheimpflug camera of Guo, Cui & Wu (Sensors 2024), eqs. (5)–(12)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .._checks import MAX_LENGTH_MM, check_physical, check_tilt
from ..geometry._plane import LaserPlane
from ..geometry._transforms import rot_x, rot_y
from ._base import AbstractCamera, Ray
from ._distortion import AbstractDistortion, NoDistortion, _solve2

_FIXED_POINT_STEPS = 12


def check_thick_lens_values(owner: str, cam) -> None:
    """Physical bounds of a thick-lens camera built from numbers (tracers skipped): f and
    the pixel pitch finite and positive (a negative pitch mirrors the image, f ≤ 0 has no
    real image), the tilt within a Scheimpflug rig's range, lengths and the principal
    pixel finite and within `MAX_LENGTH_MM` (px for x0, y0)."""
    check_physical(owner, "f", cam.f, positive=True, max_abs=MAX_LENGTH_MM, unit="mm")
    for name in ("dx", "dy"):
        check_physical(owner, name, getattr(cam, name), positive=True, max_abs=MAX_LENGTH_MM,
                       unit="mm", why=" (a pixel pitch <= 0 mirrors the image)")  # fmt: skip
    for name in ("e", "z0"):
        check_physical(owner, name, getattr(cam, name), max_abs=MAX_LENGTH_MM, unit="mm")
    for name in ("x0", "y0"):
        check_physical(owner, name, getattr(cam, name), max_abs=MAX_LENGTH_MM, unit="px")
    check_tilt(owner, "phi", cam.phi)
    check_tilt(owner, "theta", cam.theta)


class ThickLensScheimpflug(AbstractCamera):
    """Thick lens with a tilted sensor (paper eqs. 5–12).

    Camera frame: origin at the image-side principal point H′, +z along the optical axis
    towards the object; the object-side principal point is H = (0, 0, e).
    A pixel p = (u, v) lies on the sensor at `P′ = S + R_s [dx (u − x0), dy (v − y0), 0]`
    with `S = (0, 0, −z0)` and `R_s = R_y(θ) R_x(φ)` (eqs. 5–8); its conjugate object
    point follows from Newton's formula (eqs. 9–11),
    `P = (f x′, f y′, (e + f) z′ + e f) / (z′ + f)`.

    As in the paper (eq. 3), the pixel's ray starts at the origin and passes through
    the conjugate point P, so `K_f = (B A)[:3]` acts as a 3×3 projection matrix.

    Lens distortion (optional, beyond the paper) acts in the untilted image plane
    `z = −z0`, as in Steger's tilt-lens models: the ideal image-side ray from H′ meets
    that plane at `z0 · (ξ, −1)`; the lens displaces ξ to `distortion.distort(ξ)`, and the
    displaced ray continues to the tilted sensor. With `NoDistortion()` (the default) the
    model is exactly the paper's.

    **Fields** (mm, rad, px): `f` focal length, `e` principal-plane separation,
    `z0` distance from H′ to where the axis meets the sensor, `phi`, `theta` sensor
    tilt about x and y, `x0`, `y0` pixel where the axis meets the sensor,
    `dx`, `dy` pixel pitch, `distortion` an `AbstractDistortion`.
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

    def __init__(self, f, e, z0, phi, theta, x0, y0, dx, dy, distortion=None):
        self.f, self.e, self.z0 = (jnp.asarray(v, dtype=float) for v in (f, e, z0))
        self.phi, self.theta = (jnp.asarray(v, dtype=float) for v in (phi, theta))
        self.x0, self.y0 = (jnp.asarray(v, dtype=float) for v in (x0, y0))
        self.dx, self.dy = (jnp.asarray(v, dtype=float) for v in (dx, dy))
        self.distortion = NoDistortion() if distortion is None else distortion

    def __check_init__(self):
        for name in ("f", "e", "z0", "phi", "theta", "x0", "y0", "dx", "dy"):
            if jnp.shape(getattr(self, name)) != ():
                raise ValueError(f"ThickLensScheimpflug.{name} must be a scalar")
        check_thick_lens_values("ThickLensScheimpflug", self)

    # --- the matrices of the paper -------------------------------------------------
    def parameters_ok(self):
        return super().parameters_ok() & (self.f > 0) & (self.dx > 0) & (self.dy > 0)

    @property
    def R_s(self) -> Float[Array, "3 3"]:
        """Sensor tilt `R_y(θ) R_x(φ)` (about the point where the axis meets the sensor)."""
        return rot_y(self.theta) @ rot_x(self.phi)

    def sensor_matrix(self) -> Float[Array, "4 3"]:
        """`A` (eq. 8): homogeneous pixel `[u, v, 1]` → homogeneous sensor point."""
        z = jnp.zeros_like(self.f)
        one = jnp.ones_like(self.f)
        pix_to_mm = jnp.stack(
            [
                jnp.stack([self.dx, z, -self.dx * self.x0]),
                jnp.stack([z, self.dy, -self.dy * self.y0]),
                jnp.stack([z, z, one]),
            ]
        )  # eq. 5: [x_im, y_im, 1]
        R = self.R_s
        top = R[:, :2] @ pix_to_mm[:2] + jnp.stack([z, z, -self.z0])[:, None] * pix_to_mm[2]
        return jnp.concatenate([top, pix_to_mm[2:]], axis=0)

    def newton_matrix(self) -> Float[Array, "4 4"]:
        """`B` (eq. 11): homogeneous image point → homogeneous conjugate object point."""
        f, e = self.f, self.e
        z = jnp.zeros_like(f)
        return jnp.stack(
            [
                jnp.stack([f, z, z, z]),
                jnp.stack([z, f, z, z]),
                jnp.stack([z, z, e + f, e * f]),
                jnp.stack([z, z, jnp.ones_like(f), f]),
            ]
        )

    def pixel_to_object_matrix(self) -> Float[Array, "4 3"]:
        """`B A`: homogeneous pixel → homogeneous conjugate object point."""
        return self.newton_matrix() @ self.sensor_matrix()

    @property
    def K_f(self) -> Float[Array, "3 3"]:
        """The paper's 3×3 imaging matrix `K_f` (eq. 12): `X_c = λ K_f [u, v, 1]`."""
        return self.pixel_to_object_matrix()[:3]

    # --- points ---------------------------------------------------------------------
    def sensor_point(self, uv: Float[Array, "2"]) -> Float[Array, "3"]:
        """The sensor point P′ of a pixel, camera frame (mm)."""
        return (self.sensor_matrix() @ _homogeneous(uv))[:3]

    def conjugate(self, P_image: Float[Array, "3"]) -> Float[Array, "3"]:
        """Object point conjugate to an image-space point (Newton's formula)."""
        Ph = self.newton_matrix() @ jnp.append(P_image, jnp.ones((), P_image.dtype))
        return Ph[:3] / Ph[3]

    @property
    def is_distorted(self) -> bool:
        return not isinstance(self.distortion, NoDistortion)

    def project_one(self, X):
        pix = jnp.linalg.solve(self.K_f, X)  # X = λ K_f p̃ with λ = pix[2]
        uv = pix[:2] / pix[2]
        w = self.pixel_to_object_matrix()[3] @ _homogeneous(uv)  # z′ + f of that pixel
        # X lies on the ray from the origin through P = K_f p̃ / w when λ w > 0.
        valid = (pix[2] * w > 0) & jnp.all(jnp.isfinite(uv))
        if self.is_distorted:
            xi = self._untilted(self.sensor_point(uv))
            uv = self._sensor_pixel(self.distortion.distort(xi))
            valid = valid & jnp.all(jnp.isfinite(uv))
        return uv, valid

    def backproject_one(self, uv):
        ray, ok = self.backproject_one_with_mask(uv)
        return Ray(jnp.where(ok, ray.origin, jnp.nan), jnp.where(ok, ray.direction, jnp.nan))

    def backproject_one_with_mask(self, uv):
        # Double `where`: a non-finite pixel or a failed undistortion is replaced by a
        # finite stand-in (the principal pixel / the distorted point) *before* the rest of
        # the computation, so NaN never reaches the primal values and a masked loss keeps
        # finite gradients for the shared parameters.
        ok = jnp.all(jnp.isfinite(uv))
        uv = jnp.where(ok, uv, jnp.stack([self.x0, self.y0]).astype(uv.dtype))
        if self.is_distorted:
            xi, ok_u = self._undistort(self._untilted(self.sensor_point(uv)))
            uv = self._sensor_pixel(xi)
            ok = ok & ok_u
        Ph = self.pixel_to_object_matrix() @ _homogeneous(uv)
        ok = ok & (Ph[3] != 0) & jnp.all(jnp.isfinite(Ph))
        P = Ph[:3] / jnp.where(ok, Ph[3], jnp.ones_like(Ph[3]))
        ok = ok & (jnp.sum(P * P) > 0)
        P = jnp.where(ok, P, jnp.zeros_like(P).at[2].set(1.0))
        return Ray(jnp.zeros_like(P), P / jnp.linalg.norm(P)), ok

    def _undistort(self, xi_d: Float[Array, "2"]) -> tuple[Float[Array, "2"], Bool[Array, ""]]:
        """Invert the distortion by fixed-point iteration, convergence-checked.

        In the untilted plane of a Scheimpflug camera the field is small (|ξ| ≲ 0.02) and
        the distortion's Jacobian is close to the identity, so `ξ ← ξ_d − δ(ξ)` contracts
        by orders of magnitude per step: a few steps reach float64 precision with no
        Jacobian. Where it has not converged (strong distortion, beyond a fold) the flag
        is False and the returned point is the finite stand-in `ξ_d` (the caller masks
        it: `backproject_one` gives a NaN ray, reconstruction reports INVALID_PIXEL).
        """
        # Iterate on constants; the derivative comes from one Newton step at the fixed
        # point (implicit function theorem: dξ = J⁻¹ (dξ_d − ∂δ/∂k dk), J = ∂distort/∂ξ),
        # not from differentiating every iteration — a tenth of the cost in the
        # Jacobians of calibration.
        dist = jax.lax.stop_gradient(self.distortion)
        target = jax.lax.stop_gradient(xi_d)
        # a `lax` loop, not an unrolled Python one: one copy of the distortion in every
        # compiled program that back-projects (the same arithmetic, step for step)
        xi = jax.lax.fori_loop(
            0, _FIXED_POINT_STEPS, lambda _, x: target - (dist.distort(x) - x), target
        )
        xi_c = xi - _solve2(jax.jacfwd(dist.distort)(xi), dist.distort(xi) - target)
        err = jnp.max(jnp.abs(dist.distort(xi_c) - target))
        tol = 1e-13 if xi_d.dtype == jnp.float64 else 1e-6
        ok = jnp.isfinite(err) & (err <= tol * jnp.maximum(1.0, jnp.max(jnp.abs(xi_d))))
        # The differentiable Newton step starts from a finite point in every case.
        xi = jnp.where(ok, xi, target)
        J = jax.jacfwd(dist.distort)(xi)
        xi = xi - _solve2(J, self.distortion.distort(xi) - xi_d)
        return jnp.where(ok, xi, xi_d), ok

    def _untilted(self, P_image: Float[Array, "3"]) -> Float[Array, "2"]:
        """Normalised coordinates ξ where the ray H′ → P′ meets the plane z = −z0."""
        return -P_image[:2] / P_image[2]

    def _sensor_pixel(self, xi: Float[Array, "2"]) -> Float[Array, "2"]:
        """Pixel where the ray from H′ through `z0 (ξ, −1)` meets the tilted sensor."""
        R = self.R_s
        S = jnp.stack([jnp.zeros_like(self.z0), jnp.zeros_like(self.z0), -self.z0])
        w = jnp.stack([xi[0], xi[1], -jnp.ones_like(xi[0])])
        t = jnp.dot(R[:, 2], S) / jnp.dot(R[:, 2], w)
        ab = (R.T @ (t * w - S))[:2]
        return jnp.stack([ab[0] / self.dx + self.x0, ab[1] / self.dy + self.y0])

    def object_point(self, uv: Float[Array, "2"]) -> Float[Array, "3"]:
        """The point on the plane of sharp focus conjugate to a pixel (mm)."""
        Ph = self.pixel_to_object_matrix() @ _homogeneous(uv)
        return Ph[:3] / Ph[3]

    # --- Scheimpflug helpers --------------------------------------------------------
    def focus_plane(self) -> LaserPlane:
        """The plane of sharp focus: the conjugate of the sensor plane."""
        p = [
            self.object_point(jnp.stack([self.x0 + a, self.y0 + b]))
            for a, b in ((0.0, 0.0), (100.0, 0.0), (0.0, 100.0))
        ]
        return LaserPlane.from_points(*p)

    def scheimpflug_line(self) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
        """The hinge of the Scheimpflug condition, as `(point, unit direction)`.

        It is where the plane of sharp focus meets the object-side principal plane
        `z = e`; the sensor plane meets the image-side principal plane `z = 0` in the
        line with the same x, y (principal planes image each other at unit
        magnification). Undefined (infinite) for an untilted sensor.
        """
        n = self.R_s[:, 2]  # sensor normal; sensor plane: n · (P′ − S) = 0
        # image side, z = 0: n_x x + n_y y = n · S = −n_z z0
        d = jnp.stack([-n[1], n[0], jnp.zeros_like(n[0])])
        d = d / jnp.linalg.norm(d)
        k = -n[2] * self.z0 / (n[0] ** 2 + n[1] ** 2)
        point = jnp.stack([k * n[0], k * n[1], self.e])
        return point, d

    def magnification(self, uv: Float[Array, "*batch 2"]) -> Float[Array, "*batch"]:
        """Lateral magnification image/object `x′/x = (z′ + f)/f` at pixels.

        Negative: the image is inverted. The paper's ×1.5 preset gives about −1.57.
        """
        A = self.sensor_matrix()
        z_img = jnp.asarray(uv) @ A[2, :2] + A[2, 2]
        return (z_img + self.f) / self.f


def _homogeneous(uv):
    return jnp.append(uv, jnp.ones((), uv.dtype))
