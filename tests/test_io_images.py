"""Broken and unusual images through telefringe.io.images (issue 6, "Broken images").

Decisions tested here (documented in docs/formats.md, "Images"): 8- and 16-bit gray
is read as is; colour is converted to gray (BT.601); 1/2/4-bit, float, signed, 32-bit,
multi-page, palette/CMYK/raw-Bayer TIFF and JPEG are refused; the size is checked from
the header before decoding (a decompression bomb costs nothing).
"""

from __future__ import annotations

import struct
import time
import zlib

import cv2
import numpy as np
import pytest
import tifffile
from hypothesis import given, settings
from hypothesis import strategies as st

from telefringe.io.errors import InputError
from telefringe.io.images import MAX_PIXELS, image_header, image_info, read_image, write_png


def png_bytes(width, height, depth, color, rows, *, extra=b""):
    """A hand-made PNG (any header, any rows) so that hostile headers can be written."""
    def chunk(kind, data):
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data)))
    ihdr = struct.pack(">IIBBBBB", width, height, depth, color, 0, 0, 0)
    raw = b"".join(b"\0" + r for r in rows)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + extra
            + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


GRAY = (np.arange(48 * 64).reshape(48, 64) % 251).astype(np.uint8)


def _refused(path, *tokens):
    with pytest.raises(InputError) as info:
        read_image(path)
    msg = str(info.value)
    assert msg.startswith(str(path) + ":"), msg
    for t in tokens:
        assert t in msg, (t, msg)
    return msg


# --------------------------------------------------------------------------- good images
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_png_round_trip(tmp_path, dtype):
    img = GRAY.astype(dtype) * (257 if dtype == np.uint16 else 1)
    write_png(tmp_path / "a.png", img)
    back = read_image(tmp_path / "a.png")
    assert back.dtype == dtype and np.array_equal(back, img)
    info = image_info(tmp_path / "a.png")
    assert (info.format, info.rows, info.cols, info.bits, info.channels) == \
        ("png", 48, 64, np.dtype(dtype).itemsize * 8, 1)
    assert image_header(tmp_path / "a.png") == (48, 64)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("compression", [None, "zlib"])
def test_tiff_gray(tmp_path, dtype, compression):
    img = GRAY.astype(dtype) * 3
    tifffile.imwrite(tmp_path / "a.tif", img, compression=compression)
    assert np.array_equal(read_image(tmp_path / "a.tif"), img)


def test_tiff_needing_imagecodecs_says_so(tmp_path):
    """LZW is common in camera software; tifffile needs 'imagecodecs' to decode it."""
    try:
        import imagecodecs  # noqa: F401
    except ImportError:
        pass
    else:
        pytest.skip("imagecodecs is installed: LZW decodes")
    path = tmp_path / "lzw.tif"
    # an uncompressed TIFF relabelled as LZW: tifffile then asks for imagecodecs
    tifffile.imwrite(path, GRAY)
    with tifffile.TiffFile(path) as tif:
        off = tif.pages[0].tags["Compression"].valueoffset
    data = bytearray(path.read_bytes())
    struct.pack_into("<H", data, off, 5)
    path.write_bytes(bytes(data))
    _refused(path, "imagecodecs")


def test_format_comes_from_the_content_not_the_name(tmp_path):
    tifffile.imwrite(tmp_path / "looks.png", GRAY)
    write_png(tmp_path / "looks.tif", GRAY)
    assert np.array_equal(read_image(tmp_path / "looks.png"), GRAY)
    assert np.array_equal(read_image(tmp_path / "looks.tif"), GRAY)


def _bt601(rgb):
    return 0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_colour_is_converted_to_gray(tmp_path, dtype):
    rng = np.random.default_rng(1)
    top = np.iinfo(dtype).max
    rgb = rng.integers(0, top, (12, 10, 3), endpoint=True).astype(dtype)
    want = _bt601(rgb.astype(float))
    cv2.imwrite(str(tmp_path / "c.png"), rgb[..., ::-1])  # OpenCV writes BGR
    cv2.imwrite(str(tmp_path / "c4.png"), np.dstack([rgb[..., ::-1], rgb[..., :1]]))
    tifffile.imwrite(tmp_path / "c.tif", rgb, photometric="rgb")
    tifffile.imwrite(tmp_path / "cs.tif", np.moveaxis(rgb, -1, 0), photometric="rgb",
                     planarconfig="separate")
    for name in ("c.png", "c4.png", "c.tif", "cs.tif"):
        gray = read_image(tmp_path / name)
        assert gray.dtype == dtype and gray.shape == (12, 10)
        # rounded to the nearest count of the exact BT.601 gray
        assert np.max(np.abs(gray - want)) <= 0.5 + 1e-9, name


