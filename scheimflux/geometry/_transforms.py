"""Rigid transforms as small pytrees, built on jaxlie's SO3.

Naming follows `T_a_b`: the transform maps coordinates in frame b to frame a,
`X_a = R_a_b @ X_b + t_a_b`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, Float


def rotation_matrix(rotvec: Float[Array, "3"]) -> Float[Array, "3 3"]:
    """Rotation matrix of an axis-angle vector (SO3 exponential, safe at zero)."""
    return jaxlie.SO3.exp(rotvec).as_matrix()


def rotation_vector(R: Float[Array, "3 3"]) -> Float[Array, "3"]:
    """Axis-angle vector of a rotation matrix (SO3 logarithm)."""
    return jaxlie.SO3.from_matrix(R).log()


def rot_x(a):
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack([jnp.stack([o, z, z]), jnp.stack([z, c, -s]), jnp.stack([z, s, c])])


def rot_y(a):
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack([jnp.stack([c, z, s]), jnp.stack([z, o, z]), jnp.stack([-s, z, c])])


def rot_z(a):
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack([jnp.stack([c, -s, z]), jnp.stack([s, c, z]), jnp.stack([z, z, o])])


class Pose(eqx.Module):
    """A rigid transform `T_a_b` stored as an axis-angle vector and a translation.

    The axis-angle storage keeps the pytree minimal (6 numbers) so it can be optimised
    directly. Build one from a matrix with `Pose.from_matrix(R, t)`.

    **Fields:**
    - `rotvec`: axis-angle vector of `R_a_b` (rad), shape (3,).
    - `translation`: `t_a_b` (mm), shape (3,).
    """

    rotvec: Float[Array, "3"]
    translation: Float[Array, "3"]

    def __init__(self, rotvec, translation):
        self.rotvec = jnp.asarray(rotvec, dtype=float)
        self.translation = jnp.asarray(translation, dtype=float)

    def __check_init__(self):
        if self.rotvec.shape[-1:] != (3,) or self.rotvec.shape != self.translation.shape:
            raise ValueError(
                "Pose takes a (..., 3) rotation vector and a translation of the same shape, got "
                f"{self.rotvec.shape} and {self.translation.shape}"
            )

    @classmethod
    def from_matrix(cls, R, t) -> Pose:
        R = jnp.asarray(R, dtype=float)
        if R.shape != (3, 3):
            raise ValueError(f"rotation matrix must be 3x3, got {R.shape}")
        if not isinstance(R, jax.core.Tracer):  # concrete: refuse what is not a rotation
            Rn = np.asarray(R)
            if not np.all(np.isfinite(Rn)):
                raise ValueError("rotation matrix is not finite")
            err = float(np.max(np.abs(Rn @ Rn.T - np.eye(3))))
            if err > 1e-6 or np.linalg.det(Rn) < 0:
                raise ValueError(
                    f"not a rotation matrix (|R Rᵀ − I| = {err:.2g}, det = "
                    f"{np.linalg.det(Rn):.6g}; need an orthonormal matrix with det +1)"
                )
        return cls(rotation_vector(R), t)

    @classmethod
    def identity(cls) -> Pose:
        return cls(jnp.zeros(3), jnp.zeros(3))

    @property
    def R(self) -> Float[Array, "3 3"]:
        return rotation_matrix(self.rotvec)

    def as_matrix(self) -> Float[Array, "4 4"]:
        """The homogeneous 4×4 matrix."""
        top = jnp.concatenate([self.R, self.translation[:, None]], axis=1)
        bottom = jnp.array([[0.0, 0.0, 0.0, 1.0]], dtype=top.dtype)
        return jnp.concatenate([top, bottom], axis=0)

    def apply(self, X: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3"]:
        """Map points from frame b to frame a."""
        return X @ self.R.T + self.translation

    def inverse(self) -> Pose:
        """`T_b_a` from `T_a_b`."""
        R = self.R
        return Pose(-self.rotvec, -(R.T @ self.translation))

    def compose(self, other: Pose) -> Pose:
        """`T_a_c = T_a_b ∘ T_b_c` for `self = T_a_b`, `other = T_b_c`."""
        R = self.R @ other.R
        return Pose(rotation_vector(R), self.R @ other.translation + self.translation)
