"""Reconstruction of scans of any length: frames batched into fixed-size padded chunks.

A scan is a sequence of stripe frames, each an `(N_i, 2)` array of pixel centres. The
frames are packed, `chunk_frames` at a time, into a NaN-padded `(chunk_frames, width, 2)`
batch (`width` from a small set of bucket sizes, so a scan compiles a couple of shapes,
not one per chunk), reconstructed by the fused kernel, and unpacked again. While the
host unpacks and writes chunk k, chunk k + 1 is already computing (JAX dispatches
asynchronously), so the writer and the kernel overlap.

The kernel is element-wise per pixel, so a pixel's point does not depend on the chunk
it is in or on the padding: streamed results are bit for bit those of one in-memory
batch (tested).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator

import jax
import jax.numpy as jnp
import numpy as np

from ..camera._base import AbstractCamera
from ..geometry._plane import LaserPlane
from ..geometry._stage import RotaryStage
from ._reconstruct import stripe_to_camera, stripe_to_measurement

MIN_WIDTH = 64
"""The smallest padded frame width; widths are powers of two from here (≤ 2× padding)."""


def padded_width(n: int) -> int:
    """The bucket width for a chunk whose longest frame has `n` points."""
    w = MIN_WIDTH
    while w < n:
        w *= 2
    return w


def pack_frames(frames: list[np.ndarray], rows: int, width: int, dtype=np.float64):
    """Frames `(N_i, 2)` into a NaN-padded `(rows, width, 2)` batch (rows ≥ len(frames))."""
    uv = np.full((rows, width, 2), np.nan, dtype=dtype)
    for i, f in enumerate(frames):
        uv[i, : len(f)] = f
    return uv


def _check_frame(f, index: int) -> np.ndarray:
    a = np.asarray(f, dtype=np.float64)
    if a.size == 0:
        return np.zeros((0, 2))
    if a.ndim != 2 or a.shape[1] != 2:
        raise ValueError(f"frame {index}: stripe pixels must have shape (N, 2), got {a.shape}")
    return a


def _chunks(frames: Iterable, chunk_frames: int) -> Iterator[list[np.ndarray]]:
    chunk: list[np.ndarray] = []
    for i, f in enumerate(frames):
        chunk.append(_check_frame(f, i))
        if len(chunk) == chunk_frames:
            yield chunk
            chunk = []
    if chunk:
        yield chunk


def _dispatch(camera, plane, stage, chunk, first, rows, sensor_size, dtype, shard=True):
    width = padded_width(max([len(f) for f in chunk] + [1]))
    uv = pack_frames(chunk, rows, width, dtype)
    sharding = local_devices_sharding(rows) if shard else None
    # On the default device (the accelerator when JAX has one), or split by frames over
    # all local devices: the kernel is element-wise, so each device computes its own
    # frames with no communication.
    uv = jnp.asarray(uv) if sharding is None else jax.device_put(uv, sharding)
    if stage is None:
        return stripe_to_camera(camera, plane, uv, sensor_size=sensor_size)
    index = first + np.arange(rows)[:, None]  # one index per frame (row of uv)
    return stripe_to_measurement(camera, plane, stage, uv, index, sensor_size=sensor_size)


def _unpack(rec, chunk):
    pts, status = np.asarray(rec.points), np.asarray(rec.status)
    lengths = [len(f) for f in chunk]
    return [pts[i, :n] for i, n in enumerate(lengths)], [
        status[i, :n] for i, n in enumerate(lengths)
    ]


def iter_reconstruct(
    camera: AbstractCamera,
    plane: LaserPlane,
    frames: Iterable,
    *,
    stage: RotaryStage | None = None,
    sensor_size: tuple[int, int] | None = None,
    chunk_frames: int = 256,
    dtype=np.float64,
    shard: bool = True,
) -> Iterator[tuple[list[np.ndarray], list[np.ndarray]]]:
    """Reconstruct a scan chunk by chunk, in bounded memory.

    **Arguments:**
    - `camera`, `plane`: the calibration (camera frame).
    - `frames`: any iterable of `(N_i, 2)` stripe-pixel arrays in frame order (a list,
      `io.iter_stripes(path)`, a generator over images); frames may be empty.
    - `stage`: given, points are in the measurement frame, frame `i` turned by
      `i · delta_omega` (eq. 13); None: camera frame.
    - `sensor_size`: `(w, h)`: pixels outside get `Status.OUTSIDE_SENSOR`.
    - `chunk_frames`: frames per batch (the last batch is padded to the same size).
    - `dtype`: `np.float64` (metrology) or `np.float32`.
    - `shard`: with several local devices, split each chunk's frames over all of them
      (`jax.sharding`; when `chunk_frames` divides among them); False: one device.

    **Returns:** an iterator of `(points, status)` per chunk: lists with one `(N_i, 3)`
    float array (NaN where invalid) and one `(N_i,)` int8 `Status` array per frame.
    """
    if int(chunk_frames) < 1:
        raise ValueError(f"chunk_frames must be >= 1, got {chunk_frames}")
    rows = int(chunk_frames)
    pending = None  # (result being computed, its frames)
    first = 0
    for chunk in _chunks(frames, rows):
        rec = _dispatch(camera, plane, stage, chunk, first, rows, sensor_size, dtype, shard)
        first += len(chunk)
        if pending is not None:
            yield _unpack(*pending)
        pending = (rec, chunk)
    if pending is not None:
        yield _unpack(*pending)


def reconstruct_frames(
    camera: AbstractCamera,
    plane: LaserPlane,
    frames: list,
    *,
    stage: RotaryStage | None = None,
    sensor_size: tuple[int, int] | None = None,
    shard: bool = True,
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Reconstruct all frames of a scan in one padded batch (one compilation).

    **Arguments:** as `iter_reconstruct`.

    **Returns:** `(points, status)`: per frame an `(N_i, 3)` float64 array (NaN where
    invalid) and an `(N_i,)` int8 array of `Status` codes.
    """
    frames = [_check_frame(f, i) for i, f in enumerate(frames)]
    if not frames or max(len(f) for f in frames) == 0:
        return [np.zeros((len(f), 3)) for f in frames], [np.zeros(len(f), np.int8) for f in frames]
    rec = _dispatch(camera, plane, stage, frames, 0, len(frames), sensor_size, np.float64, shard)
    return _unpack(rec, frames)


def local_devices_sharding(n_rows: int):
    """A `NamedSharding` splitting a batch's first axis over all local devices, or None
    with one device (or when `n_rows` does not divide among them)."""
    devices = jax.local_devices()
    if len(devices) < 2 or n_rows % len(devices):
        return None
    mesh = jax.sharding.Mesh(np.array(devices), ("frames",))
    return jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("frames"))
