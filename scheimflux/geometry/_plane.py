"""The laser plane `A x + B y + C z = 1` (paper eq. 2)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float


class LaserPlane(eqx.Module):
    """A plane written as `n · X = 1` with `n = [A, B, C]` (paper eq. 2), camera frame.

    This form cannot hold a plane through the camera origin; such a plane is degenerate
    for triangulation anyway (every ray in it lies in the plane).
    The unit normal is `n / |n|` and the distance of the plane from the origin `1 / |n|`.

    **Fields:**
    - `n`: `[A, B, C]` in 1/mm, shape (3,).
    """

    n: Float[Array, "3"]

    def __init__(self, n):
        self.n = jnp.asarray(n, dtype=float)

    def __check_init__(self):
        if self.n.shape != (3,):
            raise ValueError(f"LaserPlane takes n = [A, B, C] of shape (3,), got {self.n.shape}")
        if isinstance(self.n, jax.core.Tracer):
            return  # traced (jit, vmap, grad): values are checked where they are used
        n = np.asarray(self.n)
        if not np.all(np.isfinite(n)):
            raise ValueError(
                f"LaserPlane n = {n.tolist()} is not finite (a plane n · X = 1 through the "
                "camera centre has infinite n: such a plane cannot triangulate)"
            )
        if not np.any(n):
            raise ValueError("LaserPlane n = [0, 0, 0] describes no plane (n · X = 1 never holds)")

    @classmethod
    def from_normal_distance(cls, normal, distance) -> LaserPlane:
        """Plane `normal · X = distance` (normal need not be unit; distance ≠ 0, mm)."""
        normal = jnp.asarray(normal, dtype=float)
        distance = jnp.asarray(distance, dtype=float)
        if not isinstance(normal, jax.core.Tracer) and not isinstance(distance, jax.core.Tracer):
            if not (np.all(np.isfinite(normal)) and np.any(normal)):
                raise ValueError(f"plane normal must be finite and non-zero, got {normal}")
            if not (np.isfinite(distance) and distance != 0):
                raise ValueError(
                    f"plane distance must be finite and non-zero (mm), got {float(distance)}"
                )
        normal = normal / jnp.linalg.norm(normal)
        return cls(normal / distance)

    @classmethod
    def from_points(cls, p0, p1, p2) -> LaserPlane:
        """Plane through three points (mm)."""
        p0, p1, p2 = (jnp.asarray(p, dtype=float) for p in (p0, p1, p2))
        normal = jnp.cross(p1 - p0, p2 - p0)
        if not any(isinstance(p, jax.core.Tracer) for p in (p0, p1, p2)):
            if not np.any(np.asarray(normal)):
                raise ValueError("LaserPlane.from_points: the three points are collinear")
            if float(jnp.dot(normal, p0)) == 0.0:
                raise ValueError(
                    "LaserPlane.from_points: the plane passes through the camera centre"
                )
        return cls(normal / jnp.dot(normal, p0))

    @property
    def normal(self) -> Float[Array, "3"]:
        """Unit normal, oriented so that the plane is at positive distance along it."""
        return self.n / jnp.linalg.norm(self.n)

    @property
    def distance(self) -> Float[Array, ""]:
        """Distance of the plane from the camera origin (mm)."""
        return 1.0 / jnp.linalg.norm(self.n)

    def signed_distance(self, X: Float[Array, "*batch 3"]) -> Float[Array, "*batch"]:
        """Signed distance (mm) of points from the plane, positive on the far side."""
        return (X @ self.n - 1.0) / jnp.linalg.norm(self.n)
