"""STRIPES.json: laser-stripe centres per frame.

```json
{"format": "scheimflux.stripes/1", "frames": [[[u, v], ...], ...]}
```

One list of `[u, v]` pixel centres per frame, in frame order (pixel (0, 0) is the centre
of the top-left pixel). Invalid points are left out; a frame without a stripe (or one
that could not be read) is an empty list so that indices stay aligned with the images.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from typing import Any

import numpy as np

from ._files import load_json, write_atomic

FORMAT = "scheimflux.stripes/1"


def _frame_array(points: Any, index: int) -> np.ndarray:
    """One frame's points as an (N, 2) float64 array, NaN rows (invalid points) dropped."""
    try:
        arr = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"frame {index}: points must be numbers [u, v]") from None
    if arr.size == 0:
        return np.zeros((0, 2))
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"frame {index}: points must have shape (N, 2), got {arr.shape}")
    return arr


def write_stripes(
    path: str | os.PathLike, frames: Sequence[Any], *, overwrite: bool = False
) -> None:
    """Write stripe centres to a STRIPES.json file, atomically.

    **Arguments:**
    - `path`: the file to write.
    - `frames`: per frame an (N_i, 2) array of `(u, v)` centres (or a `StripeResult`-like
      object with `valid_uv`). Rows containing NaN (invalid points) are left out;
      infinite values are an error.
    - `overwrite`: replace an existing file; otherwise an existing file is an error.

    The file is written to a temporary file in the same folder and moved into place, so a
    crash never leaves a half-written file.

    **Raises:** `FileExistsError` if `path` exists and `overwrite` is False; `ValueError`
    for points of the wrong shape or infinite values.
    """
    path = os.fspath(path)
    out = []
    for i, frame in enumerate(frames):
        arr = _frame_array(getattr(frame, "valid_uv", frame), i)
        arr = arr[~np.isnan(arr).any(axis=1)]
        if not np.isfinite(arr).all():
            raise ValueError(f"frame {i}: points contain infinite values")
        out.append([[float(u), float(v)] for u, v in arr])
    write_atomic(
        path,
        json.dumps({"format": FORMAT, "frames": out}, separators=(",", ":")) + "\n",
        overwrite=overwrite,
    )


def read_stripes(path: str | os.PathLike) -> list[np.ndarray]:
    """Read a STRIPES.json file: one (N_i, 2) float64 array of `(u, v)` per frame.

    **Raises:** `FileNotFoundError` if missing; `ValueError` with the reason for a file
    that is not valid JSON, has another `format`, lacks `"frames"`, or holds points of
    the wrong shape or non-finite numbers.
    """
    path = os.fspath(path)
    data = load_json(path, "stripes")
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object with a 'frames' key")
    fmt = data.get("format", FORMAT)
    if fmt != FORMAT:
        raise ValueError(f"{path}: unsupported format {fmt!r} (expected {FORMAT!r})")
    if "frames" not in data:
        raise ValueError(f"{path}: missing key 'frames'")
    frames = data["frames"]
    if not isinstance(frames, list):
        raise ValueError(f"{path}: 'frames' must be a list of frames")
    result = []
    for i, frame in enumerate(frames):
        if not isinstance(frame, list) or any(
            not isinstance(p, list)
            or len(p) != 2
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in p)
            for p in frame
        ):
            raise ValueError(f"{path}: frame {i} must be a list of [u, v] number pairs")
        arr = np.asarray(frame, dtype=np.float64).reshape(-1, 2)
        if not all(math.isfinite(x) for x in arr.ravel()):
            raise ValueError(f"{path}: frame {i} contains non-finite numbers")
        result.append(arr)
    return result
