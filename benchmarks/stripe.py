"""Laser-stripe extraction: accuracy against exact synthetic centres, and speed.

Accuracy: bias and RMS (px) of the centre across the stripe for band Steger, full-frame
Steger and the grey centroid, for stripe widths 3, 5, 8 px (FWHM) and dark/low/bright
ambient light (tilted, gently curved stripe, SNR 20, 8-bit).
Speed: frames/s on 1600 x 1200 8-bit frames for band Steger (one thread, with the
compiled per-scan-line loops and with their NumPy reference; the multi-frame API with
a thread pool; and one process per CPU, each on its share of the frames), and for a
full-frame OpenCV Steger baseline (Gaussian derivative filters over the whole frame,
per-column maximum) run here.
Captures (issue 9): one row per realistic scene of `sf.simulate.render_capture`
(laser on a dimmed checkerboard through the paper rig's ray tracer, circle grid,
oblique and vertical lines, colour with white ambient light, saturated core, glints,
JPEG), scored against the exact centre lines: bias, RMS, false-point rate (> 1 px
off), coverage, frames/s; without and with the laser-off frame, beside the plain
full-frame Steger baseline on the same image.

Stages (`--stages`): CPU time per stage of `extract_stripe` on the plain speed frames
(one thread), from timers around the stage functions.

Cold compile (`--cold-compile N`): N fresh processes, each with an empty Numba cache
directory, each timing (CPU) its first `extract_stripe` on a plain 1600 x 1200 frame,
then the first calls on the test suite's capture scenes and image kinds, then a second
process on the now filled cache; per compiled kernel its own compile time (Numba's
`numba:compile` events, less the kernels compiled inside them) and its number of
compiled specialisations; "Numba library code": the rest of the events (NumPy functions
and operators that Numba compiles for the kernels).

    python benchmarks/stripe.py [--frames N] [--quick] [--captures-only] [--views K]
                                [--stages] [--speed-only] [--cold-compile N]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import time

import cv2
import numpy as np

from scheimflux.simulate._render_stripe import render_stripe
from scheimflux.stripe import extract_stripe, extract_stripes, steger_sigma
from scheimflux.stripe._kernels import gaussian_kernels

try:  # the compiled per-scan-line loops (absent from older versions of the extractor)
    from scheimflux.stripe import _fast
except ImportError:
    _fast = None

SHAPE = (1200, 1600)


def centre(u):
    return 500.3 + 0.15 * u + 30.0 * np.sin(u / 300.0)


def opencv_full_frame_steger(img: np.ndarray, sigma: float) -> np.ndarray:
    """Baseline: cv2 Gaussian derivatives over the whole frame, Hessian eigenvalue, per
    column the strongest response and Steger's Taylor step there."""
    k0, k1, k2 = gaussian_kernels(sigma)
    f = img.astype(np.float32)
    ry = cv2.sepFilter2D(f, cv2.CV_32F, k0, k1)
    rxx = cv2.sepFilter2D(f, cv2.CV_32F, k2, k0)
    rxy = cv2.sepFilter2D(f, cv2.CV_32F, k1, k1)
    ryy = cv2.sepFilter2D(f, cv2.CV_32F, k0, k2)
    lam = 0.5 * (rxx + ryy) - np.sqrt((0.5 * (rxx - ryy)) ** 2 + rxy**2)
    best = cv2.reduceArgMax(-lam, 0).ravel()
    cols = np.arange(img.shape[1])
    return best + ry[best, cols] / np.maximum(-ryy[best, cols], 1e-6)


def accuracy_table(quick: bool) -> None:
    shape = (600, 800) if quick else SHAPE
    print("accuracy (px, across the stripe; SNR 20, 8-bit, tilted curved stripe)")
    print(
        f"{'width':>5} {'ambient':>8} | {'band bias':>9} {'rms':>6} | "
        f"{'full bias':>9} {'rms':>6} | {'centroid bias':>13} {'rms':>6}"
    )
    for width in (3, 5, 8):
        for ambient in ("dark", "low", "bright"):
            c = (lambda u: centre(u) * shape[0] / SHAPE[0]) if quick else centre
            img, truth = render_stripe(
                shape, c, width_px=width, peak=0.4, ambient=ambient, noise_sigma=0.02, seed=width
            )
            row = []
            for kw in ({}, {"band_px": None}, {"method": "centroid"}):
                res = extract_stripe(img, width_px=width, **kw)
                ok = res.valid & truth.valid
                err = res.uv[ok, 1] - truth.uv[ok, 1]
                row.append((err.mean(), np.sqrt(np.mean(err**2))))
            print(
                f"{width:>5} {ambient:>8} | {row[0][0]:>+9.4f} {row[0][1]:>6.4f} | "
                f"{row[1][0]:>+9.4f} {row[1][1]:>6.4f} | {row[2][0]:>+13.4f} {row[2][1]:>6.4f}"
            )


