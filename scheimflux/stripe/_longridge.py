"""The line as the longest continuous narrow ridge: a track where the coarse search fails.

The coarse track (`_coarse.py`) takes the strongest two-sided ridge per scan line. On a
printed pattern whose bright features are themselves ridges of about the line's width
(the white bars and frames of ChArUco markers), and with a line that the black print
leaves a few grey levels high, those features outshine the line on most scan lines and
in both directions: the scan direction comes out ambiguous and the track follows the
print. What tells the laser line apart is its shape, not its brightness:

- **narrow**: across the line the profile falls by a fixed share of its height within
  0.4 FWHM of the centre (a Gaussian line: ~ 1/3 of the fall at one FWHM), while a bar
  wider than the line has a flat top there (a fall near 0);
- **long and continuous**: the line crosses the whole board in one direction, while the
  print's narrow bars are short and run in two orthogonal directions.

`long_ridge_track` marks, per scan line, the pixels that are a narrow ridge of about the
line's width along the scan direction (a two-sided fall of at least 4 noise stds at one
FWHM, and a fall at 0.4 FWHM between 0.12 and 0.75 of it), and finds the path across the
scan lines, at most one pixel's change of the scan coordinate per scan line (any
direction within 45 degrees of the scan lines), that holds the most such pixels
(`+1` each), less `GAP_COST` per scan line without one and `STEP_COST` per pixel of
change: a local alignment (the best-scoring stretch, by dynamic programming). Strength
counts only through the noise threshold, so a bright bar counts no more than the dim
line. Both scan directions are searched; the one with the better path wins.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np

from ._coarse import CoarseTrack

# Score of a scan line on the path without a narrow-ridge pixel (the line dims or is
# refused over parts of the print: crossings of albedo edges parallel to it), and of
# a one-pixel step of the path (keeps it straight where the evidence is ambiguous).
GAP_COST = 0.5
STEP_COST = 0.1
# Accepted fall at 0.4 FWHM over the fall at one FWHM (a Gaussian line: 0.25-0.55 from
# 45-degree broadening to a 3 px line, after the 1 px pre-smoothing).
NARROW = (0.12, 0.75)
# Two-sided fall at one FWHM, in noise stds of the smoothed image.
MIN_FALL = 4.0


@dataclasses.dataclass(frozen=True)
class LongRidge:
    """The best path in one scan frame: `rows` (W,) float64 (NaN off the path),
    `score` (its dynamic-programming score) and `length` (scan lines it spans)."""

    rows: np.ndarray
    score: float
    length: int


def narrow_ridge(scan: np.ndarray, width: float, noise: float) -> np.ndarray:
    """(H, W) bool: pixels that are a narrow ridge of FWHM about `width` along the rows
    (the scan coordinate) of the scan-frame image `scan` (see the module docstring)."""
    img = cv2.GaussianBlur(np.asarray(scan, np.float32), (0, 0), 1.0)
    h = img.shape[0]
    d = max(2, int(round(width)))
    k = max(1, int(round(0.4 * width)))
    out = np.zeros(img.shape, bool)
    if h <= 2 * d + 2:
        return out
    c = img[d:-d]
    fall_d = np.minimum(c - img[: -2 * d], c - img[2 * d :])
    fall_k = np.minimum(c - img[d - k : h - d - k], c - img[d + k : h - d + k])
    # the smoothed noise: a 1 px Gaussian keeps 1 / (2 sqrt(pi)) of the variance; the
    # difference of two such pixels sqrt(2) of it
    thr = MIN_FALL * math.sqrt(2.0) * noise / (2.0 * math.sqrt(math.pi))
    ok = fall_d > thr
    ok &= (fall_k >= NARROW[0] * fall_d) & (fall_k <= NARROW[1] * fall_d)
    # the ridge's top only (and its neighbours: the path moves by whole pixels)
    top = (c >= img[d - 1 : h - d - 1]) & (c >= img[d + 1 : h - d + 1])
    top[1:] |= top[:-1].copy()
    top[:-1] |= top[1:].copy()
    out[d:-d] = ok & top
    return out


def best_path(evidence: np.ndarray) -> LongRidge:
    """The best-scoring path through the (H, W) `evidence` from scan line to scan line
    (local alignment, see the module docstring)."""
    h, w = evidence.shape
    gain = np.where(evidence, 1.0, -GAP_COST)
    prev = np.zeros(h)
    back = np.zeros((h, w), np.int8)  # -1, 0, +1: the row step from the previous scan line
    best, best_at = 0.0, (0, -1)
    pad = np.full(h + 2, -np.inf)
    for j in range(w):
        pad[1:-1] = prev
        up, stay, down = pad[:-2] - STEP_COST, pad[1:-1], pad[2:] - STEP_COST
        step = np.where(stay >= np.maximum(up, down), 0, np.where(up >= down, -1, 1))
        carry = np.maximum(np.maximum(stay, np.maximum(up, down)), 0.0)
        back[:, j] = np.where(carry > 0.0, step, 2)  # 2: the path starts here
        cur = carry + gain[:, j]
        cur = np.maximum(cur, 0.0)
        i = int(np.argmax(cur))
        if cur[i] > best:
            best, best_at = float(cur[i]), (i, j)
        prev = cur
    rows = np.full(w, np.nan)
    i, j = best_at
    end = j
    while j >= 0:
        rows[j] = i
        s = int(back[i, j])
        if s == 2:
            break
        i, j = i + s, j - 1
    start = j if j >= 0 else 0
    # (the path begins on a narrow-ridge pixel by construction, and ends on one: the
    # score peaks there)
    return LongRidge(rows, best, end - start + 1 if best > 0 else 0)


def long_ridge_track(
    img: np.ndarray,
    width: float,
    noise: float,
    roi: np.ndarray | None,
    orientation: str = "auto",
) -> tuple[str, LongRidge] | None:
    """The scan direction and best path (scan frame) of the longest continuous narrow
    ridge in `img` (image frame; `roi` an optional (H, W) bool mask), searched in both
    scan directions for `orientation="auto"`, else in the one given; None when there is
    none."""
    found = []
    for name, scan, m in (
        ("vertical-scan", img, roi),
        ("horizontal-scan", img.T, None if roi is None else roi.T),
    ):
        if orientation not in ("auto", name):
            continue
        ev = narrow_ridge(scan, width, noise)
        if m is not None:
            ev &= m
        found.append((name, best_path(ev)))
    name, path = max(found, key=lambda t: t[1].score)
    if not path.length > 0:
        return None
    return name, path


def path_track(path: LongRidge, width: float, n_rows: int, min_line: int) -> CoarseTrack:
    """The path as the coarse track of the sub-pixel pass: its rows (held constant past
    its ends), support on the scan lines it spans, and a tolerance of one line width
    (the path runs on the ridge's top pixel, or next to it). No track (`found` False)
    unless the path spans `min_line` scan lines and holds a narrow-ridge pixel on at
    least half as many (its score; the frame's test for a line, as the longest segment
    of centres is without a path)."""
    on = np.isfinite(path.rows)
    n = path.rows.size
    if path.length < min_line or path.score < 0.5 * min_line:
        return CoarseTrack(np.zeros(n), np.zeros(n, bool), width, False)
    cols = np.arange(n, dtype=np.float64)
    centre = np.clip(np.interp(cols, cols[on], path.rows[on]), 0.0, n_rows - 1.0)
    return CoarseTrack(centre, on, max(float(width), 4.0), True)
