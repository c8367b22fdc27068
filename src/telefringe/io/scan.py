"""Scan folders (format ``telefringe-scan`` v1) and calibration sets
(``telefringe-calibration-set`` v1): validated reading and atomic writing.

Every problem found in a manifest is reported, with the file it is in, as an
:class:`~telefringe.io.errors.InputError` (all problems of a manifest at once).
"""

from __future__ import annotations

import json
import math
import os
import posixpath
import stat
from pathlib import Path, PurePosixPath

import numpy as np

from telefringe.calibration.manifest import CalibrationSetManifest
from telefringe.fringes.scan import GrayGroup, PhaseGroup, Scan, ScanManifest
from telefringe.io.atomic import atomic_dir, write_json_atomic
from telefringe.io.errors import InputError
from telefringe.io.images import image_info, read_image, write_png
from telefringe.targets.grid import CIRCLE_STYLES, CircleGridTarget

__all__ = [
    "SCAN_FORMAT",
    "CALIB_FORMAT",
    "CircleGridTarget",
    "CalibrationSetManifest",
    "parse_scan_manifest",
    "load_scan_manifest",
    "read_scan",
    "write_scan",
    "scan_manifest_to_json",
    "parse_calibration_manifest",
    "load_calibration_set",
    "write_calibration_manifest",
]

SCAN_FORMAT = "telefringe-scan"
CALIB_FORMAT = "telefringe-calibration-set"


# --------------------------------------------------------------------------- helpers
#: Largest manifest accepted (bytes): a manifest is a few kB.
MAX_MANIFEST_BYTES = 16 * 1024 * 1024
_MAX_LISTED = 12  # problems spelled out in one message
#: Most phase steps accepted in one group.
MAX_STEPS = 1000
#: Largest scan read into memory (bytes of decoded images), checked from the headers.
MAX_SCAN_BYTES = 8 * 1024**3


def _r(x, limit: int = 60) -> str:
    """A short repr for messages (a hostile value can be huge)."""
    try:
        text = repr(x)
    except Exception:  # noqa: BLE001 - repr of anything JSON gives cannot fail, be safe
        text = f"<{type(x).__name__}>"
    return text if len(text) <= limit else text[:limit - 3] + "..."


class _Problems:
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


def _is_int(x) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _is_num(x) -> bool:
    """A finite JSON number (not a bool; a huge integer is not finite as a float)."""
    if isinstance(x, bool) or not isinstance(x, int | float):
        return False
    try:
        return math.isfinite(float(x))
    except OverflowError:
        return False


def _check_name(name, what: str, probs: _Problems) -> str | None:
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


