"""STRIPES.json: laser-stripe centres per frame.

```json
{"format": "scheimflux.stripes/1", "frames": [[[u, v], ...], ...],
 "confidence": [[c, ...], ...]}
```

One list of `[u, v]` pixel centres per frame, in frame order (pixel (0, 0) is the centre
of the top-left pixel). Invalid points are left out; a frame without a stripe (or one
that could not be read) is an empty list so that indices stay aligned with the images.
The optional `"confidence"` holds, per frame, one number in [0, 1] per centre (the
extractor's `StripeResult.confidence`); files without it (older ones, or simulated
centres) read as NaN confidences, and readers that ignore it see the same file as before.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np

from ._files import folder_message, load_json, write_atomic

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
    path: str | os.PathLike,
    frames: Sequence[Any],
    *,
    overwrite: bool = False,
    confidence: Sequence[Any] | None = None,
) -> None:
    """Write stripe centres to a STRIPES.json file, atomically.

    **Arguments:**
    - `path`: the file to write.
    - `frames`: per frame an (N_i, 2) array of `(u, v)` centres (or a `StripeResult`-like
      object with `valid_uv`). Rows containing NaN (invalid points) are left out;
      infinite values are an error.
    - `overwrite`: replace an existing file; otherwise an existing file is an error.
    - `confidence`: optional per frame an (N_i,) array of confidences in [0, 1], one per
      row of the frame's points. Default: taken from `StripeResult`-like frames (their
      `valid_confidence`); none are written when no frame carries any.

    The file is written to a temporary file in the same folder and moved into place, so a
    crash never leaves a half-written file.

    **Raises:** `FileExistsError` if `path` exists and `overwrite` is False; `ValueError`
    for points of the wrong shape or infinite values.
    """
    path = os.fspath(path)
    frames = list(frames)
    if confidence is not None and len(confidence) != len(frames):
        raise ValueError(f"confidence has {len(confidence)} frames, points {len(frames)}")
    out, conf_out, any_conf = [], [], False
    for i, frame in enumerate(frames):
        arr = _frame_array(getattr(frame, "valid_uv", frame), i)
        if confidence is not None:
            conf = np.asarray(confidence[i], dtype=np.float64).reshape(-1)
        elif hasattr(frame, "valid_confidence"):
            conf = np.asarray(frame.valid_confidence, dtype=np.float64).reshape(-1)
        else:
            conf = None
        if conf is not None:
            any_conf = True
            if conf.shape != (len(arr),):
                raise ValueError(f"frame {i}: {conf.size} confidences for {len(arr)} points")
            if not np.all((conf >= 0) & (conf <= 1)):
                raise ValueError(f"frame {i}: confidences must lie in [0, 1]")
        keep = ~np.isnan(arr).any(axis=1)
        arr = arr[keep]
        if not np.isfinite(arr).all():
            raise ValueError(f"frame {i}: points contain infinite values")
        out.append([[float(u), float(v)] for u, v in arr])
        conf_out.append(
            [] if conf is None else [round(float(c), 4) for c in conf[keep]]
        )
    doc: dict[str, Any] = {"format": FORMAT, "frames": out}
    if any_conf:
        doc["confidence"] = conf_out
    write_atomic(path, json.dumps(doc, separators=(",", ":")) + "\n", overwrite=overwrite)


def _parse_frame(path: str, i: int, frame: Any) -> np.ndarray:
    """One decoded JSON frame as an (N, 2) float64 array, checked."""
    if not isinstance(frame, list) or any(
        not isinstance(p, list)
        or len(p) != 2
        or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in p)
        for p in frame
    ):
        raise ValueError(f"{path}: frame {i} must be a list of [u, v] number pairs")
    arr = np.asarray(frame, dtype=np.float64).reshape(-1, 2)
    if not np.isfinite(arr).all():
        raise ValueError(f"{path}: frame {i} contains non-finite numbers")
    return arr


def read_stripes(
    path: str | os.PathLike, *, confidence: bool = False
) -> list[np.ndarray] | tuple[list[np.ndarray], list[np.ndarray]]:
    """Read a STRIPES.json file: one (N_i, 2) float64 array of `(u, v)` per frame.

    With `confidence=True` returns `(frames, confidences)`: also one (N_i,) float64
    array per frame, NaN where the file holds no confidence for that frame.

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
    result = [_parse_frame(path, i, frame) for i, frame in enumerate(frames)]
    if not confidence:
        return result
    conf = data.get("confidence")
    if conf is not None and (not isinstance(conf, list) or len(conf) != len(frames)):
        raise ValueError(f"{path}: 'confidence' must be a list with one entry per frame")
    confs = []
    for i, arr in enumerate(result):
        c = [] if conf is None else conf[i]
        if not isinstance(c, list) or not all(
            isinstance(x, (int, float)) and not isinstance(x, bool) for x in c
        ):
            raise ValueError(f"{path}: confidence of frame {i} must be a list of numbers")
        if len(c) == 0:
            confs.append(np.full(len(arr), np.nan))
        elif len(c) != len(arr):
            raise ValueError(
                f"{path}: frame {i} has {len(arr)} points but {len(c)} confidences"
            )
        else:
            confs.append(np.asarray(c, dtype=np.float64))
    return result, confs


