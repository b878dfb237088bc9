"""Point clouds: PLY (binary little-endian and ASCII), `.npy` and JSON.

- PLY: one `vertex` element with `double` properties `x y z` (mm). Binary files are
  `binary_little_endian 1.0`. Only valid (finite) points are written.
- `.npy` (from `write_points`): a float64 array `(F, N_max, 3)`, one row per stripe pixel
  of each frame in the order of the stripes, padded with NaN to the longest frame;
  invalid points stay in place as NaN rows, so index `[i, k]` is pixel `k` of frame
  `i`. A single frame given as an `(N, 3)` array is written as `(N, 3)`.
- JSON (from `write_points`): `{"format": "scheimflux.points/1", "frame": "camera" |
  "measurement", "unit": "mm", "frames": [[[x, y, z], ...], ...]}`, invalid points left
  out.
- Parquet (needs the optional `pyarrow`: `pip install "scheimflux[parquet]"`): one row
  per valid point, columns `frame` (int32, frame index), `pixel` (int32, index of the
  stripe pixel within its frame), `x`, `y`, `z` (float64, mm); the schema metadata holds
  `format`, `frame` and `unit`. Written one row group per `PointsWriter.add`.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
from collections.abc import Iterator, Sequence

import numpy as np

from ._files import atomic_output, check_writable, write_atomic

POINTS_FORMAT = "scheimflux.points/1"
FRAMES = ("camera", "measurement")
POINT_EXTENSIONS = (".json", ".ply", ".npy", ".parquet")

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


def _points3(points, what: str = "points") -> np.ndarray:
    try:
        a = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be numbers of shape (N, 3)") from None
    if a.size == 0:
        return np.zeros((0, 3))
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{what} must have shape (N, 3), got {a.shape}")
    return a


def _valid_rows(a: np.ndarray, what: str) -> np.ndarray:
    a = a[~np.isnan(a).any(axis=1)]
    if not np.isfinite(a).all():
        raise ValueError(f"{what} contain infinite values")
    return a


def ply_bytes(points, *, binary: bool = True, comments: Sequence[str] = ()) -> bytes:
    """The PLY file content for `(N, 3)` points (rows with NaN are left out)."""
    pts = _valid_rows(_points3(points), "points")
    lines = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0"]
    for c in comments:
        c = str(c)
        if "\n" in c or "\r" in c:
            raise ValueError(f"PLY comments must be single lines, got {c!r}")
        lines.append(f"comment {c}".rstrip())
    lines += [
        f"element vertex {len(pts)}",
        "property double x",
        "property double y",
        "property double z",
        "end_header",
    ]
    header = ("\n".join(lines) + "\n").encode("ascii", errors="replace")
    if binary:
        return header + np.ascontiguousarray(pts, dtype="<f8").tobytes()
    body = "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in pts.tolist())
    return header + body.encode("ascii")


def write_ply(
    path: str | os.PathLike,
    points,
    *,
    binary: bool = True,
    overwrite: bool = False,
    comments: Sequence[str] = (),
) -> None:
    """Write `(N, 3)` points (mm) as a PLY file of `double` x, y, z, atomically.

    **Arguments:**
    - `binary`: `binary_little_endian 1.0` (default) or `ascii 1.0` (full float64
      precision: shortest round-tripping decimal).
    - `overwrite`: replace an existing file; otherwise an existing file is an error.
    - `comments`: single-line `comment` records for the header.

    Rows containing NaN (invalid points) are left out; infinite values are an error.
    """
    check_writable(path, overwrite=overwrite)
    write_atomic(path, ply_bytes(points, binary=binary, comments=comments), overwrite=overwrite)


def read_ply(path: str | os.PathLike) -> np.ndarray:
    """Read the vertices of a PLY file as an `(N, 3)` float64 array of x, y, z.

    Reads ASCII, binary little- and big-endian files whose first element is `vertex`
    with scalar properties including `x`, `y`, `z` (other properties and later elements
    are ignored). **Raises:** `ValueError` for anything else.
    """
    path = os.fspath(path)
    with open(path, "rb") as fh:
        data = fh.read()
    if not data.startswith(b"ply"):
        raise ValueError(f"{path}: not a PLY file (no 'ply' magic)")
    end = data.find(b"end_header")
    if end < 0:
        raise ValueError(f"{path}: PLY header has no end_header")
    nl = data.find(b"\n", end)
    body_start = len(data) if nl < 0 else nl + 1
    header = data[:end].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for line in header[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements:
            if words[1] == "list":
                elements[-1][2].append((words[-1], "list"))
            elif len(words) == 3 and words[1] in _PLY_TYPES:
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
            else:
                raise ValueError(f"{path}: unsupported PLY property line {line!r}")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ValueError(f"{path}: unsupported PLY format {fmt!r}")
    if not elements or elements[0][0] != "vertex":
        raise ValueError(f"{path}: the first PLY element must be 'vertex'")
    _, n, props = elements[0]
    names = [p for p, _ in props]
    if any(t == "list" for _, t in props):
        raise ValueError(f"{path}: list properties in 'vertex' are not supported")
    if not {"x", "y", "z"} <= set(names):
        raise ValueError(f"{path}: PLY vertices need x, y and z properties")
    if fmt == "ascii":
        rows = data[body_start:].decode("ascii").split("\n")
        rows = [r.split() for r in rows if r.strip()][:n]
        if len(rows) < n or any(len(r) < len(props) for r in rows):
            raise ValueError(f"{path}: PLY file ends before its {n} vertices")
        arr = np.array([[float(x) for x in r[: len(props)]] for r in rows], dtype=np.float64)
        arr = arr.reshape(n, len(props))
        return np.stack([arr[:, names.index(c)] for c in "xyz"], axis=1)
    order = "<" if fmt == "binary_little_endian" else ">"
    dtype = np.dtype([(p, order + t) for p, t in props])
    if len(data) - body_start < n * dtype.itemsize:
        raise ValueError(f"{path}: PLY file ends before its {n} vertices")
    rec = np.frombuffer(data, dtype=dtype, count=n, offset=body_start)
    return np.stack([rec[c].astype(np.float64) for c in "xyz"], axis=1)


def _frame_list(frames) -> tuple[list[np.ndarray], bool]:
    """Frames as a list of `(N_i, 3)` arrays (NaN rows invalid), and whether a single
    `(N, 3)` array was given."""
    if hasattr(frames, "points") and hasattr(frames, "status"):  # a Reconstruction
        frames = np.where(np.asarray(frames.valid)[..., None], np.asarray(frames.points), np.nan)
    if isinstance(frames, np.ndarray) or hasattr(frames, "__array__"):
        a = np.asarray(frames, dtype=np.float64)
        if a.ndim == 2:
            return [_points3(a)], True
        if a.ndim == 3 and a.shape[-1] == 3:
            return list(a), False
        raise ValueError(f"points must have shape (N, 3) or (F, N, 3), got {a.shape}")
    out = []
    for i, f in enumerate(frames):
        if hasattr(f, "points") and hasattr(f, "status"):
            f = np.where(np.asarray(f.valid)[..., None], np.asarray(f.points), np.nan)
        out.append(_points3(f, f"frame {i} points"))
    return out, False


def points_extension(path: str | os.PathLike) -> str:
    """The point-cloud format of a path (`.json`, `.ply` or `.npy`), or `ValueError`."""
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext not in POINT_EXTENSIONS:
        raise ValueError(
            f"{os.fspath(path)}: unknown point-cloud format {ext or '(no extension)'!r}; "
            f"use one of {', '.join(POINT_EXTENSIONS)}"
        )
    if ext == ".parquet":
        _pyarrow(path)
    return ext


def _pyarrow(path):
    """`pyarrow.parquet`, or a one-line `ValueError` naming the file when it is missing."""
    try:
        import pyarrow.parquet as pq
    except ImportError:
        raise ValueError(
            f"{os.fspath(path)}: writing Parquet needs pyarrow, which is not installed "
            '(pip install "scheimflux[parquet]"); or use .ply or .npy'
        ) from None
    return pq


def _parquet_schema(frame: str):
    import pyarrow as pa

    meta = {"format": POINTS_FORMAT, "frame": frame, "unit": "mm"}
    fields = [("frame", pa.int32()), ("pixel", pa.int32())]
    fields += [(c, pa.float64()) for c in "xyz"]
    return pa.schema(fields, metadata=meta)


def read_points_parquet(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A Parquet point file as `(frame, pixel, xyz)`: int arrays `(N,)` and float64
    `(N, 3)`. Raises `ValueError` for a file that is not a scheimflux point file."""
    pq = _pyarrow(path)
    try:
        table = pq.read_table(os.fspath(path))
    except Exception as err:  # pyarrow raises its own types for a damaged file
        raise ValueError(f"{os.fspath(path)}: not a readable Parquet file ({err})") from None
    meta = table.schema.metadata or {}
    if meta.get(b"format") != POINTS_FORMAT.encode() or table.column_names != [
        "frame", "pixel", "x", "y", "z"
    ]:  # fmt: skip
        raise ValueError(f"{os.fspath(path)}: not a {POINTS_FORMAT} Parquet file")
    cols = [table.column(c).to_numpy() for c in table.column_names]
    return cols[0], cols[1], np.stack(cols[2:], axis=1)