def test_gray_alpha_and_palette_png(tmp_path):
    ga = png_bytes(2, 1, 8, 4, [bytes([10, 255, 200, 0])])
    (tmp_path / "ga.png").write_bytes(ga)
    assert read_image(tmp_path / "ga.png").tolist() == [[10, 200]]  # alpha ignored
    pal = png_bytes(2, 1, 8, 3, [b"\x00\x01"]).replace(
        b"IDAT", b"IDAT", 1)
    # insert a PLTE chunk (black, white) before IDAT
    plte = b"\x00\x00\x00\xff\xff\xff"
    chunk = struct.pack(">I", 6) + b"PLTE" + plte + struct.pack(">I", zlib.crc32(b"PLTE" + plte))
    pal = png_bytes(2, 1, 8, 3, [b"\x00\x01"], extra=chunk)
    (tmp_path / "pal.png").write_bytes(pal)
    assert read_image(tmp_path / "pal.png").tolist() == [[0, 255]]


def test_min_is_white_tiff_is_inverted(tmp_path):
    tifffile.imwrite(tmp_path / "w.tif", GRAY, photometric="miniswhite")
    assert np.array_equal(read_image(tmp_path / "w.tif"), 255 - GRAY)


def test_bmp(tmp_path):
    cv2.imwrite(str(tmp_path / "a.bmp"), GRAY)
    cv2.imwrite(str(tmp_path / "c.bmp"), np.dstack([GRAY] * 3))
    assert np.array_equal(read_image(tmp_path / "a.bmp"), GRAY)
    assert np.array_equal(read_image(tmp_path / "c.bmp"), GRAY)
    data = (tmp_path / "a.bmp").read_bytes()
    (tmp_path / "t.bmp").write_bytes(data[:-100])
    _refused(tmp_path / "t.bmp", "truncated BMP")


# --------------------------------------------------------------------------- refused
def test_missing_empty_and_not_a_file(tmp_path):
    _refused(tmp_path / "nope.png", "cannot read image")
    (tmp_path / "empty.png").write_bytes(b"")
    _refused(tmp_path / "empty.png", "empty (0 bytes)")
    (tmp_path / "dir.png").mkdir()
    _refused(tmp_path / "dir.png", "not a regular file")


@pytest.mark.parametrize("content, token", [
    (b"hello world, not an image", "not a PNG, TIFF or BMP"),
    (b"\xff\xd8\xff\xe0\x00\x10JFIF", "JPEG is not accepted"),
    (b"GIF89a\x01\x00", "not a PNG, TIFF or BMP"),
    (b"\x89PNG\r\n\x1a\n", "truncated PNG"),
    (b"\x89PNG\r\n\x1a\n\x00\x00\x00\x0dIHDR\x00\x00", "truncated PNG"),
    (b"II*\x00\x08\x00\x00\x00", "corrupt"),
    (b"MM\x00*\xff\xff\xff\xff", "corrupt"),
    (b"BM\x00\x00", "truncated BMP"),
])
def test_garbage_is_refused(tmp_path, content, token):
    (tmp_path / "x.png").write_bytes(content)
    _refused(tmp_path / "x.png", token)


def test_truncated_png_at_every_length_is_refused(tmp_path):
    write_png(tmp_path / "a.png", GRAY)
    data = (tmp_path / "a.png").read_bytes()
    for n in sorted({*range(1, 60), *range(60, len(data), 97), len(data) - 1}):
        (tmp_path / "t.png").write_bytes(data[:n])
        with pytest.raises(InputError, match="t.png"):
            read_image(tmp_path / "t.png")


@settings(max_examples=100, deadline=None, derandomize=True)
@given(pos=st.integers(8, 10_000), value=st.integers(1, 255))
def test_any_flipped_byte_in_a_png_is_caught(tmp_path_factory, pos, value):
    """Every PNG chunk carries a CRC: one corrupt byte never decodes to wrong pixels."""
    folder = tmp_path_factory.mktemp("flip", numbered=True)
    write_png(folder / "a.png", GRAY)
    data = bytearray((folder / "a.png").read_bytes())
    pos = pos % len(data)
    data[pos] ^= value
    (folder / "b.png").write_bytes(bytes(data))
    try:
        img = read_image(folder / "b.png")
    except InputError:
        return
    # only bytes after IEND (ignored) may change without an error
    assert np.array_equal(img, GRAY), pos


