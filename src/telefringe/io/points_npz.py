"""``points.npz``: the organised point cloud of a reconstruction (see docs/formats.md).

Written atomically; an existing file is replaced only with ``force``.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from telefringe.io import _npz
from telefringe.io.atomic import atomic_file
from telefringe.io.errors import InputError

__all__ = ["POINTS_FORMAT", "POINTS_VERSION", "write_points", "read_points", "load_points",
           "PointsFile"]

POINTS_FORMAT = "telefringe-points"
#: Written now: 2 (``directions``, the viewing direction of every pixel, or one for all).
#: Version 1 files (one ``direction`` (3,)) are read too.
POINTS_VERSION = 2
_READABLE = (1, 2)


#: the keys of a two-camera match's noise (StereoNoiseMaps' fields), optional
_STEREO_KEYS = {"stereo_u2": "u2", "stereo_v2": "v2", "stereo_var_own": "var_own",
                "stereo_coef": "coef", "stereo_sigma_2": "sigma_2"}


def write_points(path, cloud, *, texture=None, radiance=None, stereo_noise=None,
                 force: bool = False) -> Path:
    """Write an organised point cloud to ``path`` (uncompressed .npz, version 2).

    Arrays: ``xyz`` (rows, cols, 3) float64 mm, NaN where invalid; ``mask`` bool;
    ``sigma_z`` float64 mm; ``sigma_line`` float64 mm (along the camera line);
    ``directions`` float64, (3,) the camera's viewing direction when every pixel shares
    it (a telecentric camera) or (rows, cols, 3) one unit vector per pixel; ``flags``
    uint8 (why a point is invalid, ``telefringe.reconstruction.cloud.FLAG_*``);
    ``residual`` float64 projector px (only with both fringe axes); ``texture`` float32
    (rows, cols) fringe-free camera image (optional, for marker detection); ``radiance``
    float32 (rows, cols) the decoder's background per unit exposure (optional, for BGA
    highlights); ``format`` and ``version``. With ``stereo_noise`` (a two-camera
    match's :class:`~telefringe.reconstruction.stereo.StereoNoiseMaps`), float64
    ``stereo_u2``, ``stereo_v2``, ``stereo_var_own`` (rows, cols), ``stereo_coef`` (rows,
    cols, A) and ``stereo_sigma_2`` (A, rows_2, cols_2): the noise of neighbouring
    matches' shared second-camera pixels, for the covariance of fits (optional: files
    without them read as before).
    """
    arrays = {
        "format": np.array(POINTS_FORMAT),
        "version": np.array(POINTS_VERSION),
        "xyz": np.ascontiguousarray(cloud.xyz, dtype=np.float64),
        "mask": np.asarray(cloud.mask, dtype=bool),
        "sigma_z": np.asarray(cloud.sigma_z, dtype=np.float64),
        "sigma_line": np.asarray(cloud.sigma_line, dtype=np.float64),
        "directions": np.asarray(cloud.directions, dtype=np.float64),
        "flags": np.asarray(cloud.flags, dtype=np.uint8),
    }
    if cloud.residual is not None:
        arrays["residual"] = np.asarray(cloud.residual, dtype=np.float64)
    for name, img in (("texture", texture), ("radiance", radiance)):
        if img is not None:
            t = np.asarray(img, dtype=np.float32)
            if t.shape != cloud.shape:
                raise ValueError(f"{name} has shape {t.shape}, the cloud {cloud.shape}")
            arrays[name] = t
    if stereo_noise is not None:
        if tuple(stereo_noise.shape) != tuple(cloud.shape):
            raise ValueError(f"stereo_noise has shape {stereo_noise.shape}, the cloud "
                             f"{cloud.shape}")
        for key, field in _STEREO_KEYS.items():
            arrays[key] = np.asarray(getattr(stereo_noise, field), dtype=np.float64)
    path = Path(path)
    with atomic_file(path, force=force) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)
    return path


@dataclasses.dataclass(frozen=True, eq=False)
class PointsFile:
    """Content of ``points.npz``: the cloud and its optional images (float32 or None),
    and a two-camera match's noise (``StereoNoiseMaps`` or None: a single camera's
    cloud, or a file written before it was kept)."""

    cloud: object
    texture: np.ndarray | None
    radiance: np.ndarray | None
    stereo_noise: object = None


def read_points(path):
    """Read ``points.npz`` (or a folder holding it).

    Returns
    -------
    cloud : telefringe.reconstruction.cloud.PointCloud
    texture : (rows, cols) float32 ndarray or None

    Raises
    ------
    InputError
        Missing file, not a points file, inconsistent arrays.
    """
    pf = load_points(path)
    return pf.cloud, pf.texture


def load_points(path) -> PointsFile:
    """Like :func:`read_points`, with every optional array (:class:`PointsFile`)."""
    from telefringe.reconstruction.cloud import PointCloud

    path = Path(path)
    if path.is_dir():
        path = path / "points.npz"
    arrays = _npz.load(path, "points", missing_hint=" (run 'telefringe reconstruct' first)")
    if str(arrays.get("format", "")) != POINTS_FORMAT:
        raise InputError(f"{path}: not a telefringe points file (no format '{POINTS_FORMAT}')")
    version = int(arrays.get("version", -1))
    if version not in _READABLE:
        raise InputError(f"{path}: points file version {arrays.get('version')} is not "
                         f"supported (this telefringe reads versions "
                         f"{', '.join(map(str, _READABLE))})")
    dkey = "direction" if version == 1 else "directions"
    for k in ("xyz", "mask", "sigma_line", dkey, "flags"):
        if k not in arrays:
            raise InputError(f"{path}: array '{k}' is missing")
    xyz = arrays["xyz"]
    if xyz.ndim != 3 or xyz.shape[2] != 3 or xyz.dtype.kind != "f":
        raise InputError(f"{path}: 'xyz' must be a float (rows, cols, 3) array")
    shape = xyz.shape[:2]
    for k in ("mask", "sigma_line", "flags", "residual", "texture", "radiance"):
        if k in arrays and arrays[k].shape != shape:
            raise InputError(f"{path}: '{k}' has shape {arrays[k].shape}, expected {shape}")
    d = np.asarray(arrays[dkey], dtype=np.float64)
    if d.shape not in ((3,), shape + (3,)) or not np.all(np.isfinite(d)) or np.any(
            np.abs(np.linalg.norm(d, axis=-1) - 1) > 1e-6):
        what = "a unit 3-vector" if version == 1 else f"unit vectors, (3,) or {shape + (3,)}"
        raise InputError(f"{path}: '{dkey}' must be {what}")
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    mask = arrays["mask"].astype(bool)
    if np.any(mask & ~np.all(np.isfinite(xyz), axis=2)):
        raise InputError(f"{path}: 'mask' marks points whose xyz is not finite")
    xyz = np.where(mask[..., None], xyz, np.nan).astype(np.float64)
    cloud = PointCloud(xyz, mask, np.where(mask, arrays["sigma_line"], np.nan),
                       arrays.get("residual"), arrays["flags"].astype(np.uint8), d)
    return PointsFile(cloud, arrays.get("texture"), arrays.get("radiance"),
                      _stereo_noise(path, arrays, shape))


def _stereo_noise(path, arrays, shape):
    """The file's StereoNoiseMaps, or None without its keys (all or none)."""
    have = [k for k in _STEREO_KEYS if k in arrays]
    if not have:
        return None
    if len(have) != len(_STEREO_KEYS):
        missing = sorted(set(_STEREO_KEYS) - set(have))
        raise InputError(f"{path}: the stereo noise is incomplete ({', '.join(missing)} "
                         "missing)")
    from telefringe.reconstruction.stereo import StereoNoiseMaps

    try:
        maps = StereoNoiseMaps(**{f: np.asarray(arrays[k], dtype=np.float64)
                                  for k, f in _STEREO_KEYS.items()})
    except ValueError as exc:
        raise InputError(f"{path}: {exc}") from None
    if maps.shape != tuple(shape):
        raise InputError(f"{path}: the stereo noise has shape {maps.shape}, expected "
                         f"{tuple(shape)}")
    return maps
