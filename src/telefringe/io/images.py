"""Reading and writing grayscale images safely (PNG / TIFF / BMP, 8 or 16 bit).

What is accepted (see docs/formats.md, "Images"):

- PNG: 8- or 16-bit grayscale, gray + alpha, RGB, RGBA; 8-bit palette images.
- TIFF: one page of unsigned 8- or 16-bit samples, grayscale (min-is-black, or
  min-is-white, which is inverted on reading), RGB or RGBA, any compression tifffile reads.
- BMP: 8-, 24- or 32-bit, uncompressed.

Colour is converted to gray with the ITU-R BT.601 weights (0.299 R + 0.587 G + 0.114 B,
rounded to the nearest count); alpha is ignored. Everything else is refused with an
:class:`~telefringe.io.errors.InputError` naming the file: 1-, 2- and 4-bit images (a
fringe capture needs at least 8 bits: such a file is a mask or a pattern, not a camera
frame), floating-point, signed or 32-bit samples (convert them to 16-bit integers),
multi-page TIFF, palette/CMYK/YCbCr/raw-Bayer TIFF, JPEG (lossy) and anything else.
The size and bit depth come from the header and are checked before any pixel is decoded,
so a file declaring a huge image (a decompression bomb) is refused cheaply, and so is a
scan whose images differ in size or bit depth.
"""

from __future__ import annotations

import contextlib
import logging
import stat
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from telefringe.io.errors import InputError

__all__ = ["read_image", "write_png", "image_header", "image_info", "ImageInfo", "MAX_PIXELS"]

#: Largest image accepted (pixels), checked from the header before decoding.
MAX_PIXELS = 100_000_000

_PNG_SIG = b"\x89PNG\r\n\x1a\n"
_TIFF_SIGS = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
# PNG colour type -> (name, channels, allowed bit depths)
_PNG_TYPES = {
    0: ("grayscale", 1, (1, 2, 4, 8, 16)),
    2: ("RGB", 3, (8, 16)),
    3: ("palette", 3, (1, 2, 4, 8)),
    4: ("gray + alpha", 2, (8, 16)),
    6: ("RGBA", 4, (8, 16)),
}
_LOW_DEPTH = ("a fringe capture needs 8 or 16 bits per sample; save the camera frames as "
              "8- or 16-bit grayscale")


@dataclass(frozen=True)
class ImageInfo:
    """What an image file's header declares (nothing decoded).

    Attributes
    ----------
    format : str, ``"png"``, ``"tiff"`` or ``"bmp"``.
    rows, cols : int, image size in pixels.
    bits : int, bits per sample of the decoded image: 8 or 16.
    channels : int, samples per pixel in the file (1 gray, 2 gray + alpha, 3 colour,
        4 colour + alpha); what :func:`read_image` returns is always one channel.
    """

    format: str
    rows: int
    cols: int
    bits: int
    channels: int

    @property
    def shape(self) -> tuple[int, int]:
        return (self.rows, self.cols)

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(np.uint8 if self.bits == 8 else np.uint16)


# --------------------------------------------------------------------------- headers
def _read_head(path: Path, n: int) -> tuple[bytes, int]:
    try:
        st = path.stat()
    except OSError as exc:
        raise InputError(f"{path}: cannot read image ({exc.strerror or exc})") from None
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"{path}: not a regular file")
    if st.st_size == 0:
        raise InputError(f"{path}: the file is empty (0 bytes)")
    try:
        with open(path, "rb") as f:
            return f.read(n), st.st_size
    except OSError as exc:
        raise InputError(f"{path}: cannot read image ({exc.strerror or exc})") from None


def _png_info(path: Path, head: bytes) -> ImageInfo:
    if len(head) < 33:
        raise InputError(f"{path}: truncated PNG (the file ends inside the IHDR header)")
    length, ctype = struct.unpack(">I4s", head[8:16])
    if ctype != b"IHDR" or length != 13:
        raise InputError(f"{path}: corrupt PNG (the first chunk is not a valid IHDR)")
    if zlib.crc32(head[12:29]) != struct.unpack(">I", head[29:33])[0]:
        raise InputError(f"{path}: corrupt PNG (IHDR checksum mismatch)")
    cols, rows, depth, color, comp, filt, interlace = struct.unpack(">IIBBBBB", head[16:29])
    if color not in _PNG_TYPES:
        raise InputError(f"{path}: corrupt PNG (unknown colour type {color})")
    name, channels, depths = _PNG_TYPES[color]
    if depth not in depths:
        raise InputError(f"{path}: corrupt PNG ({depth}-bit {name} is not valid PNG)")
    if comp != 0 or filt != 0 or interlace not in (0, 1):
        raise InputError(f"{path}: corrupt PNG (unknown compression, filter or interlace)")
    if depth < 8 and color == 0:
        raise InputError(f"{path}: {depth}-bit grayscale PNG is not accepted: {_LOW_DEPTH}")
    return ImageInfo("png", int(rows), int(cols), 8 if color == 3 else int(depth), channels)


