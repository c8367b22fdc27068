"""The folder a reconstruction leaves: ``points.npz``, ``cloud.ply``, ``heightmap.tif`` (+
``.json``, ``_sigma.tif``), ``heightmap.x3p`` (ISO 25178-72), ``heightmap.png`` and
``summary.json``."""

from __future__ import annotations

from pathlib import Path

from telefringe.io.errors import InputError
from telefringe.io.figures.heightmap_png import write_height_png
from telefringe.io.jsonable import write_json
from telefringe.io.ply import write_ply
from telefringe.io.points_npz import write_points
from telefringe.io.tiff import write_height_tiff
from telefringe.io.x3p import write_height_x3p

__all__ = ["write_reconstruction", "preview_map", "PREVIEW_PIXELS"]


#: the longer side of the height map drawn in heightmap.png (pixels); the figure's axes
#: are about 550 px wide
PREVIEW_PIXELS = 800


def preview_map(hm):
    """``hm`` binned to about the preview's resolution (longer side <= PREVIEW_PIXELS):
    drawing every pixel of a full-size map took half a second for no visible difference."""
    return hm.binned(-(-max(hm.z.shape) // PREVIEW_PIXELS))


def write_reconstruction(folder, cloud, hm=None, *, texture=None, radiance=None,
                         title: str | None = None, ply: bool = True,
                         summary=None, force: bool = False, stereo_noise=None) -> dict:
    """Write ``points.npz``, ``cloud.ply``, ``heightmap.tif`` (+ ``.json``, ``_sigma.tif``),
    ``heightmap.x3p`` (the same heights as ISO 25178-72 X3P, :mod:`telefringe.io.x3p`),
    ``heightmap.png`` (of :func:`preview_map`) and ``summary.json`` into an existing
    ``folder``.

    Parameters
    ----------
    folder : path-like, an existing folder.
    cloud : telefringe.reconstruction.cloud.PointCloud
    hm : HeightMap or None (no height-map files without it), or a function of no
        argument returning one of them (e.g. ``lambda: height_map(cloud)``): it then runs
        on another thread while ``points.npz`` and ``cloud.ply`` are written.
    texture, radiance : (rows, cols) arrays or None, kept in points.npz (texture also
        colours the PLY).
    title : of the PNG preview.
    ply : write cloud.ply.
    summary : JSON-able dict written as summary.json (through
        :func:`telefringe.io.jsonable.write_json`), or a function of the height map (or
        None) returning it; none without it.
    force : replace existing files.
    stereo_noise : StereoNoiseMaps or None, a two-camera match's noise, kept in points.npz.

    Returns
    -------
    dict
        name -> Path of what was written.
    """
    from concurrent.futures import ThreadPoolExecutor

    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder")
    out = {}
    # the height map (when asked for: a compiled kernel without the GIL), then its X3P
    # (deflating the heights) and PNG (drawing, deflating) are made on two more threads
    # meanwhile: compression, checksums and disk writes run without the GIL, so on two
    # cores the files take about half the time of one after the other
    with ThreadPoolExecutor(max_workers=2, thread_name_prefix="telefringe-write") as pool:
        hm_job = pool.submit(hm) if callable(hm) else None

        def height():
            return hm_job.result() if hm_job is not None else hm

        jobs = {}
        if hm_job is not None or hm is not None:
            jobs["heightmap_x3p"] = pool.submit(_if_map, write_height_x3p, height,
                                                folder / "heightmap.x3p", force=force)
            jobs["heightmap_png"] = pool.submit(_if_map, _write_preview, height,
                                                folder / "heightmap.png", title=title,
                                                force=force)
        out["points"] = write_points(folder / "points.npz", cloud, texture=texture,
                                     radiance=radiance, stereo_noise=stereo_noise,
                                     force=force)
        if ply:
            out["ply"] = write_ply(folder / "cloud.ply", cloud, texture=texture, force=force)
        the_map = height()  # its error, if any, raised here (the other threads end first)
        if the_map is not None:
            out["heightmap"], out["heightmap_json"] = write_height_tiff(
                folder / "heightmap.tif", the_map, force=force)
        if callable(summary):
            summary = summary(the_map)
        if summary is not None:
            out["summary"] = write_json(folder / "summary.json", summary, force=force)
    # leaving the pool waited for the other threads' files (written or failed)
    for name, job in jobs.items():
        path = job.result()  # its error, if any, raised here
        if path is not None:
            out[name] = path
    return {name: out[name] for name in _ORDER if name in out}


def _if_map(write, height, path, **options):
    """``write(path, the height map, **options)``, or None when there is none."""
    the_map = height()
    return None if the_map is None else write(path, the_map, **options)


#: the order of write_reconstruction's result (as written before the threads)
_ORDER = ("points", "ply", "heightmap", "heightmap_json", "heightmap_x3p", "summary",
          "heightmap_png")


def _write_preview(path, hm, *, title, force):
    return write_height_png(path, preview_map(hm), title=title, force=force)
