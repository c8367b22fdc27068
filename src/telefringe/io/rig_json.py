"""``rig.json``: a calibrated rig of any devices (format ``telefringe-rig``, version 2;
version 1 files, a telecentric camera and projector, load too).

A person can read it; it holds the devices (named cameras and an optional projector,
each telecentric or pinhole), the world frame and the calibration report, with what is
needed to recompute uncertainties (the rig parameters' covariance, the observations and
the target poses). Layout of version 2::

    {
      "format": "telefringe-rig", "version": 2,
      "units": {"length": "mm", "image": "px", "angle": "rad"},
      "models": {"pinhole": "<the projection model, in words>", ...},
      "world_frame": {"definition": "...", "reference_pose": "pose_00"},
      "cameras": ["camera", "camera_2"],        # optional; default: the camera keys present
      "camera": {"model": "telecentric",
        "width": 1280, "height": 1024, "pixel_size_mm": [0.0052, 0.0052],
        "m": 0.1597, "principal_point_px": [474.9, 513.1],
        "distortion": {"k1": 1.5e-4, "s1": -2e-5, "s2": 3e-5},
        "rotation_vector": [rx, ry, rz], "t_mm": [tx, ty]},
      "camera_2": {"model": "pinhole",          # optional (a second camera)
        "width": 1280, "height": 1024, "fx": 1754.1, "fy": 1752.9, "cx": 645.4, "cy": 529.5,
        "distortion": {"k1": -0.07, "k2": -0.19, "p1": 2e-4, "p2": 5e-4, "k3": 1.84},
        "rotation_vector": [rx, ry, rz], "t_mm": [tx, ty, tz]},
      "projector": { ... a device ... },         # optional in a two-camera rig
      "source": {...},                          # optional, free-form: where the rig came from
      "calibration": {                          # optional (a hand-made rig.json may omit it)
        "rms_px": {"camera": ..., "projector": ...},     # one entry per calibrated device
        "sigma_px": {"camera": ..., "projector": ...},
        "principal_point": "estimate",
        "principal_point_weak": {"camera": false, "projector": false},
        "mirror": "projector_side=right",
        "parameters": {"names": ["camera.m", ...], "values": [...], "std": [...],
                       "covariance": [[...] x n]},  # n = the calibrated devices' parameters
        "grid_shape": [9, 11], "points_target_mm": [[x, y, 0], ...],
        "poses": [{"name": "pose_00", "used": true, "rotation_vector": [...],
                   "t_mm": [...], "rms_px": {"camera": ..., "projector": ...}}, ...],
        "observations": {"camera": [...], "projector": [...]},   # (poses, points, 2)
        "residuals": {"camera": [...], "projector": [...]},      # predicted - observed
        "outliers": [{"device": "camera", "pose": "pose_03", "marker": [1, 3],
                      "residual_px": [0.8, -0.5]}],
        "warnings": ["..."]
      },
      "phase_errors": {                         # optional: the projector nonlinearity
        "model": "<in words>",
        "groups": [{"axis": "u", "periods": 64, "steps": 4, "harmonics": [4, 8],
                    "cos_rad": [...], "sin_rad": [...]}, ...]
      }
    }

Devices follow :mod:`telefringe.devices.telecentric` (``[xu, yu] = m (R[0:2] X + t)``,
sensor mm, radial + thin-prism distortion, ``u = u0 + xd / du``) and
:mod:`telefringe.devices.pinhole` (OpenCV's model: ``X_dev = R X + t``, ``x = X_dev/Z_dev``,
distortion k1 k2 p1 p2 k3, ``u = fx xd + cx``); ``R`` is the rotation of
``rotation_vector`` (world -> device). The calibrated devices of the report are those
named in ``parameters.names`` (``"<device>.<parameter>"``, each device's parameters in
its own order, devices in any order); the report's per-device entries are keyed by the
same names. Version 1 differs only in this: no ``model`` per device (both are
telecentric), no ``cameras``, ``principal_point_weak`` and a pose's ``rms_px`` are lists
``[camera, projector]``. Missing values in the report's arrays (unobserved markers, fixed
parameters) are ``null``; anything else that is not a finite number is refused on loading.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path

import numpy as np

from telefringe.calibration import rig as _calibration_rig
from telefringe.calibration.device import Outlier
from telefringe.calibration.rig import RigCalibration
from telefringe.devices.pinhole import PinholeDevice, PinholeIntrinsics
from telefringe.devices.rig import Rig
from telefringe.devices.telecentric import Intrinsics, TelecentricDevice
from telefringe.geometry.so3 import rotation_from_rotvec, rotvec_from_rotation
from telefringe.io.atomic import write_json_atomic
from telefringe.io.errors import InputError
from telefringe.io.jsonable import number_or_none, to_jsonable

__all__ = ["RIG_FORMAT", "RIG_VERSION", "MIRROR_PINHOLE", "save_rig", "load_rig",
           "rig_to_json", "rig_from_json", "bare_rig_json", "rig_device_names",
           "rig_parameter_names_of", "bare_calibration"]

RIG_FORMAT = "telefringe-rig"
RIG_VERSION = 2
#: The versions this telefringe reads.
READ_VERSIONS = (1, 2)
#: ``calibration.mirror`` of a rig with a pinhole device: it has no mirror ambiguity.
MIRROR_PINHOLE = "none: a pinhole device fixes it"
_MODELS = {
    "telecentric": (
        "telecentric (scaled orthographic): [xu, yu] = m (R[0:2] X + t) in sensor mm; "
        "r2 = xu^2 + yu^2; xd = xu + k1 xu r2 + s1 r2; yd = yu + k1 yu r2 + s2 r2; "
        "u = u0 + xd / du, v = v0 + yd / dv; R = rotation of rotation_vector (world -> "
        "device); no tz"),
    "pinhole": (
        "pinhole (OpenCV's model): [Xc, Yc, Zc] = R X + t, x = Xc / Zc, y = Yc / Zc; "
        "r2 = x^2 + y^2, a = 1 + k1 r2 + k2 r2^2 + k3 r2^3; xd = x a + 2 p1 x y + "
        "p2 (r2 + 2 x^2); yd = y a + p1 (r2 + 2 y^2) + 2 p2 x y; u = fx xd + cx, "
        "v = fy yd + cy; R = rotation of rotation_vector (world -> device)"),
}
_WORLD = ("the calibration target at the reference pose: x along the grid's columns, y "
          "along its rows (circle (row, col) at (col * pitch, row * pitch, 0)), z = x cross y "
          "toward the camera")
_CAMERA_NAME = re.compile(r"camera(_[0-9]+)?\Z")

_PHASE_MODEL = ("projector nonlinearity per fringe group: measured wrapped phase = phi + "
                "sum_m cos_rad[m] cos(harmonics[m] phi) + sin_rad[m] sin(harmonics[m] phi), "
                "phi the true wrapped phase of the group (rad)")


# --------------------------------------------------------------------------- devices
def rig_device_names(rig: Rig) -> tuple[str, ...]:
    """The names of a rig's devices: its cameras in order, then ``"projector"`` if it has
    one."""
    return tuple(rig.cameras) + (("projector",) if rig.projector is not None else ())


def _device_of(rig: Rig, name: str):
    return rig.projector if name == "projector" else rig.cameras[name]


def rig_parameter_names_of(rig: Rig, devices=None) -> tuple[str, ...]:
    """``"<device>.<parameter>"`` for each device of ``devices`` (default: all of the rig's,
    :func:`rig_device_names`), each device's ``param_names`` in order."""
    names = rig_device_names(rig) if devices is None else tuple(devices)
    return tuple(f"{d}.{p}" for d in names for p in _device_of(rig, d).param_names)


