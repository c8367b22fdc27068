"""The folder a reconstruction leaves: ``points.npz``, ``cloud.ply``, ``heightmap.tif`` (+
``.json``, ``_sigma.tif``) and ``heightmap.png``."""

from __future__ import annotations

from pathlib import Path

from telefringe.io.errors import InputError
from telefringe.io.figures.heightmap_png import write_height_png
from telefringe.io.ply import write_ply
from telefringe.io.points_npz import write_points
from telefringe.io.tiff import write_height_tiff

__all__ = ["write_reconstruction"]


def write_reconstruction(folder, cloud, hm=None, *, texture=None, radiance=None,
                         title: str | None = None, ply: bool = True,
                         force: bool = False) -> dict:
    """Write ``points.npz``, ``cloud.ply``, ``heightmap.tif`` (+ ``.json``, ``_sigma.tif``)
    and ``heightmap.png`` into an existing ``folder``.

    Returns a dict name -> Path of what was written.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder")
    out = {"points": write_points(folder / "points.npz", cloud, texture=texture,
                                  radiance=radiance, force=force)}
    if ply:
        out["ply"] = write_ply(folder / "cloud.ply", cloud, texture=texture, force=force)
    if hm is not None:
        out["heightmap"], out["heightmap_json"] = write_height_tiff(
            folder / "heightmap.tif", hm, force=force)
        out["heightmap_png"] = write_height_png(folder / "heightmap.png", hm, title=title,
                                                force=force)
    return out
