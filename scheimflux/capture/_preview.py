"""Preview images: what detect saw in one view, drawn over the image.

Drawn: the board region (its outline in cyan, the area outside it dimmed), the target
points with their indices (green; red crosses and a title on a dropped view), the
stripe centres coloured by confidence (blue → red: weak → strong, the strength relative
to the view's 95th percentile) and, in grey, stripe centres the extractor found but
rejected (outside the board region).
"""

from __future__ import annotations

import os

import cv2
import numpy as np

__all__ = ["write_preview"]


def _bgr8(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3:
        img = img[:, :, :3]
    img = img.astype(np.float32)
    lo, hi = np.percentile(img[::4, ::4], [0.5, 99.5])
    img = np.clip((img - lo) / max(float(hi - lo), 1e-6), 0, 1) * 255
    img = img.astype(np.uint8)
    return img if img.ndim == 3 else cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)


def write_preview(
    path: str | os.PathLike,
    image: np.ndarray,
    corners_px: np.ndarray,
    *,
    hull: np.ndarray | None = None,
    stripe=None,
    mask: np.ndarray | None = None,
    title: str = "",
) -> str:
    """Write one overlay PNG (see the module doc).

    **Arguments:**
    - `path`: the PNG to write (replaced if it exists: previews are scratch output).
    - `image`: the view's image (grey or BGR, any depth).
    - `corners_px`: `(M, 2)` target points (NaN where not found).
    - `hull`: board-region outline `(P, 2)`; `mask`: board region `(H, W)` bool.
    - `stripe`: a `StripeResult` (or None).
    - `title`: text at the top (the reason a view was dropped).

    **Returns:** the path written.
    """
    out = _bgr8(image)
    H, W = out.shape[:2]
    if mask is not None and mask.shape == (H, W):
        out[~mask] = (out[~mask] * 0.45).astype(np.uint8)
    scale = max(1, round(max(H, W) / 800))
    if hull is not None and len(hull) >= 3:
        poly = np.rint(hull * 16).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(out, [poly], True, (255, 255, 0), scale, cv2.LINE_AA, 4)
    if stripe is not None:
        uv, strength = stripe.uv, np.asarray(stripe.strength, np.float64)
        fin = np.all(np.isfinite(uv), axis=1)
        inside = np.zeros(len(uv), bool)
        if mask is not None:
            iu = np.clip(np.rint(uv[fin, 0]).astype(int), 0, W - 1)
            iv = np.clip(np.rint(uv[fin, 1]).astype(int), 0, H - 1)
            inside[fin] = mask[iv, iu]
        good = fin & np.asarray(stripe.valid) & inside
        top = np.percentile(strength[good], 95) if good.any() else 1.0
        level = np.clip(strength / max(top, 1e-12), 0, 1)
        colours = cv2.applyColorMap((level * 255).astype(np.uint8).reshape(-1, 1),
                                    cv2.COLORMAP_JET).reshape(-1, 3)  # fmt: skip
        for i in np.flatnonzero(fin):
            u, v = int(round(uv[i, 0])), int(round(uv[i, 1]))
            c = tuple(int(x) for x in colours[i]) if good[i] else (128, 128, 128)
            out[max(0, v - scale + 1) : v + scale, max(0, u - scale + 1) : u + scale] = c
    dropped = bool(title)
    font = cv2.FONT_HERSHEY_SIMPLEX
    for k, (u, v) in enumerate(np.asarray(corners_px, np.float64)):
        if not (np.isfinite(u) and np.isfinite(v)):
            continue
        p = (int(round(u)), int(round(v)))
        colour = (0, 0, 255) if dropped else (0, 220, 0)
        cv2.drawMarker(out, p, colour, cv2.MARKER_CROSS, 6 * scale, scale, cv2.LINE_AA)
        cv2.putText(out, str(k), (p[0] + 3 * scale, p[1] - 3 * scale), font, 0.35 * scale,
                    colour, max(1, scale // 2), cv2.LINE_AA)  # fmt: skip
    if title:
        cv2.putText(out, title[:120], (10, 24 * scale), font, 0.6 * scale, (0, 0, 255),
                    max(1, scale), cv2.LINE_AA)  # fmt: skip
    path = os.fspath(path)
    if not cv2.imwrite(path, out):
        raise OSError(f"could not write preview {path}")
    return path