def _params_of(rig: Rig, devices) -> np.ndarray:
    parts = [_device_of(rig, d).to_params() for d in devices]
    return np.concatenate(parts) if parts else np.zeros(0)


def _telecentric_json(dev: TelecentricDevice) -> dict:
    k = dev.intrinsics
    return {"model": "telecentric", "width": int(k.width), "height": int(k.height),
            "pixel_size_mm": [float(k.du), float(k.dv)], "m": float(k.m),
            "principal_point_px": [float(k.u0), float(k.v0)],
            "distortion": {"k1": float(k.k1), "s1": float(k.s1), "s2": float(k.s2)},
            "rotation_vector": [float(v) for v in rotvec_from_rotation(dev.R_dev_world)],
            "t_mm": [float(v) for v in dev.t_dev]}


def _pinhole_json(dev: PinholeDevice) -> dict:
    k = dev.intrinsics
    return {"model": "pinhole", "width": int(k.width), "height": int(k.height),
            "fx": float(k.fx), "fy": float(k.fy), "cx": float(k.cx), "cy": float(k.cy),
            "distortion": {n: float(getattr(k, n)) for n in ("k1", "k2", "p1", "p2", "k3")},
            "rotation_vector": [float(v) for v in rotvec_from_rotation(dev.R_dev_world)],
            "t_mm": [float(v) for v in dev.t_dev]}


