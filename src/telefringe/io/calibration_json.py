"""Calibration sets (``calibration.json``, format ``telefringe-calibration-set`` v1, see
docs/formats.md): a folder of scans, one per target pose. Validated reading and atomic
writing of the manifest; the poses are read with :func:`telefringe.io.scan_json.read_scan`.

Devices: ``camera``, ``projector`` and, for two cameras, ``camera_2``, each
``{"model": "telecentric", "pixel_size_mm": [du, dv]}`` (the default model) or
``{"model": "pinhole"}``. A two-camera set may leave out ``projector`` (the projector
only codes the phase); each of its pose folders holds one scan per camera, in
``<pose>/camera/`` and ``<pose>/camera_2/``.
"""

from __future__ import annotations

from pathlib import Path

from telefringe.calibration.manifest import CalibrationSetManifest
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
from telefringe.io.atomic import write_json_atomic
from telefringe.io.errors import InputError
from telefringe.io.images import image_info
from telefringe.io.scan_json import load_scan_manifest, scan_image_names
from telefringe.targets.grid import CIRCLE_STYLES, CircleGridTarget

__all__ = ["CALIB_FORMAT", "parse_calibration_manifest", "load_calibration_set",
           "write_calibration_manifest"]

CALIB_FORMAT = "telefringe-calibration-set"

_CAL_KEYS = {"format", "version", "target", "camera", "camera_2", "projector", "poses",
             "reference_pose", "projector_side", "meta"}
#: Device models a calibration set may name.
DEVICE_MODELS = ("telecentric", "pinhole")
_SIDES = ("left", "right", "top", "bottom")
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
    probs = parse_header(doc, CALIB_FORMAT, _CAL_KEYS, where)
    t = doc.get("target")
    if not isinstance(t, dict):
        probs.add(f"'target' must be an object, got {_r(t)}")
    else:
        check_fields(t, _TARGET_KEYS, "target.", probs)
        if t.get("type") != "circle-grid":
            probs.add(f"'target.type' must be 'circle-grid', got {_r(t.get('type'))}")
        for nm in ("rows", "cols"):
            v = t.get(nm)
            if not is_int(v) or not 2 <= v <= 1000:
                probs.add(f"'target.{nm}' must be an integer in 2..1000, got {_r(v)}")
        for nm in ("pitch_mm", "diameter_mm"):
            v = t.get(nm)
            if not is_num(v) or v <= 0:
                probs.add(f"'target.{nm}' must be a positive number (mm), got {_r(v)}")
        circ = t.get("circles", "dark-on-light")
        if circ not in CIRCLE_STYLES:
            probs.add(f"'target.circles' must be 'dark-on-light' or 'light-on-dark', got "
                      f"{_r(circ)}")
        if (is_num(t.get("pitch_mm")) and is_num(t.get("diameter_mm"))
                and 0 < t["pitch_mm"] <= t["diameter_mm"]):
            probs.add("'target.diameter_mm' must be smaller than 'target.pitch_mm'")
    sizes: dict = {}
    models: dict = {}
    two = "camera_2" in doc
    for dev in ("camera", "camera_2", "projector"):
        if dev not in doc and (dev == "camera_2" or (dev == "projector" and two)):
            continue
        d = doc.get(dev)
        if not isinstance(d, dict):
            probs.add(f"'{dev}' must be an object {{\"model\": \"telecentric\", "
                      f"\"pixel_size_mm\": [du, dv]}} or {{\"model\": \"pinhole\"}}, "
                      f"got {_r(d)}")
            continue
        check_fields(d, {"model", "pixel_size_mm"}, f"{dev}.", probs)
        model = d.get("model", "telecentric")
        if model not in DEVICE_MODELS:
            probs.add(f"'{dev}.model' must be one of {', '.join(DEVICE_MODELS)}, got "
                      f"{_r(model)}")
            continue
        models[dev] = model
        ps = d.get("pixel_size_mm")
        if ps is None and model == "pinhole":
            continue
        if (not isinstance(ps, list) or len(ps) != 2
                or not all(is_num(x) and 0 < x < 1 for x in ps)):
            need = " (a telecentric device needs it)" if ps is None else ""
            probs.add(f"'{dev}.pixel_size_mm' must be [du, dv] in mm (0 < du, dv < 1), got "
                      f"{_r(ps)}{need}")
        else:
            sizes[dev] = (float(ps[0]), float(ps[1]))
    cameras = ("camera", "camera_2") if two else ("camera",)
    poses = doc.get("poses")
    if not isinstance(poses, list) or not poses:
        probs.add(f"'poses' must be a non-empty list of scan folder names, got {_r(poses)}")
        poses = []
    seen: dict[str, str] = {}
    for i, p in enumerate(poses):
        what = f"poses[{i}]"
        ok = check_rel_path(folder, p, what, probs, must_exist=folder is not None,
                             kind="folder")
        if ok is None:
            continue
        if ok[1] in seen:
            probs.add(f"{what}: {_r(p)} is the same folder as {seen[ok[1]]}")
            continue
        seen[ok[1]] = what
        if folder is None:
            continue
        if not two and not (folder / p / "scan.json").is_file():
            probs.add(f"{what}: {_r(p)} is not a scan folder (no scan.json)")
        for cam in cameras if two else ():
            sub = check_rel_path(folder, f"{p}/{cam}", f"{what} ({cam})", probs,
                                 kind="folder")
            if sub is not None and not (folder / p / cam / "scan.json").is_file():
                probs.add(f"{what}: {_r(p)}/{cam} is not a scan folder (no scan.json); a "
                          "two-camera set holds one scan per camera in <pose>/camera and "
                          "<pose>/camera_2")
    if "reference_pose" in doc:
        ref = doc["reference_pose"]
        if not isinstance(ref, str) or ref not in poses:
            probs.add(f"'reference_pose' {_r(ref)} is not one of 'poses'")
    else:
        ref = poses[0] if poses else None
    side = doc.get("projector_side")
    if side is not None and side not in _SIDES:
        probs.add(f"'projector_side' must be one of {', '.join(_SIDES)} (where the projector "
                  f"is, seen in the camera image), got {_r(side)}")
    probs.raise_if_any()
    target = CircleGridTarget(int(t["rows"]), int(t["cols"]), float(t["pitch_mm"]),
                              float(t["diameter_mm"]), t.get("circles", "dark-on-light"))
    return CalibrationSetManifest(target=target, camera_pixel_size=sizes.get("camera"),
                                  projector_pixel_size=sizes.get("projector"),
                                  poses=tuple(poses), reference_pose=ref,
                                  folder=str(folder) if folder is not None else "",
                                  models=models, pixel_sizes=sizes, projector_side=side)


