"""Which scans a batch runs: scan folders given as folders, glob patterns or list files,
and a short unique name for each (its output folder and its row in the table)."""

from __future__ import annotations

import glob
import hashlib
import os
from pathlib import Path

from telefringe.io.errors import InputError

__all__ = ["expand_scans", "scan_names", "scan_digest"]

_LIST_SUFFIXES = (".txt", ".lst", ".list")


def _is_scan(path: Path) -> bool:
    return (path / "scan.json").is_file()


def _from_list(path: Path) -> list[str]:
    """The entries of a list file: one folder or pattern per line, relative to the file's
    folder; blank lines and lines starting with '#' are skipped."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read the list of scans ({exc})") from None
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            p = Path(os.path.expanduser(line))
            out.append(str(p if p.is_absolute() else path.parent / p))
    return out


def expand_scans(specs) -> list[Path]:
    """The scan folders named by ``specs``, in order, each once.

    Parameters
    ----------
    specs : iterable of str or path-like
        Each one a scan folder (holding ``scan.json``), a glob pattern (``runs/*/scan``,
        ``**`` allowed) matching scan folders, a folder whose sub-folders are scan folders
        (one level), or a text file (``.txt``, ``.lst``, ``.list``) listing folders or
        patterns, one a line (relative to the file's folder; ``#`` comments).

    Returns
    -------
    list of Path
        Absolute, resolved, in the order given (a pattern's matches sorted), duplicates
        dropped.

    Raises
    ------
    InputError
        A spec that names nothing, or no scan at all. (A folder matched or listed that is
        not a scan folder is kept: its row in the table says why it failed.)
    """
    out: list[Path] = []
    seen: set[Path] = set()

    def add(p: Path):
        p = p.expanduser().resolve()
        if p not in seen:
            seen.add(p)
            out.append(p)

    def one(spec: str, *, listed: bool):
        p = Path(os.path.expanduser(spec))
        if glob.has_magic(spec):
            hits = sorted(glob.glob(os.path.expanduser(spec), recursive=True))
            dirs = [Path(h) for h in hits if Path(h).is_dir()]
            if not dirs:
                raise InputError(f"{spec}: the pattern matches no folder")
            for d in dirs:
                add(d)
        elif p.is_file() and p.suffix.lower() in _LIST_SUFFIXES and not listed:
            entries = _from_list(p)
            if not entries:
                raise InputError(f"{p}: the list of scans is empty")
            for e in entries:
                one(e, listed=True)
        elif p.is_dir() and not _is_scan(p) and any(_is_scan(c) for c in p.iterdir()
                                                    if c.is_dir()):
            for c in sorted(c for c in p.iterdir() if c.is_dir() and _is_scan(c)):
                add(c)
        elif p.exists() or listed:
            add(p)  # (a listed folder that is not a scan fails in its own row)
        else:
            raise InputError(f"{spec}: no such scan folder, pattern or list file")

    for s in specs:
        one(str(s), listed=False)
    if not out:
        raise InputError("no scan folder given")
    return out


def scan_names(paths) -> list[str]:
    """A short unique name per scan folder: its last path components, as few as make the
    names unique, joined by ``__`` (``runs/a/scan``, ``runs/b/scan`` -> ``a__scan``,
    ``b__scan``); a name that is still not unique gets a hash of its full path.

    >>> scan_names(["/d/a/scan", "/d/b/scan", "/d/c"])
    ['a__scan', 'b__scan', 'c']
    """
    parts = [Path(p).parts for p in paths]
    names = []
    for i, pp in enumerate(parts):
        k = 1
        while True:
            name = "__".join(pp[-k:]).lstrip("/") or "root"
            clash = any(j != i and "__".join(q[-k:]).lstrip("/") == name
                        for j, q in enumerate(parts))
            if not clash or k >= len(pp):
                break
            k += 1
        names.append(name)
    counts: dict[str, int] = {}
    for n in names:
        counts[n] = counts.get(n, 0) + 1
    return [n if counts[n] == 1 else
            f"{n}-{hashlib.blake2b(str(p).encode(), digest_size=4).hexdigest()}"
            for n, p in zip(names, paths, strict=True)]


def scan_digest(folder) -> str:
    """A hash (hex) of a scan's inputs: ``scan.json`` and every image file it names
    (their names and bytes). Raises InputError (via the manifest reader) for a folder
    that is not a valid scan."""
    from telefringe.io.scan_json import load_scan_manifest, scan_image_names

    folder = Path(folder)
    man = load_scan_manifest(folder)
    h = hashlib.blake2b(digest_size=20)
    h.update((folder / "scan.json").read_bytes())
    for name in scan_image_names(man):
        h.update(b"\0" + name.encode() + b"\0")
        with open(folder / name, "rb") as f:
            while chunk := f.read(1 << 20):
                h.update(chunk)
    return h.hexdigest()
