"""Small helpers for the files users exchange: JSON loading with clear errors, and one
atomic writer that never clobbers an existing file by accident.

Every file the package writes goes through `atomic_output` (or `write_atomic`, built
on it): the content is written to a hidden temporary file beside the target
(`.tmp-<name>-XXXX`) and then moved into place in one step:

- without `overwrite`, by `os.link(tmp, path)`, which fails if `path` exists — also if it
  appeared after the first check (no check-then-replace race). On a file system without
  hard links the target is reserved with `O_CREAT | O_EXCL` and then replaced;
- with `overwrite`, by `os.replace`, so readers see the old file or the new one, never a
  partial one.

The temporary file is removed on any failure, including `KeyboardInterrupt` and
`SIGTERM` (converted to an exception while a write is in progress); only a `SIGKILL`
or a power cut between the write and the move can leave a `.tmp-*` file behind.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import signal
import tempfile
import threading
import time
from collections.abc import Iterator
from typing import Any

TMP_PREFIX = ".tmp-"


def folder_message(path: str, what: str) -> str:
    """The error for a folder given where a `what` file was expected; for a stripes file
    and a folder of images, also how to make one from them."""
    msg = f"{path}: is a folder, not a {what} file"
    if what == "stripes":
        from .._image import IMAGE_SUFFIXES

        if any(n.lower().endswith(IMAGE_SUFFIXES) for n in os.listdir(path)):
            msg += (
                f" (for its frame images, `scheimflux extract {path} --out STRIPES.json` "
                "writes their stripe centres; `scheimflux reconstruct` also reads the folder)"
            )
    return msg


def load_json(path: str | os.PathLike, what: str) -> Any:
    """Read a JSON file; errors name the file and what it should have been."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"{what} file not found: {path}")
    if os.path.isdir(path):
        raise ValueError(folder_message(path, what))
    try:
        with open(path, encoding="utf-8") as fh:
            return json.load(fh)
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not valid JSON ({err.msg} at line {err.lineno})") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text (UTF-8 JSON) file") from None
    except RecursionError:  # e.g. 100 000 nested `[`: no file of ours nests that deep
        raise ValueError(f"{path}: not a {what} file (JSON nested too deeply to read)") from None
    except PermissionError:
        raise PermissionError(f"{path}: no permission to read it") from None


def check_writable(path: str | os.PathLike, *, overwrite: bool) -> str:
    """Refuse to replace an existing file unless asked; check the folder exists and can be
    written to (so a long computation does not end in a failed write).

    **Returns:** `path` as a string. **Raises:** `FileExistsError`, `FileNotFoundError`
    (missing folder), `PermissionError` (folder not writable), `IsADirectoryError`.
    """
    path = os.fspath(path)
    if os.path.isdir(path):
        raise IsADirectoryError(f"{path} is a folder; give a file name")
    if os.path.lexists(path) and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True (--overwrite) to replace it")
    folder = os.path.dirname(os.path.abspath(path))
    check_folder_writable(folder)
    _check_name_length(path, folder)
    return path


# What `atomic_output` adds to the output's name for its temporary file: the prefix, a
# dash, mkstemp's 8 random characters and a suffix of up to 8 (".parquet").
_TMP_EXTRA = len(TMP_PREFIX) + 1 + 8 + 8


def _check_name_length(path: str, folder: str) -> None:
    """Refuse a file name too long for the folder's file system, counting the temporary
    name `atomic_output` writes first, before any work (`OSError` ENAMETOOLONG)."""
    name = os.path.basename(path)
    try:
        limit = os.pathconf(folder, "PC_NAME_MAX")
    except (OSError, ValueError, AttributeError):
        limit = 255
    size = len(os.fsencode(name))
    if size + _TMP_EXTRA > limit:
        raise OSError(
            errno.ENAMETOOLONG,
            f"file name too long ({size} bytes; this file system allows {limit}, of which "
            f"{_TMP_EXTRA} go to the temporary name written first)",
            path,
        )


def stale_temporaries(path: str | os.PathLike) -> list[tuple[str, float, int]]:
    """The temporary files that an earlier write of `path` left beside it (a run killed
    by SIGKILL or a power cut between the write and the move): `(file, age in seconds,
    size in bytes)` for each `.tmp-<name>-*` file in its folder."""
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    start = f"{TMP_PREFIX}{os.path.basename(path)}-"
    out = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return out
    now = time.time()
    for entry in entries:
        if not entry.name.startswith(start):
            continue
        try:
            st = entry.stat(follow_symlinks=False)
        except OSError:
            continue
        if not entry.is_file(follow_symlinks=False):
            continue
        out.append((entry.path, now - st.st_mtime, st.st_size))
    return sorted(out)