_WRITERS = {"telecentric": _telecentric_json, "pinhole": _pinhole_json}


def _device_json(dev, name: str) -> dict:
    writer = _WRITERS.get(getattr(dev, "model", None))
    if writer is None:
        raise InputError(f"rig.json: cannot write the {name}, a {type(dev).__name__} of "
                         f"model {getattr(dev, 'model', None)!r} (rig.json knows "
                         f"{', '.join(_WRITERS)})")
    doc = writer(dev)
    if doc["width"] <= 0 or doc["height"] <= 0:
        raise InputError(f"rig.json: the {name} has no image size (width and height in px "
                         "are needed to check scans against it)")
    return doc


# --------------------------------------------------------------------------- writing
def _arr(a) -> list | float | None:
    """Nested lists of floats with None for NaN (a float or None for a scalar)."""
    return to_jsonable(np.asarray(a, dtype=float))


def _report_devices(calib) -> tuple[str, ...]:
    """The calibrated devices, in the order of ``calib.parameter_names``."""
    out: list[str] = []
    for n in calib.parameter_names:
        d = n.split(".", 1)[0]
        if d not in out:
            out.append(d)
    return tuple(out)


_LEGACY = ("camera", "projector")  # the devices of RigCalibration's own fields, in order


def _device_report(calib, name: str) -> dict:
    """One device's report: rms, sigma (px), observations, residuals (poses, points, 2),
    rms_per_pose (poses,), principal_point_weak. From ``calib.devices[name]`` (a
    DeviceReport) where the calibration has one, else from RigCalibration's camera /
    projector fields; NaN where it has none."""
    n_p, n_k = len(calib.pose_names), np.asarray(calib.points_target).shape[0]
    rep = (getattr(calib, "devices", None) or {}).get(name)
    if rep is not None:
        return {"rms": rep.rms, "sigma": rep.sigma, "observations": rep.observations,
                "residuals": rep.residuals, "rms_per_pose": rep.rms_per_pose,
                "principal_point_weak": rep.principal_point_weak}
    if name in _LEGACY:
        j = _LEGACY.index(name)
        per_pose = np.asarray(calib.rms_per_pose, dtype=float).reshape(n_p, -1)
        weak = tuple(calib.principal_point_weak)
        return {"rms": getattr(calib, f"rms_{name}"), "sigma": getattr(calib, f"sigma_{name}"),
                "observations": getattr(calib, f"{name}_observations"),
                "residuals": getattr(calib, f"residuals_{name}"),
                "rms_per_pose": per_pose[:, j] if j < per_pose.shape[1] else np.full(n_p,
                                                                                     np.nan),
                "principal_point_weak": bool(weak[j]) if j < len(weak) else False}
    nan = np.full((n_p, n_k, 2), np.nan)
    return {"rms": np.nan, "sigma": np.nan, "observations": nan, "residuals": nan,
            "rms_per_pose": np.full(n_p, np.nan), "principal_point_weak": False}


