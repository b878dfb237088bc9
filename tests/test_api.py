"""The public spelling: `sf.calibrate(obs)` is the function and `scheimflux.calibration` the
subpackage (no name is both), every subpackage declares `__all__` and only re-exports, and
the main entry points document every argument."""

import ast
import importlib
import inspect
import pathlib
import re
import subprocess
import sys
import types

import scheimflux as sf
from scheimflux.calibration._calibrate import calibrate as _calibrate_impl

ROOT = pathlib.Path(sf.__file__).parent


def test_sf_calibrate_is_the_function_and_calibration_the_subpackage():
    calibration = importlib.import_module("scheimflux.calibration")
    assert isinstance(sf.calibration, types.ModuleType) and sf.calibration is calibration
    assert isinstance(sf.calibrate, types.FunctionType)
    assert sf.calibrate is _calibrate_impl is calibration.calibrate
    assert sf.diagnostics is calibration.diagnostics  # both entry points are functions
    for name in ("calibrate_camera", "fit_laser_plane", "calibrate_stage", "cross_validate"):
        assert getattr(sf, name) is getattr(calibration, name)
    # the package's module is a plain module: no class swapped in to keep a name apart
    assert type(sf) is types.ModuleType


def test_sf_calibrate_does_not_depend_on_import_order():
    # importing the subpackages first leaves `sf.calibrate` the function
    code = (
        "from scheimflux.calibration import calibrate_camera, Calibration\n"
        "import scheimflux.calibration.core._stage\n"
        "import scheimflux as sf, types\n"
        "assert isinstance(sf.calibrate, types.FunctionType), type(sf.calibrate)\n"
        "assert sf.calibrate.__module__ == 'scheimflux.calibration._calibrate'\n"
        "assert calibrate_camera is sf.calibrate_camera\n"
        "print('ok')\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]


def _subpackages() -> list[pathlib.Path]:
    return sorted(p for p in ROOT.rglob("__init__.py") if p.parent != ROOT)


def test_subpackage_inits_only_re_export():
    for path in _subpackages():
        tree = ast.parse(path.read_text())
        body = tree.body[1:] if isinstance(tree.body[0], ast.Expr) else tree.body
        for node in body:
            if isinstance(node, ast.Assign) and [t.id for t in node.targets] == ["__all__"]:
                continue
            assert isinstance(node, ast.ImportFrom) and node.level >= 1, (
                f"{path}: {ast.dump(node)[:80]}"
            )
            for alias in node.names:
                assert alias.asname == alias.name, f"{path}: {alias.name}"  # `y as y`


def test_every_subpackage_declares_all_of_its_public_names():
    for path in _subpackages():
        name = ".".join(path.parent.relative_to(ROOT.parent).parts)
        module = importlib.import_module(name)
        assert hasattr(module, "__all__"), f"{name} has no __all__"
        public = {n for n in vars(module) if not n.startswith("_")}
        public -= {m for m in public if isinstance(getattr(module, m), types.ModuleType)}
        assert sorted(module.__all__) == sorted(public), name
        for n in module.__all__:
            assert hasattr(module, n), f"{name}.__all__ names {n}, which it does not have"


ENTRY_POINTS = (
    "calibrate",
    "calibrate_camera",
    "fit_laser_plane",
    "calibrate_stage",
    "diagnostics",
    "cross_validate",
)


def _documented_arguments(doc: str) -> list[str]:
    section = doc.split("**Arguments:**", 1)[1].split("**Returns:**", 1)[0]
    return re.findall(r"^\s*- `(\**\w+)`", section, flags=re.M)


def test_main_entry_points_document_every_argument():
    for name in ENTRY_POINTS:
        fn = getattr(sf, name)
        doc = inspect.getdoc(fn)
        assert "**Arguments:**" in doc and "**Returns:**" in doc, name
        params = []
        for p in inspect.signature(fn).parameters.values():
            params.append(("**" if p.kind is p.VAR_KEYWORD else "") + p.name)
        assert _documented_arguments(doc) == params, name
