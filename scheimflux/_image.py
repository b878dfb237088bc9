"""Reading one image file: the single reader behind every command that opens photos."""

from __future__ import annotations

import os

import numpy as np

# The file name endings read as images (any case), by every command that reads a folder.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")


def read_image(path) -> np.ndarray | None:
    """An image file as stored: `(H, W)` grey or `(H, W, 3)` BGR (alpha dropped), 8 or
    16 bits (EXIF orientation is ignored: pixels stay in sensor order). None when the file
    cannot be read or decoded (a truncated file, not an image, 2 channels).

    OpenCV's own log is silenced during the read: a decoder's complaint about a broken
    file ("TIFFReadDirectory: Failed to read directory …") would otherwise reach the
    terminal besides the caller's one-line message about that file."""
    import cv2

    log = cv2.utils.logging
    level = log.getLogLevel()
    log.setLogLevel(log.LOG_LEVEL_SILENT)
    try:
        image = cv2.imread(os.fspath(path), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        return None
    finally:
        log.setLogLevel(level)
    if image is None or image.size == 0:
        return None
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    elif image.ndim == 3 and image.shape[2] >= 3:
        image = np.ascontiguousarray(image[:, :, :3])
    return image if image.ndim == 2 or image.shape[2] == 3 else None


def read_grey(path) -> np.ndarray | None:
    """The image as one grey plane `(H, W)` (colour converted), or None when it cannot
    be read."""
    import cv2

    image = read_image(path)
    if image is not None and image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return image
