"""Scan folders (format ``telefringe-scan`` v1) and calibration sets
(``telefringe-calibration-set`` v1): validated reading and atomic writing.

Every problem found in a manifest is reported, with the file it is in, as an
:class:`~telefringe.io.errors.InputError` (all problems of a manifest at once).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..scan import GrayGroup, PhaseGroup, Scan, ScanManifest
from .atomic import atomic_dir
from .errors import InputError
from .images import image_header, read_image, write_png

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
            lines = "; ".join(self.items)
            raise InputError(f"{self.where}: {len(self.items)} problems: {lines}")


def _is_int(x) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _is_num(x) -> bool:
    return (isinstance(x, int | float) and not isinstance(x, bool)
            and math.isfinite(float(x)))


def _check_rel_path(folder: Path, name, what: str, probs: _Problems, *, must_exist=True):
    """Validate a relative path that must stay inside ``folder``. Returns it or None."""
    if not isinstance(name, str) or not name:
        probs.add(f"{what}: expected a file name (string), got {name!r}")
        return None
    if "\x00" in name:
        probs.add(f"{what}: file name contains a NUL byte")
        return None
    p = Path(name)
    if p.is_absolute() or name.startswith(("/", "\\")):
        probs.add(f"{what}: {name!r} is an absolute path; paths must be relative to the folder")
        return None
    if ".." in p.parts:
        probs.add(f"{what}: {name!r} leaves the folder ('..' is not allowed)")
        return None
    full = folder / p
    try:
        real_folder = folder.resolve()
        real = full.resolve()
    except (OSError, RuntimeError):
        probs.add(f"{what}: {name!r} cannot be resolved")
        return None
    if real != real_folder and real_folder not in real.parents:
        probs.add(f"{what}: {name!r} leads outside the folder (symlink)")
        return None
    if must_exist and not full.is_file():
        probs.add(f"{what}: file {name!r} is missing")
        return None
    return name


_PHASE_KEYS = {"type", "axis", "periods", "steps", "exposure", "offset", "images"}
_GRAY_KEYS = {"type", "axis", "bits", "complementary", "exposure", "images"}
_SCAN_KEYS = {"format", "version", "projector", "patterns", "white", "black", "meta"}


# --------------------------------------------------------------------------- scan manifest
def parse_scan_manifest(doc, *, folder: Path | None = None, where: str = "scan.json",
                        check_files: bool = True) -> ScanManifest:
    """Validate a parsed ``scan.json`` document and return a :class:`ScanManifest`.

    ``folder``: the scan folder, to check image paths (stay inside, exist).
    """
    probs = _Problems(where)
    if not isinstance(doc, dict):
        raise InputError(f"{where}: expected a JSON object at the top level")
    if doc.get("format") != SCAN_FORMAT:
        probs.add(f"'format' must be {SCAN_FORMAT!r}, got {doc.get('format')!r}")
    if doc.get("version") != 1:
        probs.add(f"unsupported 'version' {doc.get('version')!r} (this telefringe reads 1)")
    for k in sorted(set(doc) - _SCAN_KEYS):
        probs.add(f"unknown field {k!r}")
    proj = doc.get("projector")
    pw = ph = None
    if not isinstance(proj, dict):
        probs.add("'projector' must be an object {\"width\": W, \"height\": H}")
    else:
        pw, ph = proj.get("width"), proj.get("height")
        for nm, val in (("width", pw), ("height", ph)):
            if not _is_int(val) or val <= 0 or val > 100_000:
                probs.add(f"'projector.{nm}' must be a positive integer, got {val!r}")
        for k in sorted(set(proj) - {"width", "height"}):
            probs.add(f"unknown field 'projector.{k}'")
    pats = doc.get("patterns")
    groups: list = []
    seen_images: dict[str, str] = {}
    if not isinstance(pats, list) or not pats:
        probs.add("'patterns' must be a non-empty list of pattern groups")
        pats = []
    for i, g in enumerate(pats):
        what = f"patterns[{i}]"
        if not isinstance(g, dict):
            probs.add(f"{what}: expected an object")
            continue
        kind = g.get("type", "phase")
        allowed = _GRAY_KEYS if kind == "gray" else _PHASE_KEYS
        if kind not in ("phase", "gray"):
            probs.add(f"{what}: unknown 'type' {kind!r} (use 'phase' or 'gray')")
            continue
        for k in sorted(set(g) - allowed):
            probs.add(f"{what}: unknown field {k!r}")
        axis = g.get("axis")
        if axis not in ("u", "v"):
            probs.add(f"{what}: 'axis' must be 'u' or 'v', got {axis!r}")
        exposure = g.get("exposure", 1.0)
        if not _is_num(exposure) or exposure <= 0:
            probs.add(f"{what}: 'exposure' must be a positive number, got {exposure!r}")
        images = g.get("images")
        if not isinstance(images, list):
            probs.add(f"{what}: 'images' must be a list of file names")
            images = []
        if kind == "phase":
            periods, steps = g.get("periods"), g.get("steps")
            offset = g.get("offset", 0.0)
            if not _is_int(periods) or periods < 1:
                probs.add(f"{what}: 'periods' must be an integer >= 1, got {periods!r}")
            if not _is_int(steps) or steps < 3:
                probs.add(f"{what}: 'steps' must be an integer >= 3, got {steps!r}")
            if not _is_num(offset):
                probs.add(f"{what}: 'offset' must be a finite number (radians), got {offset!r}")
            need = steps if _is_int(steps) else None
        else:
            bits, comp = g.get("bits"), g.get("complementary", False)
            if not _is_int(bits) or not 1 <= bits <= 16:
                probs.add(f"{what}: 'bits' must be an integer in 1..16, got {bits!r}")
            if not isinstance(comp, bool):
                probs.add(f"{what}: 'complementary' must be true or false, got {comp!r}")
            need = (bits + (1 if comp is True else 0)) if _is_int(bits) else None
        if need is not None and len(images) != need:
            probs.add(f"{what}: needs {need} images, lists {len(images)}")
        names = []
        for j, name in enumerate(images):
            nm = _check_rel_path(folder, name, f"{what}.images[{j}]", probs,
                                 must_exist=check_files) if folder is not None else name
            if isinstance(nm, str):
                if nm in seen_images:
                    probs.add(f"{what}.images[{j}]: {nm!r} is also used by {seen_images[nm]}")
                seen_images[nm] = f"{what}.images[{j}]"
            names.append(nm)
        if probs.items:
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
            nm = _check_rel_path(folder, doc[key], f"'{key}'", probs,
                                 must_exist=check_files) if folder is not None else doc[key]
            if isinstance(nm, str) and nm in seen_images:
                probs.add(f"'{key}': {nm!r} is also used by {seen_images[nm]}")
            extras[key] = nm
    # duplicate groups (same identity and exposure)
    keys = [(g.key, g.exposure) for g in groups]
    for k in {k for k in keys if keys.count(k) > 1}:
        probs.add(f"two pattern groups are identical (same axis/periods/steps/exposure): {k}")
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


def _read_json(path: Path):
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{path}: not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read ({exc})") from None
    try:
        return json.loads(text, parse_constant=lambda c: float("nan"))
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: malformed JSON at line {exc.lineno} column {exc.colno}: "
                         f"{exc.msg}") from None


def load_scan_manifest(folder) -> ScanManifest:
    """Read and validate ``folder/scan.json`` (image files checked to exist, not decoded)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder (a scan is a folder with scan.json)")
    path = folder / "scan.json"
    if not path.is_file():
        raise InputError(f"{folder}: no scan.json in this folder")
    return parse_scan_manifest(_read_json(path), folder=folder, where=str(path))


