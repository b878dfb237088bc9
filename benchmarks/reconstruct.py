"""Reconstruction speed: the fused kernel against plain NumPy eq. (3), the machine's copy
bandwidth, and streaming a scan to PLY against the in-memory path.

    python benchmarks/reconstruct.py [--max-points 1e7] [--min-points 1e4] [--quick]
                                     [--repeats 9] [--stream-frames 1000,10000]
                                     [--json ROWS.json]

1. `stripe_to_camera` (public function, float32 and float64) at N = `--min-points` …
   `--max-points` on the paper's ×1.5 thick-lens preset, side by side with two plain
   NumPy versions of X = K_f p̃ / (n · K_f p̃) on the same pixels: with matrix products
   (NumPy's BLAS) and with element-wise broadcasts (no BLAS); the baseline is the faster
   of the two in that run. Ours twice: a fresh result per call, and `out=` the previous
   result (its buffers reused). All four are timed alike: each call allocates its
   result (ours: XLA's; NumPy's: NumPy's), ours waits for `block_until_ready`, one
   warm-up call each, then `--repeats` rounds calling them in turn (half as many at
   1e7), medians (the best wall time is in the note). The first call's extra time is
   the compile time. CPU-time rates (median process CPU seconds, all threads) are given
   beside the wall-clock ones. The bandwidth fraction is the kernel's bytes (2 floats
   in, 3 out, 1 status byte per point: the minimum; the kernel moves ~1.4x that,
   reading the pixels twice, see docs/throughput.md) per second over a NumPy copy's
   (read + write) measured in the same run.
2. `stripe_to_measurement` float32 on (1000 frames, N / 1000, 2) pixels for N ≥ 1e6,
   fresh and `out=`, against NumPy eq. (3) + (13) with broadcasts, the same way.
3. Streaming F frames × 1600 points (`--stream-frames`) to a binary PLY:
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
    """X = K_f p̃ / (n · K_f p̃), vectorised (N, 2) → (N, 3), with matrix products (NumPy
    hands them to its BLAS, OpenBLAS here, which may use every core)."""
    P = uv @ K_f[:, :2].T + K_f[:, 2]
    return P / (P @ n)[:, None]


def numpy_eq3_broadcast(K_f: np.ndarray, n: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """The same eq. (3) as element-wise broadcasts (no BLAS call; one thread):
    `P = u K_f[:, 0] + v K_f[:, 1] + K_f[:, 2]`, `q = m · [u, v, 1]` with `m = nᵀ K_f`."""
    u, v = uv[:, 0:1], uv[:, 1:2]
    m = n @ K_f
    return (u * K_f[:, 0] + v * K_f[:, 1] + K_f[:, 2]) / (u * m[0] + v * m[1] + m[2])


def numpy_eq13(K_f, n, R, t, c, s, uv):
    """Eq. (13) after eq. (3) on `(frames, points, 2)` pixels: `X_m = R_i (R X_c + t)`,
    `R_i` about z by the frame's angle (`c`, `s`: its cosine and sine, `(frames, 1)`)."""
    X = numpy_eq3_broadcast(K_f, n, uv.reshape(-1, 2))
    X = X[:, 0:1] * R[:, 0] + X[:, 1:2] * R[:, 1] + X[:, 2:3] * R[:, 2] + t  # no BLAS
    X = X.reshape(uv.shape[:-1] + (3,))
    x, y = X[..., 0], X[..., 1]
    return np.stack([c * x - s * y, s * x + c * y, X[..., 2]], axis=-1)


def _best(fn, repeats: int) -> float:
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def _interleaved(fns: dict, repeats: int) -> dict:
    """Median and best wall and CPU seconds (this process, all threads) of each function,
    the functions called in turn within each repeat (one warm-up call each first), so
    that a change of the machine's load falls on all of them alike.

    On a shared machine the CPU time is the load-independent measure: a run that waits
    for a core shows in the wall time only."""
    for fn in fns.values():
        fn()
    wall = {k: [] for k in fns}
    cpu = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            c, t = time.process_time(), time.perf_counter()
            fn()
            wall[k].append(time.perf_counter() - t)
            cpu[k].append(time.process_time() - c)
    return {
        k: {
            "wall": float(np.median(wall[k])),
            "cpu": float(np.median(cpu[k])),
            "wall_best": float(np.min(wall[k])),
        }
        for k in fns
    }


