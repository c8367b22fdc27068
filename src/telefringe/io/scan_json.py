"""Scan folders (``scan.json``, format ``telefringe-scan`` v1, see docs/formats.md):
validated reading and atomic writing.

Every problem found in a manifest is reported, with the file it is in, as an
:class:`~telefringe.io.errors.InputError` (all problems of a manifest at once).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from telefringe.fringes.scan import GrayGroup, PhaseGroup, Scan, ScanManifest
from telefringe.io._manifest import (
    check_fields,
    check_rel_path,
    is_int,
    is_num,
    open_manifest,
    parse_header,
    read_json,
)
from telefringe.io._manifest import short_repr as _r
from telefringe.io.atomic import atomic_dir
from telefringe.io.errors import InputError
from telefringe.io.images import image_info, read_image, write_png

__all__ = [
    "SCAN_FORMAT",
    "MAX_STEPS",
    "MAX_SCAN_BYTES",
    "parse_scan_manifest",
    "load_scan_manifest",
    "read_scan",
    "write_scan",
    "scan_manifest_to_json",
    "scan_image_names",
    "read_capture",
]

SCAN_FORMAT = "telefringe-scan"


#: Most phase steps accepted in one group.
MAX_STEPS = 1000
#: Largest scan read into memory (bytes of decoded images), checked from the headers.
MAX_SCAN_BYTES = 8 * 1024**3

_PHASE_KEYS = {"type", "axis", "periods", "steps", "exposure", "offset", "images"}
_GRAY_KEYS = {"type", "axis", "bits", "complementary", "exposure", "images"}
_SCAN_KEYS = {"format", "version", "projector", "patterns", "white", "black", "meta",
              "capture", "saturation"}
#: 16-bit scans whose values never reach 2**_LOW_RANGE_BITS need ``saturation`` said.
_LOW_RANGE_BITS = 14


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
    probs = parse_header(doc, SCAN_FORMAT, _SCAN_KEYS, where)
    proj = doc.get("projector")
    pw = ph = None
    if not isinstance(proj, dict):
        probs.add("'projector' must be an object {\"width\": W, \"height\": H}, got "
                  f"{_r(proj)}")
    else:
        pw, ph = proj.get("width"), proj.get("height")
        for nm, val in (("width", pw), ("height", ph)):
            if not is_int(val) or val <= 0 or val > 100_000:
                probs.add(f"'projector.{nm}' must be an integer in 1..100000 (pixels), "
                          f"got {_r(val)}")
        check_fields(proj, {"width", "height"}, "projector.", probs)
    sizes = {"u": pw if is_int(pw) else None, "v": ph if is_int(ph) else None}
    pats = doc.get("patterns")
    groups: list = []
    seen_images: dict[str, str] = {}

    def check_image(name, what):
        ok = check_rel_path(folder, name, what, probs, must_exist=check_files)
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
        check_fields(g, _GRAY_KEYS if kind == "gray" else _PHASE_KEYS, f"{what}.", probs)
        axis = g.get("axis")
        if axis not in ("u", "v"):
            probs.add(f"{what}: 'axis' must be 'u' or 'v', got {_r(axis)}")
        length = sizes.get(axis) if axis in ("u", "v") else None
        exposure = g.get("exposure", 1.0)
        if not is_num(exposure) or exposure <= 0:
            probs.add(f"{what}: 'exposure' must be a positive number, got {_r(exposure)}")
        images = g.get("images")
        if not isinstance(images, list):
            probs.add(f"{what}: 'images' must be a list of file names, got {_r(images)}")
            images = []
        if kind == "phase":
            periods, steps = g.get("periods"), g.get("steps")
            offset = g.get("offset", 0.0)
            if not is_int(periods) or periods < 1:
                probs.add(f"{what}: 'periods' must be an integer >= 1, got {_r(periods)}")
            elif length is not None and 2 * periods > length:
                probs.add(f"{what}: 'periods' {periods} is more than the projector's "
                          f"{'width' if axis == 'u' else 'height'} / 2 = {length / 2:g} "
                          "(a period must span at least 2 projector pixels)")
            if not is_int(steps) or not 3 <= steps <= MAX_STEPS:
                probs.add(f"{what}: 'steps' must be an integer in 3..{MAX_STEPS}, got "
                          f"{_r(steps)}")
            if not is_num(offset):
                probs.add(f"{what}: 'offset' must be a finite number (radians), got "
                          f"{_r(offset)}")
            need = steps if is_int(steps) and 3 <= steps <= MAX_STEPS else None
            counted = "'steps'"
        else:
            bits, comp = g.get("bits"), g.get("complementary", False)
            if not is_int(bits) or not 1 <= bits <= 16:
                probs.add(f"{what}: 'bits' must be an integer in 1..16, got {_r(bits)}")
            if not isinstance(comp, bool):
                probs.add(f"{what}: 'complementary' must be true or false, got {_r(comp)}")
            need = ((bits + (1 if comp is True else 0)) if is_int(bits) and 1 <= bits <= 16
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
    sat = doc.get("saturation")
    if sat is not None and not (is_int(sat) and 1 <= sat <= 65535):
        probs.add("'saturation' must be an integer in 1..65535 (the stored pixel value at "
                  f"which the camera saturates), got {_r(sat)}")
    if "capture" in doc:
        listed = {n for g in groups for n in g.images} | {
            v for v in (extras.get("white"), extras.get("black")) if v}
        _check_capture(doc["capture"], listed, probs)
    probs.raise_if_any()
    return ScanManifest(projector_width=int(pw), projector_height=int(ph), groups=tuple(groups),
                        white=extras.get("white"), black=extras.get("black"))


def _check_capture(cap, images: set, probs) -> None:
    """The optional ``capture`` block (provenance of a capture, docs/formats.md): the
    fields described there are checked; others are kept as they are."""
    w = "'capture'"
    if not isinstance(cap, dict):
        probs.add(f"{w} must be an object, got {_r(cap)}")
        return
    if cap.get("version") != 1:
        probs.add(f"{w}.version must be 1, got {_r(cap.get('version'))}")
    if cap.get("mode") not in ("streamed", "sequenced"):
        probs.add(f"{w}.mode must be 'streamed' or 'sequenced', got {_r(cap.get('mode'))}")
    for dev in ("camera", "projector"):
        d = cap.get(dev)
        if not isinstance(d, dict) or not isinstance(d.get("driver"), str):
            probs.add(f"{w}.{dev} must be an object with a 'driver' (string), got {_r(d)}")
            continue
        for key in ("model", "serial", "address", "vendor"):
            if key in d and not isinstance(d[key], str):
                probs.add(f"{w}.{dev}.{key} must be a string, got {_r(d[key])}")
    settings = cap.get("settings")
    if not isinstance(settings, list) or not settings:
        probs.add(f"{w}.settings must be a non-empty list (one per exposure), got "
                  f"{_r(settings)}")
    else:
        for i, st in enumerate(settings):
            if not isinstance(st, dict):
                probs.add(f"{w}.settings[{i}] must be an object, got {_r(st)}")
                continue
            if not is_num(st.get("exposure_s")) or st["exposure_s"] <= 0:
                probs.add(f"{w}.settings[{i}].exposure_s must be a positive number (s), got "
                          f"{_r(st.get('exposure_s'))}")
            if not isinstance(st.get("pixel_format"), str):
                probs.add(f"{w}.settings[{i}].pixel_format must be a string, got "
                          f"{_r(st.get('pixel_format'))}")
            roi = st.get("roi")
            if roi is not None and not (isinstance(roi, list) and len(roi) == 4
                                        and all(is_int(v) and v >= 0 for v in roi)):
                probs.add(f"{w}.settings[{i}].roi must be [x, y, width, height] (pixels), got "
                          f"{_r(roi)}")
    lat = cap.get("latency")
    if lat is not None and not (isinstance(lat, dict) and is_num(lat.get("latency_s"))
                                and lat["latency_s"] >= 0):
        probs.add(f"{w}.latency must be an object with 'latency_s' >= 0 (s), got {_r(lat)}")
    retries = cap.get("retries", 0)
    if not is_int(retries) or retries < 0:
        probs.add(f"{w}.retries must be an integer >= 0, got {_r(retries)}")
    frames = cap.get("frames")
    if not isinstance(frames, list):
        probs.add(f"{w}.frames must be a list (one entry per image), got {_r(frames)}")
        return
    seen = set()
    for i, f in enumerate(frames):
        fw = f"{w}.frames[{i}]"
        if not isinstance(f, dict):
            probs.add(f"{fw} must be an object, got {_r(f)}")
            continue
        name = f.get("image")
        if not isinstance(name, str) or (images and name not in images):
            probs.add(f"{fw}.image must name one of the scan's images, got {_r(name)}")
        elif name in seen:
            probs.add(f"{fw}.image {_r(name)} is listed twice")
        seen.add(name)
        if not is_int(f.get("id")):
            probs.add(f"{fw}.id must be an integer (the camera's frame id), got "
                      f"{_r(f.get('id'))}")
        ts = f.get("timestamp_ns")
        if ts is not None and not is_int(ts):
            probs.add(f"{fw}.timestamp_ns must be an integer or null, got {_r(ts)}")
        att = f.get("attempts", 1)
        if not is_int(att) or att < 1:
            probs.add(f"{fw}.attempts must be an integer >= 1, got {_r(att)}")


def read_capture(folder) -> dict | None:
    """The validated ``capture`` block of ``folder/scan.json`` (None when it has none)."""
    _, _, doc = _load_scan(folder)
    cap = doc.get("capture")
    return dict(cap) if isinstance(cap, dict) else None


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


def _load_scan(folder) -> tuple[Path, ScanManifest, dict]:
    folder, path = open_manifest(folder, "scan.json", "scan")
    doc = read_json(path)
    return folder, parse_scan_manifest(doc, folder=folder, where=str(path)), doc


def load_scan_manifest(folder) -> ScanManifest:
    """Read and validate ``folder/scan.json`` (image files checked to exist, not decoded)."""
    return _load_scan(folder)[1]


def scan_image_names(man: ScanManifest) -> list[str]:
    """Every image file of a manifest (groups in order, then white and black)."""
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
        Its ``max_value`` is the manifest's ``saturation`` when given, else 255 for
        8-bit and 65535 for 16-bit images; its ``meta`` is the manifest's ``meta``
        object (or empty).

    Raises
    ------
    InputError
        A bad manifest, or images that are missing, unreadable, too large, or differ in
        size or bit depth; pixel values above ``saturation``; 16-bit images without
        ``saturation`` whose values show a camera that cannot reach 65535 (see
        :func:`_saturation`). Sizes and bit depths are compared from the headers before
        any image is decoded.
    """
    folder, man, doc = _load_scan(folder)
    names = scan_image_names(man)
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
    max_value = _saturation(folder, doc.get("saturation"), first.bits, list(images.values()))
    return Scan(manifest=man, stacks=stacks,
                white=images.get(man.white) if man.white else None,
                black=images.get(man.black) if man.black else None,
                max_value=max_value, source=str(folder), meta=dict(doc.get("meta", {})))


