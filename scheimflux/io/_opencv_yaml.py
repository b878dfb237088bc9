"""OpenCV's camera YAML (`cv::FileStorage`), as written by OpenCV's calibration sample.

The file holds `image_width`, `image_height`, `camera_matrix` (3×3) and
`distortion_coefficients` (N×1, N in 4, 5, 8, 12, 14). Reading and writing go through
`cv2.FileStorage`, so OpenCV reads our files and we read OpenCV's (YAML, XML or JSON by
the file's extension).
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from ..camera._opencv import OpenCVCamera, opencv_dist_coeffs
from ._files import atomic_output


def _shortest_dist(dist14: np.ndarray) -> np.ndarray:
    """The shortest of OpenCV's lengths (at least 5) that holds every non-zero number."""
    nonzero = np.flatnonzero(dist14)
    last = int(nonzero[-1]) + 1 if nonzero.size else 0
    n = next(n for n in (5, 8, 12, 14) if n >= last)
    return dist14[:n]


def write_opencv_yaml(
    path: str | os.PathLike,
    camera: OpenCVCamera,
    image_size: tuple[int, int],
    *,
    overwrite: bool = False,
) -> Path:
    """Write a camera in OpenCV's calibration-file layout via `cv2.FileStorage`.

    **Arguments:**
    - `path`: the file; its extension picks the format (`.yaml`/`.yml`, `.xml`, `.json`).
    - `camera`: an `OpenCVCamera` (its distortion must have an OpenCV equivalent).
    - `image_size`: `(width, height)` in pixels.
    - `overwrite`: replace an existing file; otherwise `FileExistsError`.

    The file is written to a temporary name beside `path` and then moved into place,
    so a failed write leaves no partial file. `distortion_coefficients` is written as
    an N×1 matrix with the shortest of OpenCV's lengths 5, 8, 12, 14 that is exact.

    **Returns:** the path written.
    """
    if not isinstance(camera, OpenCVCamera):
        raise TypeError(f"camera must be an OpenCVCamera, got {type(camera).__name__}")
    width, height = (int(v) for v in image_size)
    if width <= 0 or height <= 0 or tuple(image_size) != (width, height):
        raise ValueError(f"image_size must be two positive integers, got {image_size!r}")
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    K, dist = camera.to_opencv()
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(dist))):
        raise ValueError("camera parameters must be finite")

    with atomic_output(path, overwrite=overwrite, suffix="".join(path.suffixes) or ".yaml") as tmp:
        fs = cv2.FileStorage(tmp, cv2.FILE_STORAGE_WRITE)
        if not fs.isOpened():
            raise OSError(f"cv2.FileStorage could not open {tmp} for writing")
        try:
            fs.write("image_width", width)
            fs.write("image_height", height)
            fs.write("camera_matrix", K)
            fs.write("distortion_coefficients", _shortest_dist(dist).reshape(-1, 1))
        finally:
            fs.release()
    return path


def _node(fs, name: str, path):
    node = fs.getNode(name)
    if node.empty() or node.isNone():
        raise ValueError(f"{path}: missing node '{name}'")
    return node


def _int_node(fs, name: str, path) -> int:
    node = _node(fs, name, path)
    if not (node.isInt() or node.isReal()):
        raise ValueError(f"{path}: '{name}' must be a number")
    value = node.real()
    if value != int(value) or value <= 0:
        raise ValueError(f"{path}: '{name}' must be a positive integer, got {value}")
    return int(value)


def read_opencv_yaml(path: str | os.PathLike) -> tuple[OpenCVCamera, tuple[int, int]]:
    """Read an OpenCV calibration file (`cv2.FileStorage`: YAML, XML or JSON).

    Needs `camera_matrix` (3×3, no skew), `distortion_coefficients` (4, 5, 8, 12 or 14
    numbers), `image_width` and `image_height`; other nodes are ignored.

    **Returns:** `(camera, (width, height))`. Raises `FileNotFoundError` for a missing
    file and `ValueError` naming the node for missing or malformed content.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path} does not exist")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as err:
        raise ValueError(f"{path}: cv2.FileStorage cannot parse it ({err})") from None
    if not fs.isOpened():
        raise ValueError(f"{path}: cv2.FileStorage cannot open it")
    try:
        K = _node(fs, "camera_matrix", path).mat()
        dist = _node(fs, "distortion_coefficients", path).mat()
        width = _int_node(fs, "image_width", path)
        height = _int_node(fs, "image_height", path)
    finally:
        fs.release()
    if K is None or K.shape != (3, 3):
        raise ValueError(f"{path}: 'camera_matrix' must be a 3×3 matrix")
    if dist is None:
        raise ValueError(f"{path}: 'distortion_coefficients' must be a matrix")
    try:
        dist14 = opencv_dist_coeffs(dist)
        camera = OpenCVCamera.from_opencv(K, dist14)
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None
    return camera, (width, height)
