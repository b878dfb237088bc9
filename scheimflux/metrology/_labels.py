"""Faces of a stepped profile: which point lies on which face (NumPy, before the fit)."""

from __future__ import annotations

import numpy as np

__all__ = ["label_steps"]


def label_steps(points, n_faces: int = 2, *, min_gap_ratio: float = 10.0) -> np.ndarray:
    """Label the points of a stepped profile (or scan) by face, 0 = the lowest offset.

    The points' principal plane is found by SVD; the coordinate that separates parallel
    faces is the one across the faces: the second principal axis for a single profile
    (parallel lines), the third for a scan (parallel planes) — whichever shows the
    `n_faces − 1` largest gaps between sorted coordinates. The faces are split there.

    **Arguments:** `points` `(N, 3)`; `n_faces` ≥ 2; `min_gap_ratio`: each gap must be this
    many times the largest spacing within the faces, or the split is refused.

    **Returns:** `(N,)` int32 labels. **Raises:** `ValueError` when the faces are not
    clearly separated (give the labels explicitly then).
    """
    X = np.asarray(points, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or not np.all(np.isfinite(X)):
        raise ValueError("label_steps: points must be finite, shape (N, 3)")
    if n_faces < 2 or len(X) < 2 * n_faces:
        raise ValueError(f"label_steps: need n_faces >= 2 and 2 points per face, got {len(X)}")
    _, _, vt = np.linalg.svd(X - X.mean(axis=0), full_matrices=False)
    best = None
    for axis in (0, 1, 2):
        t = (X - X.mean(axis=0)) @ vt[axis]
        order = np.argsort(t)
        gaps = np.diff(t[order])
        cut = np.sort(np.argsort(gaps)[-(n_faces - 1) :])
        inner = np.delete(gaps, cut)
        ratio = gaps[cut].min() / max(inner.max() if inner.size else 0.0, 1e-300)
        if best is None or ratio > best[0]:
            best = (ratio, t, order, cut)
    ratio, t, order, cut = best
    if ratio < min_gap_ratio:
        raise ValueError(
            f"label_steps: the {n_faces} faces are not clearly separated (gap ratio "
            f"{ratio:.3g} < {min_gap_ratio:g}): give the labels explicitly"
        )
    labels = np.empty(len(X), np.int32)
    bounds = [0, *(int(c) + 1 for c in cut), len(X)]
    for k in range(n_faces):
        labels[order[bounds[k] : bounds[k + 1]]] = k
    return labels