def _has_pinhole(rig: Rig) -> bool:
    return any(_device_of(rig, d).model == "pinhole" for d in rig_device_names(rig))


def rig_to_json(calib: RigCalibration) -> dict:
    """The ``rig.json`` document (a dict, version 2) of a calibration of any rig. The
    ``mirror`` of a rig with a pinhole device is :data:`MIRROR_PINHOLE`."""
    devs = _report_devices(calib)
    reps = {d: _device_report(calib, d) for d in devs}
    poses = []
    for i, name in enumerate(calib.pose_names):
        used = bool(calib.used[i])
        poses.append({
            "name": name, "used": used,
            "rotation_vector": ([float(v) for v in rotvec_from_rotation(calib.R_world_target[i])]
                                if used else None),
            "t_mm": _arr(calib.t_world_target[i]) if used else None,
            "rms_px": {d: number_or_none(reps[d]["rms_per_pose"][i]) for d in devs}})

    def entries(kind):
        if kind in ("rms", "sigma"):
            return {d: number_or_none(reps[d][kind]) for d in devs}
        return {d: _arr(reps[d][kind]) for d in devs}

    report = {
        "rms_px": entries("rms"),
        "sigma_px": entries("sigma"),
        "principal_point": calib.principal_point,
        "principal_point_weak": {d: bool(reps[d]["principal_point_weak"]) for d in devs},
        "mirror": MIRROR_PINHOLE if _has_pinhole(calib.rig) else calib.mirror,
        "parameters": {"names": list(calib.parameter_names), "values": _arr(calib.parameters),
                       "std": _arr(calib.std), "covariance": _arr(calib.covariance)},
        "grid_shape": list(calib.grid_shape) if calib.grid_shape is not None else None,
        "points_target_mm": _arr(calib.points_target),
        "poses": poses,
        "observations": entries("observations"),
        "residuals": entries("residuals"),
        "outliers": [{"device": o.device, "pose": o.pose, "marker": list(o.marker),
                      "residual_px": [float(v) for v in o.residual]} for o in calib.outliers],
        "warnings": list(calib.warnings),
    }
    doc = bare_rig_json(calib.rig, reference_pose=calib.reference_pose,
                        phase_errors=getattr(calib, "phase_errors", None))
    doc["calibration"] = report
    return doc


def bare_rig_json(rig: Rig, *, reference_pose: str = "", phase_errors: dict | None = None,
                  source: dict | None = None, world_definition: str | None = None) -> dict:
    """A ``rig.json`` document (a dict, version 2) of a rig's devices without a
    calibration report (the format allows leaving it out: a rig known otherwise, e.g. a
    simulation's truth or an imported OpenCV calibration), with the projector's
    nonlinearity models ``(axis, periods, steps) -> PhaseErrorModel`` and a free-form
    ``source`` (where the rig came from) when given. ``world_definition`` says in words
    what the world frame is (default: the calibration target at the reference pose).

    Raises InputError for a camera name rig.json cannot hold (``camera``,
    ``camera_<n>``), a device of a model it does not know, or one without image size.
    """
    for name in rig.cameras:
        if not _CAMERA_NAME.match(name):
            raise InputError(f"rig.json: camera name {name!r} cannot be written (use "
                             "'camera', 'camera_2', ...)")
    names = rig_device_names(rig)
    models = []
    for n in names:
        m = _device_of(rig, n).model
        if m not in models:
            models.append(m)
    doc = {"format": RIG_FORMAT, "version": RIG_VERSION,
           "units": {"length": "mm", "image": "px", "angle": "rad"},
           "models": {m: _MODELS[m] for m in models if m in _MODELS},
           "world_frame": {"definition": world_definition or _WORLD,
                           "reference_pose": reference_pose},
           "cameras": list(rig.cameras)}
    for n in names:
        doc[n] = _device_json(_device_of(rig, n), n)
    if source:
        doc["source"] = to_jsonable(source)
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