def rate(fn, frames) -> tuple[float, float]:
    """Frames per second of wall-clock time and of this process's CPU time (the latter is
    immune to other processes sharing the machine; for a thread pool it is per core)."""
    fn(frames[:2])
    t0, c0 = time.perf_counter(), time.process_time()
    fn(frames)
    return len(frames) / (time.perf_counter() - t0), len(frames) / (time.process_time() - c0)


def _process_worker(n_frames: int, barrier, queue) -> None:
    """One process of `process_rate`: its own frames, one warm-up, then timed."""
    cv2.setNumThreads(1)
    frames = _speed_frames(n_frames)
    for f in frames[:2]:
        extract_stripe(f, width_px=5)
    barrier.wait()
    t0, c0 = time.perf_counter(), time.process_time()
    for f in frames:
        extract_stripe(f, width_px=5)
    queue.put((t0, time.perf_counter(), time.process_time() - c0))


def process_rate(n_frames: int, workers: int) -> tuple[float, float]:
    """Band Steger frames/s over `workers` processes (spawned, one thread each), each
    extracting its share of the `n_frames` frames; all start together after their
    warm-up (a barrier), and the wall time runs from the first start to the last end
    (`perf_counter` is the system's monotonic clock, common to the processes). The
    second number is frames per CPU-second summed over the processes."""
    ctx = multiprocessing.get_context("spawn")
    barrier, queue = ctx.Barrier(workers), ctx.Queue()
    shares = [n_frames // workers + (i < n_frames % workers) for i in range(workers)]
    procs = [ctx.Process(target=_process_worker, args=(k, barrier, queue)) for k in shares]
    for p in procs:
        p.start()
    res = [queue.get() for _ in procs]
    for p in procs:
        p.join()
    wall = max(r[1] for r in res) - min(r[0] for r in res)
    return n_frames / wall, n_frames / sum(r[2] for r in res)


def speed_table(n_frames: int) -> None:
    frames = _speed_frames(n_frames)
    sigma = steger_sigma(5.0)
    previous = cv2.getNumThreads()
    results = {}
    cv2.setNumThreads(1)
    results["band Steger, 1 thread"] = rate(
        lambda fs: [extract_stripe(f, width_px=5) for f in fs], frames
    )
    if _fast is not None and _fast.AVAILABLE:  # the same frames through the NumPy reference loops
        _fast.enabled = False
        try:
            results["band Steger, 1 thread, NumPy reference loops"] = rate(
                lambda fs: [extract_stripe(f, width_px=5) for f in fs], frames
            )
        finally:
            _fast.enabled = True
    results["centroid, 1 thread"] = rate(
        lambda fs: [extract_stripe(f, width_px=5, method="centroid") for f in fs], frames
    )
    cv2.setNumThreads(previous)
    results[f"band Steger, extract_stripes ({os.cpu_count()} threads)"] = rate(
        lambda fs: extract_stripes(fs, width_px=5), frames
    )
    workers = os.cpu_count() or 1
    if workers > 1:
        results[f"band Steger, {workers} processes (1 thread each)"] = process_rate(
            n_frames, workers
        )
    few = frames[: max(4, n_frames // 20)]
    results[f"full-frame OpenCV Steger baseline ({cv2.getNumThreads()} cv2 threads)"] = rate(
        lambda fs: [opencv_full_frame_steger(f, sigma) for f in fs], few
    )
    results["full-frame Steger, extract_stripe(band_px=None)"] = rate(
        lambda fs: [extract_stripe(f, width_px=5, band_px=None) for f in fs], few
    )
    base = results[f"full-frame OpenCV Steger baseline ({cv2.getNumThreads()} cv2 threads)"]
    print(f"\nspeed, 1600 x 1200 8-bit, width 5 px ({n_frames} frames; baselines on {len(few)})")
    print(f"load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    print(
        "compiled per-scan-line loops: "
        + (f"Numba {_fast.numba.__version__}" if _fast and _fast.AVAILABLE else "off (NumPy)")
    )
    print(f"{'method':<58} {'frames/s':>9} {'ratio':>7} {'per CPU-s':>10} {'ratio':>7}")
    for name, (fps, cps) in results.items():
        print(f"{name:<58} {fps:>9.1f} {fps / base[0]:>6.1f}x {cps:>10.1f} {cps / base[1]:>6.1f}x")


# (the names `_extract` calls; a version without one, or not calling it, skips its row:
# `_frame_noise` and `_block_noise` are the noise estimates' compiled paths for uint8,
# which call `estimate_noise` and `block_noise` for other types: time uint8 frames only)
_STAGES = (
    "downsample",
    "estimate_noise",
    "_frame_noise",
    "_block_noise",
    "scan_direction",
    "coarse_track",
    "steger_band",
    "refit_steps",
    "consistent",
    "link_segments",
)


def _speed_frames(n_frames: int) -> list[np.ndarray]:
    frames = [
        render_stripe(
            SHAPE,
            lambda u, i=i: centre(u) + 7.3 * i,
            width_px=5,
            peak=0.5,
            ambient="low",
            noise_sigma=0.01,
            seed=i,
        )[0]
        for i in range(min(n_frames, 8))
    ]
    return (frames * (n_frames // len(frames) + 1))[:n_frames]


def stage_table(n_frames: int) -> None:
    """CPU time per stage (timers around the stage functions that `_extract` calls)."""
    import scheimflux.stripe._extract as ex

    frames = _speed_frames(n_frames)
    stages = [name for name in _STAGES if hasattr(ex, name)]
    spent = dict.fromkeys(stages, 0.0)
    original = {name: getattr(ex, name) for name in stages}

    def timed(name):
        def call(*args, **kwargs):
            t0 = time.process_time()
            try:
                return original[name](*args, **kwargs)
            finally:
                spent[name] += time.process_time() - t0

        return call

    previous = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        for f in frames[:2]:
            extract_stripe(f, width_px=5)
        for name in stages:
            setattr(ex, name, timed(name))
        t0 = time.process_time()
        for f in frames:
            extract_stripe(f, width_px=5)
        total = time.process_time() - t0
    finally:
        for name in stages:
            setattr(ex, name, original[name])
        cv2.setNumThreads(previous)
    n = len(frames)
    print(f"\nstages of extract_stripe, 1600 x 1200 plain frames ({n}; CPU ms per frame)")
    print(f"load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    for name in stages:
        if spent[name] > 0:
            print(f"{name:<28} {1e3 * spent[name] / n:>7.3f} {100 * spent[name] / total:>5.1f}%")
    rest = total - sum(spent.values())
    print(f"{'rest (checks, assembly)':<28} {1e3 * rest / n:>7.3f} {100 * rest / total:>5.1f}%")
    print(f"{'total':<28} {1e3 * total / n:>7.3f} ({n / total:.0f} frames per CPU-s)")


def _baseline_centres(img: np.ndarray, orientation: str) -> np.ndarray:
    """The plain full-frame Steger baseline's (u, v) centre per scan line (grey)."""
    grey = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    sigma = steger_sigma(5.0)
    if orientation == "vertical-scan":
        v = opencv_full_frame_steger(grey, sigma)
        return np.stack([np.arange(grey.shape[1], dtype=np.float64), v], 1)
    u = opencv_full_frame_steger(np.ascontiguousarray(grey.T), sigma)
    return np.stack([u, np.arange(grey.shape[0], dtype=np.float64)], 1)


def _scenes(quick: bool, n_views: int):
    """(name, laser-on image, laser-off image, truth) per scene."""
    from scheimflux.simulate import board_poses, board_view_capture, paper_rig, render_capture
    from scheimflux.targets._board import Checkerboard

    shape = (600, 800) if quick else SHAPE
    out = []
    t0 = time.perf_counter()
    rig = paper_rig()
    board = Checkerboard(11, 8, 0.3)
    views = board_poses(rig, board, max(n_views, 1), seed=0)
    for k, view in enumerate(views[:n_views]):
        on, off, truth = board_view_capture(
            rig, board, view, pair=True, seed=k, blur_px=(0.5, 1.2)
        )
        out.append((f"paper rig checkerboard, view {k}", on, off, truth))
    print(f"(rendered {n_views} ray-traced views in {time.perf_counter() - t0:.0f} s)")
    base = dict(line_angle_deg=15.0, line_offset_px=9.0, blur_px=(0.5, 1.2))
    scenes = {
        "checkerboard, 15 deg": {},
        "circle grid": dict(target="circles"),
        "oblique, 50 deg": dict(line_angle_deg=50.0),
        "vertical, 88 deg": dict(line_angle_deg=88.0),
        "curved": dict(line_curvature=0.0015),
        "colour, white ambient 0.5": dict(colour=True, ambient=0.5),
        "saturated core (peak 2.5)": dict(peak=2.5),
        "12 glints": dict(glints=12),
        "JPEG q85": dict(jpeg_quality=85),
        "plain surface (no board)": dict(target="plain"),
    }
    for i, (name, kw) in enumerate(scenes.items()):
        args = {**base, **kw}
        on, truth = render_capture(shape=shape, seed=10 + i, **args)
        off, _ = render_capture(shape=shape, seed=10 + i, laser_on=False, **args)
        out.append((name, on, off, truth))
    return out


def capture_table(quick: bool, n_views: int) -> None:
    from scheimflux.simulate import score_stripe

    print("\ncaptures: centres vs the exact centre line (px; false = > 1 px off or past an end)")
    print(f"load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    head = f"{'scene':<36} {'mode':<9} {'bias':>8} {'rms':>6} {'false':>7} {'cover':>6} {'f/s':>6}"
    print(head)
    totals: dict[str, list] = {}
    previous = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        for name, on, off, truth in _scenes(quick, n_views):
            shape = on.shape[:2]
            rows = []
            for mode, kw in (("on", {}), ("on+off", {"background": off})):
                extract_stripe(on, **kw)
                t0 = time.perf_counter()
                res = extract_stripe(on, **kw)
                fps = 1.0 / (time.perf_counter() - t0)
                rows.append((mode, score_stripe(res.valid_uv, res.orientation, truth, shape), fps))
                orientation = res.orientation
            t0 = time.perf_counter()
            uv = _baseline_centres(on, orientation)
            fps = 1.0 / (time.perf_counter() - t0)
            rows.append(("baseline", score_stripe(uv, orientation, truth, shape), fps))
            for mode, sc, fps in rows:
                print(
                    f"{name:<36} {mode:<9} {sc.bias:>+8.4f} {sc.rms:>6.3f} "
                    f"{100 * sc.false_rate:>6.2f}% {100 * sc.coverage:>5.1f}% {fps:>6.1f}"
                )
                if name.startswith("paper rig"):
                    totals.setdefault(mode, []).append(sc)
    finally:
        cv2.setNumThreads(previous)
    for mode, scores in totals.items():
        n = np.array([s.n for s in scores], float)
        false = float(np.sum(n * [s.false_rate for s in scores]) / max(n.sum(), 1))
        rms = float(np.sqrt(np.nansum(n * np.array([s.rms for s in scores]) ** 2) / n.sum()))
        bias = float(np.nanmean([s.bias for s in scores]))
        cover = float(np.mean([s.coverage for s in scores]))
        print(
            f"{'paper rig, all views':<36} {mode:<9} {bias:>+8.4f} {rms:>6.3f} "
            f"{100 * false:>6.2f}% {100 * cover:>5.1f}%"
        )


def _cold_child() -> None:
    """One process of `cold_compile_table` (run with its own `NUMBA_CACHE_DIR`): prints
    one line of JSON with the CPU times and the per-kernel compile times."""
    import json

    from numba.core import event

    spent: dict[str, float] = {}
    stack: list[list] = []  # per open compile: [kernel, start, time of the nested ones]

    class _Timer(event.Listener):
        def on_start(self, ev):
            stack.append([ev.data["dispatcher"].py_func.__name__, time.process_time(), 0.0])

        def on_end(self, ev):
            name, t0, nested = stack.pop()
            total = time.process_time() - t0
            spent[name] = spent.get(name, 0.0) + total - nested
            if stack:
                stack[-1][2] += total

    frame = _speed_frames(1)[0]
    steps = {}
    cv2.setNumThreads(1)
    with event.install_listener("numba:compile", _Timer()):
        for label in ("plain, first call", "plain, second call"):
            c0 = time.process_time()
            extract_stripe(frame, width_px=5)
            steps[label] = time.process_time() - c0
        cases = []
        img, _ = render_stripe(
            (300, 800), lambda u: 150.0 + 40.0 * np.sin(u / 150.0), width_px=5, peak=0.4,
            ambient="low", noise_sigma=0.02, seed=1,
        )  # fmt: skip
        cases += [(img, {}), (img, {"width_px": 5}), (img.T.copy(), {})]
        cases += [(img.astype(np.float32) / 255, {"band_px": 12})]
        from scheimflux.simulate import render_capture

        base = dict(shape=(300, 400), line_angle_deg=15.0, line_offset_px=9.0, blur_px=(0.5, 1.2))
        for kw in ({}, dict(line_angle_deg=88.0), dict(colour=True, ambient=0.5)):
            on, _ = render_capture(seed=3, **{**base, **kw})
            off, _ = render_capture(seed=3, laser_on=False, **{**base, **kw})
            cases += [(on, {}), (on, {"background": off})]
        c0 = time.process_time()
        for img, kw in cases:
            extract_stripe(img, **kw)
        steps["test images and captures, first calls"] = time.process_time() - c0
    counts = {
        name: len(d.signatures)
        for name, d in vars(_fast).items()
        if isinstance(d, _fast.numba.core.registry.CPUDispatcher)
    }
    print(json.dumps({"steps": steps, "compile": spent, "signatures": counts}))


def cold_compile_table(runs: int) -> None:
    """`runs` fresh processes, each on an empty Numba cache, then one on its filled cache
    (the per-kernel times: the mean over the cold runs)."""
    import json
    import subprocess
    import sys
    import tempfile

    print(f"\ncold compile (Numba {_fast.numba.__version__}; CPU s; fresh processes)")
    print(f"load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    results = []
    for k in range(runs + 1):
        if k < runs:
            cache = tempfile.mkdtemp(prefix="numba-cold-")
        env = {**os.environ, "NUMBA_CACHE_DIR": cache}
        out = subprocess.run(
            [sys.executable, __file__, "--cold-child"], env=env, check=True,
            capture_output=True, text=True,
        ).stdout  # fmt: skip
        res = json.loads(out.strip().splitlines()[-1])
        kind = "cold" if k < runs else "filled cache"
        print(
            f"{kind:<13}"
            + "".join(f" | {name} {t:6.2f}" for name, t in res["steps"].items())
            + f" | compile events {sum(res['compile'].values()):6.2f}"
        )
        if k < runs:
            results.append(res)
    names = sorted(results[0]["signatures"], key=lambda n: -results[0]["compile"].get(n, 0))
    print(f"{'kernel':<22} {'compile s':>9} {'specialisations':>15}")
    for name in names:
        mean = np.mean([r["compile"].get(name, 0.0) for r in results])
        print(f"{name:<22} {mean:>9.2f} {results[0]['signatures'][name]:>15}")
    own = [sum(r["compile"].get(n, 0.0) for n in names) for r in results]
    library = np.mean([sum(r["compile"].values()) - o for r, o in zip(results, own)])
    print(f"{'(Numba library code)':<22} {library:>9.2f}")
    total = np.mean([sum(r["compile"].values()) for r in results])
    print(f"{'total':<22} {total:>9.2f} {sum(results[0]['signatures'].values()):>15}")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--frames", type=int, default=200, help="frames for the speed test")
    parser.add_argument("--quick", action="store_true", help="smaller accuracy images, 40 frames")
    parser.add_argument("--captures-only", action="store_true", help="only the capture table")
    parser.add_argument("--views", type=int, default=4, help="ray-traced board views")
    parser.add_argument("--stages", action="store_true", help="only the per-stage CPU table")
    parser.add_argument("--speed-only", action="store_true", help="only the speed table")
    parser.add_argument(
        "--cold-compile", type=int, metavar="N", help="only the compile time on N empty caches"
    )
    parser.add_argument("--cold-child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.cold_child:
        _cold_child()
        return
    if args.cold_compile:
        cold_compile_table(args.cold_compile)
        return
    if args.stages:
        stage_table(40 if args.quick else args.frames)
        return
    if args.speed_only:
        speed_table(40 if args.quick else args.frames)
        return
    if not args.captures_only:
        accuracy_table(args.quick)
        speed_table(40 if args.quick else args.frames)
    capture_table(args.quick, args.views)


if __name__ == "__main__":
    main()
