"""The ``lightcrafter`` projector: TI DLP LightCrafter 4500 (DLPC350), HDMI + USB.

``--projector lightcrafter:[SERIAL][,monitor=SPEC]``: the controller found by its USB
serial (empty: the first DLPC350), its HDMI input being the desktop monitor SPEC (as for
the ``window`` projector; default: the last non-primary monitor).

- Streamed mode (:meth:`LightCrafterProjector.show`): the controller is put in video mode
  and the image goes out on HDMI through a borderless window (912 x 1140, the DMD's
  native diamond-pixel size).
- Sequenced mode (:meth:`~LightCrafterProjector.load_sequence`): up to three 8-bit
  patterns are packed into one 24-bit HDMI frame (pattern k in the colour plane that the
  LUT entry k names: G, R, B) and the controller shows them one after the other within each
  video frame (video pattern mode, VSYNC trigger), pulsing TRIG_OUT_1 for each so that
  the camera is triggered in hardware.

The USB side is our own encoder of TI's documented commands
(:mod:`~telefringe.acquisition.drivers.dlpc350`), sent through hidapi (PyPI ``hidapi``;
Linux needs read/write access to the hidraw device: see docs/acquisition_hardware.md).
What could not be tested without the hardware is listed there as a checklist.
"""

from __future__ import annotations

from collections.abc import Sequence

import hid  # hidapi: the optional package (its absence is the registry's one-line message)
import numpy as np

from telefringe.acquisition.base import (
    DeviceError,
    DeviceListing,
    NotSupported,
    ProjectorInfo,
    SequenceSettings,
    Shown,
)
from telefringe.acquisition.drivers import dlpc350 as _d

__all__ = ["LightCrafterProjector", "HidTransport", "open_projector", "list_projectors",
           "NATIVE_SIZE", "PLANE_OF_PATTERN"]

#: DMD size in pixels (width, height) of the LightCrafter 4500
NATIVE_SIZE = (912, 1140)
#: the colour plane (index into R, G, B) each 8-bit LUT pattern number shows
PLANE_OF_PATTERN = {0: 1, 1: 0, 2: 2}
_VIDEO_HZ = 60.0


class HidTransport:
    """64-byte HID reports to and from a DLPC350 through hidapi (either the ``hidapi``
    Cython module, ``hid.device``, or the ctypes ``hid`` package, ``hid.Device``)."""

    def __init__(self, serial: str = ""):
        devs = [d for d in hid.enumerate(_d.VID, _d.PID)
                if not serial or d.get("serial_number") == serial]
        if not devs:
            raise DeviceError(f"no DLP LightCrafter 4500 (USB {_d.VID:04x}:{_d.PID:04x}"
                              f"{' serial ' + serial if serial else ''}) found; is it powered "
                              f"and may this user open its hidraw device?")
        path = devs[0]["path"]
        try:
            if hasattr(hid, "device"):
                self._dev = hid.device()
                self._dev.open_path(path)
                self._read = lambda n, ms: bytes(self._dev.read(n, ms))
            else:
                self._dev = hid.Device(path=path)
                self._read = lambda n, ms: bytes(self._dev.read(n, ms) or b"")
        except Exception as exc:
            raise DeviceError(f"cannot open the LightCrafter's USB device: {exc}") from exc
        self.serial = devs[0].get("serial_number") or ""

    def write(self, report: bytes) -> None:
        self._dev.write(b"\0" + bytes(report))         # report id 0 first

    def read(self, timeout_ms: int) -> bytes:
        return self._read(_d.REPORT_SIZE, int(timeout_ms))

    def close(self) -> None:
        self._dev.close()


def list_projectors() -> list[DeviceListing]:
    """The DLPC350 controllers on USB."""
    return [DeviceListing("lightcrafter", d.get("serial_number") or "",
                          model=d.get("product_string") or "DLPC350",
                          serial=d.get("serial_number") or "",
                          detail=f"USB {_d.VID:04x}:{_d.PID:04x}")
            for d in hid.enumerate(_d.VID, _d.PID)]


def _parse(address: str) -> tuple[str, str]:
    serial, monitor = "", ""
    for part in filter(None, (p.strip() for p in address.split(","))):
        key, eq, value = part.partition("=")
        if eq and key == "monitor":
            monitor = value
        elif not eq and not serial:
            serial = part
        else:
            raise DeviceError(f"lightcrafter:{address}: expected [SERIAL][,monitor=SPEC]")
    return serial, monitor


