"""Reading and writing grayscale images safely (PNG / TIFF, 8 or 16 bit)."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from .errors import InputError

__all__ = ["read_image", "write_png", "image_header", "MAX_PIXELS"]

#: Largest image accepted (pixels), checked from the header before decoding.
MAX_PIXELS = 100_000_000

_PNG_SIG = b"\x89PNG\r\n\x1a\n"


def image_header(path: Path) -> tuple[int, int]:
    """Return (rows, cols) read from the file header, without decoding the pixels.

    Raises :class:`InputError` for an unreadable, empty, truncated or unknown file.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(64)
    except OSError as exc:
        raise InputError(f"{path}: cannot read image ({exc.strerror})") from None
    if size == 0:
        raise InputError(f"{path}: the file is empty (0 bytes)")
    if head.startswith(_PNG_SIG):
        if len(head) < 24 or head[12:16] != b"IHDR":
            raise InputError(f"{path}: truncated or corrupt PNG header")
        cols, rows = struct.unpack(">II", head[16:24])
        return int(rows), int(cols)
    if head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        import tifffile

        try:
            with tifffile.TiffFile(path) as tif:
                shape = tif.pages[0].shape
        except Exception as exc:  # noqa: BLE001 - any parser error is a bad file
            raise InputError(f"{path}: corrupt TIFF ({exc})") from None
        return int(shape[0]), int(shape[1])
    if head[:2] == b"BM" and len(head) >= 26:
        cols, rows = struct.unpack("<ii", head[18:26])
        return abs(int(rows)), abs(int(cols))
    raise InputError(f"{path}: not a PNG, TIFF or BMP image")


def read_image(path, *, max_pixels: int = MAX_PIXELS) -> np.ndarray:
    """Read a grayscale image as a (rows, cols) uint8 or uint16 array.

    Colour images are converted to gray (ITU-R BT.601 weights, as OpenCV does). The
    size declared in the header is checked against ``max_pixels`` before any decoding,
    so a decompression bomb is refused cheaply.

    Raises
    ------
    InputError
        Missing, empty, truncated, oversized or undecodable file, or an unsupported
        bit depth (only 8 and 16 bit integer images are accepted).
    """
    path = Path(path)
    rows, cols = image_header(path)
    if rows <= 0 or cols <= 0:
        raise InputError(f"{path}: image declares a size of {cols} x {rows}")
    if rows * cols > max_pixels:
        raise InputError(
            f"{path}: image declares {cols} x {rows} pixels, more than the limit "
            f"{max_pixels} (refused before decoding)"
        )
    if path.suffix.lower() in (".tif", ".tiff"):
        import tifffile

        try:
            img = tifffile.imread(path)
        except Exception as exc:  # noqa: BLE001
            raise InputError(f"{path}: cannot decode TIFF ({exc})") from None
    else:
        import cv2

        data = np.fromfile(path, dtype=np.uint8)
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
        if img is None:
            raise InputError(f"{path}: cannot decode image (truncated or corrupt)")
        if img.ndim == 3:
            if img.shape[2] == 4:
                img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
            elif img.shape[2] == 3:
                img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
            else:
                img = img[..., 0]
    if img.ndim == 3:
        if img.shape[-1] in (3, 4):
            w = np.array([0.299, 0.587, 0.114])
            gray = img[..., :3].astype(float) @ w
            img = np.round(gray).astype(img.dtype)
        else:
            raise InputError(f"{path}: unsupported image layout {img.shape}")
    if img.dtype not in (np.uint8, np.uint16):
        raise InputError(
            f"{path}: unsupported pixel type {img.dtype} (use 8- or 16-bit grayscale)"
        )
    if img.shape != (rows, cols):
        raise InputError(f"{path}: decoded size {img.shape} differs from its header")
    return img


def write_png(path, image: np.ndarray) -> None:
    """Write a (rows, cols) uint8/uint16 array as PNG (``path`` written as given)."""
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
        f.flush()
