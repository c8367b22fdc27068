"""Decoded projector coordinates as ``.npz`` (written atomically).

Arrays (camera image shape (rows, cols)):

- ``u_p``, ``v_p`` float64, projector pixels, NaN where invalid (each only when the scan
  has fringes along that axis);
- ``mask`` bool, every present coordinate valid;
- ``modulation`` float64, DN, of the finest u group (v when there is no u);
- ``sigma_u_p``, ``sigma_v_p`` float64, projector pixels, standard uncertainty (NaN where
  invalid), with the coordinates they belong to.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from telefringe.io import _npz
from telefringe.io.atomic import atomic_file
from telefringe.io.errors import InputError

__all__ = ["write_coords", "read_coords", "COORD_ARRAYS"]

COORD_ARRAYS = ("u_p", "v_p", "mask", "modulation", "sigma_u_p", "sigma_v_p")


def write_coords(path, coords, *, force: bool = False) -> Path:
    """Write a :class:`telefringe.decode.ProjectorCoordinates` to ``path`` (.npz).

    Refuses to replace an existing file unless ``force``; never leaves a partial file.
    """
    path = Path(path)
    arrays = {}
    for name in COORD_ARRAYS:
        val = getattr(coords, name)
        if val is not None:
            arrays[name] = np.asarray(val)
    with atomic_file(path, force=force) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)
    return path


def read_coords(path) -> dict[str, np.ndarray]:
    """Read a coordinates file written by :func:`write_coords` (dict of arrays).

    Raises :class:`InputError` for a missing or malformed file.
    """
    path = Path(path)
    out = _npz.load(path, "coordinates")
    if "mask" not in out or not ({"u_p", "v_p"} & set(out)):
        raise InputError(f"{path}: not a coordinates file (needs 'mask' and 'u_p' or 'v_p')")
    return out