def open_projector(address: str) -> LightCrafterProjector:
    """Open the LightCrafter named by ``address`` (see the module docstring)."""
    from telefringe.acquisition.drivers import window

    serial, monitor = _parse(address)
    transport = HidTransport(serial)
    try:
        win = window.WindowProjector(monitor, refresh_hz=_VIDEO_HZ)
    except Exception:
        transport.close()
        raise
    return LightCrafterProjector(_d.Dlpc350(transport), win, serial=transport.serial,
                                 address=address)


class LightCrafterProjector:
    """A LightCrafter 4500: DLPC350 control + an HDMI window (the Projector protocol).

    controller : :class:`~telefringe.acquisition.drivers.dlpc350.Dlpc350`. window : a
    window projector on the LightCrafter's HDMI input (``show`` / ``show_rgb``), of the
    DMD's size.
    """

    def __init__(self, controller: _d.Dlpc350, window, *, serial: str = "",
                 address: str = ""):
        w, h = NATIVE_SIZE
        if (window.info.width, window.info.height) != (w, h):
            raise DeviceError(f"the LightCrafter's HDMI monitor must be {w} x {h} (its DMD); "
                              f"the window is {window.info.width} x {window.info.height}")
        self.ctl = controller
        self.window = window
        self.clock = window.clock
        self.info = ProjectorInfo(driver="lightcrafter", model="DLP LightCrafter 4500 (DLPC350)",
                                  serial=serial, width=w, height=h, refresh_hz=_VIDEO_HZ,
                                  bit_depth=8, sequencer=True, address=address)
        self._mode = None
        self._frame = None
        self._count = 0

    def show(self, image: np.ndarray) -> Shown:
        """Show ``image`` ((1140, 912) uint8) as plain video."""
        if self._mode != "video":
            self.ctl.video_mode()
            self._mode = "video"
        return self.window.show(image)

    def load_sequence(self, images: Sequence[np.ndarray], *, exposure_s: float,
                      period_s: float | None = None,
                      trigger_out: bool = True) -> SequenceSettings:
        """Hold up to 3 8-bit patterns (each (1140, 912) uint8) in one HDMI frame, shown
        one after the other within each 60 Hz video frame, each lit ``exposure_s`` every
        ``period_s`` (None: the video frame divided by the pattern count)."""
        images = [np.asarray(im) for im in images]
        n = len(images)
        if not 1 <= n <= 3:
            raise NotSupported(f"the LightCrafter holds 1 to 3 8-bit patterns per video "
                               f"frame; got {n}: capture with --mode streamed (or sequence "
                               f"groups of at most 3)")
        if not trigger_out:
            raise NotSupported("the LightCrafter sequence always pulses TRIG_OUT_1")
        w, h = NATIVE_SIZE
        for im in images:
            if im.shape != (h, w) or im.dtype != np.uint8:
                raise ValueError(f"each pattern must be ({h}, {w}) uint8, got {im.shape} "
                                 f"{im.dtype}")
        frame_us = int(1e6 / _VIDEO_HZ)
        period_us = int(round(period_s * 1e6)) if period_s else frame_us // n
        exposure_us = int(round(exposure_s * 1e6))
        if period_us * n > frame_us:
            raise NotSupported(f"{n} patterns of {period_us} us do not fit in one "
                               f"{frame_us} us video frame: shorten the exposure, or capture "
                               f"with --mode streamed")
        entries = [_d.lut_entry(trigger=0 if k == 0 else 3, pattern=k, bit_depth=8, leds=7,
                                buffer_swap=k == 0) for k in range(n)]
        rgb = np.zeros((h, w, 3), dtype=np.uint8)
        for k, im in enumerate(images):
            rgb[..., PLANE_OF_PATTERN[k]] = im
        self.ctl.load_video_patterns(entries, exposure_us=exposure_us, period_us=period_us,
                                     repeat=True)
        self._mode = "pattern"
        self._frame = rgb
        self._count = n
        return SequenceSettings(count=n, period_s=period_us * 1e-6,
                                exposure_s=exposure_us * 1e-6, trigger_out=True)

    def start_sequence(self, repeats: int = 1) -> Shown:
        """Put the packed frame on HDMI and start the controller's sequence; it repeats
        every video frame until :meth:`stop_sequence` (the camera takes the frames it
        needs: ``repeats`` is the number of passes the capture will collect)."""
        if self._frame is None:
            raise DeviceError("load_sequence() before start_sequence()")
        shown = self.window.show_rgb(self._frame)
        self.ctl.start()
        return shown

    def stop_sequence(self) -> None:
        if self._mode == "pattern":
            self.ctl.stop()

    def close(self) -> None:
        try:
            self.stop_sequence()
            self.ctl.video_mode()
        finally:
            self.window.close()
            t = getattr(self.ctl.t, "close", None)
            if t is not None:
                t()

    def __enter__(self) -> LightCrafterProjector:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
