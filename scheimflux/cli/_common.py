"""Helpers shared by the subcommand modules: the user-error type, option checks, the
"never clobber an output without --overwrite" check, and reading a folder of images.

Errors are raised, never printed here: `_main.main` prints any `CLIError` (or
`ValueError`, `FileNotFoundError`, `FileExistsError`, ...) as one line and exits 1.
"""

from __future__ import annotations

import math
import os
import re
import sys

from .._image import read_grey as read_grey  # the one reader, for the commands


class CLIError(Exception):
    """An error the user can fix; printed without a traceback."""


def refuse_to_clobber(*paths: str, overwrite: bool) -> None:
    """Raise `CLIError` naming the first of `paths` that exists, unless `overwrite`.

    Call it before the long part of a command, so nothing is computed for nothing."""
    if overwrite:
        return
    for path in paths:
        if os.path.exists(path):
            raise CLIError(f"{path} exists; pass --overwrite to replace it")


def _path_words(value):
    """The strings in an argparse value (a string, or a list/tuple of them)."""
    if isinstance(value, (str, os.PathLike)):
        yield os.fspath(value)
    elif isinstance(value, (list, tuple)):
        for v in value:
            yield from _path_words(v)


def _same_file(a: str, b: str) -> bool:
    """`a` and `b` name the same file: equal after resolving symlinks, or one file
    under two names (a hard link, a bind mount)."""
    try:
        if os.path.realpath(a) == os.path.realpath(b):
            return True
        return os.path.exists(a) and os.path.exists(b) and os.path.samefile(a, b)
    except (OSError, ValueError):
        return False


def _inside_input_folder(out: str, folder: str) -> bool:
    """`out` is an existing image file of the input folder `folder` (a frame the command
    reads), by name, through a symlink or as a hard link."""
    from .._image import IMAGE_SUFFIXES

    if not (os.path.isdir(folder) and os.path.isfile(out)):
        return False
    try:
        st = os.stat(out)
        with os.scandir(folder) as entries:
            return any(
                e.name.lower().endswith(IMAGE_SUFFIXES)
                and os.path.samestat(e.stat(), st)
                for e in entries
            )
    except OSError:
        return False


def refuse_output_over_input(args, outputs: dict[str, list[str]]) -> None:
    """Raise `CLIError` if an output path resolves (after symlinks, or as a hard link) to
    one of the command's inputs — with or without `--overwrite`.

    **Arguments:**
    - `args`: the parsed command line; every string value of a destination not in
      `outputs` that names an existing file or folder counts as an input.
    - `outputs`: option (argparse destination) → the output files it names.

    Called once by `_main.main` for every command, before the command runs, so nothing
    is read, computed or written when an output would replace an input (a tab-completion
    slip in `calibrate OBS.json --out OBS.json --overwrite`).
    """
    skip = set(outputs) | {"command", "func"}
    inputs = [
        (dest, word)
        for dest, value in vars(args).items()
        if dest not in skip
        for word in _path_words(value)
        if word and os.path.exists(word)
    ]
    for dest, paths in outputs.items():
        for out in paths:
            if not out:
                continue
            for name, word in inputs:
                if _same_file(out, word) or _inside_input_folder(out, word):
                    flag = "--" + dest.replace("_", "-")
                    what = f" ({name.replace('_', ' ')})"
                    raise CLIError(
                        f"{flag} {out} would replace the input {word}{what}; "
                        "choose another output name (nothing written)"
                    )


# What an OS error means for the user, by errno.
_OS_HINTS = {
    "ENOSPC": "the disk is full: free some space and run again",
    "EDQUOT": "the disk quota is exceeded: free some space and run again",
    "EROFS": "the file system is read-only: write the output elsewhere",
    "EACCES": "no permission: choose a folder you may write to",
    "EPERM": "operation not permitted: choose a folder you may write to",
    "ENAMETOOLONG": "shorten the file name",
}


def os_error_message(err: OSError) -> str:
    """One line for an `OSError`: `PATH: what happened; what to do`, and that nothing
    partial was written (every output goes through `io._files.atomic_output`, which
    removes its temporary file and never replaces the old output on failure)."""
    import errno as _errno

    if err.errno is None or not err.strerror:
        return str(err)  # raised with a message of ours
    where = f"{err.filename}: " if err.filename else ""
    hint = _OS_HINTS.get(_errno.errorcode.get(err.errno, ""), "")
    text = f"{where}{err.strerror}" + (f" ({hint})" if hint else "")
    return text + "; nothing partial was written and existing outputs are unchanged"