_PLY_COUNT_ROOM = 40  # digits reserved for the frame and vertex counts of a streamed PLY


def _ply_points_header(frame: str, n_frames: int, n_points: int, binary: bool) -> bytes:
    """The PLY header of `write_points`, of one length whatever the counts (the frame
    comment is padded), so a streamed file can be finished by rewriting it in place."""
    counts = len(str(n_frames)) + len(str(n_points))
    if counts > _PLY_COUNT_ROOM:
        raise ValueError(f"too many points for one PLY file ({n_points})")
    lines = [
        "ply",
        f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
        f"comment scheimflux {frame} frame, mm",
        f"comment frames {n_frames}" + " " * (_PLY_COUNT_ROOM - counts),
        f"element vertex {n_points}",
        "property double x",
        "property double y",
        "property double z",
        "end_header",
    ]
    return ("\n".join(lines) + "\n").encode("ascii")


def _npy_header(n_frames: int, width: int) -> bytes:
    """The `np.save` header of a float64 `(n_frames, width, 3)` array: NumPy reserves
    room for the first axis to grow (21 digits), so its length does not depend on
    `n_frames`."""
    buf = io.BytesIO()
    d = {"descr": "<f8", "fortran_order": False, "shape": (n_frames, width, 3)}
    np.lib.format.write_array_header_1_0(buf, d)
    return buf.getvalue()


