"""A measured value as a pure JAX function of calibration parameters and pixels: the
chain pixel → ray → laser plane (→ measurement frame) → fitted shape, which the
uncertainty budget differentiates."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from ..reconstruct import intersect_ray_plane
from ._lsq import fit_shape
from ._shapes import AbstractShape

__all__ = ["FRAMES", "chain_function"]


FRAMES = ("camera", "measurement")


def _reconstruct_one(params, uv, i, frame):
    ray, ok = params.camera.backproject_one_with_mask(uv)
    X, status = intersect_ray_plane(ray, params.plane, ok)
    if frame == "measurement":
        X = params.stage.to_measurement(X, i)
    return X, status


def chain_function(shape: AbstractShape, params, spec, idx, frame: str = "camera"):
    """The measured values as a JAX function of calibration parameters and pixels.

    **Arguments:**
    - `params`, `spec`: a calibration's parameter pytree and free-parameter filter spec
      (`scheimflux.calibration.residual_function(cal, "joint")[1:]`).
    - `idx`: positions, in the flattened free parameters, of those to differentiate
      (e.g. `diagnostics(cal).select(("camera.", "plane."))`).
    - `frame`: `"camera"` or `"measurement"` (rotary stage, frame index per pixel).

    **Returns:** `(f, theta0)`: `f(theta, uv, frame_index, labels) -> values (K,)` with
    `theta` `(q,)`, `uv` `(N, 2)`, `frame_index` `(N,)`, `labels` `(N,)`; and `theta0`,
    the calibration's values of `theta`. `f` is pure: jit, grad, jacrev, vmap apply.
    """
    if frame not in FRAMES:
        raise ValueError(f"frame must be 'camera' or 'measurement', got {frame!r}")
    free, static = eqx.partition(params, spec)
    x0, unravel = ravel_pytree(free)
    idx = jnp.asarray(idx, dtype=jnp.int32)

    def f(theta, uv, frame_index, labels):
        prm = eqx.combine(unravel(x0.at[idx].set(theta)), static)
        X, _ = jax.vmap(lambda p, i: _reconstruct_one(prm, p, i, frame))(uv, frame_index)
        return fit_shape(shape, X, labels).values

    return f, x0[idx]