def read_scan(folder, *, progress=None) -> Scan:
    """Load a scan folder: validated manifest and all images.

    ``progress``: optional callable ``progress(done, total)`` (the CLI passes a bar).

    Checks that all images have the same size and bit depth before decoding them
    (sizes from the headers).
    """
    folder = Path(folder)
    man = load_scan_manifest(folder)
    names = [n for g in man.groups for n in g.images]
    names += [n for n in (man.white, man.black) if n]
    shapes = {n: image_header(folder / n) for n in names}
    ref = shapes[names[0]]
    bad = [n for n in names if shapes[n] != ref]
    if bad:
        raise InputError(f"{folder}: image sizes differ: {names[0]} is {ref[1]} x {ref[0]} but "
                         f"{bad[0]} is {shapes[bad[0]][1]} x {shapes[bad[0]][0]}")
    images = {}
    total = len(names)
    dtype = None
    for i, n in enumerate(names):
        img = read_image(folder / n)
        if dtype is None:
            dtype, first = img.dtype, n
        elif img.dtype != dtype:
            raise InputError(f"{folder}: bit depths differ: {first} is {dtype} but {n} is "
                             f"{img.dtype}")
        images[n] = img
        if progress is not None:
            progress(i + 1, total)
    stacks = tuple(np.stack([images[n] for n in g.images]) for g in man.groups)
    max_value = 255.0 if dtype == np.uint8 else 65535.0
    return Scan(manifest=man, stacks=stacks,
                white=images.get(man.white) if man.white else None,
                black=images.get(man.black) if man.black else None,
                max_value=max_value, source=str(folder))


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


