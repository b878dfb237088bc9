"""Realistic laser-line captures with exact centre lines: the test data of `sf.stripe`.

A capture is what a camera records when a laser line falls on a printed target under
room light: per pixel and colour channel `c`

    E_c = A · (ambient_c · field + laser_c · peak · P) + glints_c

(fractions of full scale) where `A` is the target's albedo (checkerboard squares, a
circle grid or a plain surface, box-filtered over the pixel), `field` a smooth ambient
light field, `P ∈ [0, 1]` the laser's Gaussian profile across its exact centre line
(pixel-integrated by supersampling), and `glints` specular highlights (white, not
scaled by the albedo: small saturating spots and short streaks). The line is therefore
dimmer on black squares, as on a real board. The image is then blurred by a Gaussian
whose width varies across the field (a Scheimpflug camera is sharp on one line of the
sensor only), gets signal-dependent sensor noise, is clipped at full scale (saturated
line cores), quantised, and optionally round-tripped through JPEG.

The exact centre line is a dense polyline in pixels (samples about 0.25 px apart),
either the image of a straight line on the board through any board → pixel map (the
ray tracer, a homography) or an analytic line at any angle, optionally curved. The
laser is drawn only on the target and the truth is clipped to it.
[`score_stripe`][] compares an extractor's centres with it (perpendicular distances).

Colour images are BGR (as `cv2.imread` returns them). Pixel (0, 0) is the centre of
the top-left pixel; u grows to the right, v downwards.

(One module, longer than most: the capture model above from albedo to JPEG, one small
function per stage, and the scoring that reads its exact line.)
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import Any

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ._render_board import board_map, render_checkerboard

__all__ = ["CaptureTruth", "StripeScore", "homography_map", "render_capture", "score_stripe"]

_FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))
_SAMPLE_PX = 0.25  # spacing of the truth polyline


@dataclasses.dataclass(frozen=True)
class CaptureTruth:
    """The exact laser centre line of a rendered capture.

    **Fields:**
    - `line_px`: (K, 2) float64 `(u, v)` samples of the centre line where it lies on the
      target and inside the image, about 0.25 px apart, in order along the line.
    - `breaks`: (K,) bool, True where sample k does not continue sample k - 1 (a new
      piece of the line starts).
    - `saturated`: (K,) bool, the noise-free line core reaches full scale there.
    - `width_px`: the laser's FWHM across the line (px, before blur).
    - `region_px`: (M, 2) outline of the target in pixels (for masks), NaN-free.
    - `glints_px`: (G, 2) centres of the specular glints.
    - `laser_on`: whether the laser was drawn (False: a laser-off frame).
    """

    line_px: np.ndarray
    breaks: np.ndarray
    saturated: np.ndarray
    width_px: float
    region_px: np.ndarray
    glints_px: np.ndarray
    laser_on: bool = True


def homography_map(
    shape: Sequence[int] = (1200, 1600),
    *,
    board_size_mm: tuple[float, float] = (4.0, 3.0),
    fill: float = 0.7,
    tilt_deg: tuple[float, float] = (0.0, 0.0),
    roll_deg: float = 0.0,
) -> Callable[[np.ndarray], np.ndarray]:
    """A board mm → pixel homography: a board of `board_size_mm` centred in the image,
    `fill` of the image's smaller side tall, rolled by `roll_deg` and in perspective
    (`tilt_deg` about the board's x and y axes, viewed from 10 board sizes away)."""
    h, w = int(shape[0]), int(shape[1])
    bw, bh = board_size_mm
    scale = fill * min(h / bh, w / bw)
    a, b = (math.radians(t) for t in tilt_deg)
    r = math.radians(roll_deg)
    Rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    Ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    Rz = np.array([[math.cos(r), -math.sin(r), 0], [math.sin(r), math.cos(r), 0], [0, 0, 1]])
    R = Rz @ Ry @ Rx
    dist = 10.0 * max(bw, bh)
    f = scale * dist
    centre = np.array([0.5 * bw, 0.5 * bh, 0.0])

    def to_pixel(xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64)
        X = np.concatenate([xy, np.zeros((len(xy), 1))], axis=1) - centre
        Xc = X @ R.T + np.array([0.0, 0.0, dist])
        return f * Xc[:, :2] / Xc[:, 2:] + np.array([(w - 1) / 2.0, (h - 1) / 2.0])

    return to_pixel


def _line_samples(board_to_pixel, point_mm, direction_mm, extent, scale_px_per_mm):
    """Image samples (about 0.25 px apart) of the board line `point + s direction`
    within the board's extent."""
    p = np.asarray(point_mm, np.float64)
    d = np.asarray(direction_mm, np.float64)
    d = d / np.linalg.norm(d)
    x0, x1, y0, y1 = extent
    lo, hi = -math.inf, math.inf
    for a, b, l, h in ((p[0], d[0], x0, x1), (p[1], d[1], y0, y1)):
        if abs(b) < 1e-15:
            if not l <= a <= h:
                return np.zeros((0, 2))
            continue
        s1, s2 = sorted(((l - a) / b, (h - a) / b))
        lo, hi = max(lo, s1), min(hi, s2)
    if not hi > lo:
        return np.zeros((0, 2))
    n = int(math.ceil((hi - lo) * scale_px_per_mm / _SAMPLE_PX)) + 1
    s = np.linspace(lo, hi, n)
    return np.asarray(board_to_pixel(p + s[:, None] * d), np.float64)


def _analytic_line(shape, angle_deg, offset_px, curvature):
    """Samples of a line through the image centre (shifted by `offset_px` along its
    normal) at `angle_deg` from the u axis, bent into a parabola of `curvature` (1/px)."""
    h, w = shape
    t = np.array([math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))])
    n = np.array([-t[1], t[0]])
    c = np.array([(w - 1) / 2.0, (h - 1) / 2.0]) + offset_px * n
    half = math.hypot(h, w)
    s = np.arange(-half, half, _SAMPLE_PX)
    return c + s[:, None] * t + (0.5 * curvature * s * s)[:, None] * n


