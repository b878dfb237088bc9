"""Render a simulated calibration data set as image files (for `scheimflux detect`).

[`write_scene_images`][] takes a rig, a target and the [`Truth`][] of
[`simulate_observations`][] and writes, into one folder, in one of two layouts:

- `layout="pair"`: `view_<k>_board.<ext>`, the target (checkerboard, ChArUco board or
  circle grid) in pose k, rendered through the ray tracer (`Rig.project`, inverted
  numerically by `render_target`), slightly blurred; and `view_<k>_stripe.<ext>`, the
  laser stripe on the board in the same pose, a Gaussian line whose exact centre runs
  through the view's noise-free stripe pixels;
- `layout="single"`: `view_<k>.<ext>`, one image with both, composed as
  `albedo × (ambient + laser)`: the rendered target is the board's reflectance, lit by
  room light `ambient_level` and by the laser line (peak `laser_peak`), then noise;

and `scan/frame_<i>.<ext>`: the ring-gauge scan's frames, from the scan pixels.
`colour=True` writes 3-channel BGR images with a red laser (the board grey);
`ext="jpg"` writes JPEG (8 bits only). The names follow `scheimflux detect`'s
convention (`IMAGES_DIR` and `--scan SCAN_DIR`).
"""

from __future__ import annotations

import os
import time

import cv2
import numpy as np
from scipy.interpolate import CubicSpline

from ._render_stripe import _ambient as _ambient_field, render_stripe
from ._render_target import render_target

__all__ = ["write_scene_images"]

_STRIPE_PEAK = 0.6  # the stripe images' laser peak on white (`render_stripe`'s default)


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


def _moved(f, motion):
    """The board-to-pixel map `f` of a board slid in its own plane by `motion` =
    `(dx_mm, dy_mm, rot_deg)`: the print's point `xy` lies where the unmoved board's point
    `R(rot) xy + (dx, dy)` was (the rotation about the board's origin)."""
    dx, dy, rot = (float(m) for m in motion)
    c, s = np.cos(np.radians(rot)), np.sin(np.radians(rot))
    R = np.array([[c, -s], [s, c]])
    d = np.array([dx, dy])

    def g(xy: np.ndarray) -> np.ndarray:
        return f(np.asarray(xy, dtype=np.float64) @ R.T + d)

    return g


def _motions(motion, n_views: int) -> list:
    """`stripe_board_motion` as one `(dx_mm, dy_mm, rot_deg)` or None per view."""
    if motion is None:
        return [None] * n_views
    m = list(motion)
    if len(m) in (2, 3) and all(np.isscalar(x) for x in m):
        m = [tuple(m)] * n_views
    if len(m) != n_views:
        raise ValueError(
            f"stripe_board_motion: one (dx_mm, dy_mm[, rot_deg]) for all views or one per "
            f"view ({n_views}), got {len(m)} entries"
        )
    out = []
    for k, mk in enumerate(m):
        if mk is None:
            out.append(None)
            continue
        mk = tuple(float(x) for x in mk)
        if len(mk) not in (2, 3) or not all(np.isfinite(mk)):
            raise ValueError(
                f"stripe_board_motion of view {k} must be finite (dx_mm, dy_mm[, rot_deg]), "
                f"got {mk}"
            )
        out.append(mk + (0.0,) * (3 - len(mk)))
    return out


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
        step = np.diff(along)
        if np.any(step > 0) and np.any(step < 0):
            # not one centre per column or row (an arc that turns back, as a ring smaller
            # than the field images): the curve through the points in their order
            pts = pts[np.concatenate([[True], np.linalg.norm(np.diff(pts, axis=0), axis=1) > 0])]
            img, _ = render_stripe(shape, pts, orientation="curve", **kw)
            return img
        order = np.argsort(along)
        along, idx = np.unique(along[order], return_index=True)
        across = across[order][idx]
    if len(pts) < 2 or len(along) < 2:
        img, _ = render_stripe(shape, None, **{**kw, "peak": 0.0})
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


_EXTS = ("png", "jpg", "jpeg", "tif", "tiff", "bmp")


