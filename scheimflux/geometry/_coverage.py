"""The sensor region covered by calibration data: where the calibrated model interpolates.

Outside the pixels the calibration boards reached, the fitted model (its distortion
polynomial above all) extrapolates, and measured errors there are several times larger
(issue 16: 1.5 µm outside against 0.18 µm inside for a short wide lens). [`Coverage`][]
records that region as an occupancy grid over the sensor:

- each view's region is the convex hull of its corner pixels and board-stripe pixels
  (the board's image between its outermost detected corners, where the residuals
  constrain the model);
- the union over all views is dilated by a margin, by default one board square as
  imaged (the median spacing of neighbouring corners, in px): the next corner row
  beyond the outermost one would lie there, a step the model interpolates well;
- the grid has cells of `cell_px` pixels; a cell is covered when its centre is.

`Coverage.contains(uv)` is a pure `jax.numpy` lookup (jit- and vmap-safe), so
`stripe_to_camera(..., coverage=cov)` can flag points without touching the fused kernel.
The calibration file stores the grid as packed bits (`"coverage"`,
`"format": "scheimflux.coverage/1"`, an optional key: older files read with coverage
None, "unknown", never assumed covered).
"""

from __future__ import annotations

import base64
import dataclasses
import math
from numbers import Integral, Real

import jax.numpy as jnp
import numpy as np

__all__ = [
    "COVERAGE_FORMAT",
    "DEFAULT_CELL_PX",
    "Coverage",
    "clip_to_radius",
    "coverage_from_data",
    "coverage_of",
]

COVERAGE_FORMAT = "scheimflux.coverage/1"
# 8 px cells: a 2448 × 2048 sensor is a 306 × 256 grid (9.8 kB packed), finer than any
# board square as imaged (≥ 20 px for the boards a detector finds reliably).
DEFAULT_CELL_PX = 8


