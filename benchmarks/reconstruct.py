"""Reconstruction speed: the fused kernel against plain NumPy eq. (3), the machine's copy
bandwidth, and streaming a scan to PLY against the in-memory path.

    python benchmarks/reconstruct.py [--max-points 1e7] [--quick] [--repeats 5]
                                     [--stream-frames 1000,10000] [--json ROWS.json]

1. `stripe_to_camera` (public function, float32 and float64) at N = 1e4 … `--max-points`
   on the paper's ×1.5 thick-lens preset, side by side with a vectorised NumPy
   X = K_f p̃ / (n · K_f p̃) on the same pixels, best of `--repeats`; the first call's
   extra time is the compile time; the CPU-time rates (best process CPU seconds, all
   threads) are given beside the wall-clock ones. The bandwidth fraction is the kernel's bytes
   (2 floats in, 3 out, 1 status byte per point: the minimum; the kernel moves ~1.4x
   that, reading the pixels twice, see docs/throughput.md) per second over a NumPy copy's (read +
   write) measured in the same run.
2. Streaming F frames × 1600 points (`--stream-frames`) to a binary PLY:
   `iter_reconstruct` + `open_points_writer` against `reconstruct_frames` +
   `write_points` (one batch in memory), each in its own subprocess so that the peak
   RSS (`VmHWM`) is that path's alone.

The machine is shared: every ratio is measured side by side in one process; `uptime` is
printed with the numbers.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np


def numpy_eq3(K_f: np.ndarray, n: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """X = K_f p̃ / (n · K_f p̃), vectorised (N, 2) → (N, 3)."""
    P = uv @ K_f[:, :2].T + K_f[:, 2]
    return P / (P @ n)[:, None]


def _best(fn, repeats: int) -> float:
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def _best_wall_cpu(fn, repeats: int) -> tuple[float, float]:
    """Best wall seconds and best CPU seconds (this process, all threads) of `repeats`.

    On a shared machine the CPU time is the load-independent measure: a run that waits
    for a core shows in the wall time only."""
    wall = cpu = np.inf
    for _ in range(repeats):
        c, t = time.process_time(), time.perf_counter()
        fn()
        wall = min(wall, time.perf_counter() - t)
        cpu = min(cpu, time.process_time() - c)
    return wall, cpu


def copy_bandwidth(nbytes: int = 1 << 28, repeats: int = 5) -> float:
    """GB/s of a NumPy copy of `nbytes` (bytes read + bytes written)."""
    a = np.ones(nbytes // 8)
    b = np.empty_like(a)
    return 2 * a.nbytes / _best(lambda: np.copyto(b, a), repeats) / 1e9


def _pixels(n: int, dtype) -> np.ndarray:
    rng = np.random.default_rng(0)
    return (rng.random((n, 2)) * [1599.0, 1199.0]).astype(dtype)


def bench_camera(sizes, repeats: int, bandwidth: float) -> list[dict]:
    import jax
    import jax.numpy as jnp

    import scheimflux as sf

    cam = sf.paper_thick_lens("scheimpflug-1.5")
    plane = sf.paper_laser_plane()
    K_f, n_vec = np.asarray(cam.K_f), np.asarray(plane.n)
    rows = []
    for n in sizes:
        for dtype in (np.float32, np.float64):
            uv_np = _pixels(n, dtype)
            uv = jnp.asarray(uv_np)

            def ours():
                return sf.stripe_to_camera(cam, plane, uv).points.block_until_ready()

            t = time.perf_counter()
            rec = ours()
            first = time.perf_counter() - t
            t_ours, c_ours = _best_wall_cpu(ours, repeats)
            K, nn = K_f.astype(dtype), n_vec.astype(dtype)
            t_np, c_np = _best_wall_cpu(lambda: numpy_eq3(K, nn, uv_np), repeats)
            ref = numpy_eq3(K_f, n_vec, uv_np.astype(np.float64))
            err = float(np.nanmax(np.abs(np.asarray(rec, np.float64) - ref)))
            item = np.dtype(dtype).itemsize
            gbs = n * (5 * item + 1) / t_ours / 1e9
            rows.append(
                {
                    "operation": f"stripe_to_camera {np.dtype(dtype).name}",
                    "size": f"{n:.0e} pts",
                    "ours": f"{n / t_ours / 1e6:.0f} Mpts/s",
                    "baseline": f"{n / t_np / 1e6:.0f} Mpts/s (NumPy eq. 3)",
                    "ratio": t_np / t_ours,
                    "compile_s": max(first - t_ours, 0.0),
                    "note": f"{gbs:.1f} GB/s = {gbs / bandwidth:.0%} of copy; CPU time: "
                    f"{n / c_ours / 1e6:.0f} vs {n / c_np / 1e6:.0f} Mpts/s "
                    f"({c_np / c_ours:.2f}×, ours on {os.cpu_count()} threads); "
                    f"max abs dX {err * 1e3:.2g} µm vs float64 NumPy",
                }
            )
            print(_row(rows[-1]), flush=True)
            del rec
    del jax
    return rows


_STREAM_CHILD = """
import os, sys, time, numpy as np
import scheimflux as sf
from scheimflux.io._pointcloud import open_points_writer, write_points
from scheimflux.reconstruct import iter_reconstruct, reconstruct_frames
mode, F, out = sys.argv[1], int(sys.argv[2]), sys.argv[3]
cam, plane = sf.paper_thick_lens("scheimpflug-1.5"), sf.paper_laser_plane()
u = np.linspace(0.0, 1599.0, 1600)
def frames():
    for i in range(F):
        yield np.stack([u, np.full_like(u, 200.0 + (i % 800))], axis=1)