def load_calibration_set(folder) -> CalibrationSetManifest:
    """Read and validate ``folder/calibration.json`` and each pose's ``scan.json``.

    Also checks that every pose was taken with the same projector size and the same
    camera image size (from the first image's header). Images are not decoded here;
    read each pose with :func:`read_scan` (``Path(folder) / pose``) when it is needed,
    so memory stays bounded.
    """
    folder, path = open_manifest(folder, "calibration.json", "calibration set")
    man = parse_calibration_manifest(read_json(path), folder=folder, where=str(path))
    for cam in man.cameras:
        ref_pose = ref = None
        for p in man.poses:
            sub = man.scan_folder(p, cam)
            pm = load_scan_manifest(folder / sub)
            first = scan_image_names(pm)[0]
            info = image_info(folder / sub / first)
            this = (pm.projector_width, pm.projector_height, info.cols, info.rows)
            if ref is None:
                ref_pose, ref = sub, this
            elif this != ref:
                raise InputError(
                    f"{path}: poses differ: {ref_pose} has a {ref[0]} x {ref[1]} projector "
                    f"and {ref[2]} x {ref[3]} images, {sub} has {this[0]} x {this[1]} and "
                    f"{this[2]} x {this[3]}")
    return man


def write_calibration_manifest(folder, man: CalibrationSetManifest) -> None:
    """Write ``calibration.json`` into an existing folder (atomically)."""
    t = man.target
    doc = {"format": CALIB_FORMAT, "version": 1,
           "target": {"type": "circle-grid", "rows": int(t.rows), "cols": int(t.cols),
                      "pitch_mm": float(t.pitch_mm), "diameter_mm": float(t.diameter_mm),
                      "circles": t.circles},
           "poses": list(man.poses), "reference_pose": man.reference_pose}
    for dev, model in man.models.items():
        entry: dict = {"model": model}
        if dev in man.pixel_sizes:
            entry["pixel_size_mm"] = [float(x) for x in man.pixel_sizes[dev]]
        doc[dev] = entry
    if man.projector_side is not None:
        doc["projector_side"] = man.projector_side
    write_json_atomic(Path(folder) / "calibration.json", doc, force=True)
