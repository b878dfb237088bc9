"""Cold start: `import scheimflux` switches the compilation cache on.

Each check runs in a fresh interpreter (the test process has imported everything).
"""

import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest

_PROBE = r"""
import json, os, sys, time
t0 = time.perf_counter()
import scheimflux
dt = time.perf_counter() - t0
heavy = sorted({m.split(".")[0] for m in sys.modules} & {"jax", "cv2", "scipy", "matplotlib"})
out = {"import_s": dt, "heavy": heavy, "env": os.environ.get("JAX_COMPILATION_CACHE_DIR")}
if "--use" in sys.argv:
    import jax
    import jax.numpy as jnp
    out["x64"] = bool(jax.config.jax_enable_x64)
    out["dir"] = jax.config.jax_compilation_cache_dir
    jax.jit(lambda x: x * 2 + 1)(jnp.arange(3.0)).block_until_ready()
    out["dtype"] = str(jnp.arange(3.0).dtype)
print(json.dumps(out))
"""


def _probe(tmp_path, cache, *args):
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_")}
    env["SCHEIMFLUX_CACHE_DIR"] = cache
    env.pop("SCHEIMFLUX_NO_X64", None)
    out = subprocess.run(
        [sys.executable, "-c", _PROBE, *args],
        env=env,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_cache_on_by_default_and_written(tmp_path):
    cache = tmp_path / "cache"
    info = _probe(tmp_path, str(cache), "--use")
    assert info["env"] == str(cache) and info["dir"] == str(cache)
    assert info["x64"] and info["dtype"] == "float64"
    # the tiny program above compiles in milliseconds: cached anyway (no thresholds)
    assert any(cache.iterdir()), "nothing was written to the compilation cache"


@pytest.mark.parametrize("off", ["off", "0"])
def test_cache_switched_off(tmp_path, off):
    info = _probe(tmp_path, off, "--use")
    assert info["env"] is None and info["dir"] is None
    assert not (tmp_path / off).exists()


# --------------------------------------------------------- exported solver programs

_TRACE = "/jax/core/compile/jaxpr_trace_duration"
_SOLVER = ("_lm_solve", "_normal_detect", "_normal_at")
_counts: dict | None = None


def _listen(event, duration, **kw):
    del duration
    if event == _TRACE and _counts is not None:
        name = str(kw.get("fun_name", "?"))
        _counts[name] = _counts.get(name, 0) + 1


jax.monitoring.register_event_duration_secs_listener(_listen)


def _solver_traces(counts) -> int:
    return sum(n for k, n in counts.items() if k in _SOLVER)


@pytest.fixture(scope="module")
def small_obs():
    from scheimflux.simulate import paper_rig, simulate_observations
    from scheimflux.targets import Checkerboard

    obs, _ = simulate_observations(
        paper_rig(refine=False), Checkerboard(6, 5, 0.4), n_views=4, stage_scan=False, seed=3
    )
    return obs


def _camera_solve(obs):
    """The camera solve with distortion (two LM solves, one program), as a flat vector
    of the solved camera and board poses."""
    from scheimflux.calibration import calibrate_camera

    global _counts
    _counts = {}
    try:
        cc = calibrate_camera(obs, model="thick-lens", distortion="radial-tangential")
        counts = _counts
    finally:
        _counts = None
    x = np.concatenate(
        [np.ravel(np.asarray(a)) for a in jax.tree.leaves((cc.camera, cc.poses))]
    )
    return x, cc.fit.steps, counts


@pytest.mark.slow  # compiles a camera solve (~50 CPU s); the mechanism alone: below
def test_exported_solver_equals_traced_and_survives_damage(small_obs, tmp_path, monkeypatch,
                                                           caplog):  # fmt: skip
    import logging

    from scheimflux import _export

    # a fresh export folder (JAX's compilation cache folder was set at import and stays)
    monkeypatch.setenv("SCHEIMFLUX_CACHE_DIR", str(tmp_path))
    _export.clear()
    exported, steps, first = _camera_solve(small_obs)
    files = sorted((tmp_path / "export").glob("*.sfx"))
    assert {f.name.split("-")[0] for f in files} >= {"_lm_solve", "_normal_detect"}, files
    assert _solver_traces(first) >= 2, first  # traced once each, to be exported

    # the traced path (eqx.filter_jit, no export) gives the same solution: the same
    # StableHLO program is compiled, so the same steps and numbers to rounding (1e-12
    # relative is ~4500 ulp; equal bits are expected)
    monkeypatch.setenv("SCHEIMFLUX_EXPORT", "off")
    traced, steps_t, _ = _camera_solve(small_obs)
    monkeypatch.delenv("SCHEIMFLUX_EXPORT")
    assert steps_t == steps
    np.testing.assert_allclose(exported, traced, rtol=1e-12, atol=0)

    # read back (this process's programs forgotten): nothing traced, the same numbers
    _export.clear()
    again, _, counts = _camera_solve(small_obs)
    assert _solver_traces(counts) == 0, counts
    np.testing.assert_array_equal(again, exported)

    # a damaged file is ignored (debug log), traced and written again; same numbers
    for f in files:
        blob = bytearray(f.read_bytes())
        blob[len(blob) // 2] ^= 0xFF
        f.write_bytes(bytes(blob))
    _export.clear()
    with caplog.at_level(logging.DEBUG, logger="scheimflux._export"):
        damaged, _, counts = _camera_solve(small_obs)
    assert "checksum mismatch" in caplog.text
    assert _solver_traces(counts) == _solver_traces(first), counts
    np.testing.assert_array_equal(damaged, exported)
    assert all(_export._read(f, f.stem.split("-", 1)[1]) is not None for f in files)

    # another scheimflux source or library version: another key, so a miss (traced)
    monkeypatch.setattr(_export, "_environment_key", lambda: "another version")
    _export.clear()
    other, _, counts = _camera_solve(small_obs)
    assert _solver_traces(counts) == _solver_traces(first), counts
    np.testing.assert_array_equal(other, exported)
    _export.clear()


_SECOND = r"""
import json, sys
import jax, numpy as np
traces = []
jax.monitoring.register_event_duration_secs_listener(
    lambda e, d, **kw: traces.append(str(kw.get("fun_name")))
    if e == "/jax/core/compile/jaxpr_trace_duration" else None)
from scheimflux.calibration import calibrate_camera
from scheimflux.io import read_observations
cc = calibrate_camera(read_observations(sys.argv[1]))
x = np.concatenate([np.ravel(np.asarray(a)) for a in jax.tree.leaves((cc.camera, cc.poses))])
print(json.dumps({"traces": traces, "x": x.tolist(), "steps": cc.fit.steps}))
"""


@pytest.mark.slow  # two processes, each importing JAX and compiling or reading the solve
def test_second_process_reads_the_exported_solver(small_obs, tmp_path):
    from scheimflux.io import write_observations

    path = tmp_path / "obs.json"
    write_observations(path, small_obs)
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_")}
    env["SCHEIMFLUX_CACHE_DIR"] = str(tmp_path / "cache")

    def run():
        out = subprocess.run([sys.executable, "-c", _SECOND, str(path)], env=env,
                             cwd=tmp_path, capture_output=True, text=True, timeout=900,
                             check=True)  # fmt: skip
        return json.loads(out.stdout.strip().splitlines()[-1])

    first, second = run(), run()
    assert {"_lm_solve", "_normal_detect"} <= set(first["traces"])
    assert not set(second["traces"]) & set(_SOLVER), second["traces"]
    assert second["steps"] == first["steps"]
    np.testing.assert_array_equal(second["x"], first["x"])  # the same compiled program


def test_export_mechanism(tmp_path, monkeypatch, caplog):
    # the key, the files and the fallbacks on a small program of scheimflux's (a sum of
    # squares): read back equal to the traced program's, damage and foreign keys ignored
    import logging

    from scheimflux import _export
    from scheimflux.calibration.core._lm import _sum_squares

    monkeypatch.setenv("SCHEIMFLUX_CACHE_DIR", str(tmp_path))
    program = _export.exported_jit(_sum_squares)
    tree = {"a": jax.numpy.arange(5.0), "b": np.linspace(0.0, 1.0, 7)}
    expected = float(np.sum(np.arange(5.0) ** 2) + np.sum(np.linspace(0.0, 1.0, 7) ** 2))

    global _counts
    _counts = {}
    try:
        assert float(program(tree)) == float(program.traced(tree))
        assert abs(float(program(tree)) - expected) <= 1e-15 * expected  # ~4 ulp
        (file,) = (tmp_path / "export").glob("_sum_squares-*.sfx")
        n = _counts.get("_sum_squares", 0)
        assert n >= 1
        # another shape: another key, another file
        program({"a": jax.numpy.arange(6.0), "b": tree["b"]})
        assert len(list((tmp_path / "export").glob("*.sfx"))) == 2
        # read back in a "new process" (programs forgotten): not traced
        program.clear()
        n = _counts.get("_sum_squares", 0)
        assert float(program(tree)) == float(program.traced(tree))
        assert _counts.get("_sum_squares", 0) == n
        # truncated: ignored with a debug log, traced, written again
        file.write_bytes(file.read_bytes()[:-100])
        program.clear()
        with caplog.at_level(logging.DEBUG, logger="scheimflux._export"):
            assert float(program(tree)) == float(program.traced(tree))
        assert "ignored (checksum mismatch" in caplog.text
        assert _counts.get("_sum_squares", 0) > n
        key = file.name[len("_sum_squares-") : -len(".sfx")]
        assert _export._read(file, key) is not None  # rewritten, whole
        assert _export._read(file, "0" * len(key)) is None  # a file of another key
        file.write_bytes(b"garbage")
        assert _export._read(file, key) is None
        # under a transformation (here grad): the traced program, nested
        g = jax.grad(lambda a: program({"a": a, "b": tree["b"]}))(jax.numpy.arange(5.0))
        np.testing.assert_array_equal(g, 2 * np.arange(5.0))
    finally:
        _counts = None


def test_export_falls_back_to_tracing(tmp_path, monkeypatch):
    # what has no stable identity is not exported: a lambda among the static leaves, a
    # function of another package; the result is the traced program's
    from scheimflux import _export
    from scheimflux.calibration.core._lm import _sum_squares

    monkeypatch.setenv("SCHEIMFLUX_CACHE_DIR", str(tmp_path))

    def apply(f, x):
        return f(x)

    program = _export.exported_jit(_sum_squares)
    with pytest.raises(_export._Unkeyable):
        program.key(({"f": lambda x: x, "x": np.ones(3)},))
    outside = _export.exported_jit(apply)  # a function of the tests, not of scheimflux
    assert float(outside(jax.numpy.sin, np.zeros(2))[0]) == 0.0
    assert not (tmp_path / "export").exists()
    monkeypatch.setenv("SCHEIMFLUX_EXPORT", "off")
    assert _export.export_dir() is None
    assert float(program({"x": np.ones(3)})) == 3.0
    assert not (tmp_path / "export").exists()
