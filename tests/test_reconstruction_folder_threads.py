"""write_reconstruction's threads: a height map made by a function (on a writer thread)
gives the same files as one given, its error reaches the caller after every thread ended,
and the summary function sees the map."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from telefringe.io.points_npz import read_points
from telefringe.io.reconstruction_folder import write_reconstruction
from telefringe.reconstruction.cloud import PointCloud, TriangulationError
from telefringe.reconstruction.heightmap import height_map

_NAMES = ("cloud.ply", "heightmap.tif", "heightmap.json", "heightmap_sigma.tif",
          "heightmap.png", "summary.json")


def _cloud(shape=(60, 70)):
    rng = np.random.default_rng(3)
    v, u = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    x, y = 0.05 * u, -0.05 * v
    z = 0.2 + 0.02 * x - 0.01 * y + 0.003 * rng.standard_normal(shape)
    xyz = np.stack([x, y, z], axis=-1)
    xyz[10:14, 20:26] = np.nan
    return PointCloud.from_xyz(xyz, sigma_z=np.full(shape, 0.002))


def _summary(hm):
    return {"heightmap": None if hm is None else list(hm.z.shape)}


def test_height_map_function_gives_the_same_files(tmp_path):
    cloud = _cloud()
    tex = np.random.default_rng(4).uniform(0, 255, cloud.shape).astype(np.float32)
    given, made = tmp_path / "given", tmp_path / "made"
    given.mkdir()
    made.mkdir()
    hm = height_map(cloud)
    a = write_reconstruction(given, cloud, hm, texture=tex, title="t",
                             summary=_summary(hm))
    threads = []

    def make():
        threads.append(threading.current_thread())
        return height_map(cloud)

    b = write_reconstruction(made, cloud, make, texture=tex, title="t", summary=_summary)
    assert list(a) == list(b)  # the same names in the same order
    assert threads and threads[0] is not threading.main_thread()
    for name in _NAMES:
        assert (given / name).read_bytes() == (made / name).read_bytes(), name
    ca, cb = read_points(given)[0], read_points(made)[0]
    assert np.array_equal(ca.xyz, cb.xyz, equal_nan=True)
    from telefringe.io.x3p import read_height_x3p

    assert np.array_equal(read_height_x3p(b["heightmap_x3p"]).z, hm.z, equal_nan=True)


def test_no_height_map_from_the_function(tmp_path):
    out = write_reconstruction(tmp_path, _cloud(), lambda: None, summary=_summary)
    assert set(out) == {"points", "ply", "summary"}
    assert not list(tmp_path.glob("heightmap*"))
    assert (tmp_path / "summary.json").read_text().strip().endswith("}")
    assert '"heightmap": null' in (tmp_path / "summary.json").read_text()


def test_height_map_error_reaches_the_caller(tmp_path):
    def fail():
        raise TriangulationError("no map")

    with pytest.raises(TriangulationError, match="no map"):
        write_reconstruction(tmp_path, _cloud(), fail, summary=_summary)
    # the point files were written before; no height-map file and no writer thread left
    assert not list(tmp_path.glob("heightmap*"))
    assert not [t for t in threading.enumerate() if t.name.startswith("telefringe-write")]
