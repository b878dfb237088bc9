"""Exported solver programs: serialized StableHLO kept on disk, so a new process skips
tracing and lowering.

JAX's persistent compilation cache (`_cache.py`) skips XLA's compiler only: every new
process still traces each program in Python and lowers it to MLIR before it can look the
executable up (seconds for the Levenberg–Marquardt loops). [`exported_jit`][] wraps a
module-level function like `eqx.filter_jit`; the first call for a given key traces it
once with `jax.export`, writes the serialized program to the export folder, and compiles
it; a later process with the same key reads the program back, and its compilation is
read from the compilation cache.

**The key** (SHA-256) is made of everything the program depends on:
- the function (module and qualified name) and the compiler options;
- the source of every scheimflux module (a changed line anywhere is a new key) and the
  versions of JAX, jaxlib, equinox, optimistix, lineax, jaxtyping, jaxlie and NumPy;
- JAX's x64 and dtype-promotion settings and the backend;
- the arguments' pytree structure (with each node's type and static fields), the shape,
  dtype and weak type of every array, and the value of every non-array leaf.

A non-array leaf must have a stable, complete identity for the program to be exported: a
number, a string, None, a function of scheimflux or one of the libraries above (by
name), or an object with an `export_key()` method. Anything else (a lambda, a user's
function, an object whose repr shows its address), and a pytree node defined elsewhere,
make that call use the traced path (`eqx.filter_jit`), as does a failure to export or
serialize (logged at debug level), and a call inside a JAX transformation (`jit`, `grad`,
`vmap`: its arguments are tracers; the traced program is nested in the outer one).

**On disk**: one file per key, `<name>-<key>.sfx`, in `<cache folder>/export`: a format
line, a JSON header (key, function, JAX version, SHA-256 of the payload) and the payload
(`Exported.serialize()`). A file whose header, key or checksum does not match, or that
does not deserialize, is ignored (debug log) and written again. Writes are atomic (a
temporary file renamed), so concurrent processes cannot leave half a file.

`SCHEIMFLUX_EXPORT=off` (or `0`) switches exports off (the traced path for every call);
`SCHEIMFLUX_CACHE_DIR=off` switches them off with the compilation cache.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import json
import logging
import os
import tempfile
import types
from collections.abc import Callable
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

from ._cache import _OFF, cache_dir

log = logging.getLogger(__name__)

_MAGIC = b"scheimflux.export/1\n"
_SUFFIX = ".sfx"
# packages whose code (by version) may be inside a program, besides scheimflux's source
_DEPENDENCIES = ("jax", "jaxlib", "equinox", "optimistix", "lineax", "jaxtyping", "jaxlie",
                 "numpy")  # fmt: skip
# top-level modules whose functions and pytree node types may appear in a key
_KNOWN = ("scheimflux", "jax", "jaxlib", "equinox", "optimistix", "lineax", "jaxlie",
          "builtins", "collections", "numpy")  # fmt: skip


_ALL: list[ExportedJit] = []  # every wrapper, for `clear`


class _Unkeyable(Exception):
    """A call's static content has no stable identity: use the traced path."""


def export_dir() -> Path | None:
    """The folder of exported programs, or None when exports are off.

    `<compilation cache folder>/export` ([`cache_dir`][]); None for
    `SCHEIMFLUX_EXPORT=off` / `0` or `SCHEIMFLUX_CACHE_DIR=off`.
    """
    if os.environ.get("SCHEIMFLUX_EXPORT", "on").strip().lower() in _OFF:
        return None
    base = cache_dir()
    return None if base is None else Path(base) / "export"


@functools.cache
def _environment_key() -> str:
    """Source hash of the scheimflux package and the dependencies' versions."""
    h = hashlib.sha256()
    root = Path(__file__).resolve().parent
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(b"\0")
        h.update(path.read_bytes())
        h.update(b"\0")
    for name in _DEPENDENCIES:
        try:
            version = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            version = "-"
        h.update(f"{name}={version};".encode())
    return h.hexdigest()


def _known_module(module: str | None) -> bool:
    return bool(module) and module.split(".")[0] in _KNOWN


