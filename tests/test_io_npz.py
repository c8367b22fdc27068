"""The shared .npz reader (telefringe.io._npz): every way a file can fail to be an archive
of plain arrays is one InputError naming the file and the expected kind."""

from __future__ import annotations

import numpy as np
import pytest

from telefringe.io import _npz
from telefringe.io.coords_npz import read_coords
from telefringe.io.errors import InputError
from telefringe.io.points_npz import read_points


def test_reads_every_array(tmp_path):
    a, b = np.arange(6.0).reshape(2, 3), np.array([True, False])
    np.savez(tmp_path / "x.npz", a=a, b=b)
    got = _npz.load(tmp_path / "x.npz", "test")
    assert set(got) == {"a", "b"}
    assert np.array_equal(got["a"], a) and np.array_equal(got["b"], b)
    assert got["a"].dtype == a.dtype and got["b"].dtype == bool


def test_refusals_name_the_file_and_the_kind(tmp_path):
    with pytest.raises(InputError, match=r"nope\.npz: not found \(hint\)$"):
        _npz.load(tmp_path / "nope.npz", "points", missing_hint=" (hint)")
    with pytest.raises(InputError, match="is a folder, expected a points file"):
        _npz.load(tmp_path, "points")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match=r"junk\.npz: not a points file"):
        _npz.load(tmp_path / "junk.npz", "points")
    # a single array (.npy) is not an archive (np.load returns an ndarray for it)
    np.save(tmp_path / "one.npy", np.zeros(3))
    with pytest.raises(InputError, match="not a coordinates file.*single array"):
        _npz.load(tmp_path / "one.npy", "coordinates")
    # pickled objects are never loaded
    np.savez(tmp_path / "obj.npz", a=np.array([{"x": 1}], dtype=object))
    with pytest.raises(InputError, match=r"obj\.npz: not a points file"):
        _npz.load(tmp_path / "obj.npz", "points")
    # a truncated archive
    np.savez(tmp_path / "full.npz", a=np.arange(1000.0))
    data = (tmp_path / "full.npz").read_bytes()
    (tmp_path / "cut.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match=r"cut\.npz: not a points file"):
        _npz.load(tmp_path / "cut.npz", "points")


def test_the_readers_use_it(tmp_path):
    np.save(tmp_path / "one.npy", np.zeros(3))
    with pytest.raises(InputError, match="not a points file"):
        read_points(tmp_path / "one.npy")
    with pytest.raises(InputError, match="not a coordinates file"):
        read_coords(tmp_path / "one.npy")
    with pytest.raises(InputError, match="run 'telefringe reconstruct' first"):
        read_points(tmp_path / "missing.npz")
