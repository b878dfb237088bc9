"""Faces of a stepped profile: which point lies on which face (NumPy, before the fit)."""

from __future__ import annotations

import numpy as np

__all__ = ["label_steps"]


def _runs(order: np.ndarray, cut: np.ndarray, n: int, n_faces: int) -> np.ndarray:
    labels = np.empty(n, np.int32)
    bounds = [0, *(int(c) + 1 for c in cut), n]
    for k in range(n_faces):
        labels[order[bounds[k] : bounds[k + 1]]] = k
    return labels


def label_steps(points, n_faces: int = 2, *, min_gap_ratio: float = 3.0) -> np.ndarray:
    """Label the points of a stepped profile (or scan) by face.

    A single profile (all points in one plane, as camera-frame stripe points): the points
    are ordered along the profile (first principal axis) and split where consecutive
    points jump furthest apart; faces are numbered along the profile. A scan (points
    spread in 3-D) is refused: give its labels.

    **Arguments:** `points` `(N, 3)`; `n_faces` ≥ 2; `min_gap_ratio`: each cut must be
    this many times the largest spacing within the faces, or the split is refused.

    **Returns:** `(N,)` int32 labels. **Raises:** `ValueError` when the faces are not
    clearly separated (give the labels explicitly then).
    """
    X = np.asarray(points, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or not np.all(np.isfinite(X)):
        raise ValueError("label_steps: points must be finite, shape (N, 3)")
    if n_faces < 2 or len(X) < 2 * n_faces:
        raise ValueError(f"label_steps: need n_faces >= 2 and 2 points per face, got {len(X)}")
    n = len(X)
    c = X.mean(axis=0)
    _, s, vt = np.linalg.svd(X - c, full_matrices=False)
    if s[2] > 1e-9 * s[0]:
        raise ValueError(
            "label_steps: automatic faces only for a single profile (points in one plane); "
            "give the labels of a scan"
        )
    order = np.argsort((X - c) @ vt[0])
    jumps = np.linalg.norm(np.diff(X[order], axis=0), axis=1)
    cut = np.sort(np.argsort(jumps)[-(n_faces - 1) :])
    inner = np.delete(jumps, cut)
    ratio = jumps[cut].min() / max(inner.max() if inner.size else 0.0, 1e-300)
    if ratio < min_gap_ratio:
        raise ValueError(
            f"label_steps: the {n_faces} faces are not clearly separated (gap ratio "
            f"{ratio:.3g} < {min_gap_ratio:g}): give the labels explicitly"
        )
    return _runs(order, cut, n, n_faces)
