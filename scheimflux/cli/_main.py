"""Dispatcher for the `scheimflux` command.

Each subcommand lives in its own module with two functions:
`register(subparsers)` adds its parser and sets `func=run`, and `run(args) -> int`.
Errors that a user can fix are raised as `CLIError` (or `ValueError`/`FileNotFoundError`
from the readers) and printed as one line, never as a traceback. Helpers the subcommands
share (`CLIError`, `refuse_to_clobber`, `require_positive`, image-folder reading) live in
`_common`.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from .._cache import enable_compilation_cache

# Subcommand → (module, the one-line help it registers), in the order `--help` lists them.
# The help lines are repeated here so that `scheimflux --help` and a mistyped command need
# no subcommand module (some import JAX, OpenCV or the stripe extractor at the top); a
# test checks that each line equals what the module registers.
_SUBCOMMANDS = {
    "demo": ("_demo", "run the measurement chain end to end on built-in simulated data"),
    "lens": (
        "_lens",
        "paraxial data (focal length, principal points, pupils) of a lens prescription",
    ),
    "simulate": (
        "_simulate",
        "simulate calibration observations by ray tracing through a real lens",
    ),
    "detect": (
        "_detect",
        "detect calibration targets and laser stripes in a folder of captures",
    ),
    "extract": ("_extract", "extract sub-pixel laser-line centres from a folder of images"),
    "calibrate": (
        "_calibrate",
        "calibrate camera, laser plane and rotary stage from observations",
    ),
    "reconstruct": ("_reconstruct", "reconstruct stripe pixels as 3-D points with a calibration"),
    "measure": (
        "_measure",
        "fit a cylinder, plane, sphere, circle, steps or a distance, with uncertainty",
    ),
    "verify": (
        "_verify",
        "measure an artefact not used in calibration: measured - nominal ± U, pass/fail",
    ),
    "report": (
        "_report",
        "an HTML report of a calibration (parameters, correlations, residual maps)",
    ),
    "export": (
        "_export",
        "export a calibration to OpenCV's camera file (camera_matrix, distortion)",
    ),
}


def build_parser(load: str | tuple[str, ...] | None = None) -> argparse.ArgumentParser:
    """The `scheimflux` argument parser.

    **Arguments:**
    - `load`: the subcommand(s) whose module is imported and whose full parser is built;
      every other subcommand gets a placeholder with its one-line help only (enough for
      `scheimflux --help` and for argparse's "invalid choice" error). None: all of them.

    **Returns:** the parser.
    """
    if load is None:
        load = tuple(_SUBCOMMANDS)
    elif isinstance(load, str):
        load = (load,)
    parser = argparse.ArgumentParser(
        prog="scheimflux",
        description="Laser line-structured-light 3D measurement with Scheimpflug cameras.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for command, (name, help_line) in _SUBCOMMANDS.items():
        if command not in load:
            sub.add_parser(command, help=help_line, add_help=False)
            continue
        try:
            module = importlib.import_module(f"scheimflux.cli.{name}")
        except ModuleNotFoundError as err:
            if err.name == f"scheimflux.cli.{name}":
                continue  # subcommand not built yet
            raise
        module.register(sub)
    return parser


def _command(argv: list[str]) -> str | None:
    """The subcommand named on the command line (the first word not starting with -)."""
    for word in argv:
        if not word.startswith("-"):
            return word if word in _SUBCOMMANDS else None
        if word in ("-h", "--help"):
            return None
    return None


def _outputs(args) -> dict[str, list[str]]:
    """Option → the output files the command named in `args` writes: the module's
    `output_paths(args)` where it has one, else `--out`."""
    module = sys.modules.get(f"scheimflux.cli.{_SUBCOMMANDS[args.command][0]}")
    paths = getattr(module, "output_paths", None)
    if paths is not None:
        return paths(args)
    out = getattr(args, "out", None)
    return {} if out is None else {"out": [out]}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    command = _command(argv)
    # Only the named subcommand's module is imported (parse first, import the heavy
    # library only where it is needed): `scheimflux --help` stays light.
    parser = build_parser(load=() if command is None else command)
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 2
    enable_compilation_cache()  # already on from `import scheimflux`; idempotent
    from ._common import CLIError, refuse_output_over_input

    try:
        refuse_output_over_input(args, _outputs(args))  # every command, before it runs
        return int(args.func(args) or 0)
    except (
        CLIError,
        ValueError,
        FileNotFoundError,
        FileExistsError,
        IsADirectoryError,
        PermissionError,
    ) as err:
        print(f"scheimflux {args.command}: error: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
