"""Checkerboard geometry: inner-corner grid, square colours and the "11x8" notation.

Board frame (mm): the inner corners lie at `(i s, j s, 0)` for `i < cols`, `j < rows`
(`s = square_mm`), x along a row of corners, y from one row to the next, z = 0 on the
board, +z into the board (away from a camera that sees the printed side, as in OpenCV).
`points_mm` lists them row by row: corner `k` is `(k % cols, k // cols)`. That is the order
in which OpenCV's `findChessboardCorners` returns the corners of a board seen upright: the
first corner top-left, running along the first row.

The pattern has `(cols + 1) × (rows + 1)` squares. Square `(i, j)` (`0 ≤ i ≤ cols`,
`0 ≤ j ≤ rows`) spans `x ∈ [(i − 1) s, i s]`, `y ∈ [(j − 1) s, j s]`; it is black when
`i + j` is even. So square `(0, 0)`, diagonally outside corner 0 (x < 0, y < 0), is black.
(`simulate._render_board` numbers the same squares by their lower corner, `(i − 1, j − 1)`;
the colours agree.)
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Sequence

import numpy as np
from jaxtyping import ArrayLike

#: Array-like input: a NumPy/JAX array, a scalar or a (nested) list/tuple.
ArrayOrSeq = ArrayLike | Sequence

__all__ = ["Checkerboard", "parse_board_size"]

_SIZE = re.compile(r"^\s*(\d+)\s*[xX×*]\s*(\d+)\s*$")


def parse_board_size(text: str) -> tuple[int, int]:
    """Parse inner-corner counts written `"11x8"` (cols × rows) into `(11, 8)`.

    Raises `ValueError` with a one-line message on anything else.
    """
    if not isinstance(text, str):
        raise ValueError(f"board size must be a string like '11x8', got {text!r}")
    m = _SIZE.match(text)
    if m is None:
        raise ValueError(
            f"board size must be inner corners as COLSxROWS, e.g. '11x8', got {text!r}"
        )
    cols, rows = int(m.group(1)), int(m.group(2))
    if cols < 2 or rows < 2:
        raise ValueError(f"a checkerboard needs at least 2x2 inner corners, got {text!r}")
    return cols, rows


@dataclasses.dataclass(frozen=True)
class Checkerboard:
    """A planar checkerboard described by its inner corners.

    **Arguments:**
    - `cols`, `rows`: inner corners per row and per column (an 11 × 8 board has
      12 × 9 squares).
    - `square_mm`: side of one square (mm).

    Build one from the usual notation with `Checkerboard.parse("11x8", 0.3)`.
    """

    cols: int
    rows: int
    square_mm: float

    def __post_init__(self):
        if isinstance(self.cols, bool) or isinstance(self.rows, bool):
            raise ValueError("Checkerboard cols and rows must be integers")
        if int(self.cols) != self.cols or int(self.rows) != self.rows:
            raise ValueError(
                f"Checkerboard cols, rows must be integers, got {self.cols}, {self.rows}"
            )
        if self.cols < 2 or self.rows < 2:
            raise ValueError(
                f"a checkerboard needs at least 2x2 inner corners, got {self.cols}x{self.rows}"
            )
        s = float(self.square_mm)
        if not (math.isfinite(s) and s > 0):
            raise ValueError(f"square_mm must be a positive number, got {self.square_mm!r}")
        object.__setattr__(self, "cols", int(self.cols))
        object.__setattr__(self, "rows", int(self.rows))
        object.__setattr__(self, "square_mm", s)

    @classmethod
    def parse(cls, size: str, square_mm: float) -> Checkerboard:
        """A board from `"COLSxROWS"` inner-corner counts and the square size (mm)."""
        cols, rows = parse_board_size(size)
        return cls(cols, rows, square_mm)

    def __str__(self) -> str:
        return f"{self.cols}x{self.rows} inner corners, {self.square_mm:g} mm squares"

    @property
    def kind(self) -> str:
        """`"checkerboard"` (the target's name for `detect --target`)."""
        return "checkerboard"

    @property
    def size(self) -> str:
        """The board in `"COLSxROWS"` notation."""
        return f"{self.cols}x{self.rows}"

    @property
    def num_corners(self) -> int:
        return self.cols * self.rows

    @property
    def pattern_size(self) -> tuple[int, int]:
        """`(cols, rows)`, the `patternSize` argument of OpenCV's `findChessboardCorners`."""
        return (self.cols, self.rows)

    @property
    def points_mm(self) -> np.ndarray:
        """Inner corners in the board frame, shape `(cols · rows, 3)`, row by row, z = 0."""
        s = self.square_mm
        j, i = np.meshgrid(np.arange(self.rows), np.arange(self.cols), indexing="ij")
        xy = np.stack([i.ravel() * s, j.ravel() * s], axis=-1).astype(np.float64)
        return np.concatenate([xy, np.zeros((len(xy), 1))], axis=1)

    @property
    def centre_mm(self) -> np.ndarray:
        """Centre of the corner grid (and of the squares), board frame, shape (3,)."""
        s = self.square_mm
        return np.array([(self.cols - 1) * s / 2, (self.rows - 1) * s / 2, 0.0])

    @property
    def extent_mm(self) -> tuple[float, float, float, float]:
        """`(x_min, x_max, y_min, y_max)` of the squares (one square beyond the corners)."""
        s = self.square_mm
        return (-s, self.cols * s, -s, self.rows * s)

    def square_colour(self, i: ArrayOrSeq, j: ArrayOrSeq) -> int | np.ndarray:
        """Colour of square `(i, j)`: 0 (black) or 1 (white); black when `i + j` is even.

        Square `(i, j)`, `0 ≤ i ≤ cols`, `0 ≤ j ≤ rows`, spans `x ∈ [(i − 1) s, i s]`,
        `y ∈ [(j − 1) s, j s]`; square `(0, 0)` touches corner 0 from outside (x, y < 0).
        Integers give an `int`, integer arrays an array (broadcast); raises `ValueError`
        outside the board.
        """
        i = np.asarray(i)
        j = np.asarray(j)
        if not (np.issubdtype(i.dtype, np.integer) and np.issubdtype(j.dtype, np.integer)):
            raise ValueError("square indices must be integers")
        if np.any((i < 0) | (i > self.cols) | (j < 0) | (j > self.rows)):
            raise ValueError(
                f"square index out of range: 0 <= i <= {self.cols}, 0 <= j <= {self.rows}"
            )
        colour = ((i + j) % 2).astype(np.int64)
        return int(colour) if colour.ndim == 0 else colour

    def colour_at(self, xy_mm: ArrayOrSeq) -> np.ndarray:
        """Colour (0 black, 1 white, -1 off the pattern) at board-frame points `(..., 2)`."""
        xy = np.asarray(xy_mm, dtype=np.float64)
        s = self.square_mm
        i = np.floor(xy[..., 0] / s).astype(np.int64) + 1
        j = np.floor(xy[..., 1] / s).astype(np.int64) + 1
        inside = (i >= 0) & (i <= self.cols) & (j >= 0) & (j <= self.rows)
        return np.where(inside, (i + j) % 2, -1)

    def contains(self, xy_mm: ArrayOrSeq, *, margin_mm: float = 0.0) -> np.ndarray:
        """Whether board-frame points `(..., 2)` lie on the squares (shrunk by `margin_mm`)."""
        xy = np.asarray(xy_mm, dtype=np.float64)
        x0, x1, y0, y1 = self.extent_mm
        m = margin_mm
        return np.asarray(
            (xy[..., 0] >= x0 + m)
            & (xy[..., 0] <= x1 - m)
            & (xy[..., 1] >= y0 + m)
            & (xy[..., 1] <= y1 - m)
        )
