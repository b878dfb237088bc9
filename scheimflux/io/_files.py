"""Small helpers for the files users exchange: JSON loading with clear errors, and
atomic writes that never clobber an existing file by accident."""

from __future__ import annotations

import json
import os
import tempfile
from typing import Any


def load_json(path: str | os.PathLike, what: str) -> Any:
    """Read a JSON file; errors name the file and what it should have been."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"{what} file not found: {path}")
    try:
        with open(path, encoding="utf-8") as fh:
            return json.load(fh)
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not valid JSON ({err.msg} at line {err.lineno})") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text (UTF-8 JSON) file") from None


def check_writable(path: str | os.PathLike, *, overwrite: bool) -> str:
    """Refuse to replace an existing file unless asked; check the folder exists."""
    path = os.fspath(path)
    if os.path.exists(path) and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True (--overwrite) to replace it")
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise FileNotFoundError(f"output folder does not exist: {folder}")
    return path


def write_atomic(path: str | os.PathLike, data: bytes | str, *, overwrite: bool = False) -> None:
    """Write a file via a temporary file in the same folder and `os.replace`.

    A failure part-way leaves any existing file untouched.
    """
    path = check_writable(path, overwrite=overwrite)
    mode = "wb" if isinstance(data, bytes) else "w"
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", dir=os.path.dirname(os.path.abspath(path)))
    try:
        with os.fdopen(fd, mode, **({} if mode == "wb" else {"encoding": "utf-8"})) as fh:
            fh.write(data)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the usual permissions
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_json(path, obj, *, overwrite: bool = False) -> None:
    write_atomic(path, json.dumps(obj, indent=1, allow_nan=False) + "\n", overwrite=overwrite)