class PointsWriter:
    """Writes reconstructed frames to one point-cloud file as they come (see
    `open_points_writer`); memory holds nothing but the frames of one `add`."""

    def __init__(self, fh, ext: str, frame: str, binary: bool, width: int | None):
        self._fh, self._ext, self._frame, self._binary = fh, ext, frame, binary
        self._width = width
        self.n_frames = 0
        self.n_points = 0  # points written (valid rows; for .npy all rows)
        if ext == ".ply":
            fh.write(_ply_points_header(frame, 0, 0, binary))
        elif ext == ".npy":
            if width is None:
                raise ValueError(".npy output needs the row width (longest frame) up front")
            fh.write(_npy_header(0, width))
        elif ext == ".parquet":
            self._schema = _parquet_schema(frame)
            self._parquet = _pyarrow(getattr(fh, "name", "points.parquet")).ParquetWriter(
                fh, self._schema
            )
        else:
            head = {"format": POINTS_FORMAT, "frame": frame, "unit": "mm"}
            fh.write(json.dumps(head, separators=(",", ":"))[:-1].encode() + b',"frames":[')

    def add(self, frames) -> None:
        """Append frames: each an `(N_i, 3)` array, NaN rows = invalid points."""
        frames = [_points3(a, f"frame {self.n_frames + i} points") for i, a in enumerate(frames)]
        if self._ext == ".ply" and self._binary and frames:
            # One write per call: the valid rows of all the frames given.
            a = np.concatenate(frames).astype("<f8", copy=False)
            keep = np.isfinite(a).all(axis=1)
            if not keep.all() and np.isinf(a[~keep]).any():  # the rest are NaN rows
                i = next(i for i, f in enumerate(frames) if np.isinf(f).any())
                raise ValueError(f"frame {self.n_frames + i} points contain infinite values")
            pts = a if keep.all() else a[keep]
            if len(pts):  # a memoryview of zero rows cannot be cast to bytes
                self._fh.write(memoryview(np.ascontiguousarray(pts)).cast("B"))
            self.n_points += len(pts)
            self.n_frames += len(frames)
            return
        if self._ext == ".parquet":
            self._add_parquet(frames)
            return
        for a in frames:
            if np.isinf(a).any():
                raise ValueError(f"frame {self.n_frames} points contain infinite values")
            if self._ext == ".ply":
                pts = a[~np.isnan(a).any(axis=1)]
                if self._binary:
                    self._fh.write(np.ascontiguousarray(pts, dtype="<f8").tobytes())
                else:
                    body = "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in pts.tolist())
                    self._fh.write(body.encode("ascii"))
                self.n_points += len(pts)
            elif self._ext == ".npy":
                if len(a) > self._width:
                    raise ValueError(
                        f"frame {self.n_frames} has {len(a)} points, more than the .npy "
                        f"row width {self._width}"
                    )
                row = np.full((self._width, 3), np.nan)
                row[: len(a)] = a
                self._fh.write(row.astype("<f8").tobytes())
                self.n_points += self._width
            else:
                sep = b"," if self.n_frames else b""
                rows = _valid_rows(a, "points").tolist()
                self._fh.write(sep + json.dumps(rows, separators=(",", ":")).encode())
                self.n_points += len(rows)
            self.n_frames += 1

    def _add_parquet(self, frames: list[np.ndarray]) -> None:
        """One row group: the valid points of `frames`, with frame and pixel indices."""
        import pyarrow as pa

        if not frames:
            return
        a = np.concatenate(frames).astype(np.float64, copy=False)
        keep = np.isfinite(a).all(axis=1)
        if not keep.all() and np.isinf(a[~keep]).any():
            i = next(i for i, f in enumerate(frames) if np.isinf(f).any())
            raise ValueError(f"frame {self.n_frames + i} points contain infinite values")
        lengths = np.array([len(f) for f in frames])
        frame = np.repeat(np.arange(self.n_frames, self.n_frames + len(frames)), lengths)
        pixel = np.arange(len(a)) - np.repeat(np.cumsum(lengths) - lengths, lengths)
        columns = [frame[keep].astype(np.int32), pixel[keep].astype(np.int32)]
        columns += [np.ascontiguousarray(a[keep, k]) for k in range(3)]
        if keep.any():
            self._parquet.write_table(pa.Table.from_arrays(columns, schema=self._schema))
        self.n_points += int(keep.sum())
        self.n_frames += len(frames)

    def _abort(self) -> None:
        """Let go of the file after a failure (the temporary file is then removed)."""
        if self._ext == ".parquet":
            with contextlib.suppress(Exception):
                self._parquet.close()

    def _finish(self) -> None:
        if self._ext == ".parquet":
            self._parquet.close()
        elif self._ext == ".ply":
            self._fh.seek(0)
            self._fh.write(_ply_points_header(self._frame, self.n_frames, self.n_points,
                                              self._binary))  # fmt: skip
        elif self._ext == ".npy":
            self._fh.seek(0)
            self._fh.write(_npy_header(self.n_frames, self._width))
        else:
            self._fh.write(b"]}\n")


