"""One scan file → one point-cloud file, streamed: the work of `scheimflux reconstruct`
and of each task of the Dask scale-out."""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from ._stream import iter_reconstruct

REASONS = {
    1: "invalid pixel (not finite, or undistortion failed)",
    2: "ray parallel to the laser plane",
    3: "intersection behind the camera",
    4: "degenerate laser plane (not finite, or through the camera centre)",
    5: "outside the sensor",
    6: "invalid camera (focal length or pixel pitch not finite and positive)",
}


class ScanError(ValueError):
    """A scan that gives no output (no frames, no valid point); nothing was written."""


@dataclasses.dataclass(frozen=True)
class ScanSummary:
    """What a reconstructed scan held.

    **Fields:** `out` the file written; `frames`; `pixels` stripe pixels; `counts`
    pixels per `Status` code (index 0 = valid); `lo`, `hi` the extent of the valid
    points (mm); `model`, `frame`; `sensor_checked` whether the calibration recorded
    a sensor size (pixels range-checked); `outside`, `on_sensor` the stripe pixels on
    the sensor outside the calibration's coverage and all of them (None when the
    calibration records no coverage), counted in the same pass as the reconstruction."""

    out: str
    frames: int
    pixels: int
    counts: tuple[int, ...]
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    model: str
    frame: str
    sensor_checked: bool
    outside: int | None = None
    on_sensor: int | None = None

    @property
    def valid(self) -> int:
        return self.counts[0]


def reconstruct_scan(
    calibration,
    stripes: str | os.PathLike,
    out: str | os.PathLike,
    *,
    frame: str = "camera",
    chunk_frames: int = 256,
    overwrite: bool = False,
    progress=None,
    frames=None,
    width: int | None = None,
) -> ScanSummary:
    """Reconstruct a STRIPES.json scan into a point-cloud file, in bounded memory.

    **Arguments:**
    - `calibration`: a CAL.json path, a `Calibration` or a `CalibrationDocument`
      (`read_calibration_document`).
    - `stripes`: the STRIPES.json file (read one frame at a time).
    - `out`: `.ply`, `.npy` or `.json` (`write_points`' formats, the same bytes); written
      to a temporary file beside it and moved into place at the end.
    - `frame`: `"camera"` or `"measurement"` (needs the calibration's stage).
    - `chunk_frames`: frames per batch.
    - `overwrite`: replace an existing `out`.
    - `progress`: optional wrapper for the chunk iterator (e.g. a tqdm factory).
    - `frames`: optional iterable of `(N_i, 2)` stripe pixels per frame used instead of
      reading `stripes` (which then only names the source in messages), e.g.
      `stripe._folder.folder_stripe_frames` over a folder of images; `.npy` output then
      needs `width` (an upper bound of the frame lengths).

    **Returns:** a `ScanSummary`. **Raises:** `ScanError` (no frames, no valid point),
    `ValueError` for a malformed or cut-short STRIPES file, as `read_calibration`; in
    every case no output file is left.
    """
    from ..io._calibration import read_calibration_document
    from ..io._pointcloud import open_points_writer, points_extension
    from ..io._stripes import iter_stripes

    ext = points_extension(out)
    from_file = isinstance(calibration, (str, os.PathLike))
    loaded = read_calibration_document(calibration) if from_file else calibration
    name = calibration if isinstance(calibration, (str, os.PathLike)) else "the calibration"
    if loaded.plane is None:
        raise ScanError(
            f"{name} is a camera-only calibration (no laser_plane): reconstruct needs a "
            "laser plane (calibrate with the laser line on the board views)"
        )
    if frame == "measurement" and loaded.stage is None:
        raise ScanError(
            f"--frame measurement needs a calibrated rotary stage; {name} has none "
            "(calibrate with a gauge scan in the observations, or use --frame camera)"
        )
    # .npy rows are as long as the longest frame: one cheap first pass finds it.
    if frames is None:
        width = max([len(f) for f in iter_stripes(stripes)] + [0]) if ext == ".npy" else None
        frames = iter_stripes(stripes)
    elif ext == ".npy" and width is None:
        raise ValueError(".npy output from a frame iterator needs the row width up front")
    sensor = loaded.sensor_size
    stage = loaded.stage if frame == "measurement" else None
    coverage = loaded.coverage
    tally = [0, 0]  # stripe pixels outside the coverage, on the sensor
    if coverage is not None:
        frames = _counting_coverage(coverage, frames, tally)
    counts = np.zeros(len(REASONS) + 1, np.int64)
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    n_frames = 0
    with open_points_writer(out, frame, overwrite=overwrite, width=width) as writer:
        chunks = iter_reconstruct(
            loaded.camera,
            loaded.plane,
            frames,
            stage=stage,
            sensor_size=sensor,
            chunk_frames=chunk_frames,
        )
        for points, status in chunks if progress is None else progress(chunks):
            writer.add(points)
            n_frames += len(points)
            codes = np.concatenate([np.zeros(0, np.int8)] + status)
            counts += np.bincount(codes, minlength=len(counts))[: len(counts)]
            valid = [p[s == 0] for p, s in zip(points, status)]
            valid = np.concatenate([np.zeros((0, 3))] + valid)
            if len(valid):
                lo, hi = np.minimum(lo, valid.min(axis=0)), np.maximum(hi, valid.max(axis=0))
        # Refusals leave the `with` by an exception: the temporary file is removed.
        if n_frames == 0:
            raise ScanError(f"{os.fspath(stripes)} has no frames: nothing to reconstruct")
        if counts[0] == 0:
            why = "; ".join(f"{counts[c]} {r}" for c, r in REASONS.items() if counts[c])
            raise ScanError(
                f"no valid point from {int(counts.sum())} stripe pixels in {n_frames} frames "
                f"({why or 'no stripe pixels'}); nothing written"
            )
    return ScanSummary(
        out=os.fspath(out),
        frames=n_frames,
        pixels=int(counts.sum()),
        counts=tuple(int(c) for c in counts),
        lo=tuple(float(x) for x in lo),
        hi=tuple(float(x) for x in hi),
        model=str(loaded.model),
        frame=frame,
        sensor_checked=sensor is not None,
        outside=tally[0] if coverage is not None else None,
        on_sensor=tally[1] if coverage is not None else None,
    )


def _counting_coverage(coverage, frames, tally):
    """`frames` unchanged, adding each frame's pixels outside `coverage` and on the
    sensor to `tally` as it passes (`count_outside`)."""
    from ..geometry._coverage import count_outside

    for f in frames:
        a = np.asarray(f)
        if a.ndim == 2 and a.shape[1] == 2:  # a malformed frame is the reconstruction's to refuse
            out, n = count_outside(coverage, (a,))
            tally[0] += out
            tally[1] += n
        yield f
