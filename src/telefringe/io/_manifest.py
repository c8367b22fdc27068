"""What the manifests (``scan.json``, ``calibration.json``) share: reading the JSON safely,
collecting every problem found, the header checks, and relative paths that must stay
inside their folder."""

from __future__ import annotations

import json
import math
import posixpath
import stat
from pathlib import Path, PurePosixPath

from telefringe.io.errors import InputError

__all__ = ["MAX_MANIFEST_BYTES", "Problems", "short_repr", "is_int", "is_num",
           "check_rel_path", "check_fields", "parse_header", "read_json", "open_manifest"]


#: Largest manifest accepted (bytes): a manifest is a few kB.
MAX_MANIFEST_BYTES = 16 * 1024 * 1024
_MAX_LISTED = 12  # problems spelled out in one message


def short_repr(x, limit: int = 60) -> str:
    """A short repr for messages (a hostile value can be huge)."""
    try:
        text = repr(x)
    except Exception:  # noqa: BLE001 - repr of anything JSON gives cannot fail, be safe
        text = f"<{type(x).__name__}>"
    return text if len(text) <= limit else text[:limit - 3] + "..."


_r = short_repr


class Problems:
    def __init__(self, where: str):
        self.where = where
        self.items: list[str] = []

    def add(self, msg: str) -> None:
        self.items.append(msg)

    def raise_if_any(self) -> None:
        if self.items:
            if len(self.items) == 1:
                raise InputError(f"{self.where}: {self.items[0]}")
            shown = self.items[:_MAX_LISTED]
            more = len(self.items) - len(shown)
            lines = "; ".join(shown) + (f"; and {more} more" if more else "")
            raise InputError(f"{self.where}: {len(self.items)} problems: {lines}")


def is_int(x) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def is_num(x) -> bool:
    """A finite JSON number (not a bool; a huge integer is not finite as a float)."""
    if isinstance(x, bool) or not isinstance(x, int | float):
        return False
    try:
        return math.isfinite(float(x))
    except OverflowError:
        return False


def _check_name(name, what: str, probs: Problems) -> str | None:
    """Syntax of a relative, portable path ('/'-separated, no '..'). Returns it or None."""
    if not isinstance(name, str) or not name:
        probs.add(f"{what}: expected a file name (string), got {_r(name)}")
        return None
    if "\x00" in name:
        probs.add(f"{what}: the name contains a NUL byte")
        return None
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        probs.add(f"{what}: the name {_r(name)} is not valid UTF-8 text")
        return None
    if "\\" in name:
        probs.add(f"{what}: {_r(name)} contains '\\'; separate folders with '/'")
        return None
    if name.startswith("/") or (len(name) >= 2 and name[1] == ":" and name[0].isalpha()):
        probs.add(f"{what}: {_r(name)} is an absolute path; paths must be relative to the "
                  "folder")
        return None
    parts = PurePosixPath(name).parts
    if ".." in parts:
        probs.add(f"{what}: {_r(name)} leaves the folder ('..' is not allowed)")
        return None
    if not parts or parts == (".",):
        probs.add(f"{what}: {_r(name)} names the folder itself, not a file")
        return None
    return name


