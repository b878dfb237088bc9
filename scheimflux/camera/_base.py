"""The camera interface: project points to pixels and back-project pixels to rays."""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from .._checks import as_points, batched


class Ray(eqx.Module):
    """A ray `origin + t · direction`, `t > 0`, in the camera frame (mm).

    `direction` is a unit vector pointing into object space.
    """

    origin: Float[Array, "*batch 3"]
    direction: Float[Array, "*batch 3"]


class AbstractCamera(eqx.Module):
    """A camera model: a pytree of parameters with a projection and its inverse.

    Subclasses implement `project_one` and `backproject_one` for a single point; the
    public `project` and `backproject` accept any leading batch shape and run them under
    `jax.vmap`.

    Pixel (0, 0) is the centre of the top-left pixel; u grows to the right, v downwards.
    """

    @abc.abstractmethod
    def project_one(self, X: Float[Array, "3"]) -> tuple[Float[Array, "2"], Bool[Array, ""]]:
        """Pixel of one camera-frame point and whether it is valid (in front of the camera)."""

    @abc.abstractmethod
    def backproject_one(self, uv: Float[Array, "2"]) -> Ray:
        """The object-space ray of one pixel (NaN where the pixel has no ray)."""

    def backproject_one_with_mask(self, uv: Float[Array, "2"]) -> tuple[Ray, Bool[Array, ""]]:
        """The ray of one pixel and whether it is valid, NaN-free even where it is not.

        Where the ray is invalid (a non-finite pixel, a failed undistortion) the returned
        ray is a finite stand-in, so that a masked loss built on it has finite gradients
        for every shared parameter (the double-`where` pattern: NaN never enters the
        computation, instead of being masked afterwards). Cameras whose
        `backproject_one` can produce NaN internally override this; the default covers
        models whose only NaN source is the pixel itself.
        """
        ok_px = jnp.all(jnp.isfinite(uv))
        ray = self.backproject_one(jnp.where(ok_px, uv, jnp.zeros_like(uv)))
        ok = ok_px & jnp.all(jnp.isfinite(ray.direction)) & jnp.all(jnp.isfinite(ray.origin))
        return _finite_ray(ray, ok), ok

    def parameters_ok(self) -> Bool[Array, ""]:
        """Whether the parameters describe a camera at all: every one finite (models add
        their own conditions, e.g. a positive focal length and pixel pitch). Traceable:
        the reconstruction marks every point of an invalid camera `INVALID_CAMERA`, also
        under `jit`, where the constructors' checks cannot run."""
        import jax

        leaves = [x for x in jax.tree.leaves(self) if eqx.is_inexact_array(x)]
        ok = jnp.asarray(True)
        for x in leaves:
            ok = ok & jnp.all(jnp.isfinite(x))
        return ok

    def project(self, X: ArrayLike) -> Float[Array, "*batch 2"]:
        """Pixels of camera-frame points (mm → px).

        Points behind the camera give NaN; use `project_with_mask` to get the mask.
        """
        uv, valid = self.project_with_mask(X)
        return jnp.where(valid[..., None], uv, jnp.nan)

    def project_with_mask(
        self, X: ArrayLike
    ) -> tuple[Float[Array, "*batch 2"], Bool[Array, "*batch"]]:
        """Pixels of camera-frame points and a mask of the valid ones.

        The pixels of invalid points are returned unmasked (finite where the algebra
        allows), which is what a least-squares residual needs.
        """
        X = as_points(X, 3, "X")
        return batched(self.project_one, X, 1)

    def backproject_with_mask(self, uv: ArrayLike) -> tuple[Ray, Bool[Array, "*batch"]]:
        """Rays of pixels (finite stand-ins where invalid) and a mask of the valid ones."""
        uv = as_points(uv, 2, "uv")
        return batched(self.backproject_one_with_mask, uv, 1)

    def backproject(self, uv: ArrayLike) -> Ray:
        """Object-space rays of pixels; `Ray` fields have shape `(*batch, 3)`."""
        uv = as_points(uv, 2, "uv")
        return batched(self.backproject_one, uv, 1)


def _finite_ray(ray: Ray, ok) -> Ray:
    """`ray` where `ok`, else the optical axis (a finite stand-in; gradients stay finite)."""
    axis = jnp.zeros_like(ray.direction).at[..., 2].set(1.0)
    return Ray(
        jnp.where(ok, ray.origin, jnp.zeros_like(ray.origin)),
        jnp.where(ok, ray.direction, axis),
    )