def report_stale(command: str, outputs: dict[str, list[str]], *, age_s: float = 3600.0) -> None:
    """Deal with the hidden `.tmp-<name>-*` files that a killed earlier run (SIGKILL,
    power cut) left beside an output: remove those older than `age_s` seconds, name the
    younger ones (a run still writing the same output owns them)."""
    from ..io._files import stale_temporaries

    for paths in outputs.values():
        for path in paths:
            for tmp, age, size in stale_temporaries(path):
                if age > age_s:
                    try:
                        os.unlink(tmp)
                    except OSError:
                        continue
                    warn(command, f"removed {tmp} ({size / 1e6:.1f} MB), left by an "
                                  f"interrupted earlier write {age / 3600:.1f} h ago")  # fmt: skip
                else:
                    warn(command, f"note: {tmp} ({size / 1e6:.1f} MB) is a temporary file "
                                  "of another write of this output, running or killed; "
                                  "remove it if no other run is writing it")  # fmt: skip


def check_output(path: str, *, overwrite: bool) -> str:
    """Check, before any long computation, that the output file `path` can be written:
    it does not exist (unless `overwrite`), it is not a folder, and its folder exists and
    accepts a new file. Raises `CLIError` naming the path; returns `path`."""
    from ..io._files import check_writable

    try:
        return check_writable(path, overwrite=overwrite)
    except FileExistsError:
        raise  # "PATH exists; pass overwrite=True (--overwrite) to replace it"
    except OSError as err:
        raise CLIError(os_error_message(err)) from None


def check_output_folder(folder: str) -> str:
    """Create the output folder `folder` if missing and check a file can be written into
    it, before any long computation. Raises `CLIError` naming the folder."""
    from ..io._files import check_folder_writable

    if os.path.lexists(folder) and not os.path.isdir(folder):
        raise CLIError(f"output folder {folder} exists and is not a folder")
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as err:
        raise CLIError(f"cannot create output folder {folder} ({err.strerror or err})") from None
    try:
        return check_folder_writable(folder)
    except OSError as err:
        raise CLIError(str(err)) from None


def require_positive(args, *names: str, zero_ok: bool = False) -> None:
    """Each option `names` (argparse dests) must be a finite number > 0 (>= 0 with
    `zero_ok`); an option left at None is skipped. The message names the flag:
    `--square-mm must be positive, got -1.0`."""
    for name in names:
        value = getattr(args, name)
        if value is None:
            continue
        if not (math.isfinite(value) and (value >= 0 if zero_ok else value > 0)):
            need = ">= 0" if zero_ok else "positive"
            raise CLIError(f"--{name.replace('_', '-')} must be {need}, got {value}")


# ----------------------------------------------------------------------------- images


def natural_key(name: str) -> list:
    """Sort key that orders embedded numbers by value: `f2 < f10`."""
    return [(0, int(p), "") if p.isdigit() else (1, 0, p.lower()) for p in re.split(r"(\d+)", name)]


def list_images(folder: str, suffixes: tuple[str, ...]) -> list[str]:
    """The files in `folder` whose names end in one of `suffixes` (any case), in natural
    name order."""
    if not os.path.isdir(folder):
        raise CLIError(f"{folder} is not a folder")
    names = [
        n
        for n in os.listdir(folder)
        if n.lower().endswith(suffixes) and os.path.isfile(os.path.join(folder, n))
    ]
    return [os.path.join(folder, n) for n in sorted(names, key=natural_key)]


def progress(items, desc: str, unit: str):
    """A progress bar on stderr, shown only when stderr is a terminal."""
    from tqdm import tqdm

    return tqdm(items, desc=desc, unit=unit, file=sys.stderr, disable=None)


def warn_unmatched_laser_off(command: str, folder, suffix, pairs) -> None:
    """Warn when `--laser-off SUFFIX` paired no frame with a laser-off image (a typo in
    the suffix used to be ignored silently: every frame then went without its
    background subtracted)."""
    if suffix and pairs and all(off is None for _, off in pairs):
        warn(
            command,
            f"--laser-off {suffix!r} matches no image in {folder} (no NAME{suffix}.EXT beside "
            "a NAME.EXT): every image is taken as a frame, without a laser-off image",
        )


def warn(command: str, message: str) -> None:
    """`scheimflux COMMAND: message` on stderr, without breaking a progress bar."""
    from tqdm import tqdm

    tqdm.write(f"scheimflux {command}: {message}", file=sys.stderr)