def save_rig(path, calib, *, force: bool = False, source: dict | None = None,
             world_definition: str | None = None) -> Path:
    """Write ``calib`` (a :class:`RigCalibration`, or a bare :class:`Rig`) to ``path`` as
    ``rig.json`` version 2 (atomically; an existing file is replaced only with ``force``).
    A calibration without poses (e.g. from :func:`bare_calibration`) is written without a
    report; ``source`` and ``world_definition`` as in :func:`bare_rig_json`. Returns the
    path."""
    path = Path(path)
    if isinstance(calib, Rig):
        doc = bare_rig_json(calib, source=source, world_definition=world_definition)
    elif not len(calib.pose_names) and not np.any(np.isfinite(calib.covariance)):
        doc = bare_rig_json(calib.rig, reference_pose=calib.reference_pose,
                            phase_errors=getattr(calib, "phase_errors", None), source=source,
                            world_definition=world_definition)
    else:
        doc = rig_to_json(calib)
        if source:
            doc["source"] = to_jsonable(source)
    write_json_atomic(path, doc, force=force)
    return path


def bare_calibration(rig: Rig, *, reference_pose: str = "", phase_errors: dict | None = None,
                     mirror: str | None = None, warnings=()) -> RigCalibration:
    """A :class:`RigCalibration` that holds only ``rig`` (no poses, no report: NaN
    covariance), as :func:`load_rig` returns for a rig.json without ``calibration``.
    ``mirror`` defaults to :data:`MIRROR_PINHOLE` for a rig with a pinhole device, else
    ``"unknown"``."""
    devs = rig_device_names(rig)
    names = rig_parameter_names_of(rig, devs)
    n = len(names)
    if mirror is None:
        mirror = MIRROR_PINHOLE if _has_pinhole(rig) else "unknown"
    empty = np.zeros((0, 0, 2))
    kw = dict(
        rig=rig, pose_names=(), reference_pose=reference_pose, used=np.zeros(0, dtype=bool),
        R_world_target=np.zeros((0, 3, 3)), t_world_target=np.zeros((0, 3)),
        points_target=np.zeros((0, 3)), grid_shape=None,
        parameter_names=names, parameters=_params_of(rig, devs),
        covariance=np.full((n, n), np.nan), std=np.full(n, np.nan),
        sigma_camera=float("nan"), sigma_projector=float("nan"),
        residuals_camera=empty, residuals_projector=empty,
        rms_camera=float("nan"), rms_projector=float("nan"),
        rms_per_pose=np.zeros((0, 2)), outliers=(),
        camera_observations=empty, projector_observations=empty,
        principal_point="unknown", principal_point_weak=(False, False),
        mirror=mirror, warnings=tuple(warnings), phase_errors=dict(phase_errors or {}))
    return RigCalibration(**kw)


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



def _size(r: _Reader, d, name: str) -> tuple[int, int]:
    out = []
    for key in ("width", "height"):
        v = r.get(d, key, f"{name}.{key}")
        if isinstance(v, bool) or not isinstance(v, int) or not 0 < v <= 100_000:
            r.fail(f"{name}.{key}", f"must be a positive integer, got {v!r}")
        out.append(v)
    return out[0], out[1]


def _rotation(r: _Reader, d, name: str) -> np.ndarray:
    rv = r.vector(d, "rotation_vector", f"{name}.rotation_vector", 3)
    return rotation_from_rotvec(rv)


