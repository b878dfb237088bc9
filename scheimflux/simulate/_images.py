"""Render a simulated calibration data set as image files (for `scheimflux detect`).

[`write_scene_images`][] takes a rig, a board and the [`Truth`][] of
[`simulate_observations`][] and writes, into one folder,

- `view_<k>_board.png`: the checkerboard in pose k, rendered through the ray tracer
  (`Rig.project`, inverted numerically by `render_checkerboard`), slightly blurred;
- `view_<k>_stripe.png`: the laser stripe on the board in the same pose, a Gaussian
  line whose exact centre runs through the view's noise-free stripe pixels;
- `scan/frame_<i>.png`: the ring-gauge scan's frames, likewise from the scan pixels.

The names follow `scheimflux detect`'s convention (`IMAGES_DIR` and `--scan SCAN_DIR`).
"""

from __future__ import annotations

import os
import time

import cv2
import numpy as np
from scipy.interpolate import CubicSpline

from ._render_board import render_checkerboard
from ._render_stripe import render_stripe

__all__ = ["write_scene_images"]


def _board_to_pixel(rig, pose):
    """Vectorised board-plane (N, 2) mm → pixel (N, 2) map, unmasked (see render_board)."""
    R = np.asarray(pose.R, dtype=np.float64)
    t = np.asarray(pose.translation, dtype=np.float64)

    def f(xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64)
        X = xy @ R[:, :2].T + t  # z = 0 on the board
        uv, _ = rig.project(X)
        return np.asarray(uv, dtype=np.float64)

    return f


def _stripe_image(shape, pts, **kw) -> np.ndarray:
    """Render a stripe through the exact centres `pts` (K, 2) `(u, v)`; blank image if
    fewer than 2 finite points."""
    h, w = shape
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) >= 2:
        span = np.ptp(pts, axis=0)
        vertical = span[1] > span[0]
        along, across = (pts[:, 1], pts[:, 0]) if vertical else (pts[:, 0], pts[:, 1])
        order = np.argsort(along)
        along, idx = np.unique(along[order], return_index=True)
        across = across[order][idx]
    if len(pts) < 2 or len(along) < 2:
        img, _ = render_stripe(shape, None, peak=0.0, **kw)
        return img
    n_along = h if vertical else w
    lo, hi = float(along[0]), float(along[-1])
    if len(along) >= 4:
        spline = CubicSpline(along, across)

        def centre(s):
            return spline(np.clip(s, lo, hi))
    else:

        def centre(s):
            return np.interp(s, along, across)

    # the stripe exists only between the first and last exact centre
    gaps = []
    start, stop = int(np.ceil(lo)), int(np.floor(hi)) + 1
    if start > 0:
        gaps.append((0, start))
    if stop < n_along:
        gaps.append((stop, n_along + 1))
    img, _ = render_stripe(
        shape,
        centre,
        orientation="vertical" if vertical else "horizontal",
        gaps=gaps,
        **kw,
    )
    return img


def write_scene_images(
    out_dir: str | os.PathLike,
    rig,
    board,
    truth,
    *,
    ambient: str = "low",
    stripe_width_px: float = 5.0,
    bit_depth: int = 8,
    noise_sigma: float = 0.004,
    blur_sigma_px: float = 0.8,
    seed: int = 0,
    overwrite: bool = False,
    verbose: bool = False,
) -> list[str]:
    """Write the board, stripe and gauge-scan images of a simulated data set.

    **Arguments:**
    - `out_dir`: folder for `view_<k>_board.png` and `view_<k>_stripe.png`; the scan
      frames go to `out_dir/scan/frame_<i>.png` (folders created if missing).
    - `rig`: the simulated `Rig` (its `sensor_size` is the image size).
    - `board`: the `Checkerboard`.
    - `truth`: the `Truth` of `simulate_observations(rig, board, ...)`.
    - `ambient`: background of the stripe images, `"dark"`, `"low"` or `"bright"`.
    - `stripe_width_px`: FWHM of the laser line (px).
    - `bit_depth`: 8, 12 or 16 (16-bit PNG above 8).
    - `noise_sigma`: additive Gaussian noise, fraction of full scale.
    - `blur_sigma_px`: Gaussian blur of the board images (px).
    - `seed`: seed of the noise (each image gets its own stream).
    - `overwrite`: replace existing files; otherwise any existing target raises
      `FileExistsError` before anything is written.

    **Returns:** the paths written, views first (board, stripe per view), then the scan.
    """
    out = os.fspath(out_dir)
    scan_dir = os.path.join(out, "scan")
    w, h = (int(s) for s in rig.sensor_size)
    shape = (h, w)
    n_views = len(truth.board_poses)
    n_frames = len(truth.scan_px)
    jobs = []
    for k in range(n_views):
        jobs.append((os.path.join(out, f"view_{k}_board.png"), "board", k))
        jobs.append((os.path.join(out, f"view_{k}_stripe.png"), "stripe", k))
    for i in range(n_frames):
        jobs.append((os.path.join(scan_dir, f"frame_{i}.png"), "scan", i))
    if not overwrite:
        for path, _, _ in jobs:
            if os.path.exists(path):
                raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    os.makedirs(out, exist_ok=True)
    if n_frames:
        os.makedirs(scan_dir, exist_ok=True)

    stripe_kw = dict(
        width_px=float(stripe_width_px),
        ambient=ambient,
        noise_sigma=float(noise_sigma),
        bit_depth=int(bit_depth),
    )
    written = []
    for n, (path, kind, k) in enumerate(jobs):
        t0 = time.perf_counter()
        s = int(seed) * 100003 + n
        if kind == "board":
            img = render_checkerboard(
                board,
                _board_to_pixel(rig, truth.board_poses[k]),
                shape=shape,
                blur_sigma_px=float(blur_sigma_px),
                bit_depth=int(bit_depth),
                noise_sigma=float(noise_sigma),
                seed=s,
            )
        elif kind == "stripe":
            img = _stripe_image(shape, truth.stripe_px[k], seed=s, **stripe_kw)
        else:
            img = _stripe_image(shape, truth.scan_px[k], seed=s, **stripe_kw)
        if not cv2.imwrite(path, img):
            raise OSError(f"could not write {path}")
        written.append(path)
        if verbose:
            print(f"  {os.path.relpath(path, out)}: {time.perf_counter() - t0:.2f} s")
    return written
