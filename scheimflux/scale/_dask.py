"""Many scans across Dask workers: one task per scan file, each running the jitted
kernels through `reconstruct_scan` and writing its own output file atomically.

Dask's scheduler does the distribution, retries and failure detection (no scheduler of
our own): a task whose worker dies is rescheduled on another worker (up to Dask's
`distributed.scheduler.allowed-failures`, then reported as `KilledWorker`); a task that
raises is retried `retries` times. The output of a scan is moved into place only when
its task finishes, so a dead worker never leaves a partial point file (at most a hidden
`.tmp-*` file of the killed attempt).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence


@dataclasses.dataclass(frozen=True)
class ScanResult:
    """The outcome of one scan: `summary` (a `ScanSummary`) or `error` (one line)."""

    scan: str
    out: str
    summary: object | None
    error: str | None

    @property
    def ok(self) -> bool:
        return self.error is None


def _one_scan(calibration, scan, out, frame, chunk_frames, overwrite):
    from ..reconstruct._scan import reconstruct_scan

    return reconstruct_scan(
        calibration, scan, out, frame=frame, chunk_frames=chunk_frames, overwrite=overwrite
    )


def _out_name(scan: str, out_dir: str, ext: str) -> str:
    base = os.path.basename(os.path.normpath(scan))
    stem = base[: -len(".json")] if base.lower().endswith(".json") else base
    return os.path.join(out_dir, stem + ext)


def reconstruct_scans(
    calibration: str | os.PathLike,
    scans: Sequence[str | os.PathLike],
    out_dir: str | os.PathLike,
    *,
    client=None,
    ext: str = ".ply",
    frame: str = "camera",
    chunk_frames: int = 256,
    overwrite: bool = False,
    retries: int = 1,
) -> list[ScanResult]:
    """Reconstruct STRIPES.json scans in parallel on a Dask cluster, one output per scan.

    **Arguments:**
    - `calibration`: the CAL.json path (read by each worker; on several hosts it must be
      reachable there under the same path, e.g. a shared file system).
    - `scans`: STRIPES.json files; scan `NAME.json` is written to `out_dir/NAME<ext>`.
    - `out_dir`: an existing folder (shared by the workers).
    - `client`: a `distributed.Client`; None uses the current default client (one must
      exist: `Client(LocalCluster())` on one machine, `Client("tcp://scheduler:8786")`
      on a cluster).
    - `ext`: `.ply`, `.npy` or `.json`.
    - `frame`, `chunk_frames`, `overwrite`: as `reconstruct_scan`.
    - `retries`: extra attempts for a task that raised (Dask's `retries`).

    **Returns:** one `ScanResult` per scan, in the order given: the summary, or the
    one-line reason the scan has no output (bad input, a worker lost too often).
    """
    from distributed import as_completed, default_client

    from ..io._files import check_folder_writable
    from ..io._pointcloud import points_extension

    points_extension("x" + ext)
    check_folder_writable(out_dir)
    client = default_client() if client is None else client
    scans = [os.fspath(s) for s in scans]
    outs = [_out_name(s, os.fspath(out_dir), ext) for s in scans]
    if len(set(outs)) != len(outs):
        raise ValueError("two scans have the same file name: their outputs would collide")
    cal = os.path.abspath(os.fspath(calibration))
    futures = [
        client.submit(
            _one_scan,
            cal,
            os.path.abspath(s),
            os.path.abspath(o),
            frame,
            chunk_frames,
            overwrite,
            key=f"scheimflux-scan-{i}-{os.path.basename(s)}",
            pure=False,
            retries=retries,
        )
        for i, (s, o) in enumerate(zip(scans, outs))
    ]
    index = {f.key: i for i, f in enumerate(futures)}
    results: list[ScanResult | None] = [None] * len(scans)
    for fut in as_completed(futures):
        i = index[fut.key]
        try:
            summary, error = fut.result(), None
        except Exception as err:  # reported per scan; the others go on
            line = str(err).splitlines()[0] if str(err) else ""
            summary, error = None, f"{type(err).__name__}: {line}"
        results[i] = ScanResult(scans[i], outs[i], summary, error)
    return results  # type: ignore[return-value]
