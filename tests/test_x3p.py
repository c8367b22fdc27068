"""``heightmap.x3p`` (ISO 25178-72): read back equal to ``heightmap.tif``, its checksums
guard it, and the container holds what the standard asks for."""

from __future__ import annotations

import hashlib
import io
import re
import zipfile

import numpy as np
import pytest

from telefringe.io.errors import InputError
from telefringe.io.tiff import read_height_tiff, write_height_tiff
from telefringe.io.x3p import read_height_x3p, write_height_x3p
from telefringe.reconstruction.heightmap import HeightMap


def _height_map(seed=0, shape=(37, 53)):
    rng = np.random.default_rng(seed)
    z = rng.normal(0.3, 1.5, shape).astype(np.float32)
    z[rng.random(shape) < 0.2] = np.nan
    z[0, 0] = 1e-30  # tiny and large magnitudes survive unchanged
    z[0, 1] = -4.0e3
    return HeightMap(z, x0=-3.17, y0=25.3, pixel_mm=0.0325617)


def test_x3p_reads_back_equal_to_the_float_tiff(tmp_path):
    hm = _height_map()
    write_height_tiff(tmp_path / "h.tif", hm)
    write_height_x3p(tmp_path / "h.x3p", hm)
    tif = read_height_tiff(tmp_path / "h.tif")
    x3p = read_height_x3p(tmp_path / "h.x3p")
    assert x3p.z.dtype == np.float32 and x3p.z.shape == tif.z.shape
    # bit for bit, NaN (no data) at the same places
    assert np.array_equal(x3p.z.view(np.uint32)[np.isfinite(tif.z)],
                          tif.z.view(np.uint32)[np.isfinite(tif.z)])
    assert np.array_equal(np.isnan(x3p.z), np.isnan(tif.z))
    # the grid: metres in the file, mm here (one rounding of a product each way)
    assert x3p.pixel_mm == pytest.approx(tif.pixel_mm, rel=1e-14)
    assert x3p.x0 == pytest.approx(tif.x0, abs=1e-12)
    assert x3p.y0 == pytest.approx(tif.y0, abs=1e-12)
    # no overwrite without force
    with pytest.raises(InputError, match="already exists"):
        write_height_x3p(tmp_path / "h.x3p", hm)


def test_x3p_container_layout(tmp_path):
    import x3pio

    hm = _height_map(1, (6, 9))
    path = write_height_x3p(tmp_path / "h.x3p", hm)
    with zipfile.ZipFile(path) as zf:
        names = set(zf.namelist())
        assert {"main.xml", "md5checksum.hex", "bindata/data.bin"} <= names
        main = zf.read("main.xml")
        stored = zf.read("md5checksum.hex").decode().split()[0].lower()
        assert stored == hashlib.md5(main).hexdigest()
        data = np.frombuffer(zf.read("bindata/data.bin"), dtype="<f4").reshape(6, 9)
    text = main.decode()
    assert "<FeatureType>SUR</FeatureType>" in text
    assert re.search(r"<CZ>.*<DataType>F</DataType>", text, re.S)
    # x fastest, row 0 = smallest y: the TIFF's rows reversed, millimetres stored
    assert np.array_equal(data, hm.z[::-1], equal_nan=True)
    # an independent reader (x3pio itself): heights in metres, x and y of the first point
    f = x3pio.read(path)
    layer = f.layers[0]
    np.testing.assert_allclose(layer.z, hm.z[::-1].astype(np.float64) * 1e-3, rtol=1e-15)
    off = np.asarray(layer.placement.offset)
    assert off[0] == pytest.approx(hm.x0 * 1e-3, abs=1e-15)
    assert off[1] == pytest.approx((hm.y0 - 5 * hm.pixel_mm) * 1e-3, abs=1e-15)


def _rewrite(path, member, change):
    """A copy of the zip at ``path`` with ``member``'s bytes passed through ``change``."""
    buf = io.BytesIO()
    with zipfile.ZipFile(path) as src, zipfile.ZipFile(buf, "w") as dst:
        for info in src.infolist():
            data = src.read(info.filename)
            dst.writestr(info, change(data) if info.filename == member else data)
    path.write_bytes(buf.getvalue())


@pytest.mark.parametrize("member", ["bindata/data.bin", "main.xml"])
def test_a_corrupted_x3p_is_refused(tmp_path, member):
    hm = _height_map(2, (8, 8))
    path = write_height_x3p(tmp_path / "h.x3p", hm)
    read_height_x3p(path)  # intact: reads

    def flip(data: bytes) -> bytes:
        if member == "main.xml":  # a changed comment: the XML stays valid
            return data.replace(b"telefringe reconstruction", b"telefringe reconstructiom")
        b = bytearray(data)
        b[13] ^= 0x01  # one bit of one height
        return bytes(b)

    _rewrite(path, member, flip)
    with pytest.raises(InputError, match="damaged or changed"):
        read_height_x3p(path)


def test_not_an_x3p(tmp_path):
    (tmp_path / "x.x3p").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="not a readable X3P"):
        read_height_x3p(tmp_path / "x.x3p")
    with pytest.raises(InputError, match="not found"):
        read_height_x3p(tmp_path / "missing.x3p")
