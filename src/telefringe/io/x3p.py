"""``heightmap.x3p``: the height map as an ISO 25178-72 X3P file (the exchange format of
surface-metrology software: MountainsMap, Gwyddion, NIST's tools), written and read with
the ``x3pio`` library (MIT).

Layout of what is written (see docs/formats.md):

- a zip archive holding ``main.xml`` (the description), ``bindata/data.bin`` (the heights,
  little-endian float32, x fastest) and ``md5checksum.hex`` (MD5 of ``main.xml``, which in
  turn holds the MD5 of ``data.bin``);
- feature type SUR, x and y incremental axes at the height map's pixel size, z absolute
  float32 with an increment of 1e-3 m: the stored numbers are the height map's
  millimetres exactly as in ``heightmap.tif`` (no rounding on the way);
- row 0 of the X3P grid is the *smallest* world y (X3P's axes are right-handed with y
  growing with the row), i.e. the TIFF's rows in reverse order; the placement offset puts
  the first point at its world (x, y) in metres;
- the valid-point mask: points without data are NaN, which is how ISO 25178-72 marks
  missing float values (a ``bindata/valid.bin`` exists only for integer data, which this
  writer never uses).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from telefringe.io.atomic import atomic_file
from telefringe.io.errors import InputError

__all__ = ["write_height_x3p", "read_height_x3p"]

_MM = 1e-3  # metres per millimetre


def write_height_x3p(path, hm, *, force: bool = False, comment: str | None = None) -> Path:
    """Write a height map as an X3P file (atomically).

    Parameters
    ----------
    path : path-like, the ``.x3p`` file to write.
    hm : telefringe.reconstruction.heightmap.HeightMap
        Heights ``z`` (H, W) mm, NaN where there is no data, at ``x = x0 + j * pixel_mm``,
        ``y = y0 - i * pixel_mm``.
    force : replace an existing file.
    comment : optional free text for the file's Record2 comment.

    Returns
    -------
    Path of the file written.
    """
    import x3pio

    from telefringe import __version__

    path = Path(path)
    z = np.asarray(hm.z, dtype=np.float32)
    rows = z.shape[0]
    # X3P rows grow with y: the TIFF's last row (smallest y) comes first
    z_x3p = z[::-1].astype(np.float64) * _MM  # metres; stored as float32 mm (z_scale)
    y_first = float(hm.y0) - (rows - 1) * float(hm.pixel_mm)
    meta = x3pio.Metadata.for_software("telefringe", __version__)
    meta.comment = comment or (
        "Height map of a telefringe reconstruction: world frame of the rig's calibration "
        "(z toward the camera); heights stored as float32 millimetres (z increment 1e-3 m); "
        "NaN = no data.")
    placement = x3pio.Placement.translation(float(hm.x0) * _MM, y_first * _MM, 0.0)
    pixel_m = float(hm.pixel_mm) * _MM
    with atomic_file(path, force=force) as tmp:
        x3pio.write(tmp, z_x3p, x_scale=pixel_m, y_scale=pixel_m,
                    z_type=x3pio.DataType.FLOAT32, z_scale=_MM, metadata=meta,
                    placement=placement, coordinate_system=x3pio.CoordinateSystem.VIEW)
    return path


def read_height_x3p(path):
    """Read an X3P surface (e.g. one written by :func:`write_height_x3p`) as a HeightMap.

    Every checksum stored in the file is verified (``main.xml`` and ``bindata``): a file
    changed or damaged after it was written is refused.

    Parameters
    ----------
    path : path-like, an ``.x3p`` file holding one surface layer on a regular grid with
        equal x and y spacing and no rotation.

    Returns
    -------
    telefringe.reconstruction.heightmap.HeightMap
        ``z`` (H, W) float32 mm in the TIFF's orientation (row 0 at the largest y).

    Raises
    ------
    InputError
        Not found, not an X3P file, a checksum mismatch, or a layout this reader does not
        handle (several layers, unequal spacing, a rotated placement).
    """
    import x3pio

    from telefringe.reconstruction.heightmap import HeightMap

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: not found")
    try:
        f = x3pio.read(path, verify=True)
    except x3pio.X3pChecksumError as exc:
        raise InputError(f"{path}: damaged or changed after it was written ({exc})") from None
    except (x3pio.X3pError, OSError, ValueError) as exc:
        raise InputError(f"{path}: not a readable X3P file ({exc})") from None
    if not isinstance(f, x3pio.Surface) or len(f.layers) != 1:
        raise InputError(f"{path}: expected one surface layer (feature type SUR)")
    layer = f.layers[0]
    if not layer.is_regular_grid:
        raise InputError(f"{path}: the surface is not on a regular grid")
    sx, sy = (float(s) for s in layer.spacing[:2])
    if not np.isclose(sx, sy, rtol=1e-12, atol=0.0):
        raise InputError(f"{path}: x and y spacing differ ({sx} m, {sy} m)")
    place = layer.placement
    if not np.allclose(np.asarray(place.rotation, dtype=float), np.eye(3), atol=0.0):
        raise InputError(f"{path}: a rotated placement is not supported")
    off = np.asarray(place.offset, dtype=float) / _MM
    z = (np.asarray(layer.z, dtype=np.float64) / _MM + off[2])[::-1]
    pixel_mm = sx / _MM
    rows = z.shape[0]
    return HeightMap(z.astype(np.float32), float(off[0]),
                     float(off[1] + (rows - 1) * pixel_mm), pixel_mm)