def _tiff_info(path: Path) -> ImageInfo:
    with _tiff_file(path) as tif:
        n = len(tif.pages)
        if n == 0:
            raise InputError(f"{path}: corrupt TIFF (no image in it)")
        page = tif.pages[0]
        rows, cols = int(page.imagelength), int(page.imagewidth)
        bps, spp = page.bitspersample, int(page.samplesperpixel)
        fmt, photometric = int(page.sampleformat), int(page.photometric)
    if n != 1:
        raise InputError(f"{path}: TIFF holds {n} images; one image per file is expected")
    if fmt == 3:
        raise InputError(f"{path}: {bps}-bit floating-point TIFF is not accepted; convert the "
                         "frames to 16-bit unsigned integers (scaled to the camera's range)")
    if fmt != 1:
        raise InputError(f"{path}: signed or complex TIFF samples are not accepted; save "
                         "8- or 16-bit unsigned integers")
    if bps < 8:
        raise InputError(f"{path}: {bps}-bit TIFF is not accepted: {_LOW_DEPTH}")
    if bps not in (8, 16):
        raise InputError(f"{path}: {bps}-bit TIFF is not accepted; save 8- or 16-bit "
                         "unsigned integers")
    if photometric in (0, 1):  # min-is-white, min-is-black
        if spp not in (1, 2):
            raise InputError(f"{path}: grayscale TIFF with {spp} samples per pixel")
    elif photometric == 2:  # RGB
        if spp not in (3, 4):
            raise InputError(f"{path}: RGB TIFF with {spp} samples per pixel")
    else:
        names = {3: "palette", 5: "CMYK", 6: "YCbCr", 32803: "raw Bayer (CFA)",
                 34892: "linear raw"}
        what = names.get(photometric, f"photometric {photometric}")
        raise InputError(f"{path}: {what} TIFF is not accepted; save grayscale or RGB "
                         "(demosaiced) frames")
    return ImageInfo("tiff", rows, cols, int(bps), spp)


def _bmp_info(path: Path, head: bytes, size: int) -> ImageInfo:
    if len(head) < 30:
        raise InputError(f"{path}: truncated BMP header")
    offset, dib = struct.unpack("<II", head[10:18])
    if dib == 12:
        cols, rows, _, bpp = struct.unpack("<HHHH", head[18:26])
        comp = 0
    elif dib >= 40 and len(head) >= 34:
        cols, rows, _, bpp, comp = struct.unpack("<iiHHI", head[18:34])
    else:
        raise InputError(f"{path}: corrupt or unsupported BMP header")
    rows = abs(int(rows))
    if bpp not in (8, 24, 32):
        raise InputError(f"{path}: {bpp}-bit BMP is not accepted: {_LOW_DEPTH}")
    if comp not in (0, 3):  # BI_RGB, BI_BITFIELDS
        raise InputError(f"{path}: compressed BMP is not accepted; save PNG or TIFF")
    stride = ((int(cols) * bpp + 31) // 32) * 4
    if cols > 0 and rows > 0 and offset + stride * rows > size:
        raise InputError(f"{path}: truncated BMP ({size} bytes, the header needs "
                         f"{offset + stride * rows})")
    return ImageInfo("bmp", rows, int(cols), 8, 1 if bpp == 8 else 3)


def image_info(path, *, max_pixels: int = MAX_PIXELS) -> ImageInfo:
    """Read and check an image file's header without decoding its pixels.

    Parameters
    ----------
    path : path-like
    max_pixels : int
        Largest accepted ``rows * cols`` (default :data:`MAX_PIXELS`).

    Returns
    -------
    ImageInfo

    Raises
    ------
    InputError
        Missing, empty, truncated, unknown or unsupported file (see the module
        docstring), or a declared size of zero or above ``max_pixels``.
    """
    path = Path(path)
    head, size = _read_head(path, 64)
    if head.startswith(_PNG_SIG):
        info = _png_info(path, head)
    elif head[:4] in _TIFF_SIGS:
        info = _tiff_info(path)
    elif head[:2] == b"BM":
        info = _bmp_info(path, head, size)
    elif head[:3] == b"\xff\xd8\xff":
        raise InputError(f"{path}: JPEG is not accepted (lossy compression corrupts the "
                         "phase); save the frames as PNG or TIFF")
    else:
        raise InputError(f"{path}: not a PNG, TIFF or BMP image")
    if info.rows <= 0 or info.cols <= 0:
        raise InputError(f"{path}: the image declares a size of {info.cols} x {info.rows}")
    if info.rows * info.cols > max_pixels:
        raise InputError(
            f"{path}: the image declares {info.cols} x {info.rows} pixels, more than the "
            f"limit of {max_pixels} (refused before decoding)"
        )
    return info


def image_header(path: Path) -> tuple[int, int]:
    """Return (rows, cols) read from the file header, without decoding the pixels.

    Raises :class:`InputError` for an unreadable, empty, truncated, unknown or
    unsupported file (see :func:`image_info`, which this calls with no size limit).
    """
    info = image_info(path, max_pixels=np.iinfo(np.int64).max)
    return info.rows, info.cols


# --------------------------------------------------------------------------- decoding
@contextlib.contextmanager
def _tiff_file(path: Path):
    """Open a TIFF with tifffile; parser errors become InputError, its log is silenced."""
    import tifffile

    log = logging.getLogger("tifffile")
    level = log.level
    log.setLevel(logging.CRITICAL + 1)
    try:
        try:
            tif = tifffile.TiffFile(path)
        except Exception as exc:  # noqa: BLE001 - any parser error is a bad file
            raise InputError(f"{path}: corrupt TIFF ({exc})") from None
        with tif:
            try:
                yield tif
            except InputError:
                raise
            except Exception as exc:  # noqa: BLE001
                if "imagecodecs" in str(exc):
                    raise InputError(
                        f"{path}: this TIFF's compression needs the 'imagecodecs' package "
                        "(pip install imagecodecs), or save the frames uncompressed or with "
                        "zlib/deflate") from None
                raise InputError(f"{path}: corrupt or truncated TIFF ({exc})") from None
    finally:
        log.setLevel(level)


_ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2),
          (0, 1, 1, 2))
