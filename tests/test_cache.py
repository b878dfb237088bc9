"""Cold start: `import scheimflux` switches the compilation cache on.

Each check runs in a fresh interpreter (the test process has imported everything).
"""

import json
import os
import subprocess
import sys

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
