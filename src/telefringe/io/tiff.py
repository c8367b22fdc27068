"""``heightmap.tif``: a 32-bit float height map (NaN = no data) with its pixel size in the
TIFF resolution tags and, exactly, in the sidecar ``heightmap.json``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from telefringe.io.atomic import atomic_file, write_json_atomic
from telefringe.io.errors import InputError

__all__ = ["HEIGHTMAP_FORMAT", "HEIGHTMAP_VERSION", "write_height_tiff", "read_height_tiff"]

HEIGHTMAP_FORMAT = "telefringe-heightmap"
HEIGHTMAP_VERSION = 1


def _heightmap_meta(hm) -> dict:
    h, w = hm.z.shape
    return {
        "format": HEIGHTMAP_FORMAT, "version": HEIGHTMAP_VERSION, "units": "mm",
        "width": int(w), "height": int(h),
        "pixel_mm": float(hm.pixel_mm), "x0_mm": float(hm.x0), "y0_mm": float(hm.y0),
        "orientation": "z[row, col] is at x = x0_mm + col * pixel_mm, "
                       "y = y0_mm - row * pixel_mm (row 0 at the largest y, like the "
                       "camera image); world frame of the rig, z toward the camera",
        "nodata": "NaN",
    }


def write_height_tiff(path, hm, *, force: bool = False) -> tuple[Path, Path]:
    """Write a height map as a 32-bit float TIFF plus a sidecar JSON.

    The TIFF holds ``hm.z`` (mm, NaN where no data); its X/YResolution tags give the
    pixel size (pixels per centimetre, unit CENTIMETER) and its ImageDescription the
    metadata JSON; the sidecar ``<name>.json`` holds the same metadata exactly
    (``pixel_mm``, ``x0_mm``, ``y0_mm``, orientation). When ``hm.sigma_z`` is present it is
    written as a second TIFF ``<name>_sigma.tif``.

    Returns the paths of the TIFF and of the sidecar.
    """
    import tifffile

    path = Path(path)
    side = path.with_suffix(".json")
    meta = _heightmap_meta(hm)
    res = 10.0 / float(hm.pixel_mm)  # pixels per cm
    targets = [(path, hm.z)]
    if hm.sigma_z is not None:
        meta["sigma_file"] = path.with_name(path.stem + "_sigma.tif").name
        targets.append((path.with_name(path.stem + "_sigma.tif"), hm.sigma_z))
    for p, arr in targets:
        with atomic_file(p, force=force) as tmp:
            tifffile.imwrite(tmp, np.asarray(arr, dtype=np.float32),
                             resolution=(res, res), resolutionunit="CENTIMETER",
                             description=json.dumps(meta), metadata=None)
    write_json_atomic(side, meta, force=force)
    return path, side


def read_height_tiff(path):
    """Read a height map written by :func:`write_height_tiff` (HeightMap)."""
    import tifffile

    from telefringe.reconstruction.heightmap import HeightMap

    path = Path(path)
    side = path.with_suffix(".json")
    try:
        z = tifffile.imread(path)
        meta = json.loads(side.read_text())
    except FileNotFoundError as exc:
        raise InputError(f"{exc.filename}: not found") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not a height map ({exc})") from None
    if meta.get("format") != HEIGHTMAP_FORMAT or meta.get("version") != HEIGHTMAP_VERSION:
        raise InputError(f"{side}: not a telefringe height map sidecar (version "
                         f"{HEIGHTMAP_VERSION})")
    return HeightMap(np.asarray(z, dtype=np.float32), float(meta["x0_mm"]),
                     float(meta["y0_mm"]), float(meta["pixel_mm"]))
