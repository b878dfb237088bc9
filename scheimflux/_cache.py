"""JAX's persistent compilation cache, on by default for the library and the CLI.

A calibration compiles a few large XLA programs (the Levenberg–Marquardt solve above
all). Compiled once, they are written to a cache folder and read back by every later
process with the same program, JAX version and machine, so only the first run on a
machine pays the XLA compile time.

- Folder: `$SCHEIMFLUX_CACHE_DIR`, else `$XDG_CACHE_HOME/scheimflux/jax`, else
  `~/.cache/scheimflux/jax`.
- `SCHEIMFLUX_CACHE_DIR=off` (or `0`, `no`, `false`, or empty) switches it off.
- Every program is cached, however small or quick to compile (a warm process otherwise
  recompiles the hundreds of small programs of the eager parts).

The settings are applied with `jax.config.update` when JAX is already imported, and
otherwise through JAX's environment variables (read when JAX is first imported), so
`import scheimflux` itself does not import JAX. A setting the user made already (a
`JAX_COMPILATION_CACHE_DIR` in the environment, or `jax.config` changed before
`import scheimflux`) is left as it is.
"""

from __future__ import annotations

import os
import sys

_OFF = ("off", "0", "no", "false", "")

# JAX option → value, for every program: no minimum compile time, no minimum size
# (-1: JAX applies no size restriction of its own either).
_THRESHOLDS = {
    "jax_persistent_cache_min_compile_time_secs": 0.0,
    "jax_persistent_cache_min_entry_size_bytes": -1,
}


def cache_dir() -> str | None:
    """The compilation cache folder scheimflux uses, or None when switched off.

    **Returns:** an absolute path (not created here), or None for
    `SCHEIMFLUX_CACHE_DIR=off` / `0`.
    """
    value = os.environ.get("SCHEIMFLUX_CACHE_DIR")
    if value is not None:
        if value.strip().lower() in _OFF:
            return None
        return os.path.abspath(os.path.expanduser(value))
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "scheimflux", "jax")


def enable_compilation_cache(path: str | None = None) -> str | None:
    """Switch JAX's persistent compilation cache on (folder from [`cache_dir`][]).

    **Arguments:**
    - `path`: the folder; default [`cache_dir`][]. Ignored (None returned) when the
      cache is switched off by `SCHEIMFLUX_CACHE_DIR`.

    **Returns:** the folder in use, or None when the cache is off, when the folder cannot
    be created (read-only home: JAX then compiles as usual), or when the user chose a
    JAX cache folder of their own (which is kept).
    """
    if cache_dir() is None:
        return None
    path = path or cache_dir()
    try:
        os.makedirs(path, exist_ok=True)
    except OSError:
        return None
    if "jax" in sys.modules:
        import jax

        if jax.config.jax_compilation_cache_dir not in (None, path):
            return None  # the user's own cache folder
        jax.config.update("jax_compilation_cache_dir", path)
        for name, value in _THRESHOLDS.items():
            jax.config.update(name, value)
        return path
    if os.environ.get("JAX_COMPILATION_CACHE_DIR", path) != path:
        return None
    os.environ["JAX_COMPILATION_CACHE_DIR"] = path
    for name, value in _THRESHOLDS.items():
        os.environ.setdefault(name.upper(), str(value))
    return path


def enable_x64() -> None:
    """64-bit floats in JAX (metrology needs them) unless `SCHEIMFLUX_NO_X64=1`."""
    if os.environ.get("SCHEIMFLUX_NO_X64", "") not in ("", "0"):
        return
    if "jax" in sys.modules:
        import jax

        jax.config.update("jax_enable_x64", True)
    else:
        os.environ["JAX_ENABLE_X64"] = "1"
