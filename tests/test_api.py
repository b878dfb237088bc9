"""The public spelling: `sf.calibrate(obs)` is the function, `scheimflux.calibrate` stays the
subpackage for `from scheimflux.calibrate import X`, and the main entry points document
every argument."""

import ast
import inspect
import pathlib
import re
import subprocess
import sys
import types

import scheimflux as sf
from scheimflux.calibrate._calibrate import calibrate as _calibrate_impl

ROOT = pathlib.Path(sf.__file__).parent


def test_sf_calibrate_is_the_function_and_the_subpackage_stays_importable():
    calibrate_pkg = sys.modules["scheimflux.calibrate"]
    assert isinstance(calibrate_pkg, types.ModuleType)
    assert sf.calibrate is _calibrate_impl is calibrate_pkg.calibrate
    assert sf.diagnostics is calibrate_pkg.diagnostics  # both entry points are functions
    for name in ("calibrate_camera", "fit_laser_plane", "calibrate_stage", "cross_validate"):
        assert getattr(sf, name) is getattr(calibrate_pkg, name)


def test_import_statement_spelling():
    # `import scheimflux.calibrate as m` binds the function (Python takes the parent's
    # attribute): the subpackage is reached by `from scheimflux.calibrate import X`,
    # `importlib.import_module` or `sys.modules` (docs/api.md).
    import importlib

    import scheimflux.calibrate as m

    assert m is sf.calibrate
    assert importlib.import_module("scheimflux.calibrate") is sys.modules["scheimflux.calibrate"]


def test_sf_calibrate_does_not_depend_on_import_order():
    # A subpackage imported first must not leave `sf.calibrate` the module (the trap of a
    # lazily bound function: the import system sets the parent's attribute to the module).
    code = (
        "from scheimflux.calibrate import calibrate_camera, Calibration\n"
        "import scheimflux.calibrate._stage\n"
        "import scheimflux as sf, types\n"
        "assert isinstance(sf.calibrate, types.FunctionType), type(sf.calibrate)\n"
        "assert sf.calibrate.__module__ == 'scheimflux.calibrate._calibrate'\n"
        "assert calibrate_camera is sf.calibrate_camera\n"
        "print('ok')\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]


def test_calibrate_init_only_re_exports():
    tree = ast.parse((ROOT / "calibrate" / "__init__.py").read_text())
    body = tree.body[1:] if isinstance(tree.body[0], ast.Expr) else tree.body
    for node in body:
        assert isinstance(node, ast.ImportFrom) and node.level == 1, ast.dump(node)[:80]
        for alias in node.names:
            assert alias.asname == alias.name, alias.name  # `from ._x import y as y`


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