def _static_id(x) -> str:
    """A stable, complete identity of a non-array leaf, or `_Unkeyable`."""
    if x is None or isinstance(x, (bool, int, float, complex, str, bytes)):
        return f"{type(x).__name__}:{x!r}"
    if isinstance(x, np.dtype):
        return f"dtype:{x.str}"
    key = getattr(x, "export_key", None)
    if callable(key) and not isinstance(x, type):
        return f"{type(x).__module__}.{type(x).__qualname__}:{key()}"
    if isinstance(x, (types.FunctionType, types.BuiltinFunctionType, type)):
        module, name = getattr(x, "__module__", None), getattr(x, "__qualname__", "")
        if _known_module(module) and "<" not in name:
            return f"fn:{module}.{name}"
    raise _Unkeyable(f"{type(x).__module__}.{type(x).__qualname__}")


def _structure_id(treedef) -> list[str]:
    """Every node of `treedef` with its type's full name and its static data."""
    out = []

    def walk(td):
        data = td.node_data()
        if data is None:
            out.append("*")
            return
        kind, aux = data
        module = getattr(kind, "__module__", None)
        if not _known_module(module):
            raise _Unkeyable(f"pytree node {module}.{kind.__qualname__}")
        text = repr(aux)
        if " at 0x" in text:
            raise _Unkeyable(f"static data of {kind.__qualname__}: {text[:80]}")
        out.append(f"{module}.{kind.__qualname__}{text}(")
        for child in td.children():
            walk(child)
        out.append(")")

    walk(treedef)
    return out


def _aval(x) -> jax.ShapeDtypeStruct:
    weak = bool(getattr(x, "weak_type", False))
    return jax.ShapeDtypeStruct(np.shape(x), jax.dtypes.canonicalize_dtype(x.dtype),
                                weak_type=weak)  # fmt: skip


class _Program:
    """One exported and compiled program: call with the arrays of the arguments."""

    def __init__(self, compiled, exported: bool):
        self.compiled = compiled
        self.exported = exported  # read back from a file (True) or traced now (False)


class ExportedJit:
    """[`exported_jit`][]'s wrapper: see the module docstring."""

    def __init__(self, fun: Callable, compiler_options: dict | None = None):
        self.fun = fun
        self.compiler_options = dict(compiler_options or {})
        self.traced = eqx.filter_jit(fun, compiler_options=compiler_options)
        self.__name__ = getattr(fun, "__name__", "program")
        self.__doc__ = getattr(fun, "__doc__", None)
        self.__wrapped__ = fun
        self._programs: dict[str, _Program | None] = {}  # key → program (None: traced)
        _ALL.append(self)

    def __repr__(self) -> str:
        return f"exported_jit({self.fun.__module__}.{self.fun.__qualname__})"

    def export_key(self) -> str:  # so that another program may hold this one as static
        return f"{self.fun.__module__}.{self.fun.__qualname__}:{self.compiler_options}"

    # ----------------------------------------------------------------------- key
    def key(self, args) -> tuple[str, list, object, list]:
        """`(key, dynamic leaves, treedef, leaves)` of a call; `_Unkeyable` if none."""
        if not _known_module(self.fun.__module__) or "<" in self.fun.__qualname__:
            raise _Unkeyable(f"function {self.fun.__module__}.{self.fun.__qualname__}")
        leaves, treedef = jax.tree.flatten(args)
        dynamic = [x for x in leaves if eqx.is_array(x)]
        parts = [
            "scheimflux.export/1",
            _environment_key(),
            f"{self.fun.__module__}.{self.fun.__qualname__}",
            json.dumps(self.compiler_options, sort_keys=True),
            f"x64={jax.config.jax_enable_x64};promotion={jax.config.jax_numpy_dtype_promotion}",
            f"backend={jax.default_backend()}",
            *_structure_id(treedef),
        ]
        for x in leaves:
            if eqx.is_array(x):
                a = _aval(x)
                parts.append(f"array{a.shape}{a.dtype}{'w' if a.weak_type else ''}")
            else:
                parts.append(_static_id(x))
        key = hashlib.sha256("\n".join(parts).encode()).hexdigest()[:40]
        return key, dynamic, treedef, leaves

    # ---------------------------------------------------------------------- call
    def __call__(self, *args):
        folder = export_dir()
        if folder is None:
            return self.traced(*args)
        try:
            key, dynamic, treedef, leaves = self.key(args)
        except _Unkeyable as e:
            log.debug("%s: traced, not exported (%s has no stable identity)", self, e)
            return self.traced(*args)
        if any(isinstance(x, jax.core.Tracer) for x in dynamic):
            return self.traced(*args)  # inside jit, grad, vmap...: a nested jit
        if key not in self._programs:
            self._programs[key] = self._load_or_export(folder, key, dynamic, treedef, leaves)
        program = self._programs[key]
        if program is None:
            return self.traced(*args)
        return program.compiled(*dynamic)

    def _path(self, folder: Path, key: str) -> Path:
        return folder / f"{self.__name__}-{key}{_SUFFIX}"

    def _compile(self, exp):
        avals = [jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=a.weak_type)
                 for a in exp.in_avals]  # fmt: skip
        def run(*arrays):
            return exp.call(*arrays)

        # named for the compilation cache's files and JAX's events (not the function's
        # own name: that is traced only when the program is exported)
        run.__name__ = run.__qualname__ = f"{self.__name__}_exported"
        lowered = jax.jit(run).lower(*avals)
        return lowered.compile(compiler_options=self.compiler_options or None)

    def _load_or_export(self, folder, key, dynamic, treedef, leaves) -> _Program | None:
        path = self._path(folder, key)
        exp = _read(path, key)
        if exp is not None:
            try:
                return _Program(self._compile(exp), exported=True)
            except Exception as e:  # noqa: BLE001 - a stale file must not stop a solve
                log.debug("%s: exported program %s not usable (%.200s); tracing", self, path, e)
        try:
            exp = self._export(dynamic, treedef, leaves)
        except Exception as e:  # noqa: BLE001 - not exportable: the traced path
            log.debug("%s: not exportable (%s: %.200s); traced", self, type(e).__name__, e)
            return None
        try:
            _write(path, key, self, exp.serialize())
        except Exception as e:  # noqa: BLE001 - a read-only folder: compile as usual
            log.debug("%s: exported program not written to %s (%.200s)", self, path, e)
        return _Program(self._compile(exp), exported=False)

    def _export(self, dynamic, treedef, leaves):
        positions = [i for i, x in enumerate(leaves) if eqx.is_array(x)]
        fun = self.fun

        def flat(*arrays):
            full = list(leaves)
            for i, a in zip(positions, arrays, strict=True):
                full[i] = a
            return fun(*jax.tree.unflatten(treedef, full))

        flat.__name__ = self.__name__
        flat.__qualname__ = self.__name__
        return jax.export.export(jax.jit(flat))(*(_aval(x) for x in dynamic))

    def clear(self) -> None:
        """Forget this process's compiled programs (the files stay)."""
        self._programs.clear()