def check_folder_writable(folder: str | os.PathLike) -> str:
    """Check that `folder` exists and a file can be created in it (by creating and
    removing a temporary file: permission bits alone miss read-only mounts).

    **Raises:** `FileNotFoundError`, `NotADirectoryError` or `PermissionError`, naming
    the folder.
    """
    folder = os.fspath(folder)
    if not os.path.exists(folder):
        raise FileNotFoundError(f"output folder does not exist: {folder}")
    if not os.path.isdir(folder):
        raise NotADirectoryError(f"output folder is not a folder: {folder}")
    try:
        fd, probe = tempfile.mkstemp(prefix=TMP_PREFIX + "probe-", dir=folder)
    except OSError as err:
        raise PermissionError(
            f"cannot write into output folder {folder} ({err.strerror or err})"
        ) from None
    os.close(fd)
    os.unlink(probe)
    return folder


@contextlib.contextmanager
def _sigterm_as_exception() -> Iterator[None]:
    """While writing, turn SIGTERM into `KeyboardInterrupt` so cleanup runs (main thread
    only; elsewhere a no-op)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise KeyboardInterrupt(f"signal {signum} during a file write")

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except (ValueError, OSError):  # no signals here
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _exists_error(path: str) -> FileExistsError:
    return FileExistsError(f"{path} exists; pass overwrite=True (--overwrite) to replace it")


def _commit(tmp: str, path: str, overwrite: bool) -> None:
    """Move the finished temporary file `tmp` to `path` in one step (see module doc)."""
    if overwrite:
        os.replace(tmp, path)
        return
    try:
        os.link(tmp, path)  # atomic, and fails if path exists (even if it just appeared)
    except FileExistsError:
        raise _exists_error(path) from None
    except OSError as err:
        if err.errno not in (
            errno.EPERM,
            errno.EOPNOTSUPP,
            errno.ENOTSUP,
            errno.EXDEV,
            errno.EMLINK,
        ):
            raise
        # No hard links here: reserve the name exclusively, then replace the placeholder.
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)
        except FileExistsError:
            raise _exists_error(path) from None
        os.close(fd)
        os.replace(tmp, path)


@contextlib.contextmanager
def atomic_output(
    path: str | os.PathLike, *, overwrite: bool = False, suffix: str = ""
) -> Iterator[str]:
    """A temporary file name beside `path`; on a clean exit it is moved to `path`.

    For writers that take a file name (`cv2.imwrite`, `cv2.FileStorage`): write to the
    yielded name inside the `with` block. `suffix` (e.g. `".png"`) keeps the extension
    such writers read the format from. On an exception nothing is moved and the
    temporary file is removed; an existing `path` is refused before anything is written
    unless `overwrite`.
    """
    path = check_writable(path, overwrite=overwrite)
    folder = os.path.dirname(os.path.abspath(path))
    with _sigterm_as_exception():
        fd, tmp = tempfile.mkstemp(
            prefix=f"{TMP_PREFIX}{os.path.basename(path)}-", suffix=suffix, dir=folder
        )
        os.close(fd)
        try:
            try:
                yield tmp
                umask = os.umask(0)
                os.umask(umask)
                os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; the usual permissions
                _commit(tmp, path, overwrite)
            except OSError as err:
                if err.errno is None or err.filename == path:
                    raise
                # e.g. ENOSPC from a write into the temporary file: name the output, not
                # the hidden temporary name (which is removed below)
                raise OSError(err.errno, err.strerror or str(err), path) from None
        finally:
            if os.path.lexists(tmp):
                os.unlink(tmp)


def write_atomic(path: str | os.PathLike, data: bytes | str, *, overwrite: bool = False) -> None:
    """Write `data` to `path` atomically and without clobbering (see the module doc).

    **Raises:** `FileExistsError` if `path` exists (checked again at the final move) and
    `overwrite` is False; `FileNotFoundError` / `PermissionError` for the folder.
    """
    with atomic_output(path, overwrite=overwrite) as tmp:
        if isinstance(data, bytes):
            with open(tmp, "wb") as fh:
                fh.write(data)
        else:
            with open(tmp, "w", encoding="utf-8") as fh:
                fh.write(data)


def write_json(path, obj, *, overwrite: bool = False) -> None:
    """Write `obj` as indented JSON (NaN and infinity refused) with `write_atomic`."""
    try:
        text = json.dumps(obj, indent=1, allow_nan=False) + "\n"
    except ValueError as err:  # "Out of range float values are not JSON compliant"
        raise ValueError(
            f"{os.fspath(path)}: refusing to write non-finite numbers (NaN/inf): {err}"
        ) from None
    write_atomic(path, text, overwrite=overwrite)