def _telecentric(r: _Reader, d, name: str) -> TelecentricDevice:
    w, h = _size(r, d, name)
    du, dv = r.vector(d, "pixel_size_mm", f"{name}.pixel_size_mm", 2, positive=True)
    m = r.number(d, "m", f"{name}.m", positive=True)
    u0, v0 = r.vector(d, "principal_point_px", f"{name}.principal_point_px", 2)
    dist = r.get(d, "distortion", f"{name}.distortion")
    k1, s1, s2 = (r.number(dist, k, f"{name}.distortion.{k}") for k in ("k1", "s1", "s2"))
    R = _rotation(r, d, name)
    t = r.vector(d, "t_mm", f"{name}.t_mm", 2)
    try:
        intr = Intrinsics(m=m, du=du, dv=dv, u0=u0, v0=v0, k1=k1, s1=s1, s2=s2, width=w,
                          height=h)
        return TelecentricDevice(intr, R, t)
    except ValueError as exc:
        r.fail(name, f"is not a valid device: {exc}")


def _pinhole(r: _Reader, d, name: str) -> PinholeDevice:
    w, h = _size(r, d, name)
    fx = r.number(d, "fx", f"{name}.fx", positive=True)
    fy = r.number(d, "fy", f"{name}.fy", positive=True)
    cx = r.number(d, "cx", f"{name}.cx")
    cy = r.number(d, "cy", f"{name}.cy")
    dist = r.get(d, "distortion", f"{name}.distortion")
    coef = {k: r.number(dist, k, f"{name}.distortion.{k}") for k in ("k1", "k2", "p1", "p2",
                                                                   "k3")}
    R = _rotation(r, d, name)
    t = r.vector(d, "t_mm", f"{name}.t_mm", 3)
    try:
        return PinholeDevice(PinholeIntrinsics(fx, fy, cx, cy, **coef, width=w, height=h),
                             R, t)
    except ValueError as exc:
        r.fail(name, f"is not a valid device: {exc}")


_READERS = {"telecentric": _telecentric, "pinhole": _pinhole}


def _device(r: _Reader, doc, name: str, version: int):
    d = r.get(doc, name, name)
    if not isinstance(d, dict):
        r.fail(name, "must be an object")
    if version == 1:
        model = d.get("model", "telecentric")
        if model != "telecentric":
            r.fail(f"{name}.model", f"{model!r} needs version 2 (a version 1 rig.json holds "
                                    "telecentric devices)")
    else:
        model = r.get(d, "model", f"{name}.model")
    if not isinstance(model, str) or model not in _READERS:
        r.fail(f"{name}.model", f"must be one of {', '.join(map(repr, _READERS))}, got "
                                f"{model!r}")
    return _READERS[model](r, d, name)


def _rig(r: _Reader, doc, version: int) -> Rig:
    if version == 1:
        return Rig(_device(r, doc, "camera", 1), _device(r, doc, "projector", 1))
    names = doc.get("cameras")
    if names is None:
        names = ["camera"] + sorted((k for k in doc if _CAMERA_NAME.match(k) and k != "camera"),
                                    key=lambda k: int(k.split("_")[1]))
    if (not isinstance(names, list) or not names
            or not all(isinstance(n, str) and _CAMERA_NAME.match(n) for n in names)
            or len(set(names)) != len(names)):
        r.fail("cameras", f"must be a non-empty list of distinct camera names ('camera', "
                          f"'camera_2', ...), got {names!r}")
    cams = {n: _device(r, doc, n, 2) for n in names}
    proj = _device(r, doc, "projector", 2) if "projector" in doc else None
    if proj is None and len(cams) < 2:
        r.fail("projector", "is missing (a rig with one camera needs a projector)")
    return Rig(cameras=cams, projector=proj)


