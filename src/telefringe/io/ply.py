"""``cloud.ply``: binary little-endian PLY of the valid points (CloudCompare, MeshLab,
Open3D read it)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from telefringe.io.atomic import atomic_file

__all__ = ["write_ply"]


def write_ply(path, cloud, *, texture=None, force: bool = False) -> Path:
    """Binary little-endian PLY of the valid points (row-major pixel order).

    Vertex properties: ``x, y, z`` (float32, mm); ``red, green, blue`` (uint8, the
    texture's gray level scaled to its 0.5 / 99.5 percentiles) when ``texture`` is given;
    ``sigma_z`` (float32, mm) when the cloud has uncertainties (CloudCompare shows it as
    a scalar field; other readers skip it).
    """
    from plyfile import PlyData, PlyElement

    m = np.asarray(cloud.mask)
    pts = np.asarray(cloud.xyz)[m]
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    gray = None
    if texture is not None:
        t = np.asarray(texture, dtype=np.float64)
        vals = t[m]
        if vals.size:
            lo, hi = np.percentile(vals, [0.5, 99.5])
            gray = np.clip((vals - lo) / max(hi - lo, 1e-12) * 255.0, 0, 255).astype(np.uint8)
        else:
            gray = np.zeros(0, np.uint8)
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    sz = np.asarray(cloud.sigma_z)[m]
    has_sigma = bool(sz.size) and bool(np.all(np.isfinite(sz)))
    if has_sigma:
        fields.append(("sigma_z", "<f4"))
    v = np.empty(pts.shape[0], dtype=fields)
    v["x"], v["y"], v["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if gray is not None:
        v["red"] = v["green"] = v["blue"] = gray
    if has_sigma:
        v["sigma_z"] = sz
    el = PlyElement.describe(v, "vertex")
    ply = PlyData([el], text=False, byte_order="<",
                  comments=["telefringe point cloud, world frame, mm"])
    path = Path(path)
    with atomic_file(path, force=force) as tmp:
        ply.write(str(tmp))
    return path