def _saturation(folder: Path, given, bits: int, images: list) -> float:
    """The stored value at which the scan's camera saturates (``Scan.max_value``).

    ``given``: scan.json's ``saturation`` (validated) or None: then 255 for 8-bit images
    and 65535 for 16-bit ones, unless the 16-bit values show that the camera cannot reach
    65535 (saturated pixels would then pass as valid ones): values that never reach
    2**14 (a 10-, 12- or 14-bit camera's values stored as they are, or an 8-bit
    camera's), or whose lowest bits are always 0 (a 10-14-bit camera's values shifted
    left, saturating below 65535). Those raise an InputError asking for ``saturation``.
    """
    if given is None and bits == 8:
        return 255.0
    top = max(int(im.max()) for im in images)
    if given is not None:
        if bits == 8 and given > 255:
            raise InputError(f"{folder}/scan.json: 'saturation' {given} is above 255, the "
                             "largest value of its 8-bit images")
        if top > given:
            raise InputError(f"{folder}: pixel values reach {top}, above scan.json's "
                             f"'saturation' {given} (the stored value at which the camera "
                             "saturates): correct it")
        return float(given)
    how = ('give the stored value at which the camera saturates as "saturation" in '
           "scan.json")
    if top < 2 ** _LOW_RANGE_BITS:
        raise InputError(
            f"{folder}: these 16-bit images never exceed {top} (of 65535): the values of a "
            "10-, 12- or 14-bit camera stored as they are (saturating at 1023, 4095 or "
            f"16383)? Saturated pixels cannot be told from good ones: {how} (e.g. 4095 "
            "for 12-bit values; 65535 if this is a 16-bit scan that is just this dark)")
    used = 0
    for im in images:
        used |= int(np.bitwise_or.reduce(im, axis=None))
    zeros = (used & -used).bit_length() - 1      # trailing zero bits of every value
    if zeros >= 2:
        full = (65535 >> zeros) << zeros
        raise InputError(
            f"{folder}: the lowest {zeros} bits of every pixel value of these 16-bit images "
            f"are 0: a {16 - zeros}-bit camera's values shifted left by {zeros}, which "
            f"saturate at {full}, not 65535? Saturated pixels cannot be told from good "
            f"ones: {how} (e.g. {full})")
    return 65535.0


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


def write_scan(folder, scan: Scan, *, force: bool = False, capture: dict | None = None
               ) -> Path:
    """Write a scan folder atomically (PNG images + ``scan.json``).

    ``capture``: the provenance of a capture (the optional ``capture`` block, see
    docs/formats.md), written as is after validation.

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
    full = 255.0 if all(s.dtype == np.uint8 for s in scan.stacks) else 65535.0
    if float(scan.max_value) != full:     # a camera saturating below its images' maximum
        doc["saturation"] = int(scan.max_value)
    if capture is not None:
        doc["capture"] = capture
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