class _Tokens:
    """Incremental JSON reading of one file: values decoded one at a time from a buffer
    refilled in blocks, so memory holds one value (one frame), not the file."""

    def __init__(self, fh, path: str, block: int):
        self.fh, self.path, self.block = fh, path, block
        self.buf, self.pos, self.eof = "", 0, False
        self.decoder = json.JSONDecoder()

    def _fill(self) -> bool:
        if self.eof:
            return False
        more = self.fh.read(self.block)
        if not more:
            self.eof = True
            return False
        self.buf = self.buf[self.pos :] + more
        self.pos = 0
        return True

    def char(self) -> str:
        """The next non-blank character (not consumed); '' at the end of the file."""
        while True:
            while self.pos < len(self.buf) and self.buf[self.pos] in " \t\r\n":
                self.pos += 1
            if self.pos < len(self.buf):
                return self.buf[self.pos]
            if not self._fill():
                return ""

    def expect(self, chars: str) -> str:
        c = self.char()
        if c == "":
            raise ValueError(f"{self.path}: the file ends early (truncated JSON)")
        if c not in chars:
            raise ValueError(f"{self.path}: not valid JSON (expected {chars!r}, got {c!r})")
        self.pos += 1
        return c

    def value(self) -> Any:
        self.char()
        while True:
            try:
                v, end = self.decoder.raw_decode(self.buf, self.pos)
            except RecursionError:  # e.g. 100 000 nested `[`
                raise ValueError(
                    f"{self.path}: not a stripes file (JSON nested too deeply to read)"
                ) from None
            except json.JSONDecodeError as err:
                # A value cut by the end of the buffer: read more; at the end of the
                # file it is truncated (or malformed).
                if self._fill():
                    continue
                if err.pos >= len(self.buf) - 1 or "Unterminated" in err.msg:
                    raise ValueError(f"{self.path}: the file ends early (truncated JSON)") from None
                raise ValueError(f"{self.path}: not valid JSON ({err.msg})") from None
            # A number at the end of the buffer may continue in the next block.
            if end == len(self.buf) and not self.eof and self._fill():
                continue
            self.pos = end
            return v

    def items(self) -> Iterator[Any]:
        """The elements of the array that starts here, one at a time."""
        self.expect("[")
        if self.char() == "]":
            self.pos += 1
            return
        while True:
            yield self.value()
            if self.expect(",]") == "]":
                return


def iter_stripes(path: str | os.PathLike, *, block_size: int = 1 << 20) -> Iterator[np.ndarray]:
    """Read a STRIPES.json file one frame at a time: (N_i, 2) float64 arrays in order.

    The same file and checks as `read_stripes`, but memory holds one frame (and one
    `block_size` of text), whatever the length of the scan. The rest of the file is read
    and checked after the last frame (so a file cut short, or of another format, raises
    `ValueError` when the iteration reaches the end, after earlier frames were given).
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"stripes file not found: {path}")
    if os.path.isdir(path):
        raise ValueError(folder_message(path, "stripes"))
    with open(path, encoding="utf-8") as fh:
        tok = _Tokens(fh, path, block_size)
        try:
            tok.expect("{")
        except ValueError:
            raise ValueError(f"{path}: expected a JSON object with a 'frames' key") from None
        seen_frames = False
        if tok.char() == "}":
            tok.pos += 1
        else:
            while True:
                key = tok.value()
                if not isinstance(key, str):
                    raise ValueError(f"{path}: not valid JSON (object keys must be strings)")
                tok.expect(":")
                if key == "frames":
                    if tok.char() != "[":
                        raise ValueError(f"{path}: 'frames' must be a list of frames")
                    for i, frame in enumerate(tok.items()):
                        yield _parse_frame(path, i, frame)
                    seen_frames = True
                elif key == "confidence" and tok.char() == "[":
                    for _ in tok.items():  # checked by read_stripes(confidence=True)
                        pass
                else:
                    v = tok.value()
                    if key == "format" and v != FORMAT:
                        raise ValueError(
                            f"{path}: unsupported format {v!r} (expected {FORMAT!r})"
                        )
                if tok.expect(",}") == "}":
                    break
        if tok.char() != "":
            raise ValueError(f"{path}: not valid JSON (extra data after the object)")
        if not seen_frames:
            raise ValueError(f"{path}: missing key 'frames'")
