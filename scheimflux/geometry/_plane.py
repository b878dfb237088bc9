"""The laser plane `A x + B y + C z = 1` (paper eq. 2)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
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

    @classmethod
    def from_normal_distance(cls, normal, distance) -> LaserPlane:
        """Plane `normal · X = distance` (normal need not be unit; distance ≠ 0, mm)."""
        normal = jnp.asarray(normal, dtype=float)
        normal = normal / jnp.linalg.norm(normal)
        return cls(normal / jnp.asarray(distance, dtype=float))

    @classmethod
    def from_points(cls, p0, p1, p2) -> LaserPlane:
        """Plane through three points (mm)."""
        p0, p1, p2 = (jnp.asarray(p, dtype=float) for p in (p0, p1, p2))
        normal = jnp.cross(p1 - p0, p2 - p0)
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
