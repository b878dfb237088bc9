"""One entry point for every calibration target: build one from command-line style
options and detect it in an image.

| `kind` | class | detector | points |
|---|---|---|---|
| `checkerboard` | `Checkerboard` | `findChessboardCornersSB`, `cornerSubPix` | all or none |
| `charuco` | `CharucoBoard` | `aruco.CharucoDetector` | corners by ID, any subset |
| `circles` | `CircleGrid` | `findCirclesGrid` (symmetric) | all or none |
| `acircles` | `CircleGrid(asymmetric=True)` | `findCirclesGrid` (asymmetric) | all or none |
"""

from __future__ import annotations

from typing import Any

from ._board import Checkerboard, parse_board_size
from ._charuco import CharucoBoard, detect_charuco
from ._circles import CircleGrid, detect_circles
from ._detect import detect_checkerboard
from ._result import DetectionResult, reject_off_grid

__all__ = ["TARGET_KINDS", "Target", "make_target", "detect_target"]

TARGET_KINDS = ("checkerboard", "charuco", "circles", "acircles")

Target = Checkerboard | CharucoBoard | CircleGrid


def make_target(
    kind: str,
    size: str,
    pitch_mm: float,
    *,
    marker_mm: float | None = None,
    dictionary: str = "DICT_4X4_50",
    diameter_mm: float | None = None,
) -> Target:
    """A target from the options of `scheimflux detect`.

    **Arguments:**
    - `kind`: one of `TARGET_KINDS`.
    - `size`: `"COLSxROWS"`: inner corners (checkerboard), squares (ChArUco), circles per
      row × rows (circle grids).
    - `pitch_mm`: square side (checkerboard, ChArUco) or circle spacing (circle grids).
    - `marker_mm`: ArUco marker side (ChArUco; default 0.7 × the square).
    - `dictionary`: ArUco dictionary name (ChArUco).
    - `diameter_mm`: circle diameter (circle grids; default half the spacing).

    **Returns:** a `Checkerboard`, `CharucoBoard` or `CircleGrid`. Raises `ValueError`
    with a one-line message for unknown kinds or bad sizes.
    """
    if kind not in TARGET_KINDS:
        raise ValueError(f"target must be one of {', '.join(TARGET_KINDS)}, got {kind!r}")
    cols, rows = parse_board_size(size)
    if kind == "checkerboard":
        return Checkerboard(cols, rows, pitch_mm)
    if kind == "charuco":
        marker = 0.7 * float(pitch_mm) if marker_mm is None else marker_mm
        return CharucoBoard(cols, rows, pitch_mm, marker, dictionary)
    d = 0.5 * float(pitch_mm) if diameter_mm is None else diameter_mm
    return CircleGrid(cols, rows, pitch_mm, d, asymmetric=kind == "acircles")


def detect_target(image: Any, target: Target, *, mirrored: bool = False) -> DetectionResult:
    """Detect `target` in `image` with its detector (see the module's table).

    Every target's points are then checked against their neighbours on the board
    (`reject_off_grid`): a point off the local grid (the laser line or a glint across
    it) is set to NaN and counted in the message.

    **Returns:** a [`DetectionResult`][] in the order of `target.points_mm`.
    """
    if isinstance(target, CharucoBoard):
        return detect_charuco(image, target)  # IDs fix the order; checks its own grid
    if isinstance(target, Checkerboard):
        res, pitch = detect_checkerboard(image, target, mirrored=mirrored), target.square_mm
    elif isinstance(target, CircleGrid):
        res, pitch = detect_circles(image, target, mirrored=mirrored), target.spacing_mm
    else:
        raise TypeError(f"unknown target type {type(target).__name__}")
    if not res.found:
        return res
    uv, n_out = reject_off_grid(res.corners_px, target.points_mm, pitch)
    if not n_out:
        return res
    note = f"{n_out} point(s) off their neighbours' grid rejected"
    return DetectionResult(uv, True, f"{res.message}; {note}" if res.message else note)
