"""The package's import graph: no import cycle between modules, and no import from a lower
layer to a higher one (the layer order is written in docs/architecture.md).

Every import counts, also those deferred into functions and those only for type checkers:
a deferred import still ties the lower module to the higher one."""

import ast
import pathlib

import scheimflux

ROOT = pathlib.Path(scheimflux.__file__).parent

# Lowest first; a module may import its own layer or any lower one. A name matches a module
# and everything under it; the longest match decides (`calibration.core` before
# `calibration`).
LAYERS = (
    ("_cache", "_checks", "_image", "_export"),
    ("geometry",),
    ("camera",),
    ("_presets", "targets"),
    ("stripe",),
    ("io",),
    ("reconstruct", "export"),
    ("calibration.core",),
    ("calibration.trust",),
    ("calibration",),
    ("metrology",),
    ("simulate",),
    ("capture",),
    ("scale", "report"),
    ("_demo",),
    ("cli", "__main__"),
)


def _module_name(path: pathlib.Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: pathlib.Path, modules: set[str]) -> set[str]:
    """The package's modules that `path` imports (every import statement in the file)."""
    name = _module_name(path)
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            found = [f"{target}.{a.name}" for a in node.names if f"{target}.{a.name}" in modules]
            out.update(found or ([target] if target in modules else []))
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name in modules)
    out.discard(name)
    return out


def _graph() -> dict[str, set[str]]:
    paths = {_module_name(p): p for p in ROOT.rglob("*.py")}
    return {m: _imports(p, set(paths)) for m, p in paths.items() if m != "scheimflux"}


def _layer(module: str) -> int:
    rel = module.removeprefix("scheimflux.")
    best, best_len = None, -1
    for i, names in enumerate(LAYERS):
        for n in names:
            if (rel == n or rel.startswith(n + ".")) and len(n) > best_len:
                best, best_len = i, len(n)
    assert best is not None, f"{module} is in no layer: add it to LAYERS and docs/architecture.md"
    return best


def test_every_module_is_in_a_layer():
    for m in _graph():
        _layer(m)


def test_no_import_runs_up_a_layer():
    upward = sorted(
        f"{m} -> {t}"
        for m, targets in _graph().items()
        for t in targets
        if t != "scheimflux" and _layer(t) > _layer(m)
    )
    assert not upward, "imports from a lower layer to a higher one:\n" + "\n".join(upward)


def test_no_import_cycle():
    graph = _graph()
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_the_checks_see_a_cycle_and_an_upward_import(tmp_path, monkeypatch):
    # the walker itself: a two-module package with a cycle and an upward import
    pkg = tmp_path / "scheimflux"
    (pkg / "geometry").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "geometry" / "__init__.py").write_text("from ._a import x\n")
    (pkg / "geometry" / "_a.py").write_text(
        "from . import _b\n\ndef f():\n    from ..io import y\n"
    )
    (pkg / "geometry" / "_b.py").write_text("from ._a import x\n")
    (pkg / "io.py").write_text("")
    monkeypatch.setattr(__import__(__name__), "ROOT", pkg)
    graph = _graph()
    assert graph["scheimflux.geometry._a"] == {"scheimflux.geometry._b", "scheimflux.io"}
    assert graph["scheimflux.geometry._b"] == {"scheimflux.geometry._a"}
    assert _layer("scheimflux.io") > _layer("scheimflux.geometry._a")
