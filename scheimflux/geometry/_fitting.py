"""Small geometric fits shared by calibration, diagnostics and the demo (host side, NumPy).

These run on concrete float64 arrays outside traced code: a total-least-squares plane,
unit rows, a right-handed basis perpendicular to directions, and the least-squares rigid
alignment of two point sets (Kabsch).
"""

from __future__ import annotations

import numpy as np


def unit_rows(v: np.ndarray) -> np.ndarray:
    """`v` with every row (last axis) scaled to unit length.

    **Arguments:**
    - `v`: vectors `(..., k)`; a zero row gives NaN (not caught here).

    **Returns:** `v / |v|` along the last axis, same shape.
    """
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def perpendicular_basis(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors `a`, `b` with `(a, b, d)` a right-handed orthonormal basis.

    **Arguments:**
    - `d`: unit directions `(..., 3)`.

    **Returns:** `(a, b)`, each `(..., 3)`: `a ⟂ d` (built from the x axis, or from the
    y axis where `d` is within ~26° of x), `b = d × a`.
    """
    d = np.asarray(d, dtype=np.float64)
    h = np.where(np.abs(d[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    a = unit_rows(np.cross(d, h))
    return a, np.cross(d, a)


def fit_plane_svd(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Total-least-squares plane through 3-D points (SVD of the centred points).

    **Arguments:**
    - `points`: `(N, 3)`, N ≥ 3.

    **Returns:** `(centroid (3,), unit normal (3,), singular values (3,))`; the plane is
    `normal · (X − centroid) = 0`, the normal is the right singular vector of the smallest
    singular value (its sign is SVD's). Collinear points show as `s[1] ≈ 0`: the caller
    decides what is degenerate.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 3:
        raise ValueError(f"a plane needs at least 3 points of shape (N, 3), got {points.shape}")
    c = points.mean(axis=0)
    _, s, Vt = np.linalg.svd(points - c, full_matrices=False)
    return c, Vt[2], s


def rigid_fit(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rotation and translation that best map points `A` onto `B` (Kabsch).

    Minimises `Σ |R A_i + t − B_i|²` over proper rotations (det R = +1, no reflection).

    **Arguments:**
    - `A`, `B`: corresponding points `(N, 3)`.

    **Returns:** `(R (3, 3), t (3,))`.
    """
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    if A.shape != B.shape or A.ndim != 2 or A.shape[1] != 3:
        raise ValueError(f"rigid_fit takes two (N, 3) point sets, got {A.shape} and {B.shape}")
    ca, cb = A.mean(axis=0), B.mean(axis=0)
    U, _, Vt = np.linalg.svd((A - ca).T @ (B - cb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cb - R @ ca


def aligned_distances(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """`|R A_i + t − B_i|` per point after the rigid fit of [`rigid_fit`][].

    What remains after the alignment is a difference of shape. Fewer than 3 points
    determine no rotation: then the plain distances `|A_i − B_i|`.

    **Arguments:**
    - `A`, `B`: corresponding points `(N, 3)`.

    **Returns:** distances `(N,)`, in the points' unit.
    """
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    if len(A) < 3:
        return np.linalg.norm(A - B, axis=-1)
    R, t = rigid_fit(A, B)
    return np.linalg.norm(A @ R.T + t - B, axis=1)
