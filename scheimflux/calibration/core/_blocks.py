"""Pieces the residual blocks share: padding of ragged observations to recurring sizes,
the circle-outline model of a dot's image, the Huber loss, and the laser-plane points of
pixels (one back-projection for every block)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float


def padded_length(n: int, minimum: int = 8) -> int:
    """`n` rounded up to one of 8 sizes per octave (≤ 12.5 % padding, at least `minimum`).

    The compiled solvers are cached per array shape and never released, and each XLA
    CPU executable holds thousands of memory mappings: with the exact number of stripe
    points as the padded size, every new data set compiled a new solver and a process
    doing many calibrations ran out of mappings (`vm.max_map_count`) and crashed.
    Rounding to a few sizes per octave makes the shapes, and so the compilations, recur.
    """
    n = max(int(n), minimum)
    step = 1 << max((n - 1).bit_length() - 4, 0)
    return -(-n // step) * step


def _pad(sets: list[np.ndarray], fill: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = padded_length(max([len(s) for s in sets] + [1]))
    out = np.broadcast_to(fill, (len(sets), n, 2)).copy()
    w = np.zeros((len(sets), n))
    for i, s in enumerate(sets):
        s = np.asarray(s, dtype=np.float64).reshape(-1, 2)
        ok = np.all(np.isfinite(s), axis=1)
        out[i, : len(s)][ok] = s[ok]
        w[i, : len(s)] = ok
    return out, w


CIRCLE_VERTICES = 16


def circle_ring(diameter_mm: float, n: int = CIRCLE_VERTICES) -> np.ndarray:
    """`(n, 3)` offsets (mm) of `n` points equally spaced on a circle of `diameter_mm` in
    the board's plane (z = 0), the first on +x."""
    a = 2.0 * np.pi * np.arange(n) / n
    r = 0.5 * float(diameter_mm)
    return np.stack([r * np.cos(a), r * np.sin(a), np.zeros(n)], axis=1)


def _polygon_centroid(p: Float[Array, "*b K 2"]) -> Float[Array, "*b 2"]:
    """Area centroid of the closed polygons `p` (vertices in order, either sense); the
    vertices' mean where a polygon has no area (a disc seen edge-on)."""
    mean = jnp.mean(p, axis=-2)
    q = p - mean[..., None, :]  # about the mean: no cancellation of large pixel values
    q1 = jnp.roll(q, -1, axis=-2)
    c = q[..., 0] * q1[..., 1] - q1[..., 0] * q[..., 1]  # twice each triangle's area
    a = jnp.sum(c, axis=-1)
    scale = jnp.sum(q * q, axis=(-2, -1))
    ok = jnp.abs(a) > 1e-9 * scale
    m = jnp.sum((q + q1) * c[..., None], axis=-2) / (3.0 * jnp.where(ok, a, 1.0))[..., None]
    return mean + jnp.where(ok[..., None], m, 0.0)


def circle_outlines(board, ring) -> Float[Array, "MK 3"]:
    """The outline vertices of every board point's circle, `(M K, 3)`, point by point."""
    return (board[:, None, :] + ring[None, :, :]).reshape(-1, 3)


def outline_centroids(uv: Float[Array, "MK 2"], k: int) -> Float[Array, "M 2"]:
    """The centroids of the circles' images from their projected outlines `uv` (`k`
    vertices per circle, as [`circle_outlines`][]): Richardson's combination of the
    `k`-gon and the `k/2`-gon (see [`board_images_px`][])."""
    uv = uv.reshape(-1, k, 2)
    return (4.0 * _polygon_centroid(uv) - _polygon_centroid(uv[:, ::2])) / 3.0


def _robustify(r, k):
    """Huber loss through the square-root trick: `0.5 r'^2 = huber(r)`."""
    if k is None:
        return r
    a = jnp.abs(r)
    safe = jnp.where(a > k, a, k)
    return jnp.where(a <= k, r, jnp.sign(r) * jnp.sqrt(2 * k * safe - k * k))


def _laser_points_safe(camera, plane, uv):
    """Ray–plane intersections without the NaN masking (for residuals)."""

    def one(p):
        ray = camera.backproject_one(p)
        t = (1.0 - jnp.dot(plane.n, ray.origin)) / jnp.dot(plane.n, ray.direction)
        return ray.origin + t * ray.direction

    return jax.vmap(one)(uv)


def laser_points(camera, plane, *pixel_sets):
    """The laser-plane points `(..., 3)` of several pixel arrays `(..., 2)`, back-projected
    through ONE `vmap` of the camera: a residual function with several blocks of laser
    pixels (board stripes, gauge scan) holds one copy of the camera's back-projection
    (with its undistortion) in its compiled program, not one per block. Each point's
    arithmetic is that of `_laser_points_safe` on its own block."""
    flat = jnp.concatenate([jnp.reshape(p, (-1, 2)) for p in pixel_sets])
    X = _laser_points_safe(camera, plane, flat)
    out, i = [], 0
    for p in pixel_sets:
        n = int(np.prod(p.shape[:-1], dtype=int))
        out.append(X[i : i + n].reshape(*p.shape[:-1], 3))
        i += n
    return out