def _checker_albedo(board, board_to_pixel, shape, black, white, background):
    img = render_checkerboard(
        board, board_to_pixel, shape=shape, bit_depth=16, black=black, white=white,
        background=background, noise_sigma=0.0,
    )
    return img.astype(np.float64) / 65535.0


def _circle_albedo(xy, xy_valid, spacing, radius, n_cols, n_rows, dark, light, background):
    """Dark dots of `radius` on a light board, box-filtered by 3 x 3 supersampling of the
    board coordinates (their pixel derivatives from the central differences)."""
    x, y = xy[..., 0], xy[..., 1]
    xu, xv = np.gradient(x, axis=1), np.gradient(x, axis=0)
    yu, yv = np.gradient(y, axis=1), np.gradient(y, axis=0)
    acc = np.zeros_like(x)
    offs = (np.arange(3) - 1) / 3.0
    for du in offs:
        for dv in offs:
            xs, ys = x + xu * du + xv * dv, y + yu * du + yv * dv
            i = np.clip(np.rint(xs / spacing), 0, n_cols - 1)
            j = np.clip(np.rint(ys / spacing), 0, n_rows - 1)
            acc += np.hypot(xs - i * spacing, ys - j * spacing) <= radius
    val = light + (dark - light) * acc / 9.0
    return np.where(xy_valid, val, background)


def _profile(shape, line_px, breaks, sigma_px, on_target):
    """Laser profile P in [0, 1]: a Gaussian of the distance to the polyline, averaged
    over 2 x 2 sub-pixels, only near the line and only on the target."""
    h, w = shape
    out = np.zeros(shape)
    if len(line_px) < 2:
        return out
    reach = 5.0 * sigma_px + 2.0
    mask = np.zeros(shape, np.uint8)
    pts = np.rint(line_px).astype(np.int32)
    pieces = np.split(pts, np.flatnonzero(breaks[1:]) + 1)
    for piece in pieces:
        if len(piece) >= 2:
            cv2.polylines(mask, [piece.reshape(-1, 1, 2)], False, 1, int(2 * reach + 3))
    vv, uu = np.nonzero(mask)
    if vv.size == 0:
        return out
    tree = cKDTree(line_px)
    cont = np.ones(len(line_px), bool)
    cont[0] = False
    cont[1:] = ~breaks[1:]
    acc = np.zeros(vv.size)
    for du in (-0.25, 0.25):
        for dv in (-0.25, 0.25):
            q = np.stack([uu + du, vv + dv], axis=1)
            d = _distance_to_polyline(q, line_px, cont, tree)[0]
            acc += np.exp(-0.5 * (d / sigma_px) ** 2)
    out[vv, uu] = 0.25 * acc
    return out * on_target


