"""Argument checks shared by the camera drivers' ``configure`` (aravis, gentl, pylon)."""

from __future__ import annotations

from telefringe.acquisition.base import PIXEL_FORMAT_MAX, CameraInfo, DeviceError, NotSupported

__all__ = ["check_configure", "full_roi"]


def check_configure(info: CameraInfo, pixel_format: str, *, acquiring: bool,
                    unknown_formats_ok: bool = False) -> None:
    """Refuse to configure while acquiring (DeviceError) or a pixel format telefringe does
    not read or the camera does not offer (NotSupported). ``unknown_formats_ok``: a camera
    whose formats could not be listed (empty ``info.pixel_formats``) is let through."""
    if acquiring:
        raise DeviceError("configure the camera before start(), not while acquiring")
    if pixel_format not in PIXEL_FORMAT_MAX:
        raise NotSupported(f"pixel format {pixel_format!r} is not supported; use one of "
                           f"{', '.join(PIXEL_FORMAT_MAX)}")
    if unknown_formats_ok and not info.pixel_formats:
        return
    if pixel_format not in info.pixel_formats:
        raise NotSupported(f"camera {info.model} offers "
                           f"{', '.join(info.pixel_formats) or 'no monochrome format'}"
                           f", not {pixel_format}")


def full_roi(roi, info: CameraInfo) -> tuple[int, int, int, int]:
    """``roi`` (x, y, width, height) px as ints, or the whole sensor when None."""
    x, y, w, h = roi if roi is not None else (0, 0, info.width, info.height)
    return int(x), int(y), int(w), int(h)
