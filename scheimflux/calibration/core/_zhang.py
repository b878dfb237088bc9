"""Closed-form initialisation from plane homographies (Zhang, 2000); NumPy/OpenCV."""

from __future__ import annotations

import cv2
import numpy as np


def board_homographies(board_xy: np.ndarray, corners: np.ndarray, mask: np.ndarray):
    """Homographies board-plane (mm) → pixels, one per view; None where < 4 corners."""
    out = []
    for uv, m in zip(corners, mask):
        if m.sum() < 4:
            out.append(None)
            continue
        H, _ = cv2.findHomography(board_xy[m], uv[m], 0)
        out.append(None if H is None else H / H[2, 2])
    return out


def _v(H, i, j):
    h = H.T
    return np.array(
        [
            h[i, 0] * h[j, 0],
            h[i, 0] * h[j, 1] + h[i, 1] * h[j, 0],
            h[i, 1] * h[j, 1],
            h[i, 2] * h[j, 0] + h[i, 0] * h[j, 2],
            h[i, 2] * h[j, 1] + h[i, 1] * h[j, 2],
            h[i, 2] * h[j, 2],
        ]
    )


def zhang_intrinsics(homographies: list[np.ndarray]) -> np.ndarray:
    """Pinhole K (with skew) from ≥ 3 homographies; raises ValueError if degenerate."""
    Hs = [H for H in homographies if H is not None]
    if len(Hs) < 3:
        raise ValueError(
            f"closed-form initialisation needs at least 3 views with 4+ corners, got {len(Hs)}"
        )
    # normalise pixel coordinates for conditioning
    rows = []
    for H in Hs:
        rows.append(_v(H, 0, 1))
        rows.append(_v(H, 0, 0) - _v(H, 1, 1))
    V = np.array(rows)
    scale = np.linalg.norm(V, axis=0)
    scale[scale == 0] = 1.0
    _, s, Vt = np.linalg.svd(V / scale)
    b = Vt[-1] / scale
    B11, B12, B22, B13, B23, B33 = b
    if B11 < 0:
        B11, B12, B22, B13, B23, B33 = -b
    den = B11 * B22 - B12**2
    if den <= 0:
        raise ValueError("views are degenerate for the closed-form initialisation (tilt the board)")
    y0 = (B12 * B13 - B11 * B23) / den
    lam = B33 - (B13**2 + y0 * (B12 * B13 - B11 * B23)) / B11
    if lam / B11 <= 0 or lam * B11 / den <= 0:
        raise ValueError("views are degenerate for the closed-form initialisation (tilt the board)")
    alpha = np.sqrt(lam / B11)
    beta = np.sqrt(lam * B11 / den)
    gamma = -B12 * alpha**2 * beta / lam
    x0 = gamma * y0 / beta - B13 * alpha**2 / lam
    return np.array([[alpha, gamma, x0], [0.0, beta, y0], [0.0, 0.0, 1.0]])


def centred_intrinsics(homographies: list[np.ndarray], width: int, height: int) -> np.ndarray:
    """Pinhole K from ≥ 2 homographies with the principal point at the image's centre and
    no skew (OpenCV's `initCameraMatrix2D` start): two unknowns, where Zhang's five fail.

    Zhang's constraints `h₁ᵀ B h₂ = 0`, `h₁ᵀ B h₁ = h₂ᵀ B h₂` with the pixels taken about
    the centre and `B = diag(a, b, c) ∝ K⁻ᵀ K⁻¹`, solved for `(a, b, c)` by SVD:
    `fx = sqrt(c / a)`, `fy = sqrt(c / b)`. Lens distortion (a strong barrel on a webcam)
    biases the homographies enough to leave Zhang's `B` indefinite; this start stays
    usable, and the solve that follows fits the principal point and the distortion.
    Raises ValueError where even this is degenerate (every board parallel to the sensor).
    """
    Hs = [H for H in homographies if H is not None]
    if len(Hs) < 2:
        raise ValueError(
            f"the closed-form initialisation needs 2 views with 4+ corners, got {len(Hs)}"
        )
    c = np.array([(width - 1) / 2, (height - 1) / 2])
    T = np.array([[1.0, 0.0, -c[0]], [0.0, 1.0, -c[1]], [0.0, 0.0, 1.0]])
    rows = []
    for H in Hs:
        G = T @ H
        h1, h2 = G[:, 0], G[:, 1]
        rows.append(h1 * h2)
        rows.append(h1 * h1 - h2 * h2)
    V = np.array(rows)
    scale = np.linalg.norm(V, axis=0)
    scale[scale == 0] = 1.0
    abc = np.linalg.svd(V / scale)[2][-1] / scale
    abc = -abc if abc[2] < 0 else abc
    a, b, cc = abc
    if not (a > 0 and b > 0 and cc > 0):
        raise ValueError("views are degenerate for the closed-form initialisation (tilt the board)")
    return np.array([[np.sqrt(cc / a), 0.0, c[0]], [0.0, np.sqrt(cc / b), c[1]], [0.0, 0.0, 1.0]])


def pose_from_homography(K: np.ndarray, H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Board pose (R_c_b, t_c_b) from K and a board homography, board in front (z > 0)."""
    A = np.linalg.solve(K, H)
    lam = 1.0 / np.linalg.norm(A[:, 0])
    if A[2, 2] * lam < 0:
        lam = -lam
    r1, r2, t = lam * A[:, 0], lam * A[:, 1], lam * A[:, 2]
    R = np.stack([r1, r2, np.cross(r1, r2)], axis=1)
    U, _, Vt = np.linalg.svd(R)
    R = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    return R, t