def _check_rel_path(folder: Path | None, name, what: str, probs: _Problems, *,
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


def _check_fields(obj: dict, allowed, prefix: str, probs: _Problems) -> None:
    for k in sorted(set(obj) - set(allowed)):
        probs.add(f"unknown field {prefix}{_r(k)}")


def _check_meta(doc: dict, probs: _Problems) -> None:
    if "meta" in doc and not isinstance(doc["meta"], dict):
        probs.add(f"'meta' must be an object (free-form notes), got {_r(doc['meta'])}")


def _check_version(doc: dict, probs: _Problems) -> None:
    v = doc.get("version")
    if not (_is_int(v) and v == 1):
        probs.add(f"unsupported 'version' {_r(v)} (this telefringe reads the integer 1)")


_PHASE_KEYS = {"type", "axis", "periods", "steps", "exposure", "offset", "images"}
_GRAY_KEYS = {"type", "axis", "bits", "complementary", "exposure", "images"}
_SCAN_KEYS = {"format", "version", "projector", "patterns", "white", "black", "meta"}


# --------------------------------------------------------------------------- scan manifest
def parse_scan_manifest(doc, *, folder: Path | None = None, where: str = "scan.json",
                        check_files: bool = True) -> ScanManifest:
    """Validate a parsed ``scan.json`` document and return a :class:`ScanManifest`.

    Parameters
    ----------
    doc : the parsed JSON (anything: it is checked).
    folder : the scan folder, to check image paths (inside the folder, even through
        symlinks; existing regular files when ``check_files``). Without it only the
        paths' syntax is checked (relative, '/'-separated, no '..').
    where : the name used in messages (the manifest's path).

    Raises
    ------
    InputError
        Listing every problem found, each naming its field (see docs/formats.md).
    """
    probs = _Problems(where)
    if not isinstance(doc, dict):
        raise InputError(f"{where}: expected a JSON object at the top level, got "
                         f"{type(doc).__name__}")
    if doc.get("format") != SCAN_FORMAT:
        probs.add(f"'format' must be {SCAN_FORMAT!r}, got {_r(doc.get('format'))}")
    _check_version(doc, probs)
    _check_fields(doc, _SCAN_KEYS, "", probs)
    _check_meta(doc, probs)
    proj = doc.get("projector")
    pw = ph = None
    if not isinstance(proj, dict):
        probs.add("'projector' must be an object {\"width\": W, \"height\": H}, got "
                  f"{_r(proj)}")
    else:
        pw, ph = proj.get("width"), proj.get("height")
        for nm, val in (("width", pw), ("height", ph)):
            if not _is_int(val) or val <= 0 or val > 100_000:
                probs.add(f"'projector.{nm}' must be an integer in 1..100000 (pixels), "
                          f"got {_r(val)}")
        _check_fields(proj, {"width", "height"}, "projector.", probs)
    sizes = {"u": pw if _is_int(pw) else None, "v": ph if _is_int(ph) else None}
    pats = doc.get("patterns")
    groups: list = []
    seen_images: dict[str, str] = {}

    def check_image(name, what):
        ok = _check_rel_path(folder, name, what, probs, must_exist=check_files)
        if ok is None:
            return None
        nm, key = ok
        if key in seen_images:
            probs.add(f"{what}: {_r(nm)} is the same file as {seen_images[key]}")
        seen_images[key] = what
        return nm

    if not isinstance(pats, list) or not pats:
        probs.add(f"'patterns' must be a non-empty list of pattern groups, got {_r(pats)}")
        pats = []
    for i, g in enumerate(pats):
        what = f"patterns[{i}]"
        n_before = len(probs.items)
        if not isinstance(g, dict):
            probs.add(f"{what}: expected an object, got {_r(g)}")
            continue
        kind = g.get("type", "phase")
        if kind not in ("phase", "gray"):
            probs.add(f"{what}: unknown 'type' {_r(kind)} (use 'phase' or 'gray')")
            continue
        _check_fields(g, _GRAY_KEYS if kind == "gray" else _PHASE_KEYS, f"{what}.", probs)
        axis = g.get("axis")
        if axis not in ("u", "v"):
            probs.add(f"{what}: 'axis' must be 'u' or 'v', got {_r(axis)}")
        length = sizes.get(axis) if axis in ("u", "v") else None
        exposure = g.get("exposure", 1.0)
        if not _is_num(exposure) or exposure <= 0:
            probs.add(f"{what}: 'exposure' must be a positive number, got {_r(exposure)}")
        images = g.get("images")
        if not isinstance(images, list):
            probs.add(f"{what}: 'images' must be a list of file names, got {_r(images)}")
            images = []
        if kind == "phase":
            periods, steps = g.get("periods"), g.get("steps")
            offset = g.get("offset", 0.0)
            if not _is_int(periods) or periods < 1:
                probs.add(f"{what}: 'periods' must be an integer >= 1, got {_r(periods)}")
            elif length is not None and 2 * periods > length:
                probs.add(f"{what}: 'periods' {periods} is more than the projector's "
                          f"{'width' if axis == 'u' else 'height'} / 2 = {length / 2:g} "
                          "(a period must span at least 2 projector pixels)")
            if not _is_int(steps) or not 3 <= steps <= MAX_STEPS:
                probs.add(f"{what}: 'steps' must be an integer in 3..{MAX_STEPS}, got "
                          f"{_r(steps)}")
            if not _is_num(offset):
                probs.add(f"{what}: 'offset' must be a finite number (radians), got "
                          f"{_r(offset)}")
            need = steps if _is_int(steps) and 3 <= steps <= MAX_STEPS else None
            counted = "'steps'"
        else:
            bits, comp = g.get("bits"), g.get("complementary", False)
            if not _is_int(bits) or not 1 <= bits <= 16:
                probs.add(f"{what}: 'bits' must be an integer in 1..16, got {_r(bits)}")
            if not isinstance(comp, bool):
                probs.add(f"{what}: 'complementary' must be true or false, got {_r(comp)}")
            need = ((bits + (1 if comp is True else 0)) if _is_int(bits) and 1 <= bits <= 16
                    else None)
            counted = "'bits'" + (" + 1 ('complementary')" if comp is True else "")
        if need is not None and len(images) != need:
            probs.add(f"{what}: needs {need} images ({counted}), lists {len(images)}")
        names = [check_image(name, f"{what}.images[{j}]") for j, name in enumerate(images)]
        if len(probs.items) > n_before:
            continue
        try:
            if kind == "phase":
                groups.append(PhaseGroup(axis=axis, periods=int(periods), steps=int(steps),
                                         exposure=float(exposure), offset=float(offset),
                                         images=tuple(names)))
            else:
                groups.append(GrayGroup(axis=axis, bits=int(bits), complementary=bool(comp),
                                        exposure=float(exposure), images=tuple(names)))
        except ValueError as exc:
            probs.add(f"{what}: {exc}")
    extras = {}
    for key in ("white", "black"):
        if key in doc and doc[key] is not None:
            extras[key] = check_image(doc[key], f"'{key}'")
    # duplicate groups (same identity and exposure)
    keys = [(g.key, g.exposure) for g in groups]
    for k in sorted({k for k in keys if keys.count(k) > 1}, key=repr):
        probs.add(f"two pattern groups are identical (same type/axis/periods/steps/exposure): "
                  f"{k}")
    for gg in (g for g in groups if isinstance(g, GrayGroup)):
        if not any(isinstance(p, PhaseGroup) and p.axis == gg.axis and p.periods == 2 ** gg.bits
                   for p in groups):
            probs.add(f"gray group on axis {gg.axis!r} with {gg.bits} bits needs a phase group "
                      f"with periods = {2 ** gg.bits} on that axis")
    if groups and not any(isinstance(g, PhaseGroup) for g in groups):
        probs.add("no phase group: a scan needs at least one phase-shifted fringe group")
    probs.raise_if_any()
    return ScanManifest(projector_width=int(pw), projector_height=int(ph), groups=tuple(groups),
                        white=extras.get("white"), black=extras.get("black"))


def scan_manifest_to_json(manifest: ScanManifest) -> dict:
    """The ``scan.json`` document (dict) of a manifest."""
    pats = []
    for g in manifest.groups:
        if isinstance(g, PhaseGroup):
            d = {"axis": g.axis, "periods": int(g.periods), "steps": int(g.steps),
                 "exposure": float(g.exposure)}
            if g.offset:
                d["offset"] = float(g.offset)
            d["images"] = list(g.images)
        else:
            d = {"type": "gray", "axis": g.axis, "bits": int(g.bits),
                 "complementary": bool(g.complementary), "exposure": float(g.exposure),
                 "images": list(g.images)}
        pats.append(d)
    doc = {"format": SCAN_FORMAT, "version": 1,
           "projector": {"width": int(manifest.projector_width),
                         "height": int(manifest.projector_height)},
           "patterns": pats}
    if manifest.white:
        doc["white"] = manifest.white
    if manifest.black:
        doc["black"] = manifest.black
    return doc


class _DuplicateKey(Exception):
    pass


def _no_duplicates(pairs):
    obj = {}
    for k, v in pairs:
        if k in obj:
            raise _DuplicateKey(k)
        obj[k] = v
    return obj


def _read_json(path: Path):
    """Parse a manifest: UTF-8 (a BOM is allowed), at most MAX_MANIFEST_BYTES, no
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


def _open_manifest(folder, filename: str, what: str) -> tuple[Path, Path]:
    folder = Path(folder)
    if not folder.is_dir():
        hint = (f" (give the folder that holds {filename})" if folder.name == filename
                else "")
        raise InputError(f"{folder}: not a folder; a {what} is a folder with {filename}{hint}")
    path = folder / filename
    if not path.is_file():
        raise InputError(f"{folder}: no {filename} in this folder (is it a {what}?)")
    return folder, path


def _load_scan(folder) -> tuple[Path, ScanManifest, dict]:
    folder, path = _open_manifest(folder, "scan.json", "scan")
    doc = _read_json(path)
    return folder, parse_scan_manifest(doc, folder=folder, where=str(path)), doc


def load_scan_manifest(folder) -> ScanManifest:
    """Read and validate ``folder/scan.json`` (image files checked to exist, not decoded)."""
    return _load_scan(folder)[1]


def _scan_image_names(man: ScanManifest) -> list[str]:
    names = [n for g in man.groups for n in g.images]
    return names + [n for n in (man.white, man.black) if n]


def read_scan(folder, *, progress=None) -> Scan:
    """Load a scan folder: validated manifest and all images.

    Parameters
    ----------
    folder : path-like, the scan folder (holding ``scan.json``).
    progress : optional callable ``progress(done, total)`` (the CLI passes a bar).

    Returns
    -------
    Scan
        Its ``max_value`` is 255 for 8-bit and 65535 for 16-bit images; its ``meta`` is
        the manifest's ``meta`` object (or empty).

    Raises
    ------
    InputError
        A bad manifest, or images that are missing, unreadable, too large, or differ in
        size or bit depth. Sizes and bit depths are compared from the headers before
        any image is decoded.
    """
    folder, man, doc = _load_scan(folder)
    names = _scan_image_names(man)
    infos = {n: image_info(folder / n) for n in names}
    first = infos[names[0]]
    for n in names[1:]:
        if infos[n].shape != first.shape:
            raise InputError(
                f"{folder}: image sizes differ: {names[0]} is {first.cols} x {first.rows} "
                f"but {n} is {infos[n].cols} x {infos[n].rows}")
        if infos[n].bits != first.bits:
            raise InputError(f"{folder}: bit depths differ: {names[0]} is {first.bits}-bit "
                             f"but {n} is {infos[n].bits}-bit")
    need = len(names) * first.rows * first.cols * first.dtype.itemsize
    if need > MAX_SCAN_BYTES:
        raise InputError(f"{folder}: its {len(names)} images of {first.cols} x {first.rows} "
                         f"would take {need / 1024**3:.1f} GiB, more than the limit of "
                         f"{MAX_SCAN_BYTES / 1024**3:.0f} GiB")
    images = {}
    # decoding (zlib, OpenCV) releases the GIL: read on every core, report in order (the
    # first bad image in the manifest's order is the one named)
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=max(1, min(4, os.cpu_count() or 1))) as pool:
        for i, (n, img) in enumerate(zip(names, pool.map(lambda n: read_image(folder / n),
                                                         names), strict=True)):
            images[n] = img
            if progress is not None:
                progress(i + 1, len(names))
    stacks = tuple(np.stack([images[n] for n in g.images]) for g in man.groups)
    max_value = 255.0 if first.bits == 8 else 65535.0
    return Scan(manifest=man, stacks=stacks,
                white=images.get(man.white) if man.white else None,
                black=images.get(man.black) if man.black else None,
                max_value=max_value, source=str(folder), meta=dict(doc.get("meta", {})))


def _default_names(man: ScanManifest) -> ScanManifest:
    """Fill in image names for groups that have none."""
    groups = []
    for g in man.groups:
        if g.images:
            groups.append(g)
            continue
        exp = "" if g.exposure == 1.0 else f"_e{g.exposure:g}".replace(".", "p")
        if isinstance(g, PhaseGroup):
            off = "" if not g.offset else f"_o{g.offset:+.3f}".replace(".", "p")
            stem = f"{g.axis}_{g.periods:03d}_{g.steps}s{off}{exp}"
        else:
            stem = f"{g.axis}_gray{g.bits}{'c' if g.complementary else ''}{exp}"
        groups.append(type(g)(**{**g.__dict__, "images": tuple(
            f"{stem}_{k:02d}.png" for k in range(g.count))}))
    return ScanManifest(man.projector_width, man.projector_height, tuple(groups),
                        man.white, man.black)


def _json_default(x):
    if isinstance(x, np.generic | np.ndarray):
        return x.tolist()
    raise TypeError(f"scan.meta holds a {type(x).__name__}, which JSON cannot store")


def write_scan(folder, scan: Scan, *, force: bool = False) -> Path:
    """Write a scan folder atomically (PNG images + ``scan.json``).

    Groups without image names get systematic ones. White/black images are written as
    ``white.png`` / ``black.png`` when present; ``scan.meta`` (if not empty) as the
    manifest's ``meta``. An existing ``folder`` is replaced only with ``force``. The
    manifest written is validated as a reader would, so a scan that cannot be read back
    is never written. Returns the folder path.
    """
    folder = Path(folder)
    man = _default_names(scan.manifest)
    white = "white.png" if scan.white is not None else None
    black = "black.png" if scan.black is not None else None
    man = ScanManifest(man.projector_width, man.projector_height, man.groups, white, black)
    doc = scan_manifest_to_json(man)
    if scan.meta:
        doc["meta"] = scan.meta
    text = json.dumps(doc, indent=2, allow_nan=False, default=_json_default) + "\n"
    try:
        parse_scan_manifest(json.loads(text), where=f"{folder}/scan.json (being written)")
    except InputError as exc:
        raise ValueError(f"write_scan: {exc}") from None
    with atomic_dir(folder, force=force) as tmp:
        for g, stack in zip(man.groups, scan.stacks, strict=True):
            for name, img in zip(g.images, stack, strict=True):
                (tmp / name).parent.mkdir(parents=True, exist_ok=True)
                write_png(tmp / name, np.asarray(img))
        if white:
            write_png(tmp / white, scan.white)
        if black:
            write_png(tmp / black, scan.black)
        (tmp / "scan.json").write_text(text, encoding="utf-8")
    return folder


# --------------------------------------------------------------------------- calibration set
_CAL_KEYS = {"format", "version", "target", "camera", "projector", "poses", "reference_pose",
             "meta"}
_TARGET_KEYS = {"type", "rows", "cols", "pitch_mm", "diameter_mm", "circles"}


def parse_calibration_manifest(doc, *, folder: Path | None = None,
                               where: str = "calibration.json") -> CalibrationSetManifest:
    """Validate a parsed ``calibration.json`` document.

    Parameters
    ----------
    doc : the parsed JSON (anything: it is checked).
    folder : the calibration-set folder, to check that every pose is a sub-folder (not
        leaving it, even through a symlink) holding a ``scan.json``.
    where : the name used in messages.

    Raises
    ------
    InputError
        Listing every problem found, each naming its field (see docs/formats.md).
    """
    probs = _Problems(where)
    if not isinstance(doc, dict):
        raise InputError(f"{where}: expected a JSON object at the top level, got "
                         f"{type(doc).__name__}")
    if doc.get("format") != CALIB_FORMAT:
        probs.add(f"'format' must be {CALIB_FORMAT!r}, got {_r(doc.get('format'))}")
    _check_version(doc, probs)
    _check_fields(doc, _CAL_KEYS, "", probs)
    _check_meta(doc, probs)
    t = doc.get("target")
    if not isinstance(t, dict):
        probs.add(f"'target' must be an object, got {_r(t)}")
    else:
        _check_fields(t, _TARGET_KEYS, "target.", probs)
        if t.get("type") != "circle-grid":
            probs.add(f"'target.type' must be 'circle-grid', got {_r(t.get('type'))}")
        for nm in ("rows", "cols"):
            v = t.get(nm)
            if not _is_int(v) or not 2 <= v <= 1000:
                probs.add(f"'target.{nm}' must be an integer in 2..1000, got {_r(v)}")
        for nm in ("pitch_mm", "diameter_mm"):
            v = t.get(nm)
            if not _is_num(v) or v <= 0:
                probs.add(f"'target.{nm}' must be a positive number (mm), got {_r(v)}")
        circ = t.get("circles", "dark-on-light")
        if circ not in CIRCLE_STYLES:
            probs.add(f"'target.circles' must be 'dark-on-light' or 'light-on-dark', got "
                      f"{_r(circ)}")
        if (_is_num(t.get("pitch_mm")) and _is_num(t.get("diameter_mm"))
                and 0 < t["pitch_mm"] <= t["diameter_mm"]):
            probs.add("'target.diameter_mm' must be smaller than 'target.pitch_mm'")
    sizes = {}
    for dev in ("camera", "projector"):
        d = doc.get(dev)
        if not isinstance(d, dict):
            probs.add(f"'{dev}' must be an object {{\"pixel_size_mm\": [du, dv]}}, got {_r(d)}")
            continue
        _check_fields(d, {"pixel_size_mm"}, f"{dev}.", probs)
        ps = d.get("pixel_size_mm")
        if (not isinstance(ps, list) or len(ps) != 2
                or not all(_is_num(x) and 0 < x < 1 for x in ps)):
            probs.add(f"'{dev}.pixel_size_mm' must be [du, dv] in mm (0 < du, dv < 1), got "
                      f"{_r(ps)}")
        else:
            sizes[dev] = (float(ps[0]), float(ps[1]))
    poses = doc.get("poses")
    if not isinstance(poses, list) or not poses:
        probs.add(f"'poses' must be a non-empty list of scan folder names, got {_r(poses)}")
        poses = []
    seen: dict[str, str] = {}
    for i, p in enumerate(poses):
        what = f"poses[{i}]"
        ok = _check_rel_path(folder, p, what, probs, must_exist=folder is not None,
                             kind="folder")
        if ok is None:
            continue
        if ok[1] in seen:
            probs.add(f"{what}: {_r(p)} is the same folder as {seen[ok[1]]}")
            continue
        seen[ok[1]] = what
        if folder is not None and not (folder / p / "scan.json").is_file():
            probs.add(f"{what}: {_r(p)} is not a scan folder (no scan.json)")
    if "reference_pose" in doc:
        ref = doc["reference_pose"]
        if not isinstance(ref, str) or ref not in poses:
            probs.add(f"'reference_pose' {_r(ref)} is not one of 'poses'")
    else:
        ref = poses[0] if poses else None
    probs.raise_if_any()
    target = CircleGridTarget(int(t["rows"]), int(t["cols"]), float(t["pitch_mm"]),
                              float(t["diameter_mm"]), t.get("circles", "dark-on-light"))
    return CalibrationSetManifest(target=target, camera_pixel_size=sizes["camera"],
                                  projector_pixel_size=sizes["projector"],
                                  poses=tuple(poses), reference_pose=ref,
                                  folder=str(folder) if folder is not None else "")


def load_calibration_set(folder) -> CalibrationSetManifest:
    """Read and validate ``folder/calibration.json`` and each pose's ``scan.json``.

    Also checks that every pose was taken with the same projector size and the same
    camera image size (from the first image's header). Images are not decoded here;
    read each pose with :func:`read_scan` (``Path(folder) / pose``) when it is needed,
    so memory stays bounded.
    """
    folder, path = _open_manifest(folder, "calibration.json", "calibration set")
    man = parse_calibration_manifest(_read_json(path), folder=folder, where=str(path))
    ref_pose = ref = None
    for p in man.poses:
        pm = load_scan_manifest(folder / p)
        first = _scan_image_names(pm)[0]
        info = image_info(folder / p / first)
        this = (pm.projector_width, pm.projector_height, info.cols, info.rows)
        if ref is None:
            ref_pose, ref = p, this
        elif this != ref:
            raise InputError(
                f"{path}: poses differ: {ref_pose} has a {ref[0]} x {ref[1]} projector and "
                f"{ref[2]} x {ref[3]} images, {p} has {this[0]} x {this[1]} and "
                f"{this[2]} x {this[3]}")
    return man


def write_calibration_manifest(folder, man: CalibrationSetManifest) -> None:
    """Write ``calibration.json`` into an existing folder (atomically)."""
    t = man.target
    doc = {"format": CALIB_FORMAT, "version": 1,
           "target": {"type": "circle-grid", "rows": int(t.rows), "cols": int(t.cols),
                      "pitch_mm": float(t.pitch_mm), "diameter_mm": float(t.diameter_mm),
                      "circles": t.circles},
           "camera": {"pixel_size_mm": [float(x) for x in man.camera_pixel_size]},
           "projector": {"pixel_size_mm": [float(x) for x in man.projector_pixel_size]},
           "poses": list(man.poses), "reference_pose": man.reference_pose}
    write_json_atomic(Path(folder) / "calibration.json", doc, force=True)