def exported_jit(fun: Callable | None = None, *, compiler_options: dict | None = None):
    """`eqx.filter_jit` whose programs are exported to (and read back from) the export
    folder, so later processes skip tracing and lowering.

    Use on module-level functions of scheimflux whose arguments are pytrees of arrays
    and stable static values (see the module docstring); the outputs must be a tuple,
    list or dict of arrays (or one array). Results equal those of `eqx.filter_jit`
    (the same StableHLO program is compiled).
    """
    if fun is None:
        return functools.partial(exported_jit, compiler_options=compiler_options)
    return ExportedJit(fun, compiler_options)


def clear() -> None:
    """Forget every compiled program of this process (the files stay): the next call of
    each wrapper reads its file again, or traces."""
    for program in _ALL:
        program.clear()


def _read(path: Path, key: str):
    """The `Exported` in `path`, or None (missing, foreign, corrupt: debug log)."""
    try:
        blob = path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError as e:
        log.debug("exported program %s not readable (%s)", path, e)
        return None
    try:
        if not blob.startswith(_MAGIC):
            raise ValueError("not a scheimflux export file")
        end = blob.index(b"\n", len(_MAGIC))
        header = json.loads(blob[len(_MAGIC) : end])
        payload = blob[end + 1 :]
        if header.get("key") != key:
            raise ValueError("a different key")
        if header.get("sha256") != hashlib.sha256(payload).hexdigest():
            raise ValueError("checksum mismatch (truncated or corrupted)")
        return jax.export.deserialize(bytearray(payload))
    except Exception as e:  # noqa: BLE001 - any damage: ignore the file
        log.debug("exported program %s ignored (%s)", path, e)
        return None


def _write(path: Path, key: str, program: ExportedJit, payload: bytes | bytearray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    header = {
        "key": key,
        "function": f"{program.fun.__module__}.{program.fun.__qualname__}",
        "jax": jax.__version__,
        "sha256": hashlib.sha256(payload).hexdigest(),
    }
    fd, tmp = tempfile.mkstemp(prefix=path.name, suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(_MAGIC + json.dumps(header).encode() + b"\n" + bytes(payload))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