def check_rel_path(folder: Path | None, name, what: str, probs: Problems, *,
                    must_exist=True, kind: str = "file"):
    """Validate a relative path that must stay inside ``folder``.

    Returns ``(name, key)`` or ``None``: ``key`` identifies the file (its real path when
    ``folder`` is given, so two names of one file, e.g. ``a.png`` and ``./a.png`` or a
    symlink, have the same key).
    """
    name = _check_name(name, what, probs)
    if name is None:
        return None
    if folder is None:
        return name, posixpath.normpath(name)
    full = folder / name
    try:
        real_folder = folder.resolve()
        real = full.resolve()
    except (OSError, RuntimeError, ValueError):
        probs.add(f"{what}: {_r(name)} cannot be resolved (a symlink loop?)")
        return None
    if real != real_folder and real_folder not in real.parents:
        probs.add(f"{what}: {_r(name)} leads outside the folder (through a symlink)")
        return None
    if real == real_folder:
        probs.add(f"{what}: {_r(name)} names the folder itself, not a {kind}")
        return None
    if must_exist:
        try:
            st = full.stat()
        except FileNotFoundError:
            probs.add(f"{what}: {kind} {_r(name)} is missing")
            return None
        except OSError as exc:
            probs.add(f"{what}: {_r(name)} cannot be accessed ({exc.strerror or exc})")
            return None
        ok = stat.S_ISDIR(st.st_mode) if kind == "folder" else stat.S_ISREG(st.st_mode)
        if not ok:
            probs.add(f"{what}: {_r(name)} is not a {kind}")
            return None
    return name, str(real)


def check_fields(obj: dict, allowed, prefix: str, probs: Problems) -> None:
    for k in sorted(set(obj) - set(allowed)):
        probs.add(f"unknown field {prefix}{_r(k)}")


def parse_header(doc, fmt: str, keys, where: str) -> Problems:
    """The checks every manifest starts with: a JSON object (else raise at once), its
    ``format`` and integer ``version`` 1, no field outside ``keys``, ``meta`` an object.

    Returns the problems found so far (the caller adds its own and raises them all).
    """
    probs = Problems(where)
    if not isinstance(doc, dict):
        raise InputError(f"{where}: expected a JSON object at the top level, got "
                         f"{type(doc).__name__}")
    if doc.get("format") != fmt:
        probs.add(f"'format' must be {fmt!r}, got {_r(doc.get('format'))}")
    v = doc.get("version")
    if not (is_int(v) and v == 1):
        probs.add(f"unsupported 'version' {_r(v)} (this telefringe reads the integer 1)")
    check_fields(doc, keys, "", probs)
    if "meta" in doc and not isinstance(doc["meta"], dict):
        probs.add(f"'meta' must be an object (free-form notes), got {_r(doc['meta'])}")
    return probs


class _DuplicateKey(Exception):
    pass


def _no_duplicates(pairs):
    obj = {}
    for k, v in pairs:
        if k in obj:
            raise _DuplicateKey(k)
        obj[k] = v
    return obj


def read_json(path: Path):
    """Parse the manifest at ``path``: UTF-8 (a BOM is allowed), at most MAX_MANIFEST_BYTES, no
    duplicate keys. ``NaN`` / ``Infinity`` literals parse (to be refused by the checks,
    which name the field)."""
    try:
        size = path.stat().st_size
        if size > MAX_MANIFEST_BYTES:
            raise InputError(f"{path}: {size} bytes is too large for a manifest (limit "
                             f"{MAX_MANIFEST_BYTES})")
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputError(f"{path}: not found") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not UTF-8 text (bad byte at offset {exc.start})") from None
    try:
        return json.loads(text, object_pairs_hook=_no_duplicates, parse_constant=float)
    except _DuplicateKey as exc:
        raise InputError(f"{path}: the field {_r(exc.args[0])} appears twice in one object"
                         ) from None
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: malformed JSON at line {exc.lineno} column {exc.colno}: "
                         f"{exc.msg}") from None
    except (ValueError, RecursionError) as exc:
        raise InputError(f"{path}: malformed JSON ({type(exc).__name__}: "
                         f"{str(exc)[:100]})") from None


def open_manifest(folder, filename: str, what: str) -> tuple[Path, Path]:
    folder = Path(folder)
    if not folder.is_dir():
        hint = (f" (give the folder that holds {filename})" if folder.name == filename
                else "")
        raise InputError(f"{folder}: not a folder; a {what} is a folder with {filename}{hint}")
    path = folder / filename
    if not path.is_file():
        raise InputError(f"{folder}: no {filename} in this folder (is it a {what}?)")
    return folder, path