def _report_order(r: _Reader, rig: Rig, names, path: str, version: int) -> tuple[str, ...]:
    """Check ``parameters.names`` against the devices; return the calibrated devices in
    their order there."""
    expected_all = rig_parameter_names_of(rig)
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        r.fail(path, "must be a list of strings")
    if version == 1:
        if names != list(expected_all):
            r.fail(path, f"must be {list(expected_all)} (the devices' parameters)")
        return rig_device_names(rig)
    known = rig_device_names(rig)
    order: list[str] = []
    i = 0
    while i < len(names):
        dev = names[i].split(".", 1)[0]
        if dev not in known or dev in order:
            r.fail(path, f"names[{i}] {names[i]!r}: each name is '<device>.<parameter>' of a "
                         f"device of this file ({', '.join(known)}), each device once")
        block = list(rig_parameter_names_of(rig, (dev,)))
        if names[i:i + len(block)] != block:
            r.fail(path, f"the {dev}'s parameters must be {block} (its model's, in order)")
        order.append(dev)
        i += len(block)
    if not order:
        r.fail(path, "names no parameters")
    return tuple(order)


def _per_device_entry(r: _Reader, v, devs, path: str, version: int, check):
    """A per-device report entry: v2 an object keyed by device, v1 a list [camera,
    projector]; ``check(value, path)`` validates each value."""
    if version == 1:
        if not isinstance(v, list) or len(v) != 2:
            r.fail(path, f"must be [camera, projector], got {v!r}")
        return [check(x, f"{path}[{j}]") for j, x in enumerate(v)]
    if not isinstance(v, dict):
        r.fail(path, f"must be an object with an entry per calibrated device "
                     f"({', '.join(devs)})")
    return [check(r.get(v, d, f"{path}.{d}"), f"{path}.{d}") for d in devs]


