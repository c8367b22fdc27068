"""Exports: points.npz round trip, PLY, float TIFF + sidecar, PNG previews, BGA CSV/map."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from telefringe.io.bga_csv import write_bga_csv
from telefringe.io.errors import InputError
from telefringe.io.figures.bga_png import write_bga_png
from telefringe.io.figures.heightmap_png import write_height_png
from telefringe.io.jsonable import to_jsonable, write_json
from telefringe.io.ply import write_ply
from telefringe.io.points_npz import load_points, read_points, write_points
from telefringe.io.reconstruction_folder import write_reconstruction
from telefringe.io.tiff import read_height_tiff, write_height_tiff
from telefringe.metrology import BGANominal, fit_plane, measure_bga
from telefringe.reconstruction.cloud import PointCloud
from telefringe.reconstruction.heightmap import height_map

PNG_SIG = b"\x89PNG\r\n\x1a\n"


def small_cloud(seed=0, shape=(40, 50)):
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    x, y = 0.05 * u, -0.05 * v
    z = 0.3 + 0.01 * x + 0.002 * rng.standard_normal(shape)
    xyz = np.stack([x, y, z], axis=-1)
    xyz[5:9, 7:12] = np.nan
    return PointCloud.from_xyz(xyz, sigma_z=np.full(shape, 0.002))


def test_points_round_trip(tmp_path):
    cloud = small_cloud()
    tex = np.random.default_rng(1).uniform(0, 255, cloud.shape).astype(np.float32)
    p = write_points(tmp_path / "points.npz", cloud, texture=tex)
    c2, t2 = read_points(tmp_path)  # a folder works too
    assert np.array_equal(c2.mask, cloud.mask)
    assert np.array_equal(c2.xyz, cloud.xyz, equal_nan=True)
    assert np.array_equal(c2.sigma_z, cloud.sigma_z, equal_nan=True)
    assert np.array_equal(c2.flags, cloud.flags)
    assert np.array_equal(t2, tex)
    assert c2.residual is None
    with np.load(p) as z:
        assert {"xyz", "mask", "sigma_z"} <= set(z.files)
        assert z["xyz"].shape == cloud.shape + (3,)
    with pytest.raises(InputError, match="already exists"):
        write_points(p, cloud)
    write_points(p, cloud, force=True)
    with pytest.raises(ValueError, match="texture"):
        write_points(tmp_path / "x.npz", cloud, texture=tex[:-1])
    rad = 3.0 * tex
    write_points(tmp_path / "r.npz", cloud, radiance=rad)
    pf = load_points(tmp_path / "r.npz")
    assert pf.texture is None and np.array_equal(pf.radiance, rad)
    assert np.array_equal(pf.cloud.xyz, cloud.xyz, equal_nan=True)


def test_read_points_refuses_bad_files(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_points(tmp_path / "nope.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="not a points file"):
        read_points(tmp_path / "junk.npz")
    np.savez(tmp_path / "other.npz", xyz=np.zeros((2, 2, 3)))
    with pytest.raises(InputError, match="not a telefringe points file"):
        read_points(tmp_path / "other.npz")
    cloud = small_cloud()
    write_points(tmp_path / "p.npz", cloud)
    with np.load(tmp_path / "p.npz") as z:
        arrays = {k: z[k] for k in z.files}
    bad = dict(arrays, mask=np.ones(cloud.shape, bool))  # marks NaN points valid
    np.savez(tmp_path / "bad.npz", **bad)
    with pytest.raises(InputError, match="not finite"):
        read_points(tmp_path / "bad.npz")
    bad = dict(arrays, version=np.array(7))
    np.savez(tmp_path / "bad2.npz", **bad)
    with pytest.raises(InputError, match="version"):
        read_points(tmp_path / "bad2.npz")
    bad = dict(arrays, sigma_line=np.zeros((3, 3)))
    np.savez(tmp_path / "bad3.npz", **bad)
    with pytest.raises(InputError, match="shape"):
        read_points(tmp_path / "bad3.npz")


def test_points_versions_and_per_pixel_directions(tmp_path):
    """Version 2 keeps one direction or one per pixel; a version-1 file (one 'direction',
    as written before version 2) still loads to the same cloud."""
    cloud = small_cloud()
    p = write_points(tmp_path / "p.npz", cloud)
    with np.load(p) as z:
        arrays = {k: z[k] for k in z.files}
    assert int(arrays["version"]) == 2 and arrays["directions"].shape == (3,)
    v1 = {k: v for k, v in arrays.items() if k != "directions"}
    v1.update(version=np.array(1), direction=arrays["directions"])
    np.savez(tmp_path / "v1.npz", **v1)
    old, _ = read_points(tmp_path / "v1.npz")
    assert np.array_equal(old.xyz, cloud.xyz, equal_nan=True)
    np.testing.assert_array_equal(old.direction, cloud.direction)
    # a cloud whose pixels look along different directions (a pinhole camera)
    rng = np.random.default_rng(4)
    d = rng.normal(size=cloud.shape + (3,)) + [0.0, 0.0, -5.0]
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    fan = PointCloud(cloud.xyz, cloud.mask, cloud.sigma_line, None, cloud.flags, d)
    write_points(tmp_path / "fan.npz", fan)
    back, _ = read_points(tmp_path / "fan.npz")
    np.testing.assert_allclose(back.directions, d, rtol=0, atol=1e-15)
    np.testing.assert_allclose(back.sigma_z, fan.sigma_z, rtol=1e-15)
    for bad_d in (np.array([0.0, 0.0, 2.0]), np.zeros((2, 2, 3)), np.full(3, np.nan)):
        np.savez(tmp_path / "bad.npz", **dict(arrays, directions=bad_d))
        with pytest.raises(InputError, match="directions"):
            read_points(tmp_path / "bad.npz")


def test_ply_binary_readable(tmp_path):
    from plyfile import PlyData

    cloud = small_cloud()
    tex = np.linspace(0, 255, cloud.mask.size).reshape(cloud.shape)
    p = write_ply(tmp_path / "cloud.ply", cloud, texture=tex)
    head = p.read_bytes()[:300]
    assert head.startswith(b"ply\nformat binary_little_endian 1.0\n")
    ply = PlyData.read(str(p))
    v = ply["vertex"]
    assert v.count == cloud.count
    names = [pr.name for pr in v.properties]
    assert names[:3] == ["x", "y", "z"] and "red" in names and "sigma_z" in names
    pts = cloud.points()
    assert np.allclose(v["x"], pts[:, 0], atol=1e-6)
    assert np.allclose(v["z"], pts[:, 2], atol=1e-6)
    # without texture or uncertainty: xyz only
    bare = PointCloud.from_xyz(cloud.xyz)
    ply = PlyData.read(str(write_ply(tmp_path / "bare.ply", bare)))
    assert [pr.name for pr in ply["vertex"].properties] == ["x", "y", "z"]


def test_height_tiff_and_sidecar(tmp_path):
    import tifffile

    cloud = small_cloud()
    hm = height_map(cloud, pixel_mm=0.05)
    tif, side = write_height_tiff(tmp_path / "heightmap.tif", hm)
    with tifffile.TiffFile(tif) as t:
        page = t.pages[0]
        z = page.asarray()
        assert z.dtype == np.float32 and z.shape == hm.z.shape
        xres = page.tags["XResolution"].value
        assert page.tags["ResolutionUnit"].value == 3  # centimetre
        assert xres[0] / xres[1] == pytest.approx(10.0 / 0.05, rel=1e-6)
        meta = json.loads(page.description)
        assert meta["pixel_mm"] == 0.05
    assert np.array_equal(z, hm.z, equal_nan=True)
    assert np.isnan(z).any()
    meta = json.loads(side.read_text())
    assert meta["x0_mm"] == hm.x0 and meta["y0_mm"] == hm.y0 and meta["units"] == "mm"
    assert (tmp_path / "heightmap_sigma.tif").exists()
    hm2 = read_height_tiff(tif)
    assert hm2.pixel_mm == hm.pixel_mm and np.array_equal(hm2.z, hm.z, equal_nan=True)
    with pytest.raises(InputError, match="already exists"):
        write_height_tiff(tif, hm)


def test_previews_are_png(tmp_path):
    cloud = small_cloud()
    hm = height_map(cloud)
    p = write_height_png(tmp_path / "h.png", hm, title="test")
    assert p.read_bytes()[:8] == PNG_SIG
    # an all-NaN map still renders
    from telefringe.reconstruction.heightmap import HeightMap

    p = write_height_png(tmp_path / "nan.png", HeightMap(np.full((4, 5), np.nan, np.float32),
                                                         0.0, 0.0, 0.1))
    assert p.read_bytes()[:8] == PNG_SIG


def test_write_reconstruction(tmp_path):
    cloud = small_cloud()
    out = write_reconstruction(tmp_path, cloud, height_map(cloud), title="x",
                               summary={"valid": np.int64(cloud.count), "s": np.nan})
    for name in ("points.npz", "cloud.ply", "heightmap.tif", "heightmap.json",
                 "heightmap.png", "heightmap_sigma.tif", "summary.json"):
        assert (tmp_path / name).exists(), name
    assert set(out) == {"points", "ply", "heightmap", "heightmap_json", "heightmap_png",
                        "heightmap_x3p", "summary"}
    assert json.loads(out["summary"].read_text()) == {"valid": cloud.count, "s": None}
    # the X3P beside the TIFF holds the same heights, bit for bit (tests/test_x3p.py)
    from telefringe.io.tiff import read_height_tiff
    from telefringe.io.x3p import read_height_x3p

    assert np.array_equal(read_height_x3p(out["heightmap_x3p"]).z,
                          read_height_tiff(out["heightmap"]).z, equal_nan=True)
    with pytest.raises(InputError, match="already exists"):  # nothing replaced unforced
        write_reconstruction(tmp_path, cloud, height_map(cloud))
    with pytest.raises(InputError):
        write_reconstruction(tmp_path / "missing", cloud)


def test_preview_map_is_the_least_binning_that_fits_the_preview():
    from telefringe.io.reconstruction_folder import PREVIEW_PIXELS, preview_map
    from telefringe.reconstruction.heightmap import HeightMap

    assert PREVIEW_PIXELS == 800
    big = HeightMap(np.zeros((900, 1700)), 0.0, 0.0, 0.01)
    p = preview_map(big)  # factor ceil(1700 / 800) = 3, partial edge blocks kept
    assert p.z.shape == (300, 567) and p.pixel_mm == pytest.approx(0.03)
    edge = HeightMap(np.zeros((10, 1600)), 0.0, 0.0, 0.01)
    assert preview_map(edge).z.shape == (5, 800)  # exactly 800: factor 2, not 3
    small = HeightMap(np.zeros((40, 50)), 0.0, 0.0, 0.01)
    assert preview_map(small) is small


def test_bga_csv_and_map(tmp_path):
    from test_metrology import bga_cloud

    cloud, present, offs, apex = bga_cloud(rows=4, cols=5, missing=((1, 2),))
    m = measure_bga(cloud, BGANominal(rows=4, cols=5, pitch_mm=0.8, ball_diameter_mm=0.45))
    p = write_bga_csv(tmp_path / "bga.csv", m)
    with open(p, newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 20
    miss = [r for r in rows if r["status"] == "missing"]
    assert [(int(r["row"]), int(r["col"])) for r in miss] == [(1, 2)]
    ok = [r for r in rows if r["status"] == "ok"]
    h = np.array([float(r["height_mm"]) for r in ok])
    assert np.allclose(h, m.height, atol=1e-6)
    assert sum(int(r["seating_contact"]) for r in ok) == len(m.coplanarity.contacts)
    assert max(float(r["coplanarity_mm"]) for r in ok) == pytest.approx(m.coplanarity.value,
                                                                         abs=1e-6)
    png = write_bga_png(tmp_path / "bga.png", m)
    assert png.read_bytes()[:8] == PNG_SIG


def test_to_jsonable(tmp_path):
    rng = np.random.default_rng(0)
    p = rng.normal(size=(50, 3))
    p[:, 2] *= 0.01
    fit = fit_plane(p)
    d = to_jsonable(fit)
    json.dumps(d, allow_nan=False)
    assert d["n_points"] == 50 and len(d["normal"]) == 3 and isinstance(d["inliers"][0], bool)
    assert to_jsonable({"a": np.nan, "b": (1, np.int64(2)), "c": np.array([1.0, np.inf])}) == {
        "a": None, "b": [1, 2], "c": [1.0, None]}
    out = write_json(tmp_path / "r.json", {"fit": fit})
    assert json.loads(out.read_text())["fit"]["n_points"] == 50


def test_height_preview_colours_follow_the_colour_bar(tmp_path):
    """The map's pixels carry the colour of their height on the preview's own scale, the
    colour bar runs from the top (high) to the bottom (low), no-data is grey, and drawing
    does not import a plotting library (the reconstruct command's start-up)."""
    import subprocess
    import sys

    import cv2

    from telefringe.io.figures.heightmap_png import height_colours
    from telefringe.reconstruction.heightmap import HeightMap

    z = np.tile(np.linspace(-1.0, 1.0, 200), (100, 1))  # rising left to right, mm
    z[:10, :10] = np.nan
    hm = HeightMap(z, 0.0, 10.0, 0.05)
    p = write_height_png(tmp_path / "ramp.png", hm)
    rgb = cv2.imread(str(p))[..., ::-1].astype(int)
    lo, hi = np.percentile(z[np.isfinite(z)], [0.5, 99.5])
    want = height_colours(z, lo, hi).astype(int)
    # find the map in the image: the block of the no-data grey at its top-left corner
    grey = np.all(rgb == (217, 217, 217), axis=2)
    r0, c0 = (int(v.min()) for v in np.nonzero(grey))
    scale = int(round(np.sqrt(grey.sum() / 100)))
    got = rgb[r0:r0 + 100 * scale:scale, c0:c0 + 200 * scale:scale]
    assert np.abs(got - want).max() <= 1
    # ends of the colour map: viridis' dark violet at lo, yellow at hi
    assert tuple(height_colours(np.array([lo - 1, hi + 1]), lo, hi)[0]) == (68, 1, 84)
    assert tuple(height_colours(np.array([lo - 1, hi + 1]), lo, hi)[1]) == (253, 231, 37)
    code = ("import sys, numpy as np\n"
            "from telefringe.io.figures.heightmap_png import write_height_png\n"
            "from telefringe.reconstruction.heightmap import HeightMap\n"
            f"write_height_png({str(tmp_path / 'x.png')!r}, HeightMap(np.zeros((4, 5)), 0, 0, 1))\n"
            "assert 'matplotlib' not in sys.modules\n")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_preview_tick_labels_are_round_and_never_minus_zero():
    from telefringe.io.figures.heightmap_png import _label, _ticks

    t = _ticks(-6.5, 37.2, 6)
    assert [_label(v, t[1] - t[0]) for v in t] == ["0", "10", "20", "30"]
    t = _ticks(-0.012, 0.334, 6)
    assert [_label(v, t[1] - t[0]) for v in t] == ["0.0", "0.1", "0.2", "0.3"]
    t = _ticks(0.0, 0.25, 6)  # step 0.05: two decimals
    assert [_label(v, t[1] - t[0]) for v in t] == ["0.00", "0.05", "0.10", "0.15", "0.20",
                                                   "0.25"]
