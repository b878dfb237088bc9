"""Input checks that run before tracing, so shape mistakes give a clear message."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def as_points(x, last: int, name: str):
    """Return `x` as a floating array whose last axis has length `last`.

    Raises `ValueError` naming the argument when the shape is wrong, before any tracing.
    Integer input is promoted to the default float type; float32 and float64 are kept;
    float16 and bfloat16 are refused.
    """
    arr = x if hasattr(x, "dtype") and hasattr(x, "shape") else np.asarray(x)
    if arr.ndim == 0 or arr.shape[-1] != last:
        raise ValueError(f"{name} must have shape (..., {last}), got shape {tuple(arr.shape)}")
    if not jnp.issubdtype(arr.dtype, jnp.floating):
        if not (jnp.issubdtype(arr.dtype, jnp.integer) or arr.dtype == bool):
            raise ValueError(f"{name} must be numeric, got dtype {arr.dtype}")
        arr = jnp.asarray(arr, dtype=float)
    elif jnp.dtype(arr.dtype).itemsize < 4:
        # float16 / bfloat16 hold pixels to 1 px above 1024 and points to ~0.1 mm at
        # 150 mm: refused rather than upcast, as the precision is already lost.
        raise ValueError(
            f"{name} is {jnp.dtype(arr.dtype).name}, too coarse for metrology; "
            "pass float32 or float64"
        )
    return jnp.asarray(arr)


def batched(fn, x, core: int):
    """Apply a one-point function `fn` over all leading axes of `x` with `jax.vmap`.

    `core` is the number of trailing axes `fn` consumes. Outputs keep the leading
    batch shape of `x` (an empty batch shape calls `fn` directly).
    """
    batch = x.shape[: x.ndim - core]
    if not batch:
        return fn(x)
    flat = x.reshape((-1,) + x.shape[x.ndim - core :])
    out = jax.vmap(fn)(flat)
    return jax.tree.map(lambda o: o.reshape(batch + o.shape[1:]), out)