@contextlib.contextmanager
def open_points_writer(
    path: str | os.PathLike,
    frame: str = "camera",
    *,
    overwrite: bool = False,
    binary: bool = True,
    width: int | None = None,
) -> Iterator[PointsWriter]:
    """A `PointsWriter` that streams frames into `path`, made atomic at the end.

    The file is written under a temporary name beside `path` (`atomic_output`) and moved
    into place only when the `with` block ends without an exception, so a failure
    midway (bad input, a crash, Ctrl-C) leaves no partial output. The bytes equal those
    of `write_points` with the same frames (`.ply`: the counts are rewritten in the
    fixed-length header at the end; `.npy`: `np.save`'s header, whose length does not
    depend on the number of frames, rewritten at the end; `.json`: the same compact
    text).

    **Arguments:**
    - `frame`: `"camera"` or `"measurement"`.
    - `binary`: binary PLY (default) or ASCII.
    - `width`: for `.npy`, the row length (the longest frame); frames are NaN-padded to it.
    """
    if frame not in FRAMES:
        raise ValueError(f"frame must be one of {FRAMES}, got {frame!r}")
    ext = points_extension(path)
    with atomic_output(path, overwrite=overwrite) as tmp:
        with open(tmp, "wb") as fh:
            writer = PointsWriter(fh, ext, frame, binary, width)
            try:
                yield writer
            except BaseException:
                writer._abort()
                raise
            writer._finish()


def write_points(
    path: str | os.PathLike,
    frames,
    frame: str = "camera",
    *,
    overwrite: bool = False,
    binary: bool = True,
) -> None:
    """Write reconstructed points, picking the format by the file extension.

    **Arguments:**
    - `frames`: per frame an `(N_i, 3)` array (NaN rows = invalid points) or a
      `Reconstruction`; or one `(N, 3)` / `(F, N, 3)` array.
    - `frame`: `"camera"` or `"measurement"`, the frame the points are in (recorded in
      JSON and PLY files).
    - `.json`: `{"format": "scheimflux.points/1", "frame", "unit": "mm", "frames"}`,
      invalid points left out. `.ply`: every valid point of every frame (binary unless
      `binary=False`). `.npy`: float64 `(F, N_max, 3)` padded with NaN, invalid points
      kept as NaN rows (`(N, 3)` for a single array of points).

    The same bytes as streaming the frames through `open_points_writer`.
    """
    if frame not in FRAMES:
        raise ValueError(f"frame must be one of {FRAMES}, got {frame!r}")
    ext = points_extension(path)
    check_writable(path, overwrite=overwrite)
    arrays, single = _frame_list(frames)
    for i, a in enumerate(arrays):
        if np.isinf(a).any():
            raise ValueError(f"frame {i} points contain infinite values")
    if ext == ".npy" and single:
        buf = io.BytesIO()
        np.save(buf, np.ascontiguousarray(arrays[0], dtype=np.float64), allow_pickle=False)
        write_atomic(path, buf.getvalue(), overwrite=overwrite)
        return
    width = max([len(a) for a in arrays] + [0])
    with open_points_writer(path, frame, overwrite=overwrite, binary=binary, width=width) as w:
        w.add(arrays)
