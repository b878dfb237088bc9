"""The pinhole camera of the paper's comparison (eq. 14)."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from .._checks import MAX_LENGTH_MM, check_physical
from ._base import AbstractCamera, Ray


class Pinhole(AbstractCamera):
    """Pinhole camera `[u, v, 1] ∝ K_h X` with `K_h = [[α, γ, x0], [0, β, y0], [0, 0, 1]]`.

    Projection centre at the origin, looking along +z; α, β, γ, x0, y0 in px.
    """

    alpha: Float[Array, ""]
    beta: Float[Array, ""]
    gamma: Float[Array, ""]
    x0: Float[Array, ""]
    y0: Float[Array, ""]

    def __init__(self, alpha, beta, gamma, x0, y0):
        self.alpha, self.beta, self.gamma = (
            jnp.asarray(v, dtype=float) for v in (alpha, beta, gamma)
        )
        self.x0, self.y0 = (jnp.asarray(v, dtype=float) for v in (x0, y0))

    def __check_init__(self):
        for name in ("alpha", "beta", "gamma", "x0", "y0"):
            if jnp.shape(getattr(self, name)) != ():
                raise ValueError(f"Pinhole.{name} must be a scalar")
        for name in ("alpha", "beta"):  # focal lengths in px
            check_physical("Pinhole", name, getattr(self, name), nonzero=True, unit="px",
                           why=" (a focal length in px; negative for an inverted image)")
        for name in ("gamma", "x0", "y0"):
            check_physical("Pinhole", name, getattr(self, name), max_abs=MAX_LENGTH_MM, unit="px")

    def parameters_ok(self):
        return super().parameters_ok() & (self.alpha != 0) & (self.beta != 0)

    @property
    def K(self) -> Float[Array, "3 3"]:
        z = jnp.zeros_like(self.alpha)
        return jnp.stack(
            [
                jnp.stack([self.alpha, self.gamma, self.x0]),
                jnp.stack([z, self.beta, self.y0]),
                jnp.stack([z, z, jnp.ones_like(z)]),
            ]
        )

    def project_one(self, X):
        p = self.K @ X
        uv = p[:2] / p[2]
        return uv, (X[2] > 0) & jnp.all(jnp.isfinite(uv))

    def backproject_one(self, uv):
        # K is upper triangular: solve by back-substitution (differentiable, exact).
        y = (uv[1] - self.y0) / self.beta
        x = (uv[0] - self.x0 - self.gamma * y) / self.alpha
        d = jnp.stack([x, y, jnp.ones_like(x)])
        return Ray(jnp.zeros_like(d), d / jnp.linalg.norm(d))
