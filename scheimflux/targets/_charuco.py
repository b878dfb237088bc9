"""ChArUco boards: geometry and detection through OpenCV's `aruco.CharucoDetector`.

A ChArUco board is a checkerboard of `squares_x × squares_y` squares whose white squares
hold ArUco markers. Every marker has an ID, so each chessboard corner the markers
around it locate is identified on its own: a board partly outside the image, or partly
hidden by the laser line, still gives the corners that are seen.

Board frame (mm), as OpenCV's `CharucoBoard`: origin at the board's top-left outer
corner as printed by `CharucoBoard.generateImage`, x to the right along the first row
of squares, y down the printed image, z = 0 on the board, +z into the board. The
square at the origin is black (OpenCV's pattern since 4.6; pass `legacy=True` for a board
printed by an older OpenCV with an even number of rows). Point order (`points_mm`): the
`(squares_x − 1) × (squares_y − 1)` inner chessboard corners row by row, corner `k` at
`((k % (squares_x − 1) + 1) s, (k // (squares_x − 1) + 1) s, 0)` — corner `k` is
OpenCV's ChArUco corner ID `k`. The order needs no orientation heuristics: it comes
from the marker IDs.
"""

from __future__ import annotations

import dataclasses
import math
import re
from typing import Any

import cv2
import numpy as np

from ._result import DetectionResult, grey_float, reject_off_grid, to_uint8

__all__ = ["CharucoBoard", "detect_charuco", "aruco_dictionary_names"]

_SIZE = re.compile(r"^\s*(\d+)\s*[xX×*]\s*(\d+)\s*$")