_PNG_SAMPLES = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}


def _png_raw_size(rows: int, cols: int, bits_per_pixel: int, interlaced: bool) -> int:
    """Bytes of filtered image data the header implies (a filter byte per row)."""
    if not interlaced:
        return rows * (1 + (cols * bits_per_pixel + 7) // 8)
    total = 0
    for x0, y0, dx, dy in _ADAM7:
        w = (cols - x0 + dx - 1) // dx if cols > x0 else 0
        h = (rows - y0 + dy - 1) // dy if rows > y0 else 0
        if w and h:
            total += h * (1 + (w * bits_per_pixel + 7) // 8)
    return total


def _check_png_chunks(path: Path, data: bytes) -> None:
    """Verify a PNG before it is decoded: every chunk inside the file with the right
    checksum, an IEND, and compressed image data that inflates to exactly the size the
    header declares, with valid row filters. So the decoder only sees sound files (and
    a truncated or corrupt one gets a message saying so)."""
    pos, n, idat, palette = 8, len(data), [], False
    while True:
        if pos + 8 > n:
            raise InputError(f"{path}: truncated PNG (the file ends after {n} bytes, "
                             "before the IEND chunk)")
        length, ctype = struct.unpack(">I4s", data[pos:pos + 8])
        name = ctype.decode("latin-1")
        if length > 0x7FFFFFFF or pos + 12 + length > n:
            raise InputError(f"{path}: truncated PNG (chunk {name!r} at byte {pos} needs "
                             f"{length} bytes, the file ends after {n})")
        crc = struct.unpack(">I", data[pos + 8 + length:pos + 12 + length])[0]
        if zlib.crc32(data[pos + 4:pos + 8 + length]) != crc:
            raise InputError(f"{path}: corrupt PNG (checksum mismatch in chunk {name!r} at "
                             f"byte {pos})")
        if ctype == b"IDAT":
            idat.append((pos + 8, pos + 8 + length))
        elif ctype == b"PLTE" and not idat:
            palette = True
        if ctype == b"IEND":
            break
        pos += 12 + length
    if not idat:
        raise InputError(f"{path}: corrupt PNG (no image data)")
    cols, rows, depth, color, _, _, interlace = struct.unpack(">IIBBBBB", data[16:29])
    if color == 3 and not palette:
        raise InputError(f"{path}: corrupt PNG (a palette image without its PLTE chunk)")
    bpp = depth * _PNG_SAMPLES[color]
    expected = _png_raw_size(rows, cols, bpp, interlace == 1)
    stride = 1 + (cols * bpp + 7) // 8
    inflater = zlib.decompressobj()
    got = 0
    view = memoryview(data)
    try:
        for a, b in idat:
            chunk = view[a:b]
            while chunk:
                out = inflater.decompress(chunk, 1 << 20)
                if got + len(out) > expected:
                    raise InputError(f"{path}: corrupt PNG (more image data than the "
                                     f"{cols} x {rows} header declares)")
                if not interlace and out:
                    # the filter bytes: every stride-th byte of the raw stream
                    filters = np.frombuffer(out, np.uint8)[(-got) % stride::stride]
                    if np.any(filters > 4):
                        raise InputError(f"{path}: corrupt PNG (invalid row filter)")
                got += len(out)
                chunk = inflater.unconsumed_tail
    except zlib.error as exc:
        raise InputError(f"{path}: corrupt PNG (compressed data: {exc})") from None
    if got != expected or not inflater.eof:
        raise InputError(f"{path}: truncated PNG (image data ends after {got} of "
                         f"{expected} bytes)")


def _cv2_decode(path: Path, data: bytes) -> np.ndarray:
    import cv2

    log = cv2.utils.logging
    level = log.getLogLevel()
    log.setLogLevel(log.LOG_LEVEL_SILENT)
    try:
        img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise InputError(f"{path}: cannot decode image ({str(exc).strip()})") from None
    finally:
        log.setLogLevel(level)
    if img is None:
        raise InputError(f"{path}: cannot decode image (truncated or corrupt data)")
    if img.ndim == 3:
        img = _to_gray(img[..., 2::-1] if img.shape[2] >= 3 else img[..., :1])
    return img


def _to_gray(rgb: np.ndarray) -> np.ndarray:
    """(rows, cols, 3) RGB or (rows, cols, 1) -> (rows, cols) gray of the same dtype,
    with the BT.601 weights, rounded to nearest (exact to half a count)."""
    if rgb.shape[-1] == 1:
        return np.ascontiguousarray(rgb[..., 0])
    gray = rgb.astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    top = np.iinfo(rgb.dtype).max
    return np.clip(np.rint(gray), 0, top).astype(rgb.dtype)


def _tiff_decode(path: Path) -> np.ndarray:
    with _tiff_file(path) as tif:
        page = tif.pages[0]
        img = page.asarray()
        spp, planar, photometric = int(page.samplesperpixel), int(page.planarconfig), \
            int(page.photometric)
    if spp > 1 and planar == 2:  # separate planes: (samples, rows, cols)
        img = np.moveaxis(img, 0, -1)
    if photometric == 2:  # RGB(A)
        img = _to_gray(img[..., :3])
    elif spp > 1:  # gray + extra samples
        img = img[..., 0]
    if photometric == 0:  # min-is-white: 0 is white
        img = np.iinfo(img.dtype).max - img
    return np.ascontiguousarray(img)


def read_image(path, *, max_pixels: int = MAX_PIXELS) -> np.ndarray:
    """Read a grayscale image as a (rows, cols) uint8 or uint16 array.

    Colour images are converted to gray (ITU-R BT.601 weights, rounded). The
    header is checked first (size against ``max_pixels``, bit depth, layout), so a
    decompression bomb or an unsupported file is refused before any decoding; a PNG's
    chunk structure and checksums are verified before it is decoded.

    Parameters
    ----------
    path : path-like, a PNG, TIFF or BMP file (the format is read from the file's
        first bytes, not from its name).
    max_pixels : int, largest accepted ``rows * cols``.

    Returns
    -------
    image : (rows, cols) ndarray of uint8 or uint16

    Raises
    ------
    InputError
        Missing, empty, truncated, oversized or undecodable file, or an unsupported
        bit depth or layout (see the module docstring).
    """
    path = Path(path)
    info = image_info(path, max_pixels=max_pixels)
    if info.format == "tiff":
        img = _tiff_decode(path)
    else:
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise InputError(f"{path}: cannot read image ({exc.strerror or exc})") from None
        if info.format == "png":
            _check_png_chunks(path, data)
        img = _cv2_decode(path, data)
    if img.dtype != info.dtype:
        raise InputError(f"{path}: decoded pixel type {img.dtype} differs from the "
                         f"{info.bits}-bit header")
    if img.shape != info.shape:
        raise InputError(f"{path}: decoded size {img.shape[1::-1]} differs from the "
                         f"header's {info.cols} x {info.rows}")
    return img


def write_png(path, image: np.ndarray) -> None:
    """Write a (rows, cols) uint8/uint16 array as PNG (``path`` written as given).

    Not atomic by itself: write into an :func:`~telefringe.io.atomic.atomic_dir` or via
    :func:`~telefringe.io.atomic.atomic_file`.
    """
    import cv2

    image = np.asarray(image)
    if image.dtype not in (np.uint8, np.uint16) or image.ndim != 2:
        raise ValueError(
            f"write_png needs a 2-D uint8/uint16 array, got {image.dtype} {image.shape}"
        )
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise OSError(f"{path}: PNG encoding failed")
    with open(path, "wb") as f:
        f.write(buf.tobytes())