@dataclasses.dataclass(frozen=True)
class Coverage:
    """Occupancy grid of the sensor region covered by calibration data.

    **Fields:**
    - `grid`: bool `(rows, cols)`; `grid[r, c]` covers pixels
      `u ∈ [c·cell − 0.5, (c+1)·cell − 0.5)`, `v ∈ [r·cell − 0.5, (r+1)·cell − 0.5)`.
    - `cell_px`: the cell size (px).
    - `margin_px`: the dilation applied to the union of per-view hulls (px).
    - `sensor_size`: `(width, height)` (px).
    """

    grid: np.ndarray
    cell_px: int
    margin_px: float
    sensor_size: tuple[int, int]

    @property
    def fraction(self) -> float:
        """Fraction of the sensor area covered (cells clipped to the sensor)."""
        return float(np.sum(self.grid * _cell_areas(self)) / _sensor_area(self))

    def contains(self, uv):
        """True where pixel `uv` `(*batch, 2)` lies in a covered cell (False for NaN or
        off-sensor pixels). Pure `jax.numpy`: usable under `jit`/`vmap`."""
        uv = jnp.asarray(uv)
        rows, cols = self.grid.shape
        cr = jnp.floor((uv + 0.5) / self.cell_px)
        finite = jnp.all(jnp.isfinite(uv), axis=-1)
        w, h = self.sensor_size
        on = finite & jnp.all((uv >= -0.5) & (uv <= jnp.asarray([w, h], uv.dtype) - 0.5), -1)
        c = jnp.clip(jnp.where(finite, cr[..., 0], 0), 0, cols - 1).astype(jnp.int32)
        r = jnp.clip(jnp.where(finite, cr[..., 1], 0), 0, rows - 1).astype(jnp.int32)
        return on & jnp.asarray(self.grid)[r, c]

    def to_dict(self) -> dict:
        """The JSON form stored in the calibration file."""
        return {
            "format": COVERAGE_FORMAT,
            "cell_px": int(self.cell_px),
            "margin_px": float(self.margin_px),
            "shape": [int(n) for n in self.grid.shape],
            "fraction": self.fraction,
            "bits": base64.b64encode(np.packbits(self.grid.reshape(-1)).tobytes()).decode(),
        }

    @classmethod
    def from_dict(cls, doc, sensor_size, where: str = "coverage") -> Coverage:
        """Parse `to_dict`'s form; `ValueError` naming the key for anything malformed."""
        if not isinstance(doc, dict):
            raise ValueError(f"{where} must be an object")
        if doc.get("format") != COVERAGE_FORMAT:
            got = doc.get("format")
            raise ValueError(f"{where}.format must be {COVERAGE_FORMAT!r}, got {got!r}")
        unknown = set(doc) - {"format", "cell_px", "margin_px", "shape", "fraction", "bits"}
        if unknown:
            raise ValueError(f"{where}: unknown key {sorted(unknown)[0]!r}")
        if sensor_size is None:
            raise ValueError(f"{where} needs the file's sensor size (key sensor)")
        try:
            cell = int(doc["cell_px"])
            margin = float(doc["margin_px"])
            rows, cols = (int(n) for n in doc["shape"])
            raw = base64.b64decode(doc["bits"], validate=True)
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(f"{where}: malformed ({type(err).__name__}: {err})") from None
        w, h = (int(v) for v in sensor_size)
        if cell < 1 or not math.isfinite(margin) or margin < 0:
            raise ValueError(f"{where}: cell_px must be >= 1 and margin_px >= 0")
        if (rows, cols) != (-(-h // cell), -(-w // cell)):
            raise ValueError(
                f"{where}.shape {[rows, cols]} does not match the sensor {w} x {h} px in "
                f"{cell} px cells"
            )
        bits = np.unpackbits(np.frombuffer(raw, np.uint8))
        if len(bits) < rows * cols or len(raw) != -(-rows * cols // 8):
            raise ValueError(f"{where}.bits holds {len(raw)} bytes, {rows} x {cols} cells need "
                             f"{-(-rows * cols // 8)}")
        grid = bits[: rows * cols].reshape(rows, cols).astype(bool)
        return cls(grid, cell, margin, (w, h))

    def summary(self) -> str:
        return (
            f"calibration data cover {100 * self.fraction:.0f} % of the sensor "
            f"(per-view hulls of corners and stripes, dilated by {self.margin_px:.0f} px)"
        )


def _sensor_area(cov: Coverage) -> float:
    w, h = cov.sensor_size
    return float(w) * float(h)


def _cell_areas(cov: Coverage) -> np.ndarray:
    w, h = cov.sensor_size
    rows, cols = cov.grid.shape
    cw = np.minimum((np.arange(cols) + 1) * cov.cell_px, w) - np.arange(cols) * cov.cell_px
    ch = np.minimum((np.arange(rows) + 1) * cov.cell_px, h) - np.arange(rows) * cov.cell_px
    return ch[:, None] * cw[None, :].astype(np.float64)


def _hull(p: np.ndarray) -> np.ndarray:
    """Convex hull (counter-clockwise in u-v, Andrew's monotone chain) of points (n, 2)."""
    p = np.unique(p, axis=0)
    if len(p) < 3:
        return p

    def cross(a, b):
        return a[0] * b[1] - a[1] * b[0]

    def half(points):
        out = []
        for q in points:
            while len(out) >= 2 and cross(out[-1] - out[-2], q - out[-2]) <= 0:
                out.pop()
            out.append(q)
        return out

    lower, upper = half(p), half(p[::-1])
    return np.asarray(lower[:-1] + upper[:-1])


def _distance_to_hull(q: np.ndarray, hull: np.ndarray) -> np.ndarray:
    """Euclidean distance of points q (n, 2) to the filled convex polygon (0 inside)."""
    a, b = hull, np.roll(hull, -1, axis=0)
    ab = b - a
    length2 = np.maximum(np.sum(ab**2, axis=1), 1e-300)
    t = np.clip(np.einsum("nkd,kd->nk", q[:, None, :] - a[None], ab) / length2, 0.0, 1.0)
    nearest = a[None] + t[..., None] * ab[None]
    d = np.sqrt(np.min(np.sum((q[:, None, :] - nearest) ** 2, axis=-1), axis=1))
    if len(hull) >= 3:
        cross = ab[None, :, 0] * (q[:, None, 1] - a[None, :, 1]) - ab[None, :, 1] * (
            q[:, None, 0] - a[None, :, 0]
        )
        d = np.where(np.all(cross >= 0, axis=1), 0.0, d)
    return d


def _corner_spacing_px(corner_sets) -> float:
    """Median distance from each corner to its nearest neighbour in the same view (px)."""
    gaps = []
    for c in corner_sets:
        if len(c) >= 2:
            d = np.sqrt(np.sum((c[:, None] - c[None]) ** 2, axis=-1))
            np.fill_diagonal(d, np.inf)
            gaps.append(d.min(axis=1))
    return float(np.median(np.concatenate(gaps))) if gaps else 0.0


def coverage_of(
    corner_sets,
    stripe_sets,
    sensor_size,
    *,
    margin_px: Real | None = None,
    cell_px: Integral = DEFAULT_CELL_PX,
) -> Coverage:
    """The covered sensor region of per-view corner and stripe pixels.

    **Arguments:**
    - `corner_sets`, `stripe_sets`: per view, the pixels `(n, 2)` used by the
      calibration (finite rows only are kept).
    - `sensor_size`: `(width, height)` in px.
    - `margin_px`: dilation of the union of per-view hulls (px); None: one board square
      as imaged (the median nearest-neighbour corner spacing).
    - `cell_px`: grid cell size (px).

    **Returns:** a [`Coverage`][].
    """
    w, h = (int(v) for v in sensor_size)
    if w < 1 or h < 1:
        raise ValueError(f"coverage needs the sensor size, got {sensor_size!r}")
    clean = [
        [np.asarray(s, np.float64).reshape(-1, 2) for s in sets]
        for sets in (corner_sets, stripe_sets)
    ]
    clean = [[s[np.all(np.isfinite(s), axis=1)] for s in sets] for sets in clean]
    corners, stripes = clean
    if margin_px is None:
        margin_px = _corner_spacing_px(corners)
    rows, cols = -(-h // cell_px), -(-w // cell_px)
    cu, cv = _cell_centres((w, h), (rows, cols), cell_px)
    centres = np.stack(np.meshgrid(cu, cv), axis=-1).reshape(-1, 2)
    grid = np.zeros(rows * cols, bool)
    for k in range(max(len(corners), len(stripes))):
        pts = [s[k] for s in (corners, stripes) if k < len(s)]
        pts = np.concatenate(pts) if pts else np.zeros((0, 2))
        if len(pts) == 0:
            continue
        grid |= _distance_to_hull(centres, _hull(pts)) <= margin_px
    return Coverage(grid.reshape(rows, cols), int(cell_px), float(margin_px), (w, h))


def _cell_centres(sensor_size, shape, cell_px) -> tuple[np.ndarray, np.ndarray]:
    """The grid's cell centres along u and v (px), the last (partial) cell's clipped to
    the sensor's last pixel."""
    (w, h), (rows, cols) = sensor_size, shape
    cu = np.minimum((np.arange(cols) + 0.5) * cell_px - 0.5, w - 1)
    cv = np.minimum((np.arange(rows) + 0.5) * cell_px - 0.5, h - 1)
    return cu, cv


def clip_to_radius(cov: Coverage, radius_px: float) -> Coverage:
    """`cov` without the cells whose centre lies farther than `radius_px` from the
    sensor's centre: a calibration made inside that radius (`calibrate(max_radius_px=)`)
    does not cover what the dilation of its hulls reaches beyond it."""
    w, h = cov.sensor_size
    cu, cv = _cell_centres(cov.sensor_size, cov.grid.shape, cov.cell_px)
    du, dv = np.meshgrid(cu - (w - 1) / 2.0, cv - (h - 1) / 2.0)
    return dataclasses.replace(cov, grid=cov.grid & (np.hypot(du, dv) <= radius_px))


def coverage_from_data(data, sensor_size, **kw) -> Coverage | None:
    """[`coverage_of`][] the observations a calibration used (`CalibrationData`: corners
    and board stripes with weight > 0); None when the sensor size is unknown."""
    if sensor_size is None or not all(int(v) > 0 for v in sensor_size):
        return None
    corners, cw = np.asarray(data.corners), np.asarray(data.corner_w) > 0
    stripes, sw = np.asarray(data.stripe), np.asarray(data.stripe_w) > 0
    return coverage_of(
        [c[m] for c, m in zip(corners, cw)],
        [s[m] for s, m in zip(stripes, sw)],
        sensor_size,
        **kw,
    )


def count_outside(coverage: Coverage, frames) -> tuple[int, int]:
    """`(outside, on_sensor)`: of the finite pixels on the sensor in `frames` (an iterable
    of `(K, 2)` arrays, e.g. `io.iter_stripes(path)`), how many lie outside `coverage`.
    NumPy, one frame at a time (memory does not grow with the scan)."""
    outside = on_sensor = 0
    w, h = coverage.sensor_size
    rows, cols = coverage.grid.shape
    for uv in frames:
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        ok = np.all(np.isfinite(uv), axis=1)
        ok &= np.all((uv >= -0.5) & (uv <= np.array([w, h]) - 0.5), axis=1)
        cr = np.floor((uv[ok] + 0.5) / coverage.cell_px).astype(np.int64)
        inside = coverage.grid[np.clip(cr[:, 1], 0, rows - 1), np.clip(cr[:, 0], 0, cols - 1)]
        on_sensor += int(ok.sum())
        outside += int((~inside).sum())
    return outside, on_sensor
