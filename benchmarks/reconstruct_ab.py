"""The fused reconstruction kernel against an earlier version of it, NumPy eq. (3) and the
copy bandwidth, side by side in one process.

    python benchmarks/reconstruct_ab.py [--baseline REV] [--sizes 1e6,1e7]
                                        [--dtypes float32,float64] [--repeats 15]
                                        [--rounds 3]

The baseline is `scheimflux/reconstruct/_kernel.py` as committed at `REV` (read with
`git show`, loaded as a sibling module, so it runs on this checkout's cameras and planes);
"new" is the kernel of this checkout. For each size and dtype they are called in
turn within each repeat (one warm-up call each first), `--rounds` times over, and each
round prints median wall and CPU times (process CPU seconds, all threads) as points per
second, with `uptime`'s load. Both kernels are called with a fresh result per call and
with their output buffers donated (`out=`, the previous result reused), which takes the
page faults of fresh outputs above glibc's mmap threshold out of the comparison, and
`stripe_to_measurement`'s kernel on the same pixels as 1000 frames (fresh results). The
points and statuses of the two kernels are compared (bit for bit) before timing.

The NumPy baseline is the faster of eq. (3) with matrix products and with broadcasts
(`benchmarks/reconstruct.py`); the copy bandwidth is a NumPy copy of 256 MiB (read +
write), measured in each round.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import subprocess
import sys
from functools import partial

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from reconstruct import (  # noqa: E402
    _interleaved,
    copy_bandwidth,
    numpy_eq3,
    numpy_eq3_broadcast,
)


def load_baseline(rev: str):
    """`scheimflux/reconstruct/_kernel.py` at `rev`, as module
    `scheimflux.reconstruct._kernel_baseline` (its relative imports resolve in this
    checkout)."""
    import scheimflux.reconstruct as pkg

    src = subprocess.run(
        ["git", "show", f"{rev}:scheimflux/reconstruct/_kernel.py"],
        cwd=os.path.dirname(HERE),
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    name = "scheimflux.reconstruct._kernel_baseline"
    spec = importlib.util.spec_from_loader(name, loader=None, origin=f"{rev}:_kernel.py")
    mod = importlib.util.module_from_spec(spec)
    mod.__package__ = pkg.__name__
    sys.modules[name] = mod
    exec(compile(src, f"<{rev}:scheimflux/reconstruct/_kernel.py>", "exec"), mod.__dict__)
    return mod


def _uptime() -> str:
    with open("/proc/loadavg") as f:
        return " ".join(f.read().split()[:3])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", default="HEAD", help="git revision of the baseline kernel")
    ap.add_argument("--sizes", default="1e6,1e7")
    ap.add_argument("--dtypes", default="float32,float64")
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args(argv)

    import jax
    import jax.numpy as jnp

    import scheimflux as sf
    from scheimflux.reconstruct import _kernel as new

    old = load_baseline(args.baseline)
    cam, plane = sf.paper_thick_lens("scheimpflug-1.5"), sf.paper_laser_plane()
    stage = sf.RotaryStage(np.eye(3), [1.0, 2.0, 3.0], np.radians(0.5))
    K_f = np.asarray(cam.pixel_to_object_matrix())[:3]
    n_vec = np.asarray(plane.n)
    print(f"baseline {args.baseline}; jax {jax.__version__}; load {_uptime()}", flush=True)

    for size in (int(float(s)) for s in args.sizes.split(",")):
        for dtype in args.dtypes.split(","):
            rng = np.random.default_rng(0)
            uv_np = (rng.random((size, 2)) * [1599.0, 1199.0]).astype(dtype)
            uv = jnp.asarray(uv_np)
            K, nn = K_f.astype(dtype), n_vec.astype(dtype)

            ref = old.fast_stripe_to_camera(cam, plane, uv)
            got = new.fast_stripe_to_camera(cam, plane, uv)
            same = bool(
                np.array_equal(np.asarray(ref[0]), np.asarray(got[0]), equal_nan=True)
                and np.array_equal(np.asarray(ref[1]), np.asarray(got[1]))
            )
            del ref, got
            state = {}

            def fresh(mod):
                mod.fast_stripe_to_camera(cam, plane, uv)[0].block_until_ready()

            def into(mod, key):
                buf = state.get(key) or mod.fast_stripe_to_camera(cam, plane, uv)
                state[key] = mod.fast_stripe_to_camera_into(cam, plane, uv, buf)
                state[key][0].block_until_ready()

            def np_best():
                numpy_eq3(K, nn, uv_np)

            def np_bcast():
                numpy_eq3_broadcast(K, nn, uv_np)

            # stripe_to_measurement on the same pixels as 1000 frames (the first 1000 k)
            uv_m = uv[: size - size % 1000].reshape(1000, -1, 2)
            fi = jnp.arange(1000)[:, None]

            def meas(mod):
                mod.fast_stripe_to_measurement(cam, plane, stage, uv_m, fi)[0].block_until_ready()

            m_old = old.fast_stripe_to_measurement(cam, plane, stage, uv_m, fi)
            m_new = new.fast_stripe_to_measurement(cam, plane, stage, uv_m, fi)
            same_m = bool(
                np.array_equal(np.asarray(m_old[0]), np.asarray(m_new[0]), equal_nan=True)
                and np.array_equal(np.asarray(m_old[1]), np.asarray(m_new[1]))
            )
            del m_old, m_new
            fns = {
                "meas_old": partial(meas, old),
                "meas_new": partial(meas, new),
                "old": partial(fresh, old),
                "new": partial(fresh, new),
                "old_out": partial(into, old, "old"),
                "new_out": partial(into, new, "new"),
                "numpy_blas": np_best,
                "numpy_bcast": np_bcast,
            }
            reps = args.repeats if size <= 2_000_000 else max(3, args.repeats // 3)
            for r in range(args.rounds):
                load = _uptime()
                bw = copy_bandwidth()
                timed = _interleaved(fns, reps)
                w = {k: v["wall"] for k, v in timed.items()}
                c = {k: v["cpu"] for k, v in timed.items()}
                npk = min(("numpy_blas", "numpy_bcast"), key=w.get)
                item = np.dtype(dtype).itemsize
                minbytes = size * (5 * item + 1)  # 2 floats in, 3 out, 1 status byte

                def mps(sec):
                    return size / sec / 1e6

                print(
                    f"N={size} {dtype} round {r + 1} load {load} copy {bw:.1f} GB/s "
                    f"(old == new bit for bit: camera {same}, measurement {same_m})\n"
                    + "".join(
                        f"  {k:12s} wall {mps(w[k]):6.0f} Mpts/s  CPU {mps(c[k]):6.0f} Mpts/CPU-s"
                        f"  {minbytes / w[k] / 1e9 / bw:5.0%} of copy\n"
                        for k in fns
                    )
                    + f"  measurement new/old {w['meas_old'] / w['meas_new']:.2f}x wall "
                    f"{c['meas_old'] / c['meas_new']:.2f}x CPU;"
                    f" new/old {w['old'] / w['new']:.2f}x wall {c['old'] / c['new']:.2f}x CPU;"
                    f" new_out/old_out {w['old_out'] / w['new_out']:.2f}x wall "
                    f"{c['old_out'] / c['new_out']:.2f}x CPU; new/NumPy({npk}) "
                    f"{w[npk] / w['new']:.2f}x wall {c[npk] / c['new']:.2f}x CPU; new_out/NumPy "
                    f"{w[npk] / w['new_out']:.2f}x wall {c[npk] / c['new_out']:.2f}x CPU",
                    flush=True,
                )
            state.clear()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