# compile outside the timing (one chunk shape; the in-memory shape is compiled by a
# same-shape warm-up on zeros)
if mode == "stream":
    for _ in iter_reconstruct(cam, plane, [np.zeros((1600, 2))] * 256, chunk_frames=256):
        pass
    t = time.perf_counter()
    with open_points_writer(out, width=1600) as w:
        for p, _ in iter_reconstruct(cam, plane, frames(), chunk_frames=256):
            w.add(p)
else:
    reconstruct_frames(cam, plane, [np.zeros((1600, 2))] * F)
    t = time.perf_counter()
    pts, _ = reconstruct_frames(cam, plane, list(frames()))
    write_points(out, pts)
dt = time.perf_counter() - t
# VmHWM, not ru_maxrss: Linux carries ru_maxrss over from the parent across fork/exec
hwm = [l for l in open("/proc/self/status") if l.startswith("VmHWM")][0].split()[1]
print(dt, int(hwm) * 1024, os.path.getsize(out))
"""


def bench_stream(frame_counts) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for F in frame_counts:
            res = {}
            for mode in ("memory", "stream"):
                out = os.path.join(tmp, f"{mode}{F}.ply")
                r = subprocess.run(
                    [sys.executable, "-c", _STREAM_CHILD, mode, str(F), out],
                    capture_output=True,
                    text=True,
                )
                if r.returncode:
                    raise RuntimeError(r.stderr[-2000:])
                dt, rss, size = r.stdout.split()[-3:]
                res[mode] = (float(dt), int(rss), int(size))
            same = open(os.path.join(tmp, f"memory{F}.ply"), "rb").read() == open(
                os.path.join(tmp, f"stream{F}.ply"), "rb"
            ).read()
            n = F * 1600
            ts, tm = res["stream"][0], res["memory"][0]
            rows.append(
                {
                    "operation": "reconstruct → PLY, streamed (256-frame chunks)",
                    "size": f"{F} × 1600 pts",
                    "ours": f"{n / ts / 1e6:.1f} Mpts/s",
                    "baseline": f"{n / tm / 1e6:.1f} Mpts/s (one batch in memory)",
                    "ratio": tm / ts,
                    "compile_s": None,
                    "note": f"peak RSS {res['stream'][1] / 2**20:.0f} MiB vs "
                    f"{res['memory'][1] / 2**20:.0f} MiB; files identical: {same}",
                }
            )
            print(_row(rows[-1]), flush=True)
            for mode in ("memory", "stream"):
                os.unlink(os.path.join(tmp, f"{mode}{F}.ply"))
    return rows


def _row(r: dict) -> str:
    c = "" if r["compile_s"] is None else f"{r['compile_s']:.2f}"
    return (
        f"| {r['operation']} | {r['size']} | {r['ours']} | {r['baseline']} | "
        f"{r['ratio']:.2f}× | {c} | {r['note']} |"
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-points", type=float, default=1e7)
    ap.add_argument("--quick", action="store_true", help="up to 1e5 points, 2 repeats")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--stream-frames", default="1000,10000", help="frame counts, or ''")
    ap.add_argument("--json", metavar="ROWS.json", help="also write the rows as JSON")
    args = ap.parse_args(argv)
    max_n = 1e5 if args.quick else args.max_points
    repeats = 2 if args.quick else args.repeats
    bw = copy_bandwidth()
    print(f"load: {os.getloadavg()}  NumPy copy bandwidth {bw:.1f} GB/s")
    print("| operation | size | ours | baseline | ratio | compile s | note |")
    print("|---|---|---|---|---|---|---|")
    sizes = [int(10**k) for k in range(4, 8) if 10**k <= max_n]
    rows = bench_camera(sizes, repeats, bw)
    counts = [int(x) for x in args.stream_frames.split(",") if x.strip()]
    if args.quick:
        counts = [c for c in counts if c <= 1000] or counts[:1]
    rows += bench_stream(counts)
    print(f"load after: {os.getloadavg()}; peak RSS here "
          f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**10:.0f} MiB")  # fmt: skip
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"copy_GBps": bw, "rows": rows}, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
