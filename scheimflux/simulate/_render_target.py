"""Render any calibration target (checkerboard, ChArUco, circle grid) through a board-plane
→ pixel map, such as the ray-traced rig.

Checkerboards go to the analytic renderer `render_checkerboard`. Other targets are
printed patterns: the target draws itself as a texture (`pattern(px_per_mm)`), and each
image pixel averages `supersample²` bilinear texture samples taken at the board
coordinates of points spread over the pixel (the inverse map `board_map`, as for the
checkerboard). The texture is chosen so that a texel is a quarter of the smallest
pixel footprint on the board and, for ChArUco boards, so that square edges fall on texel
edges; the box filter is then symmetric about every edge and corner, so corner and
circle-centre positions are unbiased to far below 0.01 px.

A white quiet zone `margin_mm` wide surrounds the target and a grey background lies
beyond it. Pixel (0, 0) is the centre of the top-left pixel.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from ._render_board import _finish, board_map, render_checkerboard

__all__ = ["render_target"]

_MAX_TEXELS = 8192  # per side of the texture


def _footprint_mm(bmap, shape) -> float:
    """Smallest side (mm) of a pixel's footprint on the board, over a few image rows."""
    H = shape[0]
    sides = []
    for v in sorted({0, H // 4, H // 2, (3 * H) // 4, H - 1}):
        r = bmap.rows(v, v + 1)
        ok = r["valid"]
        if not ok.any():
            continue
        for a, b in (("x_u", "y_u"), ("x_v", "y_v")):
            sides.append(np.hypot(r[a][ok], r[b][ok]))
    if not sides:
        raise ValueError("the target is nowhere in the image")
    return float(np.min(np.concatenate(sides)))


def render_target(
    target: Any,
    board_to_pixel: Callable,
    *,
    shape: tuple[int, int] = (1200, 1600),
    blur_sigma_px: float | Callable = 0.0,
    vignetting: float = 0.0,
    bit_depth: int = 8,
    black: float = 0.08,
    white: float = 0.85,
    background: float = 0.45,
    noise_sigma: float = 0.0,
    seed: int | None = None,
    margin_mm: float | None = None,
    supersample: int = 4,
    grid_step_px: int = 16,
) -> np.ndarray:
    """Render `target` seen through `board_to_pixel`.

    **Arguments:**
    - `target`: a `Checkerboard` (rendered by `render_checkerboard`), `CharucoBoard` or
      `CircleGrid` (rendered from its `pattern`).
    - `board_to_pixel`: vectorised board-plane `(N, 2)` mm → pixel `(N, 2)` map, as for
      `render_checkerboard` (unmasked beyond the sensor).
    - `shape`, `blur_sigma_px`, `vignetting`, `bit_depth`, `black`, `white`,
      `background`, `noise_sigma`, `seed`, `grid_step_px`: as for `render_checkerboard`.
    - `margin_mm`: white quiet zone around the pattern (default: one square or spacing).
    - `supersample`: texture samples per pixel side.

    **Returns:** the `(H, W)` image, uint8 for 8 bits and uint16 otherwise.
    """
    if getattr(target, "kind", None) == "checkerboard":
        return render_checkerboard(
            target, board_to_pixel, shape=shape, blur_sigma_px=blur_sigma_px,
            vignetting=vignetting, bit_depth=bit_depth, black=black, white=white,
            background=background, noise_sigma=noise_sigma, seed=seed,
            margin_squares=1.0 if margin_mm is None else margin_mm / target.square_mm,
            grid_step_px=grid_step_px,
        )  # fmt: skip
    if not hasattr(target, "pattern"):
        raise TypeError(f"cannot render a {type(target).__name__}")
    if bit_depth not in (8, 12, 16):
        raise ValueError(f"bit_depth must be 8, 12 or 16, got {bit_depth}")
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    if not (noise_sigma >= 0 and 0 <= vignetting < 1):
        raise ValueError("noise_sigma must be >= 0 and vignetting in [0, 1)")
    pitch = float(getattr(target, "square_mm", None) or target.spacing_mm)
    margin = pitch if margin_mm is None else float(margin_mm)
    if not (margin >= 0 and math.isfinite(margin)):
        raise ValueError(f"margin_mm must be >= 0, got {margin_mm}")
    x0, x1, y0, y1 = target.extent_mm
    H, W = int(shape[0]), int(shape[1])
    outer = (x0 - margin, x1 + margin, y0 - margin, y1 + margin)
    bmap = board_map(board_to_pixel, (H, W), outer, grid_step_px=grid_step_px)

    # texels per pitch: an integer (ChArUco square edges on texel edges), a quarter of
    # the pixel footprint or finer, and a texture of at most _MAX_TEXELS per side
    n = math.ceil(4.0 * pitch / _footprint_mm(bmap, (H, W)))
    n = max(4, min(n, int(_MAX_TEXELS * pitch / max(x1 - x0, y1 - y0))))
    ppm = n / pitch
    tex = target.pattern(ppm).astype(np.float32) / 255.0
    tex = black + (white - black) * tex
    pad = int(math.ceil(margin * ppm))
    tex = cv2.copyMakeBorder(tex, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=white)
    tx0, ty0 = x0 - pad / ppm, y0 - pad / ppm

    img = np.empty((H, W), np.float64)
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    block = max(1, (1 << 20) // W)
    for v0 in range(0, H, block):
        v1 = min(H, v0 + block)
        r = bmap.rows(v0, v1)
        acc = np.zeros((v1 - v0, W), np.float64)
        for du in offsets:
            for dv in offsets:
                xs = r["x"] + r["x_u"] * du + r["x_v"] * dv
                ys = r["y"] + r["y_u"] * du + r["y_v"] * dv
                mx = ((xs - tx0) * ppm - 0.5).astype(np.float32)
                my = ((ys - ty0) * ppm - 0.5).astype(np.float32)
                acc += cv2.remap(
                    tex, mx, my, cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=float(background),
                )  # fmt: skip
        block_img = acc / supersample**2
        block_img[~r["valid"]] = background
        img[v0:v1] = block_img
    return _finish(img, bmap, blur_sigma_px, vignetting, noise_sigma, seed, bit_depth)