def write_scan(folder, scan: Scan, *, force: bool = False) -> Path:
    """Write a scan folder atomically (PNG images + ``scan.json``).

    Groups without image names get systematic ones. White/black images are written as
    ``white.png`` / ``black.png`` when present. Returns the folder path.
    """
    folder = Path(folder)
    man = _default_names(scan.manifest)
    white = "white.png" if scan.white is not None else None
    black = "black.png" if scan.black is not None else None
    man = ScanManifest(man.projector_width, man.projector_height, man.groups, white, black)
    with atomic_dir(folder, force=force) as tmp:
        for g, stack in zip(man.groups, scan.stacks, strict=True):
            for name, img in zip(g.images, stack, strict=True):
                write_png(tmp / name, np.asarray(img))
        if white:
            write_png(tmp / white, scan.white)
        if black:
            write_png(tmp / black, scan.black)
        (tmp / "scan.json").write_text(json.dumps(scan_manifest_to_json(man), indent=2) + "\n")
    return folder


# --------------------------------------------------------------------------- calibration set
@dataclass(frozen=True)
class CircleGridTarget:
    """A planar grid of circles: ``rows`` x ``cols`` at ``pitch_mm``; dark on light."""

    rows: int
    cols: int
    pitch_mm: float
    diameter_mm: float
    circles: str = "dark-on-light"

    def points_target(self) -> np.ndarray:
        """Circle centres in the target frame, (rows * cols, 3) mm, row-major (row, col):
        x = col * pitch, y = row * pitch, z = 0."""
        r, c = np.mgrid[0:self.rows, 0:self.cols]
        return np.stack([c.ravel() * self.pitch_mm, r.ravel() * self.pitch_mm,
                         np.zeros(r.size)], axis=1)


@dataclass(frozen=True)
class CalibrationSetManifest:
    """Content of ``calibration.json``: the target, pixel sizes and pose scan folders."""

    target: CircleGridTarget
    camera_pixel_size: tuple[float, float]
    projector_pixel_size: tuple[float, float]
    poses: tuple[str, ...]
    reference_pose: str
    folder: str = ""


_CAL_KEYS = {"format", "version", "target", "camera", "projector", "poses", "reference_pose",
             "meta"}