def copy_bandwidth(nbytes: int = 1 << 28, repeats: int = 5) -> float:
    """GB/s of a NumPy copy of `nbytes` (bytes read + bytes written)."""
    a = np.ones(nbytes // 8)
    b = np.empty_like(a)
    return 2 * a.nbytes / _best(lambda: np.copyto(b, a), repeats) / 1e9


def _pixels(n: int, dtype) -> np.ndarray:
    rng = np.random.default_rng(0)
    return (rng.random((n, 2)) * [1599.0, 1199.0]).astype(dtype)


def _rows_for(op, size, n, t, keys_ours, baselines, bandwidth, first, item, err, threads):
    """Table rows: each of our variants against the faster NumPy variant (medians)."""
    base = min(baselines, key=lambda k: t[k]["wall"])
    rows = []
    for key, label in keys_ours:
        w, c = t[key]["wall"], t[key]["cpu"]
        gbs = n * (5 * item + 1) / w / 1e9
        others = ", ".join(f"{lab} {n / t[k]['wall'] / 1e6:.0f}" for k, lab in baselines.items())
        rows.append(
            {
                "operation": f"{op}{label}",
                "size": size,
                "ours": f"{n / w / 1e6:.0f} Mpts/s",
                "baseline": f"{n / t[base]['wall'] / 1e6:.0f} Mpts/s (NumPy {baselines[base]})",
                "ratio": t[base]["wall"] / w,
                "compile_s": max(first - w, 0.0) if key == keys_ours[0][0] else None,
                "note": f"medians; NumPy {others} Mpts/s; best wall "
                f"{n / t[key]['wall_best'] / 1e6:.0f} Mpts/s; {gbs:.1f} GB/s = "
                f"{gbs / bandwidth:.0%} of copy; CPU time {n / c / 1e6:.0f} vs "
                f"{n / t[base]['cpu'] / 1e6:.0f} Mpts/s ({t[base]['cpu'] / c:.2f}×, ours on "
                f"{threads} threads); max abs dX {err * 1e3:.2g} µm vs float64 NumPy",
            }
        )
        print(_row(rows[-1]), flush=True)
    return rows


def bench_camera(sizes, repeats: int, bandwidth: float) -> list[dict]:
    """`stripe_to_camera` (a fresh result per call, and `out=` the previous result)
    against NumPy eq. (3) (matrix products, and broadcasts), interleaved, medians."""
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
            box = {}

            def ours():
                return sf.stripe_to_camera(cam, plane, uv).points.block_until_ready()

            def ours_out():
                box["rec"] = sf.stripe_to_camera(cam, plane, uv, out=box["rec"])
                box["rec"].points.block_until_ready()

            t0 = time.perf_counter()
            rec = ours()
            first = time.perf_counter() - t0
            box["rec"] = sf.stripe_to_camera(cam, plane, uv)
            K, nn = K_f.astype(dtype), n_vec.astype(dtype)
            fns = {
                "ours": ours,
                "ours_out": ours_out,
                "np_blas": lambda: numpy_eq3(K, nn, uv_np),
                "np_bcast": lambda: numpy_eq3_broadcast(K, nn, uv_np),
            }
            t = _interleaved(fns, repeats if n < 10**7 else max(3, repeats // 2))
            ref = numpy_eq3(K_f, n_vec, uv_np.astype(np.float64))
            err = float(np.nanmax(np.abs(np.asarray(rec, np.float64) - ref)))
            assert np.array_equal(np.asarray(box["rec"].points), np.asarray(rec), equal_nan=True)
            rows += _rows_for(
                f"stripe_to_camera {np.dtype(dtype).name}",
                f"{n:.0e} pts",
                n,
                t,
                [("ours", ""), ("ours_out", ", out= reused")],
                {"np_blas": "eq. 3 matmul", "np_bcast": "eq. 3 broadcast"},
                bandwidth,
                first,
                np.dtype(dtype).itemsize,
                err,
                os.cpu_count(),
            )
            box.clear()
            del rec
    return rows


def bench_measurement(sizes, repeats: int, bandwidth: float) -> list[dict]:
    """`stripe_to_measurement` float32 on `(1000, n / 1000, 2)` pixels, one frame index
    per row, against NumPy eq. (3) + (13), interleaved, medians."""
    import math

    import jax.numpy as jnp

    import scheimflux as sf

    cam, plane = sf.paper_thick_lens("scheimpflug-1.5"), sf.paper_laser_plane()
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    t_mc, dw = np.array([1.0, 2.0, 300.0]), math.radians(0.5)
    stage = sf.RotaryStage(R, t_mc, dw)
    K_f, n_vec = np.asarray(cam.K_f), np.asarray(plane.n)
    rows = []
    for n in sizes:
        dtype = np.float32
        frames = 1000
        uv_np = _pixels(n, dtype).reshape(frames, n // frames, 2)
        uv, fi = jnp.asarray(uv_np), jnp.arange(frames, dtype=jnp.int32)[:, None]
        ang = np.arange(frames)[:, None] * dw
        c, s = np.cos(ang).astype(dtype), np.sin(ang).astype(dtype)
        K, nn, RR, tt = (x.astype(dtype) for x in (K_f, n_vec, R, t_mc))
        box = {}

        def ours():
            return sf.stripe_to_measurement(cam, plane, stage, uv, fi).points.block_until_ready()

        def ours_out():
            box["rec"] = sf.stripe_to_measurement(cam, plane, stage, uv, fi, out=box["rec"])
            box["rec"].points.block_until_ready()

        t0 = time.perf_counter()
        rec = ours()
        first = time.perf_counter() - t0
        box["rec"] = sf.stripe_to_measurement(cam, plane, stage, uv, fi)
        fns = {
            "ours": ours,
            "ours_out": ours_out,
            "np13": lambda: numpy_eq13(K, nn, RR, tt, c, s, uv_np),
        }
        t = _interleaved(fns, repeats if n < 10**7 else max(3, repeats // 2))
        ref = numpy_eq13(K_f, n_vec, R, t_mc, np.cos(ang), np.sin(ang), uv_np.astype(float))
        err = float(np.nanmax(np.abs(np.asarray(rec, np.float64) - ref)))
        rows += _rows_for(
            "stripe_to_measurement float32",
            f"{n:.0e} pts",
            n,
            t,
            [("ours", ""), ("ours_out", ", out= reused")],
            {"np13": "eq. 3 + 13 broadcast"},
            bandwidth,
            first,
            4,
            err,
            os.cpu_count(),
        )
        box.clear()
        del rec
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
            same = (
                open(os.path.join(tmp, f"memory{F}.ply"), "rb").read()
                == open(os.path.join(tmp, f"stream{F}.ply"), "rb").read()
            )
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
    ap.add_argument("--repeats", type=int, default=9, help="median of this many (1e7: half)")
    ap.add_argument("--min-points", type=float, default=1e4)
    ap.add_argument("--stream-frames", default="1000,10000", help="frame counts, or ''")
    ap.add_argument("--json", metavar="ROWS.json", help="also write the rows as JSON")
    ap.add_argument("--label", default="", help="appended to every operation's name")
    ap.add_argument(
        "--copy-gbps", type=float, help="the copy bandwidth to compare with (else measured)"
    )
    args = ap.parse_args(argv)
    max_n = 1e5 if args.quick else args.max_points
    repeats = 2 if args.quick else args.repeats
    bw = args.copy_gbps or copy_bandwidth()
    print(f"load: {os.getloadavg()}  NumPy copy bandwidth {bw:.1f} GB/s", flush=True)
    print("| operation | size | ours | baseline | ratio | compile s | note |")
    print("|---|---|---|---|---|---|---|")
    sizes = [int(10**k) for k in range(4, 8) if args.min_points <= 10**k <= max_n]
    rows = bench_camera(sizes, repeats, bw)
    rows += bench_measurement([x for x in sizes if x >= 10**6], repeats, bw)
    counts = [int(x) for x in args.stream_frames.split(",") if x.strip()]
    if args.quick:
        counts = [c for c in counts if c <= 1000] or counts[:1]
    rows += bench_stream(counts)
    for r in rows:
        r["operation"] += args.label
    print(f"load after: {os.getloadavg()}; peak RSS here "
          f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**10:.0f} MiB")  # fmt: skip
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"copy_GBps": bw, "rows": rows}, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