def _distance_to_polyline(q, line_px, cont, tree):
    """Signed perpendicular distance of points `q` (N, 2) to the polyline, and whether the
    foot lies strictly inside the line (not beyond one of its ends)."""
    _, k = tree.query(q)
    best = np.full(len(q), np.inf)
    signed = np.zeros(len(q))
    inside = np.zeros(len(q), bool)
    n_pts = len(line_px)
    for a_off in (-1, 0):
        a = k + a_off
        b = a + 1
        ok = (a >= 0) & (b < n_pts)
        a, b = np.clip(a, 0, n_pts - 1), np.clip(b, 0, n_pts - 1)
        ok &= cont[b]
        pa, pb = line_px[a], line_px[b]
        seg = pb - pa
        L2 = np.maximum(np.einsum("ij,ij->i", seg, seg), 1e-30)
        t = np.einsum("ij,ij->i", q - pa, seg) / L2
        tc = np.clip(t, 0.0, 1.0)
        foot = pa + tc[:, None] * seg
        r = q - foot
        dist = np.hypot(r[:, 0], r[:, 1])
        cross = seg[:, 0] * (q[:, 1] - pa[:, 1]) - seg[:, 1] * (q[:, 0] - pa[:, 0])
        sgn = np.where(cross >= 0, 1.0, -1.0)
        # the foot is an end of the line only at a piece's first/last sample
        first = ~cont[a] & (t < 0)
        last = ((b + 1 >= n_pts) | ~cont[np.minimum(b + 1, n_pts - 1)]) & (t > 1)
        better = ok & (dist < best)
        best = np.where(better, dist, best)
        signed = np.where(better, sgn * dist, signed)
        inside = np.where(better, ~(first | last), inside)
    lone = ~np.isfinite(best)
    if lone.any():  # isolated samples: the distance to the point itself
        r = q[lone] - line_px[k[lone]]
        signed[lone] = np.hypot(r[:, 0], r[:, 1])
    return signed, inside