def parse_calibration_manifest(doc, *, folder: Path | None = None,
                               where: str = "calibration.json") -> CalibrationSetManifest:
    """Validate a parsed ``calibration.json`` document."""
    probs = _Problems(where)
    if not isinstance(doc, dict):
        raise InputError(f"{where}: expected a JSON object at the top level")
    if doc.get("format") != CALIB_FORMAT:
        probs.add(f"'format' must be {CALIB_FORMAT!r}, got {doc.get('format')!r}")
    if doc.get("version") != 1:
        probs.add(f"unsupported 'version' {doc.get('version')!r} (this telefringe reads 1)")
    for k in sorted(set(doc) - _CAL_KEYS):
        probs.add(f"unknown field {k!r}")
    t = doc.get("target")
    target = None
    if not isinstance(t, dict):
        probs.add("'target' must be an object")
    else:
        if t.get("type") != "circle-grid":
            probs.add(f"'target.type' must be 'circle-grid', got {t.get('type')!r}")
        for nm in ("rows", "cols"):
            if not _is_int(t.get(nm)) or not 2 <= t.get(nm) <= 1000:
                probs.add(f"'target.{nm}' must be an integer >= 2, got {t.get(nm)!r}")
        for nm in ("pitch_mm", "diameter_mm"):
            if not _is_num(t.get(nm)) or t.get(nm) <= 0:
                probs.add(f"'target.{nm}' must be a positive number, got {t.get(nm)!r}")
        circ = t.get("circles", "dark-on-light")
        if circ not in ("dark-on-light", "light-on-dark"):
            probs.add(f"'target.circles' must be 'dark-on-light' or 'light-on-dark', got {circ!r}")
        if (_is_num(t.get("pitch_mm")) and _is_num(t.get("diameter_mm"))
                and t["diameter_mm"] >= t["pitch_mm"]):
            probs.add("'target.diameter_mm' must be smaller than 'target.pitch_mm'")
        if not probs.items:
            target = CircleGridTarget(int(t["rows"]), int(t["cols"]), float(t["pitch_mm"]),
                                      float(t["diameter_mm"]), circ)
    sizes = {}
    for dev in ("camera", "projector"):
        d = doc.get(dev)
        ps = d.get("pixel_size_mm") if isinstance(d, dict) else None
        if (not isinstance(ps, list) or len(ps) != 2
                or not all(_is_num(x) and 0 < x < 1 for x in ps)):
            probs.add(f"'{dev}.pixel_size_mm' must be [du, dv] in mm (0 < du, dv < 1), got {ps!r}")
        else:
            sizes[dev] = (float(ps[0]), float(ps[1]))
    poses = doc.get("poses")
    if not isinstance(poses, list) or not poses:
        probs.add("'poses' must be a non-empty list of scan folder names")
        poses = []
    seen = set()
    for i, p in enumerate(poses):
        if folder is not None:
            ok = _check_rel_path(folder, p, f"poses[{i}]", probs, must_exist=False)
            if ok and not (folder / p / "scan.json").is_file():
                probs.add(f"poses[{i}]: {p!r} is not a scan folder (no scan.json)")
        elif not isinstance(p, str):
            probs.add(f"poses[{i}]: expected a folder name, got {p!r}")
        if isinstance(p, str):
            if p in seen:
                probs.add(f"poses[{i}]: {p!r} is listed twice")
            seen.add(p)
    ref = doc.get("reference_pose", poses[0] if poses else None)
    if ref not in poses:
        probs.add(f"'reference_pose' {ref!r} is not one of 'poses'")
    probs.raise_if_any()
    return CalibrationSetManifest(target=target, camera_pixel_size=sizes["camera"],
                                  projector_pixel_size=sizes["projector"],
                                  poses=tuple(poses), reference_pose=ref,
                                  folder=str(folder) if folder is not None else "")


def load_calibration_set(folder) -> CalibrationSetManifest:
    """Read and validate ``folder/calibration.json`` and each pose's ``scan.json``.

    Images are not decoded here; read each pose with :func:`read_scan`
    (``Path(folder) / pose``) when it is needed, so memory stays bounded.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder (a calibration set is a folder with "
                         "calibration.json)")
    path = folder / "calibration.json"
    if not path.is_file():
        raise InputError(f"{folder}: no calibration.json in this folder")
    man = parse_calibration_manifest(_read_json(path), folder=folder, where=str(path))
    for p in man.poses:
        load_scan_manifest(folder / p)
    return man


def write_calibration_manifest(folder, man: CalibrationSetManifest) -> None:
    """Write ``calibration.json`` into an existing folder (atomically)."""
    t = man.target
    doc = {"format": CALIB_FORMAT, "version": 1,
           "target": {"type": "circle-grid", "rows": t.rows, "cols": t.cols,
                      "pitch_mm": t.pitch_mm, "diameter_mm": t.diameter_mm,
                      "circles": t.circles},
           "camera": {"pixel_size_mm": list(man.camera_pixel_size)},
           "projector": {"pixel_size_mm": list(man.projector_pixel_size)},
           "poses": list(man.poses), "reference_pose": man.reference_pose}
    path = Path(folder) / "calibration.json"
    tmp = path.with_name(".calibration.json.part")
    tmp.write_text(json.dumps(doc, indent=2) + "\n")
    os.replace(tmp, path)
