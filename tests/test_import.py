"""`import scheimflux` is light (no JAX), yet every public name resolves on first use to the
same object as its home module's, and the JAX settings (float64) still come first.

The lightness is checked as a property (which modules a fresh interpreter has loaded), not
as a time: the time is in benchmarks/run.py.
"""

import importlib
import os
import subprocess
import sys

import pytest

import scheimflux as sf

# The public top level as it was when everything was imported eagerly (main before issue
# 14): name → the subpackage it comes from (the calibration's file functions moved from
# `io` to `calibration`, which reads a file into a `Calibration`). Written out here, not
# read from the package.
_PUBLIC = {
    "paper_laser_plane": "scheimflux._presets",
    "paper_pinhole": "scheimflux._presets",
    "paper_stage": "scheimflux._presets",
    "paper_thick_lens": "scheimflux._presets",
    "Calibration": "scheimflux.calibration",
    "calibrate": "scheimflux.calibration",
    "calibrate_camera": "scheimflux.calibration",
    "calibrate_stage": "scheimflux.calibration",
    "cross_validate": "scheimflux.calibration",
    "diagnostics": "scheimflux.calibration",
    "fit_laser_plane": "scheimflux.calibration",
    "AbstractCamera": "scheimflux.camera",
    "Pinhole": "scheimflux.camera",
    "Ray": "scheimflux.camera",
    "ThickLensScheimpflug": "scheimflux.camera",
    "LaserPlane": "scheimflux.geometry",
    "Pose": "scheimflux.geometry",
    "RotaryStage": "scheimflux.geometry",
    "Observations": "scheimflux.io",
    "read_calibration": "scheimflux.calibration",
    "read_observations": "scheimflux.io",
    "write_calibration": "scheimflux.calibration",
    "write_observations": "scheimflux.io",
    "write_points": "scheimflux.io",
    "Reconstruction": "scheimflux.reconstruct",
    "Status": "scheimflux.reconstruct",
    "stripe_to_camera": "scheimflux.reconstruct",
    "stripe_to_measurement": "scheimflux.reconstruct",
    "StripeResult": "scheimflux.stripe",
    "extract_stripe": "scheimflux.stripe",
    "extract_stripes": "scheimflux.stripe",
    "Checkerboard": "scheimflux.targets",
    "detect_checkerboard": "scheimflux.targets",
    "fit_cylinder": "scheimflux.metrology",
    "fit_plane": "scheimflux.metrology",
    "step_height": "scheimflux.metrology",
}
_SUBPACKAGES = (
    "calibration",
    "camera",
    "capture",
    "export",
    "geometry",
    "io",
    "metrology",
    "reconstruct",
    "simulate",
    "stripe",
    "targets",
)
_HEAVY = ("jax", "jaxlib", "equinox", "optimistix", "numpy", "cv2", "scipy")


def _run(code: str, **env) -> subprocess.CompletedProcess:
    environ = {k: v for k, v in os.environ.items() if not k.startswith("JAX_")}
    environ.pop("SCHEIMFLUX_NO_X64", None)
    environ.update(env)
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=600, env=environ
    )


def test_import_scheimflux_and_the_cli_parser_import_no_jax():
    # `import scheimflux`, the CLI's --help and a mistyped command load none of the heavy
    # libraries (not even NumPy); a subcommand's --help or argument error loads no JAX.
    code = (
        "import sys\n"
        f"heavy = {_HEAVY!r}\n"
        "import scheimflux\n"
        "loaded = sorted(m for m in heavy if m in sys.modules)\n"
        "assert not loaded, loaded\n"
        "from scheimflux.cli import main\n"
        "for argv in (['--help'], ['frobnicate'], [], ['reconstruct'], ['calibrate', '-h'],\n"
        "             ['measure', '--bogus'], ['export']):\n"
        "    try:\n"
        "        main(argv)\n"
        "    except SystemExit:\n"
        "        pass\n"
        "    assert 'jax' not in sys.modules, argv\n"
        "    if argv in (['--help'], ['frobnicate'], []):\n"
        "        assert not [m for m in heavy if m in sys.modules], argv\n"
        "print('ok')\n"
    )
    out = _run(code)
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr[-2000:]


def test_every_public_name_resolves_to_its_home_object():
    assert set(_PUBLIC) | set(_SUBPACKAGES) | {"__version__"} <= set(sf.__all__)
    for name in sf.__all__:
        assert getattr(sf, name) is not None, name
    for name, home in _PUBLIC.items():
        assert getattr(sf, name) is getattr(importlib.import_module(home), name), name
        exec(f"from scheimflux import {name} as _x", globals())
        assert globals()["_x"] is getattr(sf, name), name
    for name in _SUBPACKAGES:
        assert getattr(sf, name) is sys.modules[f"scheimflux.{name}"]
    assert sf.calibrate is sys.modules["scheimflux.calibration"].calibrate  # the function
    assert set(sf.__all__) <= set(dir(sf))
    assert isinstance(sf.__version__, str) and sf.__version__


def test_a_typo_is_an_attribute_error_with_a_suggestion():
    with pytest.raises(AttributeError, match="has no attribute 'stripe_to_camerra'"):
        sf.stripe_to_camerra  # noqa: B018
    with pytest.raises(ImportError):
        exec("from scheimflux import ThickLensScheimpflugg", {})
    out = _run("import scheimflux as sf\nsf.stripe_to_camerra")
    assert out.returncode == 1
    assert "Did you mean: 'stripe_to_camera'?" in out.stderr, out.stderr[-2000:]
    assert "jax" not in out.stderr  # refused before anything heavy was imported


@pytest.mark.parametrize("jax_first", [False, True])
def test_float64_after_a_lazy_import(jax_first):
    # float64 must be on before the first scheimflux computation, whether JAX is imported
    # by scheimflux on first use (environment variable) or by the user before (jax.config).
    code = (
        ("import jax\n" if jax_first else "")
        + "import sys, numpy as np\n"
        "import scheimflux as sf\n"
        "cam, plane = sf.paper_thick_lens(), sf.paper_laser_plane()\n"
        "rec = sf.stripe_to_camera(cam, plane, np.array([[800.0, 600.0], [900.0, 650.0]]))\n"
        "print(rec.points.dtype, bool(rec.valid.all()))\n"
    )
    out = _run(code)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["float64", "True"]


def test_cli_help_lines_match_the_subcommand_modules():
    # The dispatcher repeats each subcommand's one-line help (so --help imports no
    # subcommand module): each must equal what the module itself registers.
    import argparse

    from scheimflux.cli import _main

    for command, (module, help_line) in _main._SUBCOMMANDS.items():
        parser = argparse.ArgumentParser()
        sub = parser.add_subparsers()
        importlib.import_module(f"scheimflux.cli.{module}").register(sub)
        registered = {a.dest: a.help for a in sub._choices_actions}
        assert registered == {command: help_line}, command
    full = _main.build_parser().format_help()
    light = _main.build_parser(load=()).format_help()
    assert full == light
