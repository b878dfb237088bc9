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
from ._common import CLIError

# Subcommand modules, in the order `--help` lists them.
_SUBCOMMANDS = (
    "_demo",
    "_lens",
    "_simulate",
    "_detect",
    "_extract",
    "_calibrate",
    "_reconstruct",
    "_measure",
    "_verify",
    "_report",
    "_export",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scheimflux",
        description="Laser line-structured-light 3D measurement with Scheimpflug cameras.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in _SUBCOMMANDS:
        try:
            module = importlib.import_module(f"scheimflux.cli.{name}")
        except ModuleNotFoundError as err:
            if err.name == f"scheimflux.cli.{name}":
                continue  # subcommand not built yet
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 2
    enable_compilation_cache()  # already on from `import scheimflux`; idempotent
    try:
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
