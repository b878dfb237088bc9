"""Throughput of the sequential ray tracer (rays / s), float64, on the shipped double Gauss.

Compares `scheimflux.simulate._trace.trace` under `jax.jit(jax.vmap(...))` with the same
algorithm in plain NumPy, once as a per-ray Python loop (run on a small N, extrapolated)
and once vectorised over rays, for 10^3 … 10^6 rays. Also times chief-ray aiming + trace
(Newton on the launch direction), and the one-off compile time.

    .venv/bin/python benchmarks/trace.py [--max-rays 1000000]
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from scheimflux.simulate._lens import load_lens, paraxial  # noqa: E402
from scheimflux.simulate._trace import aim_ray, trace  # noqa: E402


def _numpy_trace_one(z, c, n1, n2, sd, p, d):
    """The tracer's algorithm for one ray, in NumPy scalars/3-vectors."""
    d = d / np.sqrt(d @ d)
    ok = True
    for i in range(len(z)):
        rel = p - np.array([0.0, 0.0, z[i]])
        f = c[i] * (rel @ rel) - 2.0 * rel[2]
        g = d[2] - c[i] * (rel @ d)
        disc = g * g - c[i] * f
        if disc < 0:
            return p, d, False
        t = f / (g + np.sqrt(disc))
        q = rel + t * d
        nrm = np.array([-c[i] * q[0], -c[i] * q[1], 1.0 - c[i] * q[2]])
        nrm /= np.sqrt(nrm @ nrm)
        mu = n1[i] / n2[i]
        cos_i = d @ nrm
        k = 1.0 - mu * mu * (1.0 - cos_i * cos_i)
        if k < 0:
            return p, d, False
        d = mu * d + (np.copysign(np.sqrt(k), cos_i) - mu * cos_i) * nrm
        p = q + np.array([0.0, 0.0, z[i]])
        ok = ok and q[0] ** 2 + q[1] ** 2 <= sd[i] ** 2 and t >= -1e-9
    return p, d, ok


def _numpy_trace_vec(z, c, n1, n2, sd, p, d):
    """The same, vectorised over rays (arrays of shape (N, 3))."""
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    ok = np.ones(len(p), dtype=bool)
    for i in range(len(z)):
        rel = p - np.array([0.0, 0.0, z[i]])
        f = c[i] * np.einsum("ij,ij->i", rel, rel) - 2.0 * rel[:, 2]
        g = d[:, 2] - c[i] * np.einsum("ij,ij->i", rel, d)
        disc = g * g - c[i] * f
        hit = disc >= 0
        t = f / (g + np.sqrt(np.where(hit, disc, 0.0)))
        q = rel + t[:, None] * d
        nrm = np.stack([-c[i] * q[:, 0], -c[i] * q[:, 1], 1.0 - c[i] * q[:, 2]], axis=-1)
        nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
        mu = n1[i] / n2[i]
        cos_i = np.einsum("ij,ij->i", d, nrm)
        k = 1.0 - mu * mu * (1.0 - cos_i**2)
        tir = k < 0
        sq = np.sqrt(np.where(tir, 1.0, k))
        d = mu * d + (np.copysign(sq, cos_i) - mu * cos_i)[:, None] * nrm
        p = q + np.array([0.0, 0.0, z[i]])
        ok &= hit & ~tir & (q[:, 0] ** 2 + q[:, 1] ** 2 <= sd[i] ** 2) & (t >= -1e-9)
    return p, d, ok


def _rays(n, seed=0):
    """Rays from a 20 mm object field at z = -100 towards the entrance pupil."""
    rng = np.random.default_rng(seed)
    obj = np.concatenate([rng.uniform(-10, 10, (n, 2)), np.full((n, 1), -100.0)], axis=1)
    pupil = np.concatenate([rng.uniform(-10, 10, (n, 2)), np.full((n, 1), 58.8)], axis=1)
    return obj, pupil - obj


def _best(fn, repeat=3):
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--max-rays", type=int, default=1_000_000)
    args = parser.parse_args()
    lens = load_lens("double-gauss")
    par = paraxial(lens)
    surf = lens.surfaces()
    arrays = [
        np.asarray(a)
        for a in (surf.z, surf.curvature, surf.n_before, surf.n_after, surf.semi_diameter)
    ]

    traced = jax.jit(jax.vmap(lambda p, d: _out(trace(surf, p, d))))

    def aimed_one(p):
        d, _ = aim_ray(
            surf, p, jnp.zeros(2), par.z_entrance_pupil, par.entrance_pupil_magnification
        )
        return _out(trace(surf, p, d))

    aimed = jax.jit(jax.vmap(aimed_one))

    # One-off compile times.
    p0, d0 = (jnp.asarray(a) for a in _rays(1000))
    t = time.perf_counter()
    traced.lower(p0, d0).compile()
    compile_trace = time.perf_counter() - t
    t = time.perf_counter()
    aimed.lower(p0).compile()
    compile_aim = time.perf_counter() - t

    # NumPy per-ray loop, extrapolated per ray.
    p_np, d_np = _rays(300)
    t = time.perf_counter()
    loop_out = [_numpy_trace_one(*arrays, p_np[i], d_np[i]) for i in range(len(p_np))]
    loop_rate = len(p_np) / (time.perf_counter() - t)
    jax_out = traced(jnp.asarray(p_np), jnp.asarray(d_np))
    ok = np.asarray(jax_out[2])
    np.testing.assert_array_equal(ok, [o[2] for o in loop_out])
    np.testing.assert_allclose(
        np.asarray(jax_out[0])[ok], np.stack([o[0] for o in loop_out])[ok], atol=1e-9
    )

    print(f"device: {jax.devices()[0].device_kind}, float64, lens: double-gauss (11 surfaces)")
    print(f"compile: trace {compile_trace:.2f} s, aim + trace {compile_aim:.2f} s")
    print(f"NumPy per-ray Python loop: {loop_rate:,.0f} rays/s (300 rays, extrapolated)")
    print()
    cols = ("JAX trace", "JAX aim+trace", "NumPy vec")
    header = f"{'rays':>9} | " + " | ".join(f"{c:>14}" for c in cols) + f" | {'NumPy loop':>12}"
    print(header)
    print("-" * len(header))
    n = 1000
    while n <= args.max_rays:
        p, d = _rays(n)
        pj, dj = jnp.asarray(p), jnp.asarray(d)
        jax.block_until_ready(traced(pj, dj))
        jax_rate = n / _best(lambda: jax.block_until_ready(traced(pj, dj)))
        jax.block_until_ready(aimed(pj))
        aim_rate = n / _best(
            lambda: jax.block_until_ready(aimed(pj)), repeat=1 if n >= 10**5 else 3
        )
        vec_rate = n / _best(lambda: _numpy_trace_vec(*arrays, p, d))
        print(
            f"{n:>9,} | {jax_rate:>10,.0f} r/s | {aim_rate:>10,.0f} r/s | "
            f"{vec_rate:>10,.0f} r/s | {loop_rate:>8,.0f} r/s"
        )
        n *= 10


def _out(tr):
    return tr.point, tr.direction, tr.ok


if __name__ == "__main__":
    main()
