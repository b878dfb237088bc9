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
import contextlib
import importlib
import sys
import threading

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


def _deferred_here(frame, codes) -> bool:
    """`frame` runs (inside) a function whose code is in `codes`."""
    while frame is not None:
        if frame.f_code in codes:
            return True
        frame = frame.f_back
    return False


@contextlib.contextmanager
def _interrupts_honoured():
    """Ctrl-C honoured at any instant while a command runs.

    JAX runs `_xla_gc_callback` on every garbage collection (`gc.callbacks`). A SIGINT
    that arrived meanwhile raised `KeyboardInterrupt` inside that callback, where the
    collector cannot propagate it: Python printed `Exception ignored in:
    _xla_gc_callback ... KeyboardInterrupt` and carried on, so an early Ctrl-C (JAX's
    import and first compilations collect often) was lost and the command went on to
    replace its output. While a command runs:

    - the SIGINT handler raises `KeyboardInterrupt` as Python's does, except inside a
      garbage-collection callback or while a C extension module initialises (jaxlib's
      MLIR bindings call back into Python then, and an exception there aborts the
      process): there it records the interrupt and arms a 5 ms timer (`SIGALRM`),
      whose handler raises it once that has returned (re-arming while it has not);
    - a `KeyboardInterrupt` swallowed elsewhere (a `__del__`, a weakref callback, or
      a `SIGTERM` turned into one during a file write) reaches `sys.unraisablehook`,
      which does not print it and delivers it again the same way.

    Without `signal.setitimer` (Windows) Python's own handling is kept.
    """
    import gc
    import signal
    from importlib.machinery import ExtensionFileLoader

    if threading.current_thread() is not threading.main_thread() or not hasattr(
        signal, "setitimer"
    ):
        yield lambda: False
        return
    pending = False
    loading = {ExtensionFileLoader.create_module.__code__, ExtensionFileLoader.exec_module.__code__}

    def later() -> None:
        nonlocal pending
        pending = True
        signal.setitimer(signal.ITIMER_REAL, 0.005)

    def deliver(frame) -> None:
        nonlocal pending
        codes = {getattr(cb, "__code__", None) for cb in gc.callbacks}
        if _deferred_here(frame, codes | loading | {hook.__code__}):
            later()
            return
        pending = False
        raise KeyboardInterrupt

    def on_sigint(signum, frame) -> None:
        deliver(frame)

    def on_alarm(signum, frame) -> None:
        if pending:
            deliver(frame)

    def hook(unraisable) -> None:
        if unraisable.exc_type is not None and issubclass(
            unraisable.exc_type, KeyboardInterrupt
        ):
            later()
            return
        previous_hook(unraisable)

    # SIGALRM and the real-time timer are taken only when nobody uses them (a test
    # runner's timeout may); otherwise Python's own handling is kept.
    if signal.getsignal(signal.SIGALRM) not in (signal.SIG_DFL, None) or any(
        signal.getitimer(signal.ITIMER_REAL)
    ):
        yield lambda: False
        return
    previous_hook = sys.unraisablehook
    previous_int = signal.getsignal(signal.SIGINT)
    ours = previous_int is signal.default_int_handler  # not when SIGINT is ignored
    signal.signal(signal.SIGALRM, on_alarm)
    if ours:
        signal.signal(signal.SIGINT, on_sigint)
    sys.unraisablehook = hook
    try:
        yield lambda: pending
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        sys.unraisablehook = previous_hook
        signal.signal(signal.SIGALRM, signal.SIG_DFL)
        if ours:
            signal.signal(signal.SIGINT, previous_int)


def main(argv: list[str] | None = None) -> int:
    """Run the `scheimflux` command line `argv` (default: `sys.argv[1:]`); returns the
    exit code: 0, 1 for an error (one line on stderr), 130 when interrupted.

    Run as the program (`argv` None), an interrupted command ends the process at once
    (`os._exit(130)`) once its own cleanup has run: an interrupt that fell in JAX's
    start-up can leave a native thread half made, and the interpreter's shutdown then
    aborts ("pure virtual method called", exit -6) instead of exiting 130."""
    code = _main_honouring_interrupts(argv)
    if code == 130 and argv is None:
        import os

        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        os._exit(130)
    return code


def _main_honouring_interrupts(argv: list[str] | None) -> int:
    with _interrupts_honoured() as interrupted:
        try:
            code = _main(argv)
            if not interrupted():
                return code
        except KeyboardInterrupt:  # before the command ran (parsing, importing JAX)
            pass
        print("interrupted", file=sys.stderr)
        return 130


def _main(argv: list[str] | None = None) -> int:
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
    from ._common import CLIError, os_error_message, refuse_output_over_input, report_stale

    try:
        outputs = _outputs(args)
        refuse_output_over_input(args, outputs)  # every command, before it runs
        report_stale(args.command, outputs)
        return int(args.func(args) or 0)
    except (CLIError, ValueError) as err:
        print(f"scheimflux {args.command}: error: {err}", file=sys.stderr)
        return 1
    except OSError as err:  # disk full, name too long, permission, read-only, ...
        print(f"scheimflux {args.command}: error: {os_error_message(err)}", file=sys.stderr)
        return 1
    except RecursionError:
        print(
            f"scheimflux {args.command}: error: an input is nested too deeply to read "
            "(not a file this command reads)",
            file=sys.stderr,
        )
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
