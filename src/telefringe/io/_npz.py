"""Reading ``.npz`` files: one place that maps NumPy's errors to :class:`InputError`."""

from __future__ import annotations

import zipfile
import zlib
from pathlib import Path

import numpy as np
from numpy.lib.npyio import NpzFile

from telefringe.io.errors import InputError

__all__ = ["load"]


def load(path, kind: str, *, missing_hint: str = "") -> dict[str, np.ndarray]:
    """All arrays of the ``.npz`` archive ``path`` (read into memory, no pickles).

    Parameters
    ----------
    path : path-like.
    kind : what the file should be, for messages ("points", "coordinates", ...).
    missing_hint : appended to the message for a missing file (e.g. the command that
        writes it).

    Raises
    ------
    InputError
        ``"{path}: not found{missing_hint}"``, or ``"{path}: not a {kind} file (...)"``
        for anything NumPy cannot read as an archive of plain arrays (a ``.npy`` file,
        pickled objects, a truncated or foreign file).
    """
    path = Path(path)
    # the file is opened here, not by np.load: np.load leaks its handle when the archive
    # is corrupt (numpy 2.x)
    try:
        f = open(path, "rb")  # closed by the with below
    except FileNotFoundError:
        raise InputError(f"{path}: not found{missing_hint}") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a folder, expected a {kind} file") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    with f:
        try:
            z = np.load(f, allow_pickle=False)
            if not isinstance(z, NpzFile):  # a .npy file: one array
                raise ValueError("a single array, not an .npz archive")
            with z:
                return {k: z[k] for k in z.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
            raise InputError(f"{path}: not a {kind} file ({exc})") from None
