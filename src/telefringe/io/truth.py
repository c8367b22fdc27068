"""Ground truth of the virtual rig on disk, kept apart from the scan folders.

A truth folder (e.g. ``OUT/truth/``) holds, per rendered scan ``NAME``:

- ``NAME.npz``: arrays ``xyz_world`` (rows, cols, 3) mm (NaN where not lit/visible),
  ``u_p``, ``v_p`` (rows, cols) projector px (NaN where not lit), ``lit``, ``visible``
  (bool), ``part`` (int), and the array-valued features as ``feature__KEY``. The
  per-pixel float arrays are stored as float32 (relative precision 6e-8: about 2 nm on
  ``xyz_world``, 5e-5 px on ``u_p``; a full-resolution pose is ~15 MB instead of 60);
  features keep float64;
- ``NAME.json``: the scene's features (readable: circle centres, step heights, sphere,
  ball apexes, ...) and, when given, the true rig.

and ``rig_true.json``: the virtual rig's true camera and projector (intrinsics, rotation
vector, translation) and photometry. A truth folder is refused inside a scan folder (a
folder holding ``scan.json``), so a decoder can never read the answer by accident.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from telefringe.io import _npz
from telefringe.io.atomic import atomic_file, write_json_atomic
from telefringe.io.errors import InputError
from telefringe.io.jsonable import to_jsonable

__all__ = ["write_truth", "read_truth", "truth_features_to_json", "true_rig_to_json",
           "write_rig_truth", "TRUTH_FORMAT"]

TRUTH_FORMAT = "telefringe-truth"
_ARRAYS = ("xyz_world", "u_p", "v_p", "lit", "visible", "part")


def truth_features_to_json(features: dict) -> dict:
    """Features as plain JSON values (arrays become nested lists, NaN becomes null)."""
    return to_jsonable(features)


def _device_state(dev) -> dict:
    """A device's true state as the simulator holds it: every field of its intrinsics (the
    dataclass as it is, whatever the model) and its pose. The readable, loadable form of a
    device is rig.json's (:mod:`telefringe.io.rig_json`)."""
    return {"model": dev.model, "intrinsics": to_jsonable(dev.intrinsics),
            "R_dev_world": dev.R_dev_world, "rotvec": dev.rotvec, "t_dev_mm": dev.t_dev,
            "axis_world": dev.R_dev_world[2]}


def true_rig_to_json(vrig) -> dict:
    """The ``rig_true.json`` document of a :class:`~telefringe.simulate.presets.VirtualRig`:
    its true devices, photometry and target."""
    cams = {name: _device_state(dev) for name, dev in vrig.rig.cameras.items()}
    return to_jsonable({
        "format": TRUTH_FORMAT + "-rig", "version": 1, "name": vrig.name,
        **cams, "projector": _device_state(vrig.projector),
        "photometry": vrig.photometry, "target": vrig.target,
        "world_frame": "calibration target at its reference pose (x along columns, y along "
                       "rows, z toward the camera)",
    })


def _check_not_in_scan(folder: Path) -> None:
    for p in (folder, *folder.resolve().parents):
        if (p / "scan.json").is_file():
            raise InputError(f"{folder}: refusing to write ground truth inside a scan folder "
                             f"({p} holds scan.json)")


def write_rig_truth(folder, vrig, *, force: bool = True) -> Path:
    """Write ``folder/rig_true.json`` (the folder must exist)."""
    folder = Path(folder)
    _check_not_in_scan(folder)
    path = folder / "rig_true.json"
    write_json_atomic(path, true_rig_to_json(vrig), force=force)
    return path


def write_truth(folder, name: str, truth, *, extra: dict | None = None,
                force: bool = True) -> tuple[Path, Path]:
    """Write ``folder/NAME.npz`` and ``folder/NAME.json`` (atomically each).

    ``truth``: a :class:`~telefringe.simulate.render.Truth`. ``extra``: more JSON to
    keep beside the features (e.g. the pose). The folder is created if needed; it must
    not be (inside) a scan folder.
    """
    folder = Path(folder)
    if not name or "/" in name or name.startswith("."):
        raise ValueError(f"bad truth name {name!r}")
    folder.mkdir(parents=True, exist_ok=True)
    _check_not_in_scan(folder)
    arrays = {}
    for k in _ARRAYS:
        v = getattr(truth, k)
        if v is not None:
            v = np.asarray(v)
            arrays[k] = v.astype(np.float32) if v.dtype.kind == "f" else v
    for k, v in truth.features.items():
        if isinstance(v, np.ndarray):
            arrays[f"feature__{k}"] = v
    npz = folder / f"{name}.npz"
    with atomic_file(npz, force=force) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)
    doc = {"format": TRUTH_FORMAT, "version": 1, "name": name,
           "shape": list(truth.lit.shape), "arrays": f"{name}.npz",
           "lit_pixels": int(np.count_nonzero(truth.lit)),
           "features": truth_features_to_json(truth.features)}
    if extra:
        doc.update(to_jsonable(extra))
    js = folder / f"{name}.json"
    write_json_atomic(js, doc, force=force)
    return npz, js


def read_truth(folder, name: str):
    """Read ``folder/NAME.npz`` + ``NAME.json`` back into a
    :class:`~telefringe.simulate.render.Truth` (array features from the npz, the rest
    from the JSON)."""
    from telefringe.simulate.render import Truth

    folder = Path(folder)
    npz, js = folder / f"{name}.npz", folder / f"{name}.json"
    for p in (npz, js):
        if not p.is_file():
            raise InputError(f"{p}: ground truth file not found")
    try:
        doc = json.loads(js.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"{js}: cannot read ground truth ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != TRUTH_FORMAT:
        raise InputError(f"{js}: not a telefringe ground-truth file")
    arrays = _npz.load(npz, "ground truth")
    missing = [k for k in ("xyz_world", "u_p", "v_p", "lit") if k not in arrays]
    if missing:
        raise InputError(f"{npz}: missing arrays {missing}")
    features = dict(doc.get("features", {}))
    for k, v in arrays.items():
        if k.startswith("feature__"):
            features[k[len("feature__"):]] = v
    return Truth(xyz_world=arrays["xyz_world"].astype(float), u_p=arrays["u_p"].astype(float),
                 v_p=arrays["v_p"].astype(float),
                 lit=arrays["lit"].astype(bool), features=features,
                 visible=arrays.get("visible"), part=arrays.get("part"))