def rig_from_json(doc, *, where: str = "rig.json") -> RigCalibration:
    """Validate a parsed ``rig.json`` document (version 1 or 2) and return the
    :class:`RigCalibration` (a rig.json without ``calibration``: a bare one, see
    :func:`bare_calibration`).

    Raises :class:`~telefringe.io.errors.InputError` naming ``where`` and the key.
    """
    r = _Reader(where)
    if not isinstance(doc, dict):
        raise InputError(f"{where}: expected a JSON object at the top level")
    if doc.get("format") != RIG_FORMAT:
        r.fail("format", f"must be {RIG_FORMAT!r}, got {doc.get('format')!r}")
    version = doc.get("version")
    if isinstance(version, bool) or version not in READ_VERSIONS:
        r.fail("version", f"{version!r} is not supported (this telefringe reads "
                          f"{', '.join(map(str, READ_VERSIONS))})")
    rig = _rig(r, doc, version)
    world = r.get(doc, "world_frame", "world_frame")
    ref = world.get("reference_pose", "") if isinstance(world, dict) else ""
    if not isinstance(ref, str):
        r.fail("world_frame.reference_pose", f"must be a string, got {ref!r}")
    phase_errors = _phase_errors(r, doc.get("phase_errors"))
    rep = doc.get("calibration")
    if rep is None:
        return bare_calibration(rig, reference_pose=ref, phase_errors=phase_errors)
    if not isinstance(rep, dict):
        r.fail("calibration", "must be an object")
    c = "calibration"
    par = r.get(rep, "parameters", f"{c}.parameters")
    names = r.get(par, "names", f"{c}.parameters.names")
    devs = _report_order(r, rig, names, f"{c}.parameters.names", version)
    n = len(names)
    values = r.array(r.get(par, "values", f"{c}.parameters.values"),
                     f"{c}.parameters.values", (n,))
    std = r.array(r.get(par, "std", f"{c}.parameters.std"), f"{c}.parameters.std", (n,))
    cov = r.array(r.get(par, "covariance", f"{c}.parameters.covariance"),
                  f"{c}.parameters.covariance", (n, n))

    def number(x, path):
        if isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(x):
            r.fail(path, f"must be a finite number, got {x!r}")
        return float(x)

    def number_or_null(x, path):
        return float("nan") if x is None else number(x, path)

    # rms_px and sigma_px are objects keyed by device in both versions
    rms = _per_device_entry(r, r.get(rep, "rms_px", f"{c}.rms_px"), devs, f"{c}.rms_px",
                            2, number_or_null)
    sig = _per_device_entry(r, r.get(rep, "sigma_px", f"{c}.sigma_px"), devs,
                            f"{c}.sigma_px", 2, number_or_null)
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
    rms_pose = np.full((n_p, len(devs)), np.nan)
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
        rms_pose[i] = _per_device_entry(r, r.get(p, "rms_px", f"{path}.rms_px"), devs,
                                        f"{path}.rms_px", version, number_or_null)
    if ref and ref not in names_p:
        r.fail("world_frame.reference_pose", f"{ref!r} is not one of the poses")
    arrays = {}
    for grp in ("observations", "residuals"):
        d = r.get(rep, grp, f"{c}.{grp}")
        for dev in devs:
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

    def boolean(x, path):
        if not isinstance(x, bool):
            r.fail(path, f"must be true or false, got {x!r}")
        return x

    weak_doc = rep.get("principal_point_weak")
    weak = ([False] * len(devs) if weak_doc is None else
            _per_device_entry(r, weak_doc, devs, f"{c}.principal_point_weak", version,
                              boolean))
    nan = float("nan")
    missing = np.full((n_p, n_k, 2), np.nan)
    by = dict(zip(devs, range(len(devs)), strict=True))

    def pick(seq, dev, default):
        return seq[by[dev]] if dev in by else default

    def pose_rms(dev):
        return rms_pose[:, by[dev]] if dev in by else np.full(n_p, np.nan)

    kw = dict(
        rig=rig, pose_names=tuple(names_p), reference_pose=ref, used=used,
        R_world_target=R_all, t_world_target=T_all, points_target=pts,
        grid_shape=tuple(gs) if gs is not None else None, parameter_names=tuple(names),
        parameters=values, covariance=cov, std=std,
        sigma_camera=pick(sig, "camera", nan), sigma_projector=pick(sig, "projector", nan),
        residuals_camera=arrays.get(("residuals", "camera"), missing),
        residuals_projector=arrays.get(("residuals", "projector"), missing),
        rms_camera=pick(rms, "camera", nan), rms_projector=pick(rms, "projector", nan),
        rms_per_pose=np.column_stack([pose_rms("camera"), pose_rms("projector")]),
        outliers=tuple(outs),
        camera_observations=arrays.get(("observations", "camera"), missing),
        projector_observations=arrays.get(("observations", "projector"), missing),
        principal_point=str(rep.get("principal_point", "estimate")),
        principal_point_weak=(pick(weak, "camera", False), pick(weak, "projector", False)),
        mirror=str(rep.get("mirror", "unknown")), warnings=tuple(warns),
        phase_errors=phase_errors)
    # every calibrated device's report (camera_2 too), where RigCalibration holds them
    report_cls = getattr(_calibration_rig, "DeviceReport", None)
    if report_cls is not None and "devices" in {f.name for f in
                                                dataclasses.fields(RigCalibration)}:
        kw["devices"] = {d: report_cls(
            model=_device_of(rig, d).model, sigma=sig[k], observations=arrays["observations", d],
            residuals=arrays["residuals", d], rms=rms[k], rms_per_pose=rms_pose[:, k],
            principal_point_weak=weak[k]) for k, d in enumerate(devs)}
    return RigCalibration(**kw)


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




def load_rig(path) -> RigCalibration:
    """Read and validate ``rig.json``.

    Returns
    -------
    RigCalibration
        Of any rig (version 2: named cameras and an optional projector, each telecentric
        or pinhole; version 1: a telecentric camera and projector). Stands for a
        :class:`telefringe.devices.rig.Rig` too (``.camera``, ``.projector``); ``.rig``
        is the Rig itself (``.rig.cameras`` names every camera).

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