def _write(path: str, img: np.ndarray, ext: str, jpeg_quality: int) -> None:
    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if ext in ("jpg", "jpeg") else []
    if not cv2.imwrite(path, img, params):
        raise OSError(f"could not write {path}")


def _quantise(img: np.ndarray, bit_depth: int) -> np.ndarray:
    full = float(2**bit_depth - 1)
    out = np.rint(np.clip(img, 0.0, 1.0) * full)
    return out.astype(np.uint8 if bit_depth == 8 else np.uint16)


def write_scene_images(
    out_dir: str | os.PathLike,
    rig,
    board,
    truth,
    *,
    layout: str = "pair",
    ext: str = "png",
    colour: bool = False,
    jpeg_quality: int = 95,
    ambient: str | float = "low",
    ambient_level: float = 0.55,
    laser_peak: float = 0.6,
    stripe_width_px: float = 5.0,
    bit_depth: int = 8,
    noise_sigma: float = 0.004,
    blur_sigma_px: float = 0.8,
    seed: int = 0,
    stripe_on_board: bool = True,
    stripe_board_motion=None,
    overwrite: bool = False,
    verbose: bool = False,
) -> list[str]:
    """Write the board, stripe and gauge-scan images of a simulated data set.

    **Arguments:**
    - `out_dir`: folder for the view images; the scan frames go to
      `out_dir/scan/frame_<i>.<ext>` (folders created if missing).
    - `rig`: the simulated `Rig` (its `sensor_size` is the image size).
    - `board`: the target (`Checkerboard`, `CharucoBoard` or `CircleGrid`).
    - `truth`: the `Truth` of `simulate_observations(rig, board, ...)`.
    - `layout`: `"pair"` (board and stripe images) or `"single"` (one image per view).
    - `ext`: file type, one of png, jpg, jpeg, tif, tiff, bmp.
    - `colour`: 3-channel BGR images, red laser.
    - `jpeg_quality`: JPEG quality (0–100).
    - `ambient`: background of the stripe images (pair layout, scan), `"dark"`, `"low"`
      or `"bright"`, or a uniform level (fraction of full scale; 0: room light off).
    - `ambient_level`, `laser_peak`: room light and laser peak (fractions of full scale
      on a white surface) of the single layout; a `laser_peak` far above
      `1 - ambient_level` renders an overexposed line, clipped into a plateau wider than
      the line (e.g. `0.6 * 255`: about 14 px for a 5 px line).
    - `stripe_width_px`: FWHM of the laser line (px).
    - `bit_depth`: 8, 12 or 16 (16-bit PNG/TIFF above 8; JPEG and BMP need 8).
    - `noise_sigma`: additive Gaussian noise, fraction of full scale.
    - `blur_sigma_px`: Gaussian blur of the board images (px).
    - `seed`: seed of the noise (each image gets its own stream).
    - `stripe_on_board`: the pair layout's stripe images on the board's albedo, as a
      laser-only exposure of the printed board sees it: `albedo x (ambient + 0.6 x
      line)` (the `ambient` field and the stripe's peak as on a plain surface), so the
      line is dimmer on the dark print and the print shows faintly (default, as a real
      pair capture); False: on a plain surface (albedo 1), which no real pair shows (its
      board image holds the print, its stripe image none).
    - `stripe_board_motion`: the board slid in its own plane between a pair's two
      exposures (pair layout, `stripe_on_board`: in the stripe image; single layout: in
      the image, e.g. a laser-off image, `laser_peak=0`, beside an unmoved laser-on
      one): `(dx_mm, dy_mm[, rot_deg])` for every view, or a sequence of them (None:
      not moved) per view. The moved image's print point `xy` lies where the unmoved
      board's point `R(rot) xy + (dx, dy)` was (rotation about the board's origin); the
      laser line stays where it was (the board's plane and the laser plane do not move,
      so neither does their intersection). None (default): the board did not move.
    - `overwrite`: replace existing files; otherwise any existing target raises
      `FileExistsError` before anything is written.

    **Returns:** the paths written, views first (board then stripe per view in the pair
    layout), then the scan.
    """
    if layout not in ("pair", "single"):
        raise ValueError(f"layout must be 'pair' or 'single', got {layout!r}")
    ext = str(ext).lower().lstrip(".")
    if ext not in _EXTS:
        raise ValueError(f"ext must be one of {', '.join(_EXTS)}, got {ext!r}")
    if ext in ("jpg", "jpeg", "bmp") and bit_depth != 8:
        raise ValueError(f"{ext} images hold 8 bits; got bit_depth={bit_depth}")
    out = os.fspath(out_dir)
    scan_dir = os.path.join(out, "scan")
    w, h = (int(s) for s in rig.sensor_size)
    shape = (h, w)
    n_views = len(truth.board_poses)
    n_frames = len(truth.scan_px)
    motions = _motions(stripe_board_motion, n_views)
    if any(m is not None for m in motions) and layout == "pair" and not stripe_on_board:
        raise ValueError("stripe_board_motion of a pair needs stripe_on_board=True")
    jobs = []
    for k in range(n_views):
        if layout == "single":
            jobs.append((os.path.join(out, f"view_{k}.{ext}"), "single", k))
        else:
            jobs.append((os.path.join(out, f"view_{k}_board.{ext}"), "board", k))
            jobs.append((os.path.join(out, f"view_{k}_stripe.{ext}"), "stripe", k))
    for i in range(n_frames):
        jobs.append((os.path.join(scan_dir, f"frame_{i}.{ext}"), "scan", i))
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

    def on_board(f, k, light, peak, seed):
        """The print lit by `light` (a level or an (H, W) field) and the laser line of
        view `k` (peak `peak` on white) on it: `albedo x (light + peak x line)`, noise
        added per channel; the room light grey on every channel and the red laser on R
        alone in colour."""
        albedo = render_target(
            board, f, shape=shape, blur_sigma_px=float(blur_sigma_px), bit_depth=16,
        ) / 65535.0  # fmt: skip
        # the line's profile, peak 1 (unclipped grey levels of an 8-bit image divided by
        # its full scale)
        laser = _stripe_image(
            shape, truth.stripe_px[k], width_px=float(stripe_width_px), peak=1.0,
            ambient=0.0, noise_sigma=0.0, saturate=False, bit_depth=8, seed=seed,
        ) / 255.0  # fmt: skip
        lit = albedo * light
        line = albedo * peak * laser
        rng = np.random.default_rng(seed)
        chans = [lit, lit, lit + line] if colour else [lit + line]
        img = np.dstack(
            [_quantise(c + rng.normal(0, noise_sigma, c.shape), bit_depth) for c in chans]
        )  # fmt: skip
        return img if colour else img[:, :, 0]

    written = []
    for n, (path, kind, k) in enumerate(jobs):
        t0 = time.perf_counter()
        s = int(seed) * 100003 + n
        if kind in ("board", "single"):
            f = _board_to_pixel(rig, truth.board_poses[k])
            if kind == "board":
                img = render_target(
                    board, f, shape=shape, blur_sigma_px=float(blur_sigma_px),
                    bit_depth=int(bit_depth), noise_sigma=float(noise_sigma), seed=s,
                )  # fmt: skip
                if colour:
                    img = np.dstack([img] * 3)
            else:
                if motions[k] is not None:
                    f = _moved(f, motions[k])
                img = on_board(f, k, float(ambient_level), float(laser_peak), s)
        elif kind == "stripe" and stripe_on_board:
            f = _board_to_pixel(rig, truth.board_poses[k])
            if motions[k] is not None:
                f = _moved(f, motions[k])
            img = on_board(f, k, _ambient_field(ambient, shape), _STRIPE_PEAK, s)
        else:
            pts = truth.stripe_px[k] if kind == "stripe" else truth.scan_px[k]
            img = _stripe_image(shape, pts, seed=s, **stripe_kw)
            if colour:
                dark = _stripe_image(shape, pts, seed=s, **{**stripe_kw, "peak": 0.0})
                img = np.dstack([dark, dark, img])
        _write(path, img, ext, jpeg_quality)
        written.append(path)
        if verbose:
            print(f"  {os.path.relpath(path, out)}: {time.perf_counter() - t0:.2f} s")
    return written