def aruco_dictionary_names() -> tuple[str, ...]:
    """The predefined ArUco dictionaries OpenCV offers, e.g. `"DICT_4X4_50"`."""
    return tuple(sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_")))


def _dictionary(name: str):
    if not isinstance(name, str) or not name.startswith("DICT_") or not hasattr(cv2.aruco, name):
        raise ValueError(
            f"unknown ArUco dictionary {name!r}; use one of OpenCV's predefined ones, e.g. "
            "DICT_4X4_50, DICT_5X5_100, DICT_6X6_250, DICT_APRILTAG_36h11"
        )
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


@dataclasses.dataclass(frozen=True)
class CharucoBoard:
    """A ChArUco board (see the module doc for its frame and point order).

    **Arguments:**
    - `squares_x`, `squares_y`: squares per row and per column (a 6 × 5-square board
      has 5 × 4 inner corners).
    - `square_mm`: side of one square (mm).
    - `marker_mm`: side of one ArUco marker (mm), smaller than `square_mm`.
    - `dictionary`: name of an OpenCV predefined dictionary, e.g. `"DICT_4X4_50"`.
    - `legacy`: OpenCV's pre-4.6 pattern (differs for an even number of rows).
    """

    squares_x: int
    squares_y: int
    square_mm: float
    marker_mm: float
    dictionary: str = "DICT_4X4_50"
    legacy: bool = False

    def __post_init__(self):
        for name in ("squares_x", "squares_y"):
            v = getattr(self, name)
            if isinstance(v, bool) or int(v) != v or v < 3:
                raise ValueError(f"ChArUco {name} must be an integer >= 3, got {v!r}")
            object.__setattr__(self, name, int(v))
        s, m = float(self.square_mm), float(self.marker_mm)
        if not (math.isfinite(s) and s > 0):
            raise ValueError(f"square_mm must be a positive number, got {self.square_mm!r}")
        if not (math.isfinite(m) and 0 < m < s):
            raise ValueError(
                f"marker_mm must be positive and smaller than square_mm ({s:g}), got "
                f"{self.marker_mm!r}"
            )
        object.__setattr__(self, "square_mm", s)
        object.__setattr__(self, "marker_mm", m)
        d = _dictionary(self.dictionary)
        n_markers = (self.squares_x * self.squares_y) // 2
        if d.bytesList.shape[0] < n_markers:
            raise ValueError(
                f"{self.dictionary} has {d.bytesList.shape[0]} markers but a "
                f"{self.squares_x}x{self.squares_y}-square board needs {n_markers}"
            )

    @classmethod
    def parse(
        cls, squares: str, square_mm: float, marker_mm: float, dictionary: str = "DICT_4X4_50"
    ) -> CharucoBoard:
        """A board from `"SXxSY"` square counts (e.g. `"12x9"`), square and marker size."""
        m = _SIZE.match(squares) if isinstance(squares, str) else None
        if m is None:
            raise ValueError(
                f"ChArUco size must be squares as SXxSY, e.g. '12x9', got {squares!r}"
            )
        return cls(int(m.group(1)), int(m.group(2)), square_mm, marker_mm, dictionary)

    def opencv_board(self):
        """The equivalent `cv2.aruco.CharucoBoard` (lengths in mm)."""
        b = cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y),
            self.square_mm,
            self.marker_mm,
            _dictionary(self.dictionary),
        )
        b.setLegacyPattern(bool(self.legacy))
        return b

    def __str__(self) -> str:
        return (
            f"ChArUco {self.squares_x}x{self.squares_y} squares of {self.square_mm:g} mm, "
            f"{self.marker_mm:g} mm {self.dictionary} markers"
        )

    @property
    def kind(self) -> str:
        return "charuco"

    @property
    def size(self) -> str:
        return f"{self.squares_x}x{self.squares_y}"

    @property
    def num_corners(self) -> int:
        return (self.squares_x - 1) * (self.squares_y - 1)

    @property
    def points_mm(self) -> np.ndarray:
        """Inner corners, board frame, `(num_corners, 3)`, in ChArUco ID order."""
        s, cx = self.square_mm, self.squares_x - 1
        k = np.arange(self.num_corners)
        xy = np.stack([(k % cx + 1) * s, (k // cx + 1) * s], axis=1).astype(np.float64)
        return np.concatenate([xy, np.zeros((len(xy), 1))], axis=1)

    @property
    def centre_mm(self) -> np.ndarray:
        s = self.square_mm
        return np.array([self.squares_x * s / 2, self.squares_y * s / 2, 0.0])

    @property
    def extent_mm(self) -> tuple[float, float, float, float]:
        """`(x_min, x_max, y_min, y_max)` of the squares."""
        return (0.0, self.squares_x * self.square_mm, 0.0, self.squares_y * self.square_mm)

    def pattern(self, px_per_mm: float) -> np.ndarray:
        """The printed pattern, uint8 (255 white), one texel per `1 / px_per_mm` mm over
        `extent_mm` (texel `(r, c)` covers `x ∈ [c, c + 1] / px_per_mm`)."""
        w = int(round(self.squares_x * self.square_mm * px_per_mm))
        h = int(round(self.squares_y * self.square_mm * px_per_mm))
        return self.opencv_board().generateImage((w, h), marginSize=0, borderBits=1)


def detect_charuco(
    image: Any, board: CharucoBoard, *, min_corners: int = 6, refine: bool = False
) -> DetectionResult:
    """Find the ChArUco corners of `board` that `image` shows.

    **Arguments:**
    - `image`: `(H, W)` grey or `(H, W, 3)` BGR image, 8- or 16-bit or float.
    - `board`: the [`CharucoBoard`][].
    - `min_corners`: fewest corners (not all on one line) for the board to count as found.
    - `refine`: refine the corners with `cornerSubPix` on the full-precision image (as
      for checkerboards), after OpenCV's own refinement on an 8-bit copy.

    **Returns:** a [`DetectionResult`][] with one row per board corner in ID order (NaN
    where not seen).
    """
    norm, problem = grey_float(image)
    if problem:
        return DetectionResult.failed(board.num_corners, problem)
    img8 = to_uint8(norm)
    detector = cv2.aruco.CharucoDetector(board.opencv_board())
    corners, ids, _, marker_ids = detector.detectBoard(img8)
    n_markers = 0 if marker_ids is None else len(marker_ids)
    uv = np.full((board.num_corners, 2), np.nan)
    if ids is not None and corners is not None and len(ids):
        uv[np.asarray(ids).ravel()] = np.asarray(corners, np.float64).reshape(-1, 2)
    n = int(np.isfinite(uv[:, 0]).sum())
    if n < min_corners:
        return DetectionResult(
            uv * np.nan,
            False,
            f"only {n} ChArUco corner(s) found ({n_markers} {board.dictionary} marker(s)); "
            f"{min_corners} needed",
        )
    if not _spans_plane(board.points_mm[np.isfinite(uv[:, 0]), :2], board.square_mm):
        return DetectionResult(uv * np.nan, False, f"the {n} ChArUco corners found lie on a line")
    if refine:
        uv = _refine_found(norm, uv, board)
    uv, n_out = reject_off_grid(uv, board.points_mm, board.square_mm)
    n = int(np.isfinite(uv[:, 0]).sum())
    if n < min_corners:
        return DetectionResult(uv * np.nan, False, f"only {n} consistent ChArUco corner(s)")
    note = "" if n == board.num_corners else f"{n} of {board.num_corners} corners seen"
    if n_out:
        note += f"; {n_out} corner(s) off their neighbours' grid rejected"
    return DetectionResult(uv, True, note.lstrip("; "))


def _refine_found(norm: np.ndarray, uv: np.ndarray, board: CharucoBoard) -> np.ndarray:
    """`cornerSubPix` on the full-precision image, window sized by the square in pixels
    (the median distance between found corners that are row neighbours)."""
    from ._detect import _refine

    cx = board.squares_x - 1
    ok = np.isfinite(uv[:, 0])
    k = np.flatnonzero(ok[:-1] & ok[1:] & ((np.arange(len(uv) - 1) % cx) != cx - 1))
    if k.size == 0:
        return uv
    square = float(np.median(np.linalg.norm(uv[k + 1] - uv[k], axis=1)))
    # the window must stay inside the white gap between the corner and the markers
    # (half the gap is (s - marker) / 2): _refine's half-window is 0.3 x its spacing
    gap = 0.5 * (board.square_mm - board.marker_mm) / board.square_mm
    out = uv.copy()
    out[ok] = _refine(norm, uv[ok], square * min(1.0, gap / 0.3))
    return out


def _spans_plane(xy: np.ndarray, spacing: float) -> bool:
    """The points are not (nearly) collinear: both principal extents exceed a spacing."""
    c = xy - xy.mean(axis=0)
    sv = np.linalg.svd(c, compute_uv=False)
    return bool(len(xy) >= 3 and sv[-1] / math.sqrt(len(xy)) > 0.25 * spacing)
