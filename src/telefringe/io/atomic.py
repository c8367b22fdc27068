"""Atomic outputs: write under a temporary name, then rename; never half-write.

Every output of telefringe goes through :func:`atomic_file` or :func:`atomic_dir`:

- the content is written under a hidden temporary name beside the target
  (``.NAME.<random>.part``) and renamed onto the target only once it is complete, so a
  failed or interrupted run (an exception, Ctrl-C) leaves no partial output and the
  previous content untouched;
- an existing output is refused unless ``force`` (the ``--force`` option), and without
  ``force`` an output that appears while we write is not overwritten either;
- outputs get the usual permissions (0666 / 0777 minus the umask), not the private
  ones of temporary files.

A process killed outright (SIGKILL, power cut) can leave a ``.NAME.*.part`` behind,
never a half-written ``NAME``.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from pathlib import Path

from telefringe.io.errors import InputError

__all__ = ["atomic_file", "atomic_dir", "write_json_atomic", "check_can_write"]


def _umask() -> int:
    """The process umask (read without changing it where /proc allows)."""
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _held_input(path: Path, inputs) -> str | None:
    """The first of ``inputs`` (paths or None) that ``path`` is or holds, else None."""
    try:
        real = path.resolve()
    except (OSError, RuntimeError):
        return None
    for inp in inputs:
        if inp is None:
            continue
        try:
            r = Path(inp).resolve()
        except (OSError, RuntimeError):
            continue
        if r == real or real in r.parents:
            return str(inp)
    return None


def check_can_write(path, *, force: bool, kind: str | None = None, inputs=()) -> Path:
    """Refuse to overwrite an existing output unless ``force``; return the path.

    Parameters
    ----------
    path : path-like, the output to be written.
    force : bool, replace an existing output.
    kind : ``"file"``, ``"folder"`` or None; with ``force``, an existing output of the
        other kind is still refused (a folder is never replaced by a file, nor the
        reverse).
    inputs : paths (or None) the command reads: an existing output that is one of them
        or holds one (``reconstruct scans/a -o scans/a --force``, ``-o scans``) is
        refused even with ``force``, as replacing it would delete the input.

    Raises
    ------
    InputError
        The output exists (without ``force``), is of the other kind, is or holds an
        input, or its parent folder does not exist.
    """
    path = Path(path)
    if path.exists() or path.is_symlink():
        if not force:
            raise InputError(f"{path}: already exists; pass --force to replace it")
        held = _held_input(path, inputs)
        if held is not None:
            what = "is" if Path(held).resolve() == path.resolve() else "holds"
            raise InputError(f"{path}: {what} the input {held}, which replacing it would "
                             "delete; write the output somewhere else")
        if kind == "file" and path.is_dir():
            raise InputError(f"{path}: is a folder; refusing to replace it with a file")
        if kind == "folder" and not path.is_dir():
            raise InputError(f"{path}: is a file; refusing to replace it with a folder")
    parent = path.parent
    if not parent.is_dir():
        raise InputError(f"{path}: the folder {parent} does not exist")
    return path


@contextlib.contextmanager
def atomic_file(path, *, force: bool = True, inputs=()):
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success.

    The caller writes the whole file to the yielded path. On success it is flushed to
    disk and renamed onto ``path``; on an exception (or interruption) the temporary
    file is removed and ``path`` is left untouched. Without ``force`` an existing
    ``path`` is refused (:class:`InputError`), also if it appears while writing; so is
    one of ``inputs`` (the command's input paths) even with ``force``.
    """
    path = Path(path)
    check_can_write(path, force=force, kind="file", inputs=inputs)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_umask())
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        if force:
            os.replace(tmp, path)
        else:
            try:
                os.link(tmp, path)  # fails if path exists: no clobbering
            except FileExistsError:
                raise InputError(f"{path}: appeared while writing; pass --force to replace "
                                 "it") from None
            except OSError:  # no hard links on this file system
                if path.exists():
                    raise InputError(f"{path}: appeared while writing; pass --force to "
                                     "replace it") from None
                os.replace(tmp, path)
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(OSError):
            path.unlink()


@contextlib.contextmanager
def atomic_dir(path, *, force: bool = False, inputs=()):
    """Yield a temporary folder beside ``path``; it becomes ``path`` on success.

    An existing ``path`` is replaced only with ``force`` (and only once the new one is
    complete). On failure the temporary folder is removed and nothing else changes; if
    the final swap itself fails, the previous ``path`` is put back. A ``path`` that is
    or holds one of ``inputs`` (the command's input paths) is never replaced.
    """
    path = Path(path)
    check_can_write(path, force=force, kind="folder", inputs=inputs)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent))
    try:
        yield tmp
        os.chmod(tmp, 0o777 & ~_umask())
        if path.exists() or path.is_symlink():
            if not force:
                raise InputError(f"{path}: appeared while writing; pass --force to replace it")
            old = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old",
                                        dir=path.parent))
            old.rmdir()
            os.replace(path, old)
            try:
                os.replace(tmp, path)
            except BaseException:
                os.replace(old, path)
                raise
            _remove(old)
        else:
            # (an empty folder created by someone else in the instant between the check
            # above and this rename would be replaced: POSIX rename allows it)
            os.replace(tmp, path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def write_json_atomic(path, obj, *, force: bool = True) -> None:
    """Write ``obj`` as indented JSON (UTF-8, no NaN/Infinity) to ``path`` atomically.

    Raises ``ValueError`` (before anything is written) if ``obj`` holds NaN or infinity,
    which JSON cannot represent.
    """
    text = json.dumps(obj, indent=2, allow_nan=False) + "\n"
    with atomic_file(path, force=force) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")
