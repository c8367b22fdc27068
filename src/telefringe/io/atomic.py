"""Atomic outputs: write under a temporary name, then rename; never half-write."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from pathlib import Path

from .errors import InputError

__all__ = ["atomic_file", "atomic_dir", "write_json_atomic", "check_can_write"]


def check_can_write(path, *, force: bool) -> Path:
    """Refuse to overwrite an existing output unless ``force``; return the path."""
    path = Path(path)
    if path.exists() and not force:
        raise InputError(f"{path}: already exists; pass --force to replace it")
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.exists():
        raise InputError(f"{path}: the folder {parent} does not exist")
    return path


@contextlib.contextmanager
def atomic_file(path, *, force: bool = True):
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success.

    On an exception (or interruption) the temporary file is removed and ``path`` is
    left untouched.
    """
    path = Path(path)
    check_can_write(path, force=force)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent or ".")
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


@contextlib.contextmanager
def atomic_dir(path, *, force: bool = False):
    """Yield a temporary folder beside ``path``; it becomes ``path`` on success.

    An existing ``path`` is replaced only with ``force`` (and only once the new one is
    complete). On failure the temporary folder is removed and nothing else changes.
    """
    path = Path(path)
    check_can_write(path, force=force)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent or "."))
    try:
        yield tmp
        if path.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old",
                                        dir=path.parent or "."))
            old.rmdir()
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def write_json_atomic(path, obj, *, force: bool = True) -> None:
    """Write ``obj`` as indented JSON to ``path`` atomically."""
    with atomic_file(path, force=force) as tmp:
        Path(tmp).write_text(json.dumps(obj, indent=2, allow_nan=False) + "\n")
