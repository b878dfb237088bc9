"""Shared test utilities: tree comparisons and central finite differences."""

import jax
import jax.numpy as jnp
import numpy as np


def tree_allclose(x, y, *, rtol=1e-7, atol=1e-9):
    """True when two pytrees have the same structure and all leaves are close."""
    if jax.tree.structure(x) != jax.tree.structure(y):
        return False
    return all(
        np.allclose(np.asarray(a), np.asarray(b), rtol=rtol, atol=atol, equal_nan=True)
        for a, b in zip(jax.tree.leaves(x), jax.tree.leaves(y))
    )


def central_difference(fn, x, *, step=1e-6):
    """Jacobian of `fn` at the 1-D float64 array `x` by central differences.

    Returns an array of shape `fn(x).shape + x.shape`.
    """
    x = np.asarray(x, dtype=np.float64)
    cols = []
    for i in range(x.size):
        h = step * max(1.0, abs(x[i]))
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        cols.append((np.asarray(fn(jnp.asarray(xp))) - np.asarray(fn(jnp.asarray(xm)))) / (2 * h))
    return np.stack(cols, axis=-1)
