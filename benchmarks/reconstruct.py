"""Reconstruction speed: `stripe_to_camera` (jit + vmap) against plain NumPy eq. (3).

For N = 1e4 … `--max-points` pixels on the paper's ×1.5 thick-lens preset: points/s of
the public `stripe_to_camera` in float32 and float64 (compiled once per shape; the
one-off compile time is reported separately), of a vectorised NumPy implementation of
eq. (3), X = K_f p̃ / (n · K_f p̃), in the same run, and their ratio. Then
`stripe_to_measurement` on (frames, points) batches.

    python benchmarks/reconstruct.py [--max-points 1e7] [--quick] [--repeats 3]

Memory: 1e7 float64 pixels are 160 MB in, 240 MB out (plus NumPy temporaries of about
1 GB); the script skips sizes whose estimate exceeds half the available memory.
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

import scheimflux as sf


def numpy_eq3(K_f: np.ndarray, n: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """X = K_f p̃ / (n · K_f p̃), vectorised (N, 2) → (N, 3)."""
    P = uv @ K_f[:, :2].T + K_f[:, 2]
    return P / (P @ n)[:, None]


def _time(fn, repeats: int) -> float:
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def _available_bytes() -> float:
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError):
        return np.inf


def _pixels(n: int, dtype) -> np.ndarray:
    rng = np.random.default_rng(0)
    return (rng.random((n, 2)) * [1599.0, 1199.0]).astype(dtype)


def bench_camera(sizes, repeats: int) -> None:
    cam = sf.paper_thick_lens("scheimpflug-1.5")
    plane = sf.paper_laser_plane()
    K_f = np.asarray(cam.K_f)
    n_vec = np.asarray(plane.n)
    print(f"stripe_to_camera vs NumPy eq. (3)   [{jax.devices()[0].platform}, best of {repeats}]")
    hdr = (
        f"{'N':>9} {'dtype':>7} | {'compile s':>9} | {'jax Mpts/s':>10} | "
        f"{'numpy Mpts/s':>12} | {'jax/numpy':>9} | {'max |dX| µm':>11}"
    )
    print(hdr)
    print("-" * len(hdr))
    for n in sizes:
        for dtype in (np.float32, np.float64):
            item = np.dtype(dtype).itemsize
            need = n * item * (2 + 3 + 3) * 4  # in, out, temporaries (rough)
            if need > 0.5 * _available_bytes():
                print(f"{n:>9.0e} {np.dtype(dtype).name:>7} | skipped (needs ~{need / 1e9:.1f} GB)")
                continue
            uv_np = _pixels(n, dtype)
            uv = jnp.asarray(uv_np)
            t = time.perf_counter()
            rec = sf.stripe_to_camera(cam, plane, uv)
            rec.points.block_until_ready()
            first = time.perf_counter() - t
            t_jax = _time(lambda: sf.stripe_to_camera(cam, plane, uv).points.block_until_ready(),
                          repeats)  # fmt: skip
            compile_s = max(first - t_jax, 0.0)
            K, nn = K_f.astype(dtype), n_vec.astype(dtype)
            t_np = _time(lambda: numpy_eq3(K, nn, uv_np), repeats)
            ref = numpy_eq3(K_f, n_vec, uv_np.astype(np.float64))
            err = 1e3 * float(np.nanmax(np.abs(np.asarray(rec.points, np.float64) - ref)))
            print(
                f"{n:>9.0e} {np.dtype(dtype).name:>7} | {compile_s:>9.2f} | "
                f"{n / t_jax / 1e6:>10.1f} | {n / t_np / 1e6:>12.1f} | "
                f"{t_np / t_jax:>9.2f} | {err:>11.3g}"
            )
            del rec


def bench_measurement(shapes, repeats: int) -> None:
    cam = sf.paper_thick_lens("scheimpflug-1.5")
    plane = sf.paper_laser_plane()
    stage = sf.paper_stage()
    print("\nstripe_to_measurement on (frames, points) batches, float64")
    hdr = f"{'frames':>7} {'points':>7} | {'compile s':>9} | {'Mpts/s':>7}"
    print(hdr)
    print("-" * len(hdr))
    for frames, pts in shapes:
        uv = jnp.asarray(_pixels(frames * pts, np.float64).reshape(frames, pts, 2))
        idx = jnp.arange(frames)[:, None]  # one index per frame
        t = time.perf_counter()
        sf.stripe_to_measurement(cam, plane, stage, uv, idx).points.block_until_ready()
        first = time.perf_counter() - t
        dt = _time(
            lambda: sf.stripe_to_measurement(cam, plane, stage, uv, idx).points.block_until_ready(),
            repeats,
        )
        print(
            f"{frames:>7} {pts:>7} | {max(first - dt, 0):>9.2f} | {frames * pts / dt / 1e6:>7.1f}"
        )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-points", type=float, default=1e7)
    ap.add_argument("--quick", action="store_true", help="up to 1e5 points, 1 repeat")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    max_n = 1e5 if args.quick else args.max_points
    repeats = 1 if args.quick else args.repeats
    sizes = [int(10**k) for k in range(4, 8) if 10**k <= max_n]
    bench_camera(sizes, repeats)
    shapes = [(100, 1600), (360, 1600)] if args.quick else [(100, 1600), (360, 1600), (3600, 1600)]
    bench_measurement(shapes, repeats)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