@settings(max_examples=60, deadline=None, derandomize=True)
@given(data=st.binary(max_size=300), head=st.sampled_from(
    [b"", b"\x89PNG\r\n\x1a\n", b"II*\x00", b"MM\x00*", b"BM"]))
def test_random_bytes_never_crash(tmp_path_factory, data, head):
    path = tmp_path_factory.mktemp("rnd", numbered=True) / "r.img"
    path.write_bytes(head + data)
    try:
        img = read_image(path)
    except InputError:
        return
    assert img.ndim == 2 and img.dtype in (np.uint8, np.uint16)


@pytest.mark.parametrize("depth", [1, 2, 4])
def test_low_bit_depth_png_is_refused(tmp_path, depth):
    (tmp_path / "b.png").write_bytes(png_bytes(8, 2, depth, 0, [b"\xaa" * depth] * 2))
    _refused(tmp_path / "b.png", f"{depth}-bit grayscale PNG", "8 or 16 bits")


def test_invalid_png_headers(tmp_path):
    (tmp_path / "a.png").write_bytes(png_bytes(4, 4, 3, 0, [b"\0"] * 4))
    _refused(tmp_path / "a.png", "3-bit grayscale is not valid PNG")
    (tmp_path / "b.png").write_bytes(png_bytes(4, 4, 8, 7, [b"\0"] * 4))
    _refused(tmp_path / "b.png", "unknown colour type 7")
    (tmp_path / "c.png").write_bytes(png_bytes(0, 4, 8, 0, [b""] * 4))
    _refused(tmp_path / "c.png", "size of 0 x 4")
    data = bytearray(png_bytes(4, 4, 8, 0, [b"\0" * 4] * 4))
    data[29] ^= 1  # IHDR CRC
    (tmp_path / "d.png").write_bytes(bytes(data))
    _refused(tmp_path / "d.png", "IHDR checksum")


@pytest.mark.parametrize("size", [(100_000, 100_000), (2**31 - 1, 2**31 - 1), (20_000, 5_001)])
def test_decompression_bomb_is_refused_before_decoding(tmp_path, size):
    """A tiny file whose header declares a huge image: refused from the header alone."""
    (tmp_path / "bomb.png").write_bytes(png_bytes(*size, 8, 0, [b"\0"]))
    t0 = time.perf_counter()
    msg = _refused(tmp_path / "bomb.png", f"{size[0]} x {size[1]}", "refused before decoding")
    assert str(MAX_PIXELS) in msg
    assert time.perf_counter() - t0 < 1.0  # nothing was decoded
    assert image_header(tmp_path / "bomb.png") == (size[1], size[0])


def test_tiff_bomb_is_refused_before_decoding(tmp_path):
    # a real, small compressed TIFF whose IFD we patch to declare 100000 x 100000
    tifffile.imwrite(tmp_path / "b.tif", np.zeros((4, 4), np.uint8), compression="zlib")
    with tifffile.TiffFile(tmp_path / "b.tif") as tif:
        tags = tif.pages[0].tags
        offs = [(tags["ImageWidth"].valueoffset, tags["ImageWidth"].dtype),
                (tags["ImageLength"].valueoffset, tags["ImageLength"].dtype)]
    data = bytearray((tmp_path / "b.tif").read_bytes())
    for off, dtype in offs:
        fmt = "<I" if int(dtype) == 4 else "<H"
        struct.pack_into(fmt, data, off, 60_000)
    (tmp_path / "b.tif").write_bytes(bytes(data))
    _refused(tmp_path / "b.tif", "60000 x 60000", "refused before decoding")


def test_max_pixels_is_a_parameter(tmp_path):
    write_png(tmp_path / "a.png", GRAY)
    with pytest.raises(InputError, match="limit of 1000"):
        read_image(tmp_path / "a.png", max_pixels=1000)


@pytest.mark.parametrize("dtype, token", [
    (np.float32, "32-bit floating-point TIFF"),
    (np.float64, "64-bit floating-point TIFF"),
    (np.int16, "signed"),
    (np.uint32, "32-bit TIFF"),
    (bool, "1-bit TIFF"),
])
def test_unsupported_tiff_sample_types(tmp_path, dtype, token):
    tifffile.imwrite(tmp_path / "x.tif", (GRAY > 100).astype(dtype))
    _refused(tmp_path / "x.tif", token)