def _blur(img: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Gaussian blur whose sigma varies per pixel: a few levels blended linearly."""
    lo, hi = float(sigma.min()), float(sigma.max())

    def one(s):
        return img if s <= 0 else cv2.GaussianBlur(img, (0, 0), s, borderType=cv2.BORDER_REFLECT)

    if hi - lo < 0.02:
        return one(0.5 * (lo + hi))
    levels = np.linspace(lo, hi, min(8, int(math.ceil((hi - lo) / 0.2)) + 1))
    t = (sigma - lo) / (hi - lo) * (len(levels) - 1)
    i = np.clip(np.floor(t).astype(int), 0, len(levels) - 2)
    frac = t - i
    if img.ndim == 3:
        frac, i = frac[..., None], np.broadcast_to(i[..., None], img.shape)
    out = np.zeros_like(img)
    prev = one(float(levels[0]))
    for k in range(len(levels) - 1):
        nxt = one(float(levels[k + 1]))
        sel = i == k
        out[sel] = ((1 - frac) * prev + frac * nxt)[sel]
        prev = nxt
    return out


def _glints(shape, n, line_px, rng, keep_away_px):
    """Specular glints: (image of peak levels, centres). Half are round spots (sigma
    0.8–2.5 px), half short streaks (sigma 2–6 px along); all at least `keep_away_px` from the
    laser line, peaks 1.5–4 times full scale (they saturate)."""
    h, w = shape
    img = np.zeros(shape)
    centres = []
    tree = cKDTree(line_px) if len(line_px) else None
    tries = 0
    while len(centres) < n and tries < 50 * max(n, 1):
        tries += 1
        c = rng.uniform([10, 10], [w - 11, h - 11])
        if tree is not None and tree.query(c)[0] < keep_away_px:
            continue
        centres.append(c)
        streak = len(centres) % 2 == 0
        s_across = rng.uniform(0.8, 2.5) if not streak else rng.uniform(0.8, 1.5)
        s_along = s_across if not streak else rng.uniform(2.0, 6.0)
        ang = rng.uniform(0, math.pi)
        r = int(math.ceil(4 * max(s_across, s_along)))
        u0, v0 = int(round(c[0])), int(round(c[1]))
        vv, uu = np.mgrid[max(v0 - r, 0) : min(v0 + r + 1, h), max(u0 - r, 0) : min(u0 + r + 1, w)]
        du, dv = uu - c[0], vv - c[1]
        a = du * math.cos(ang) + dv * math.sin(ang)
        b = -du * math.sin(ang) + dv * math.cos(ang)
        peak = rng.uniform(1.5, 4.0)
        img[vv, uu] += peak * np.exp(-0.5 * ((a / s_along) ** 2 + (b / s_across) ** 2))
    return img, np.asarray(centres, np.float64).reshape(-1, 2)


def render_capture(
    board_to_pixel: Callable | None = None,
    *,
    shape: Sequence[int] = (1200, 1600),
    target: str = "checkerboard",
    board: Any = None,
    line_mm: tuple[Sequence[float], Sequence[float]] | None = None,
    line_angle_deg: float = 0.0,
    line_offset_px: float = 0.0,
    line_curvature: float = 0.0,
    line_px: np.ndarray | None = None,
    width_px: float = 5.0,
    peak: float = 0.6,
    ambient: float = 0.3,
    black: float = 0.25,
    white: float = 0.85,
    background: float = 0.35,
    colour: bool = False,
    laser_bgr: Sequence[float] = (0.02, 0.08, 1.0),
    glints: int = 0,
    blur_px: tuple[float, float] = (0.6, 0.6),
    read_noise: float = 0.003,
    shot_noise: float = 0.0001,
    bit_depth: int = 8,
    jpeg_quality: int | None = None,
    laser_on: bool = True,
    distractors: Sequence[np.ndarray] = (),
    seed: int = 0,
) -> tuple[np.ndarray, CaptureTruth]:
    """Render a laser line on a target, as a camera records it, with its exact centres.

    **Arguments:**
    - `board_to_pixel`: vectorised map of board points (N, 2) mm → pixels (N, 2) (e.g.
      the ray tracer `lambda xy: rig.project(pose_apply(xy))[0]`); `None`:
      [`homography_map`][] of a 4 x 3 mm board.
    - `shape`: `(H, W)` of the image.
    - `target`: `"checkerboard"` (`board`: `cols`, `rows` inner corners and `square_mm`;
      default 7 x 5 corners of 0.5 mm), `"circles"` (dark dots of radius 0.3 squares on
      the same grid) or `"plain"` (a uniform surface of albedo `white` filling the image).
    - `line_mm`: `(point, direction)` of the laser line on the board (mm); `None`: an
      image line at `line_angle_deg` from the u axis, `line_offset_px` off the image
      centre along its normal, bent by `line_curvature` (1/px, a parabola).
    - `line_px`: the exact centre line itself, a polyline (K, 2) of `(u, v)` pixels (e.g.
      a ring gauge's traced scan pixels, densified); replaces `line_mm` and the
      analytic line. Keep its samples <= 1 px apart (the truth is the polyline).
    - `width_px`: FWHM of the laser line across itself (px) before the blur.
    - `peak`: laser peak on a white (albedo 1) surface, fraction of full scale; above
      `1 / white` the core saturates.
    - `ambient`: ambient light on albedo 1 (a smooth field ± 25 % around it).
    - `black`, `white`, `background`: albedos of the dark squares or dots, the light
      squares and quiet zone, and the surface beyond the board.
    - `colour`: a BGR image with a laser of colour `laser_bgr` and white ambient light;
      otherwise a grey (mono sensor) image.
    - `glints`: number of specular glints (white spots and short streaks).
    - `blur_px`: Gaussian blur sigma at the top and at the bottom of the image (px),
      linear in between (the Scheimpflug focus varies across the field).
    - `read_noise`, `shot_noise`: noise variance `read_noise² + shot_noise · E` (the
      default 0.0001 is the shot noise of a 10 000 e⁻ full well)
      (fractions of full scale).
    - `bit_depth`: 8 (uint8) or 16 (uint16).
    - `jpeg_quality`: round-trip the 8-bit image through JPEG at this quality.
    - `laser_on`: False renders the laser-off frame of the same pose (same glints).
    - `distractors`: extra laser polylines (K_i, 2) in pixels (reflections, the laser on
      other surfaces), drawn on any surface and not part of the truth.
    - `seed`: seed of the glints and the noise (a laser-off frame gets its own noise).

    **Returns:** `(image, truth)`: (H, W) or (H, W, 3) BGR uint8/uint16 and a
    [`CaptureTruth`][].
    """
    h, w = int(shape[0]), int(shape[1])
    if target not in ("checkerboard", "circles", "plain"):
        raise ValueError(f"target must be 'checkerboard', 'circles' or 'plain', got {target!r}")
    if bit_depth not in (8, 16):
        raise ValueError(f"bit_depth must be 8 or 16, got {bit_depth}")
    if jpeg_quality is not None and (bit_depth != 8 or not 1 <= int(jpeg_quality) <= 100):
        raise ValueError("jpeg_quality needs bit_depth=8 and a quality 1..100")
    if not (width_px > 0 and peak >= 0 and ambient >= 0 and min(blur_px) >= 0):
        raise ValueError("width_px must be > 0 and peak, ambient, blur_px >= 0")
    if board is None:
        from ..targets._board import Checkerboard

        board = Checkerboard(7, 5, 0.5)
    cols, rows, sq = int(board.cols), int(board.rows), float(board.square_mm)
    extent = (-sq * 2, sq * (cols + 1), -sq * 2, sq * (rows + 1))  # squares + 1 quiet zone
    if board_to_pixel is None:
        board_to_pixel = homography_map(
            (h, w), board_size_mm=(extent[1] - extent[0], extent[3] - extent[2])
        )
        base = board_to_pixel

        def board_to_pixel(xy, base=base):  # the default view is centred on the extent
            return base(np.asarray(xy) - np.array([extent[0], extent[2]]))

    rng = np.random.default_rng(seed)

    # Albedo and the target's region.
    if target == "plain":
        albedo = np.full((h, w), float(white))
        on_target = np.ones((h, w))
        region = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], np.float64)
    else:
        bmap = board_map(board_to_pixel, (h, w), extent)
        xy = bmap.xy()
        ok = np.all(np.isfinite(xy), axis=-1)
        x, y = xy[..., 0], xy[..., 1]
        inside = ok & (x >= extent[0]) & (x <= extent[1]) & (y >= extent[2]) & (y <= extent[3])
        on_target = cv2.GaussianBlur(inside.astype(np.float64), (0, 0), 0.5)
        if target == "checkerboard":
            albedo = _checker_albedo(board, board_to_pixel, (h, w), black, white, background)
        else:
            alb = _circle_albedo(
                np.nan_to_num(xy), inside, sq, 0.3 * sq, cols, rows, black, white, background
            )
            albedo = alb
        edge = np.linspace(0.0, 1.0, 50)
        x0, x1, y0, y1 = extent
        outline = np.concatenate(
            [
                np.stack([x0 + (x1 - x0) * edge, np.full(50, y0)], 1),
                np.stack([np.full(50, x1), y0 + (y1 - y0) * edge], 1),
                np.stack([x1 - (x1 - x0) * edge, np.full(50, y1)], 1),
                np.stack([np.full(50, x0), y1 - (y1 - y0) * edge], 1),
            ]
        )
        region = np.asarray(board_to_pixel(outline), np.float64)
        region = region[np.all(np.isfinite(region), axis=1)]

    # The exact centre line, clipped to the target and the image.
    if line_px is not None:
        line = np.asarray(line_px, np.float64).reshape(-1, 2)
    elif line_mm is not None:
        scale = float(np.median(np.hypot(*np.diff(region, axis=0).T))) / (
            (extent[1] - extent[0]) / 49.0
        ) if target != "plain" else 1.0
        line = _line_samples(board_to_pixel, line_mm[0], line_mm[1], extent, 2.0 * scale)
    else:
        line = _analytic_line((h, w), line_angle_deg, line_offset_px, line_curvature)
    iu = np.clip(np.rint(line[:, 0]).astype(int), 0, w - 1) if len(line) else np.zeros(0, int)
    iv = np.clip(np.rint(line[:, 1]).astype(int), 0, h - 1) if len(line) else np.zeros(0, int)
    keep = (
        np.all(np.isfinite(line), axis=1)
        & (line[:, 0] >= 0) & (line[:, 0] <= w - 1)
        & (line[:, 1] >= 0) & (line[:, 1] <= h - 1)
    )
    keep &= on_target[iv, iu] >= 0.5 if len(line) else keep
    idx = np.flatnonzero(keep)
    line_px = line[idx]
    breaks = np.ones(len(idx), bool)
    if len(idx) > 1:
        breaks[1:] = np.diff(idx) != 1

    sigma = float(width_px) / _FWHM_PER_SIGMA
    prof = _profile((h, w), line_px, breaks, sigma, on_target) if laser_on else np.zeros((h, w))
    for extra in distractors:
        extra = np.asarray(extra, np.float64)
        prof = prof + (_profile((h, w), extra, np.r_[True, np.zeros(len(extra) - 1, bool)],
                                sigma, 1.0) if laser_on else 0.0)
    glint_img, glint_c = _glints((h, w), int(glints), line_px, rng, 6.0 * width_px + 10.0)

    vv, uu = np.mgrid[0:h, 0:w]
    field = ambient * (1.0 + 0.25 * (uu / max(w - 1, 1) - 0.5) - 0.15 * (vv / max(h - 1, 1) - 0.5))
    if colour:
        laser_c = np.asarray(laser_bgr, np.float64)
        E = albedo[..., None] * (field[..., None] + peak * prof[..., None] * laser_c)
        E = E + glint_img[..., None]
    else:
        E = albedo * (field + peak * prof) + glint_img
    sat_core = albedo[iv[idx], iu[idx]] * (field[iv[idx], iu[idx]] + peak) >= 1.0 if laser_on \
        else np.zeros(len(idx), bool)

    sig_map = blur_px[0] + (blur_px[1] - blur_px[0]) * vv / max(h - 1, 1)
    E = _blur(E, sig_map)
    noise_rng = np.random.default_rng([seed, 1 if laser_on else 2])
    std = np.sqrt(read_noise**2 + shot_noise * np.clip(E, 0.0, None))
    E = E + std * noise_rng.standard_normal(E.shape)
    full = float(2**bit_depth - 1)
    img = np.rint(np.clip(E, 0.0, 1.0) * full).astype(np.uint8 if bit_depth == 8 else np.uint16)
    if jpeg_quality is not None:
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    truth = CaptureTruth(
        line_px=line_px,
        breaks=breaks,
        saturated=np.asarray(sat_core, bool),
        width_px=float(width_px),
        region_px=region,
        glints_px=glint_c,
        laser_on=bool(laser_on),
    )
    return img, truth


@dataclasses.dataclass(frozen=True)
class StripeScore:
    """An extractor's centres against a [`CaptureTruth`][].

    **Fields:** `n` accepted centres; `false_rate` fraction of them more than `tol_px`
    from the true line (or past its ends); `coverage` fraction of the scan lines crossed
    by the visible line (away from the image border) holding a correct centre; `bias`
    and `rms` (px) of the signed perpendicular distance of the correct centres;
    `max_error` (px) of all accepted centres.
    """

    n: int
    false_rate: float
    coverage: float
    bias: float
    rms: float
    max_error: float


def score_stripe(
    uv: np.ndarray, orientation: str, truth: CaptureTruth, shape, *, tol_px: float = 1.0,
    border_px: int = 8,
) -> StripeScore:
    """Score accepted centres `uv` (M, 2) (NaN rows ignored) found with scan
    `orientation` ("vertical-scan": one per column) against the exact centre line."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    uv = uv[np.all(np.isfinite(uv), axis=1)]
    line = truth.line_px
    h, w = int(shape[0]), int(shape[1])
    axis = 0 if orientation == "vertical-scan" else 1
    n_scan = w if axis == 0 else h
    lo_u, hi_u = border_px, w - 1 - border_px
    lo_v, hi_v = border_px, h - 1 - border_px
    interior = (
        (line[:, 0] >= lo_u) & (line[:, 0] <= hi_u) & (line[:, 1] >= lo_v) & (line[:, 1] <= hi_v)
    )
    expected = np.zeros(n_scan, bool)
    if len(line):
        expected[np.clip(np.rint(line[interior, axis]).astype(int), 0, n_scan - 1)] = True
    if len(uv) == 0 or len(line) < 2:
        return StripeScore(len(uv), 0.0 if len(uv) == 0 else 1.0, 0.0, math.nan, math.nan,
                           0.0 if len(uv) == 0 else math.inf)
    cont = np.ones(len(line), bool)
    cont[0] = False
    cont[1:] = ~truth.breaks[1:]
    d, inside = _distance_to_polyline(uv, line, cont, cKDTree(line))
    good = np.abs(d) <= tol_px  # past an end: the distance to the end point
    perp = good & inside
    covered = np.zeros(n_scan, bool)
    covered[np.clip(np.rint(uv[good, axis]).astype(int), 0, n_scan - 1)] = True
    n_exp = int(expected.sum())
    return StripeScore(
        n=len(uv),
        false_rate=float(np.mean(~good)),
        coverage=float((covered & expected).sum() / n_exp) if n_exp else 0.0,
        bias=float(np.mean(d[perp])) if perp.any() else math.nan,
        rms=float(np.sqrt(np.mean(d[perp] ** 2))) if perp.any() else math.nan,
        max_error=float(np.max(np.abs(d))),
    )


def board_view_capture(rig, board, view, *, pair: bool = False, **kwargs):
    """[`render_capture`][] of one simulated board pose seen through the ray tracer.

    **Arguments:**
    - `rig`: the simulated `Rig` (its `sensor_size` is the image size).
    - `board`: the `Checkerboard`.
    - `view`: a `BoardView` of [`board_poses`][] (its pose `T_c_b`); the laser line is
      the laser plane ∩ the board plane ([`stripe_on_board`][]).
    - `pair`: also render the laser-off frame of the same pose.
    - `**kwargs`: passed to `render_capture` (not `board_to_pixel`, `shape`, `line_mm`).

    **Returns:** `(image, truth)` (`(image, laser_off_image, truth)` with `pair`), or
    raises `ValueError` when the laser misses the board. The traced map is memoised per
    call, so the pair costs one inversion of the ray tracer.
    """
    from ._scenes import stripe_on_board

    R = np.asarray(view.T_c_b.R, np.float64)
    t = np.asarray(view.T_c_b.translation, np.float64)

    memo: dict[bytes, np.ndarray] = {}

    def to_pixel(xy: np.ndarray) -> np.ndarray:
        xy = np.ascontiguousarray(xy, np.float64)
        key = xy.tobytes()
        if key not in memo:
            X = xy @ R[:, :2].T + t
            uv, _ = rig.project(X)
            memo[key] = np.asarray(uv, np.float64)
        return memo[key].copy()

    prof = stripe_on_board(rig, view.T_c_b, board)
    if len(prof.points_c) < 2:
        raise ValueError("the laser plane misses this board pose")
    xb = (np.asarray(prof.points_c) - t) @ R  # board coordinates (z ~ 0)
    point, direction = xb[0, :2], xb[-1, :2] - xb[0, :2]
    w, h = (int(s) for s in rig.sensor_size)
    on, truth = render_capture(
        to_pixel, shape=(h, w), board=board, line_mm=(point, direction), **kwargs
    )
    if not pair:
        return on, truth
    kwargs["laser_on"] = False
    off, _ = render_capture(
        to_pixel, shape=(h, w), board=board, line_mm=(point, direction), **kwargs
    )
    return on, off, truth
