"""Shared test utilities: tree comparisons, central finite differences, correlated noise
and the calibration covariance as stated before it counted correlated centres."""

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


def ar1_noise(rng, shape, rho):
    """Unit-variance AR(1) noise along the last axis."""
    e = rng.standard_normal(shape)
    x = np.empty_like(e)
    x[..., 0] = e[..., 0]
    for k in range(1, shape[-1]):
        x[..., k] = rho * x[..., k - 1] + np.sqrt(1 - rho**2) * e[..., k]
    return x


def former_fit_covariance(fit):
    """`max(1, s²) (JᵀJ)⁺` of a solve, as fit_diagnostics stated it before it counted the
    correlation of neighbouring centres (same operations: bit-for-bit)."""
    from scheimflux.calibration.core._solve import RANK_RTOL

    H = np.asarray(fit.normal_matrix, dtype=np.float64)
    d = np.sqrt(np.clip(np.diag(H), 0.0, None))
    d = np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 1.0)
    lam, V = np.linalg.eigh(H * np.outer(d, d))
    lam, V = lam[::-1], V[:, ::-1]
    big = max(float(lam[0]), 1e-300)
    keep = lam > RANK_RTOL * big
    inv = np.where(keep, 1.0 / np.where(keep, lam, 1.0), 0.0)
    n, p = int(fit.n_observations), H.shape[0]
    s2 = 2.0 * fit.cost / (n - p)
    return max(1.0, s2) * (d[:, None] * ((V * inv) @ V.T) * d[None, :])