def test_multi_page_and_odd_tiffs(tmp_path):
    tifffile.imwrite(tmp_path / "m.tif", np.stack([GRAY, GRAY]))
    _refused(tmp_path / "m.tif", "holds 2 images")
    tifffile.imwrite(tmp_path / "p.tif", GRAY, photometric="palette",
                     colormap=np.tile(np.arange(256, dtype=np.uint16) * 257, (3, 1)))
    _refused(tmp_path / "p.tif", "palette TIFF")
    tifffile.imwrite(tmp_path / "k.tif", np.dstack([GRAY] * 4), photometric="separated")
    _refused(tmp_path / "k.tif", "CMYK TIFF")


@pytest.mark.parametrize("compression", [None, "zlib"])
def test_truncated_tiff_is_refused(tmp_path, compression):
    tifffile.imwrite(tmp_path / "a.tif", GRAY, compression=compression)
    data = (tmp_path / "a.tif").read_bytes()
    for n in (len(data) - 10, len(data) // 2, 200, 16, 9):
        (tmp_path / "t.tif").write_bytes(data[:n])
        _refused(tmp_path / "t.tif", "TIFF")


def test_nothing_is_printed_for_broken_files(tmp_path, capfd):
    """libpng / OpenCV / tifffile chatter must not reach the user's terminal."""
    write_png(tmp_path / "a.png", GRAY)
    data = (tmp_path / "a.png").read_bytes()
    # corrupt the compressed stream but fix the CRC, so the decoder itself fails
    idat = data.index(b"IDAT")
    n = struct.unpack(">I", data[idat - 4:idat])[0]
    body = bytearray(data[idat + 4: idat + 4 + n])
    body[2:12] = b"\xff" * 10
    fixed = (data[:idat + 4] + bytes(body)
             + struct.pack(">I", zlib.crc32(b"IDAT" + bytes(body))) + data[idat + 8 + n:])
    (tmp_path / "z.png").write_bytes(fixed)
    _refused(tmp_path / "z.png", "corrupt PNG")
    (tmp_path / "p.png").write_bytes(png_bytes(2, 1, 8, 3, [b"\x00\x01"]))  # no PLTE
    _refused(tmp_path / "p.png", "PLTE")
    tifffile.imwrite(tmp_path / "a.tif", GRAY)
    (tmp_path / "t.tif").write_bytes((tmp_path / "a.tif").read_bytes()[:200])
    _refused(tmp_path / "t.tif")
    out, err = capfd.readouterr()
    assert out == "" and "libpng" not in err and "WARN" not in err and "Tiff" not in err


def test_write_png_refuses_what_it_cannot_store(tmp_path):
    for bad in (GRAY.astype(float), np.dstack([GRAY] * 3), GRAY.astype(np.int16)):
        with pytest.raises(ValueError, match="write_png"):
            write_png(tmp_path / "x.png", bad)
    assert not (tmp_path / "x.png").exists()


def _png_bytes(raw: bytes, cols: int, rows: int) -> bytes:
    """A grey 8-bit PNG around raw (filtered) scanlines, with valid checksums."""

    def chunk(ctype: bytes, body: bytes) -> bytes:
        return (struct.pack(">I", len(body)) + ctype + body
                + struct.pack(">I", zlib.crc32(ctype + body)))

    head = struct.pack(">IIBBBBB", cols, rows, 8, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", head)
            + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


@pytest.mark.parametrize("bad_row", [None, 0, 500, 999])
def test_png_row_filters_are_checked_across_inflate_blocks(tmp_path, bad_row):
    # 1100 x 1000 px: 1.1 MB of raw data, inflated in 1 MiB pieces, so the last rows'
    # filter bytes sit in the second piece at an offset that is not a row start of it
    cols, rows = 1100, 1000
    raw = bytearray((np.arange(rows * (cols + 1)) % 251).astype(np.uint8).tobytes())
    raw[::cols + 1] = b"\x00" * rows  # filter "none" on every row
    if bad_row is not None:
        raw[bad_row * (cols + 1)] = 7
    path = tmp_path / "f.png"
    path.write_bytes(_png_bytes(bytes(raw), cols, rows))
    if bad_row is None:
        assert read_image(path).shape == (rows, cols)
    else:
        with pytest.raises(InputError, match="invalid row filter"):
            read_image(path)
