"""``rig.json``: a calibrated telecentric rig (format ``telefringe-rig``, version 1).

A person can read it; it holds both devices, the world frame and the calibration
report, with what is needed to recompute uncertainties (the rig parameters' covariance,
the observations and the target poses). Layout::

    {
      "format": "telefringe-rig", "version": 1,
      "units": {"length": "mm", "image": "px", "angle": "rad"},
      "model": "<the projection model, in words>",
      "world_frame": {"definition": "...", "reference_pose": "pose_00"},
      "camera": {
        "width": 1280, "height": 1024, "pixel_size_mm": [0.0052, 0.0052],
        "m": 0.1597, "principal_point_px": [474.9, 513.1],
        "distortion": {"k1": 1.5e-4, "s1": -2e-5, "s2": 3e-5},
        "rotation_vector": [rx, ry, rz], "t_mm": [tx, ty]
      },
      "projector": { ... the same keys ... },
      "calibration": {                       # optional (a hand-made rig.json may omit it)
        "rms_px": {"camera": ..., "projector": ...},
        "sigma_px": {"camera": ..., "projector": ...},
        "principal_point": "estimate", "principal_point_weak": [false, false],
        "mirror": "projector_side=right",
        "parameters": {"names": ["camera.m", ...], "values": [...], "std": [...],
                       "covariance": [[...] x n]},   # n = both devices' parameters
        "grid_shape": [9, 11], "points_target_mm": [[x, y, 0], ...],
        "poses": [{"name": "pose_00", "used": true, "rotation_vector": [...],
                   "t_mm": [...], "rms_px": [camera, projector]}, ...],
        "observations": {"camera": [...], "projector": [...]},   # (poses, points, 2)
        "residuals": {"camera": [...], "projector": [...]},      # predicted - observed
        "outliers": [{"device": "camera", "pose": "pose_03", "marker": [1, 3],
                      "residual_px": [0.8, -0.5]}],
        "warnings": ["..."]
      },
      "phase_errors": {                      # optional: the projector nonlinearity
        "model": "<in words>",
        "groups": [{"axis": "u", "periods": 64, "steps": 4, "harmonics": [4, 8],
                    "cos_rad": [...], "sin_rad": [...]}, ...]
      }
    }

Devices follow :mod:`telefringe.devices.telecentric`: ``[xu, yu] = m (R[0:2] X + t)`` (sensor mm),
radial + thin-prism distortion on the sensor plane, ``u = u0 + xd / du``; ``R`` is the
rotation of ``rotation_vector`` (world -> device). Missing values in the report's
arrays (unobserved markers, fixed parameters) are ``null``; anything else that is not
a finite number is refused on loading.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from telefringe.calibration.device import Outlier
from telefringe.calibration.rig import RigCalibration, rig_parameter_names
from telefringe.devices.rig import Rig
from telefringe.devices.telecentric import Intrinsics, TelecentricDevice
from telefringe.geometry.so3 import rotation_from_rotvec, rotvec_from_rotation
from telefringe.io.atomic import write_json_atomic
from telefringe.io.errors import InputError
from telefringe.io.jsonable import number_or_none, to_jsonable

__all__ = ["RIG_FORMAT", "RIG_VERSION", "save_rig", "load_rig", "rig_to_json", "rig_from_json",
           "bare_rig_json"]

RIG_FORMAT = "telefringe-rig"
RIG_VERSION = 1
_MODEL = ("telecentric (scaled orthographic): [xu, yu] = m (R[0:2] X + t) in sensor mm; "
          "r2 = xu^2 + yu^2; xd = xu + k1 xu r2 + s1 r2; yd = yu + k1 yu r2 + s2 r2; "
          "u = u0 + xd / du, v = v0 + yd / dv; R = rotation of rotation_vector (world -> "
          "device); no tz")
_WORLD = ("the calibration target at the reference pose: x along the grid's columns, y "
          "along its rows (circle (row, col) at (col * pitch, row * pitch, 0)), z = x cross y "
          "toward the camera")


_PHASE_MODEL = ("projector nonlinearity per fringe group: measured wrapped phase = phi + "
                "sum_m cos_rad[m] cos(harmonics[m] phi) + sin_rad[m] sin(harmonics[m] phi), "
                "phi the true wrapped phase of the group (rad)")


# --------------------------------------------------------------------------- writing
def _arr(a) -> list | float | None:
    """Nested lists of floats with None for NaN (a float or None for a scalar)."""
    return to_jsonable(np.asarray(a, dtype=float))


def _device_json(dev: TelecentricDevice) -> dict:
    k = dev.intrinsics
    return {"width": int(k.width), "height": int(k.height),
            "pixel_size_mm": [float(k.du), float(k.dv)], "m": float(k.m),
            "principal_point_px": [float(k.u0), float(k.v0)],
            "distortion": {"k1": float(k.k1), "s1": float(k.s1), "s2": float(k.s2)},
            "rotation_vector": [float(v) for v in rotvec_from_rotation(dev.R_dev_world)],
            "t_mm": [float(v) for v in dev.t_dev]}


def rig_to_json(calib: RigCalibration) -> dict:
    """The ``rig.json`` document (a dict) of a calibration."""
    poses = []
    for i, name in enumerate(calib.pose_names):
        used = bool(calib.used[i])
        poses.append({
            "name": name, "used": used,
            "rotation_vector": ([float(v) for v in rotvec_from_rotation(calib.R_world_target[i])]
                                if used else None),
            "t_mm": _arr(calib.t_world_target[i]) if used else None,
            "rms_px": _arr(calib.rms_per_pose[i])})
    report = {
        "rms_px": {"camera": number_or_none(calib.rms_camera),
                   "projector": number_or_none(calib.rms_projector)},
        "sigma_px": {"camera": number_or_none(calib.sigma_camera),
                     "projector": number_or_none(calib.sigma_projector)},
        "principal_point": calib.principal_point,
        "principal_point_weak": [bool(v) for v in calib.principal_point_weak],
        "mirror": calib.mirror,
        "parameters": {"names": list(calib.parameter_names), "values": _arr(calib.parameters),
                       "std": _arr(calib.std), "covariance": _arr(calib.covariance)},
        "grid_shape": list(calib.grid_shape) if calib.grid_shape is not None else None,
        "points_target_mm": _arr(calib.points_target),
        "poses": poses,
        "observations": {"camera": _arr(calib.camera_observations),
                         "projector": _arr(calib.projector_observations)},
        "residuals": {"camera": _arr(calib.residuals_camera),
                      "projector": _arr(calib.residuals_projector)},
        "outliers": [{"device": o.device, "pose": o.pose, "marker": list(o.marker),
                      "residual_px": [float(v) for v in o.residual]} for o in calib.outliers],
        "warnings": list(calib.warnings),
    }
    doc = bare_rig_json(calib.rig, reference_pose=calib.reference_pose,
                        phase_errors=getattr(calib, "phase_errors", None))
    doc["calibration"] = report
    return doc


def bare_rig_json(rig: Rig, *, reference_pose: str = "", phase_errors: dict | None = None
                  ) -> dict:
    """A ``rig.json`` document (a dict) of both devices without a calibration report (the
    format allows leaving it out: a rig known otherwise, e.g. a simulation's truth), with
    the projector's nonlinearity models ``(axis, periods, steps) -> PhaseErrorModel``
    when given."""
    doc = {"format": RIG_FORMAT, "version": RIG_VERSION,
           "units": {"length": "mm", "image": "px", "angle": "rad"},
           "model": _MODEL,
           "world_frame": {"definition": _WORLD, "reference_pose": reference_pose},
           "camera": _device_json(rig.camera), "projector": _device_json(rig.projector)}
    if phase_errors:
        doc["phase_errors"] = _phase_errors_json(phase_errors)
    return doc


def _phase_errors_json(models: dict) -> dict:
    """The ``phase_errors`` block of rig.json for ``(axis, periods, steps) ->
    PhaseErrorModel`` (see docs/formats.md)."""
    return {"model": _PHASE_MODEL,
            "groups": [{"axis": axis, "periods": int(periods), "steps": int(steps),
                        "harmonics": [int(h) for h in m.harmonics],
                        "cos_rad": [float(v) for v in m.cos_coef],
                        "sin_rad": [float(v) for v in m.sin_coef]}
                       for (axis, periods, steps), m in sorted(models.items())]}


def save_rig(path, calib: RigCalibration, *, force: bool = False) -> Path:
    """Write ``calib`` to ``path`` as ``rig.json`` (atomically; an existing file is
    replaced only with ``force``). Returns the path."""
    path = Path(path)
    write_json_atomic(path, rig_to_json(calib), force=force)
    return path


# --------------------------------------------------------------------------- reading
class _Reader:
    def __init__(self, where: str):
        self.where = where

    def fail(self, key: str, msg: str):
        raise InputError(f"{self.where}: '{key}' {msg}")

    def get(self, d, key: str, path: str):
        if not isinstance(d, dict) or key not in d:
            self.fail(path, "is missing")
        return d[key]

    def number(self, d, key: str, path: str, *, positive=False) -> float:
        v = self.get(d, key, path)
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            self.fail(path, f"must be a finite number, got {v!r}")
        if positive and v <= 0:
            self.fail(path, f"must be > 0, got {v!r}")
        return float(v)

    def vector(self, d, key: str, path: str, n: int, *, positive=False) -> np.ndarray:
        v = self.get(d, key, path)
        if not isinstance(v, list) or len(v) != n:
            self.fail(path, f"must be a list of {n} numbers, got {v!r}")
        for j, x in enumerate(v):
            if isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(x):
                self.fail(f"{path}[{j}]", f"must be a finite number, got {x!r}")
            if positive and x <= 0:
                self.fail(f"{path}[{j}]", f"must be > 0, got {x!r}")
        return np.array(v, dtype=float)

    def array(self, v, path: str, shape) -> np.ndarray:
        """Nested lists (None allowed = NaN) of the given shape (-1: any)."""
        try:
            a = np.array([np.nan if x is None else x for x in _flatten(v)], dtype=float)
        except (TypeError, ValueError):
            self.fail(path, "must be nested lists of numbers (or null)")
        if any(isinstance(x, bool) or (x is not None and not isinstance(x, int | float))
               for x in _flatten(v)):
            self.fail(path, "must be nested lists of numbers (or null)")
        if np.any(np.isinf(a)) or any(isinstance(x, float) and math.isnan(x)
                                      for x in _flatten(v)):
            self.fail(path, "holds NaN or infinity (write null for a missing value)")
        got = _shape(v)
        if got is None or len(got) != len(shape) or any(
                s != -1 and s != g for s, g in zip(shape, got, strict=True)):
            self.fail(path, f"must have shape {tuple(shape)}, got {got}")
        return a.reshape(got)


def _flatten(v):
    if isinstance(v, list):
        for x in v:
            yield from _flatten(x)
    else:
        yield v


def _shape(v):
    """Shape of regular nested lists, or None if ragged."""
    if not isinstance(v, list):
        return ()
    if not v:
        return (0,)
    subs = [_shape(x) for x in v]
    if any(s is None for s in subs) or len(set(subs)) != 1:
        return None
    return (len(v),) + subs[0]


def _device(r: _Reader, doc, name: str) -> TelecentricDevice:
    d = r.get(doc, name, name)
    if not isinstance(d, dict):
        r.fail(name, "must be an object")
    w = r.get(d, "width", f"{name}.width")
    h = r.get(d, "height", f"{name}.height")
    for key, v in (("width", w), ("height", h)):
        if isinstance(v, bool) or not isinstance(v, int) or not 0 < v <= 100_000:
            r.fail(f"{name}.{key}", f"must be a positive integer, got {v!r}")
    du, dv = r.vector(d, "pixel_size_mm", f"{name}.pixel_size_mm", 2, positive=True)
    m = r.number(d, "m", f"{name}.m", positive=True)
    u0, v0 = r.vector(d, "principal_point_px", f"{name}.principal_point_px", 2)
    dist = r.get(d, "distortion", f"{name}.distortion")
    k1 = r.number(dist, "k1", f"{name}.distortion.k1")
    s1 = r.number(dist, "s1", f"{name}.distortion.s1")
    s2 = r.number(dist, "s2", f"{name}.distortion.s2")
    rv = r.vector(d, "rotation_vector", f"{name}.rotation_vector", 3)
    t = r.vector(d, "t_mm", f"{name}.t_mm", 2)
    try:
        intr = Intrinsics(m=m, du=du, dv=dv, u0=u0, v0=v0, k1=k1, s1=s1, s2=s2, width=w,
                          height=h)
        return TelecentricDevice(intr, rotation_from_rotvec(rv), t)
    except ValueError as exc:
        r.fail(name, f"is not a valid device: {exc}")


def rig_from_json(doc, *, where: str = "rig.json") -> RigCalibration:
    """Validate a parsed ``rig.json`` document and return the :class:`RigCalibration`.

    Raises :class:`~telefringe.io.errors.InputError` naming ``where`` and the key.
    """
    r = _Reader(where)
    if not isinstance(doc, dict):
        raise InputError(f"{where}: expected a JSON object at the top level")
    if doc.get("format") != RIG_FORMAT:
        r.fail("format", f"must be {RIG_FORMAT!r}, got {doc.get('format')!r}")
    if doc.get("version") != RIG_VERSION:
        r.fail("version", f"{doc.get('version')!r} is not supported (this telefringe reads "
                          f"{RIG_VERSION})")
    rig = Rig(_device(r, doc, "camera"), _device(r, doc, "projector"))
    world = r.get(doc, "world_frame", "world_frame")
    ref = world.get("reference_pose", "") if isinstance(world, dict) else ""
    if not isinstance(ref, str):
        r.fail("world_frame.reference_pose", f"must be a string, got {ref!r}")
    phase_errors = _phase_errors(r, doc.get("phase_errors"))
    rep = doc.get("calibration")
    expected = rig_parameter_names(rig)
    n = len(expected)
    if rep is None:
        return RigCalibration(
            rig=rig, pose_names=(), reference_pose=ref, used=np.zeros(0, dtype=bool),
            R_world_target=np.zeros((0, 3, 3)), t_world_target=np.zeros((0, 3)),
            points_target=np.zeros((0, 3)), grid_shape=None,
            parameter_names=expected, parameters=_params_of(rig),
            covariance=np.full((n, n), np.nan),
            std=np.full(n, np.nan), sigma_camera=float("nan"), sigma_projector=float("nan"),
            residuals_camera=np.zeros((0, 0, 2)), residuals_projector=np.zeros((0, 0, 2)),
            rms_camera=float("nan"), rms_projector=float("nan"),
            rms_per_pose=np.zeros((0, 2)), outliers=(),
            camera_observations=np.zeros((0, 0, 2)),
            projector_observations=np.zeros((0, 0, 2)), principal_point="unknown",
            principal_point_weak=(False, False), mirror="unknown", warnings=(),
            phase_errors=phase_errors)
    if not isinstance(rep, dict):
        r.fail("calibration", "must be an object")
    c = "calibration"
    rms = r.get(rep, "rms_px", f"{c}.rms_px")
    sig = r.get(rep, "sigma_px", f"{c}.sigma_px")
    par = r.get(rep, "parameters", f"{c}.parameters")
    names = r.get(par, "names", f"{c}.parameters.names")
    if names != list(expected):
        r.fail(f"{c}.parameters.names", f"must be {list(expected)} (the devices' parameters)")
    values = r.array(r.get(par, "values", f"{c}.parameters.values"),
                     f"{c}.parameters.values", (n,))
    std = r.array(r.get(par, "std", f"{c}.parameters.std"), f"{c}.parameters.std", (n,))
    cov = r.array(r.get(par, "covariance", f"{c}.parameters.covariance"),
                  f"{c}.parameters.covariance", (n, n))
    pts = r.array(r.get(rep, "points_target_mm", f"{c}.points_target_mm"),
                  f"{c}.points_target_mm", (-1, 3))
    if np.any(np.isnan(pts)):
        r.fail(f"{c}.points_target_mm", "must not hold null")
    gs = rep.get("grid_shape")
    if gs is not None and (not isinstance(gs, list) or len(gs) != 2 or not all(
            isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in gs)
            or gs[0] * gs[1] != pts.shape[0]):
        r.fail(f"{c}.grid_shape", f"must be [rows, cols] with rows * cols = "
                                  f"{pts.shape[0]} points, got {gs!r}")
    poses = r.get(rep, "poses", f"{c}.poses")
    if not isinstance(poses, list):
        r.fail(f"{c}.poses", "must be a list")
    n_p, n_k = len(poses), pts.shape[0]
    names_p, used = [], np.zeros(n_p, dtype=bool)
    R_all = np.full((n_p, 3, 3), np.nan)
    T_all = np.full((n_p, 3), np.nan)
    rms_pose = np.full((n_p, 2), np.nan)
    for i, p in enumerate(poses):
        path = f"{c}.poses[{i}]"
        nm = r.get(p, "name", f"{path}.name")
        if not isinstance(nm, str):
            r.fail(f"{path}.name", f"must be a string, got {nm!r}")
        names_p.append(nm)
        u = r.get(p, "used", f"{path}.used")
        if not isinstance(u, bool):
            r.fail(f"{path}.used", f"must be true or false, got {u!r}")
        used[i] = u
        if u:
            R_all[i] = rotation_from_rotvec(r.vector(p, "rotation_vector",
                                                     f"{path}.rotation_vector", 3))
            T_all[i] = r.vector(p, "t_mm", f"{path}.t_mm", 3)
        rms_pose[i] = r.array(r.get(p, "rms_px", f"{path}.rms_px"), f"{path}.rms_px", (2,))
    if ref and ref not in names_p:
        r.fail("world_frame.reference_pose", f"{ref!r} is not one of the poses")
    obs = r.get(rep, "observations", f"{c}.observations")
    res = r.get(rep, "residuals", f"{c}.residuals")
    arrays = {}
    for grp, d in (("observations", obs), ("residuals", res)):
        for dev in ("camera", "projector"):
            arrays[grp, dev] = r.array(r.get(d, dev, f"{c}.{grp}.{dev}"), f"{c}.{grp}.{dev}",
                                       (n_p, n_k, 2) if n_p else (-1,))
            if not n_p:
                arrays[grp, dev] = np.zeros((0, n_k, 2))
    outs = []
    for j, o in enumerate(r.get(rep, "outliers", f"{c}.outliers") or []):
        path = f"{c}.outliers[{j}]"
        try:
            outs.append(Outlier(str(o["device"]), str(o["pose"]),
                                (int(o["marker"][0]), int(o["marker"][1])),
                                (float(o["residual_px"][0]), float(o["residual_px"][1]))))
        except (KeyError, TypeError, IndexError, ValueError):
            r.fail(path, "must be {device, pose, marker: [row, col], residual_px: [du, dv]}")
    warns = rep.get("warnings", [])
    if not isinstance(warns, list) or not all(isinstance(w, str) for w in warns):
        r.fail(f"{c}.warnings", "must be a list of strings")
    weak = rep.get("principal_point_weak", [False, False])
    if not (isinstance(weak, list) and len(weak) == 2 and all(isinstance(v, bool) for v in weak)):
        r.fail(f"{c}.principal_point_weak", f"must be [bool, bool], got {weak!r}")
    return RigCalibration(
        rig=rig, pose_names=tuple(names_p), reference_pose=ref, used=used,
        R_world_target=R_all, t_world_target=T_all, points_target=pts,
        grid_shape=tuple(gs) if gs is not None else None, parameter_names=expected,
        parameters=values, covariance=cov,
        std=std, sigma_camera=r.number(sig, "camera", f"{c}.sigma_px.camera"),
        sigma_projector=r.number(sig, "projector", f"{c}.sigma_px.projector"),
        residuals_camera=arrays["residuals", "camera"],
        residuals_projector=arrays["residuals", "projector"],
        rms_camera=r.number(rms, "camera", f"{c}.rms_px.camera"),
        rms_projector=r.number(rms, "projector", f"{c}.rms_px.projector"),
        rms_per_pose=rms_pose, outliers=tuple(outs),
        camera_observations=arrays["observations", "camera"],
        projector_observations=arrays["observations", "projector"],
        principal_point=str(rep.get("principal_point", "estimate")),
        principal_point_weak=(weak[0], weak[1]), mirror=str(rep.get("mirror", "unknown")),
        warnings=tuple(warns), phase_errors=phase_errors)


def _phase_errors(r: _Reader, doc) -> dict:
    """The optional ``phase_errors`` block: ``(axis, periods, steps) -> PhaseErrorModel``."""
    from telefringe.fringes.nonlinearity import PhaseErrorModel

    if doc is None:
        return {}
    if not isinstance(doc, dict) or not isinstance(doc.get("groups"), list):
        r.fail("phase_errors", "must be an object with a list 'groups'")
    out = {}
    for i, g in enumerate(doc["groups"]):
        path = f"phase_errors.groups[{i}]"
        if not isinstance(g, dict):
            r.fail(path, "must be an object")
        axis = g.get("axis")
        if axis not in ("u", "v"):
            r.fail(f"{path}.axis", f"must be 'u' or 'v', got {axis!r}")
        ints = {}
        for key, low in (("periods", 1), ("steps", 3)):
            v = g.get(key)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= low):
                r.fail(f"{path}.{key}", f"must be an integer >= {low}, got {v!r}")
            ints[key] = v
        harm = g.get("harmonics")
        if not (isinstance(harm, list) and all(isinstance(h, int) and not isinstance(h, bool)
                                               and 1 <= h <= 4096 for h in harm)
                and len(set(harm)) == len(harm)):
            r.fail(f"{path}.harmonics", f"must be distinct integers in 1..4096, got {harm!r}")
        coef = [r.array(g.get(k), f"{path}.{k}", (len(harm),)) for k in ("cos_rad", "sin_rad")]
        if not all(np.all(np.isfinite(c)) for c in coef):
            r.fail(path, "cos_rad and sin_rad must be finite numbers")
        key = (axis, ints["periods"], ints["steps"])
        if key in out:
            r.fail(path, f"a second model for axis {axis}, {key[1]} periods, {key[2]} steps")
        m = PhaseErrorModel(ints["periods"], tuple(harm), coef[0], coef[1])
        if not m.invertible:
            r.fail(path, "the model is not invertible (its slope reaches -1)")
        out[key] = m
    return out


def _params_of(rig: Rig) -> np.ndarray:
    return np.concatenate([rig.camera.to_params(), rig.projector.to_params()])


def load_rig(path) -> RigCalibration:
    """Read and validate ``rig.json``.

    Returns
    -------
    RigCalibration
        Stands for a :class:`telefringe.devices.rig.Rig` too (``.camera``, ``.projector``);
        ``.rig`` is the Rig itself.

    Raises
    ------
    InputError
        Missing or unreadable file, malformed JSON, wrong format or version, a missing
        key, a value that is not a finite number where one is needed; the message names
        the file and the key.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{path}: not found") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a folder, expected a rig.json file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read ({exc})") from None
    try:
        doc = json.loads(text, parse_constant=lambda s: float("nan"))
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: malformed JSON at line {exc.lineno} column {exc.colno}: "
                         f"{exc.msg}") from None
    return rig_from_json(doc, where=str(path))
