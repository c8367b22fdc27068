"""What a camera and a projector are to telefringe's capture, and how drivers are found.

This file is the contract between the capture sequences (``sequence.py``), the
verification (``verify.py``) and every driver (``drivers/``). It holds:

- small frozen dataclasses: :class:`CameraInfo`, :class:`CameraSettings`, :class:`Frame`,
  :class:`ProjectorInfo`, :class:`Shown`, :class:`SequenceSettings`;
- the :class:`Camera` and :class:`Projector` protocols and a :class:`Clock` (the sim pair
  runs on a virtual clock; real devices on :data:`SYSTEM_CLOCK`);
- the driver registry: ``DRIVER[:ADDRESS]`` strings (``sim``, ``aravis:127.0.0.1``,
  ``window:912x1140+1280+0``), each driver a module of ``telefringe.acquisition.drivers``
  imported only when asked for, so that the core never needs a driver's extra; a missing
  extra is one line saying what to install.

Units: seconds for durations (exposure, latency, timeouts, periods), integer nanoseconds
for time stamps, decibels for gain, pixels for images and regions.

A driver module ``telefringe.acquisition.drivers.NAME`` provides, for the kinds it serves:

- ``open_camera(address: str, *, projector=None) -> Camera`` (``projector``: the
  projector opened for the same capture, which a simulated camera renders from; real
  cameras ignore it);
- ``open_projector(address: str) -> Projector``;
- ``list_cameras() -> list[DeviceListing]`` / ``list_projectors() -> list[DeviceListing]``.

It imports its third-party package at module level, so that a missing package is an
``ImportError`` the registry turns into :class:`DriverUnavailable`.
"""

from __future__ import annotations

import enum
import importlib
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

__all__ = [
    "AcquisitionError", "DriverUnavailable", "DeviceError", "NotSupported",
    "Trigger", "FrameStatus", "PIXEL_FORMAT_MAX", "pixel_format_max",
    "CameraInfo", "CameraSettings", "Frame", "ProjectorInfo", "Shown", "SequenceSettings",
    "Clock", "SystemClock", "SYSTEM_CLOCK", "Camera", "Projector",
    "DeviceListing", "DriverEntry", "CAMERA_DRIVERS", "PROJECTOR_DRIVERS",
    "parse_spec", "open_camera", "open_projector", "list_devices", "load_driver",
]


# ------------------------------------------------------------------------------ errors
class AcquisitionError(RuntimeError):
    """A capture could not be done as asked (device, driver, or verification failure).

    The message is one line a user can act on; the command line prints it alone.
    """


class DriverUnavailable(AcquisitionError):
    """The driver's optional package is not installed (the message says what to install),
    or the driver is unknown."""


class DeviceError(AcquisitionError):
    """A device refused a setting, disappeared, or reported a failure."""


class NotSupported(AcquisitionError):
    """The device cannot do what was asked (e.g. a window projector has no sequencer)."""


# ------------------------------------------------------------------------- dataclasses
class Trigger(enum.Enum):
    """How a camera starts an exposure.

    SOFTWARE: on :meth:`Camera.fire`. HARDWARE: on an edge of an input line (a projector's
    trigger output; ``fire`` is then a no-op). FREE_RUN: continuously (not for capture of
    fringes: which pattern a frame saw is unknown; enumeration and focusing only).
    """

    SOFTWARE = "software"
    HARDWARE = "hardware"
    FREE_RUN = "free-run"


class FrameStatus(enum.Enum):
    """What the transport said about a frame.

    OK: complete. INCOMPLETE: a buffer arrived with missing packets/lines (its image may
    hold garbage). TIMEOUT: no frame within the grab's timeout (no image).
    """

    OK = "ok"
    INCOMPLETE = "incomplete"
    TIMEOUT = "timeout"


#: the largest pixel value of each supported monochrome pixel format (12-bit formats are
#: delivered in 16-bit containers, LSB-aligned like GenICam's Mono12)
PIXEL_FORMAT_MAX = {"Mono8": 255, "Mono10": 1023, "Mono12": 4095, "Mono14": 16383,
                    "Mono16": 65535}


def pixel_format_max(pixel_format: str) -> int:
    """The largest value of ``pixel_format`` (a GenICam PFNC name such as ``"Mono12"``).

    >>> pixel_format_max("Mono12")
    4095
    """
    try:
        return PIXEL_FORMAT_MAX[pixel_format]
    except KeyError:
        raise NotSupported(f"pixel format {pixel_format!r} is not supported; use one of "
                           f"{', '.join(PIXEL_FORMAT_MAX)}") from None


@dataclass(frozen=True)
class CameraInfo:
    """Who a camera is.

    driver : str, registry name (``"aravis"``). model, serial, vendor : str, as the device
    reports them ("" when unknown). width, height : int, full sensor size in pixels.
    pixel_formats : tuple of str, the monochrome formats it offers. address : str, the
    address it was opened with.
    """

    driver: str
    model: str
    serial: str
    vendor: str = ""
    width: int = 0
    height: int = 0
    pixel_formats: tuple[str, ...] = ()
    address: str = ""


@dataclass(frozen=True)
class CameraSettings:
    """The settings a camera actually applied (which may differ from the ones asked for:
    exposure and gain are rounded to the device's steps and clipped to its range).

    exposure_s : float, seconds. gain_db : float, dB. pixel_format : str (``"Mono12"``).
    roi : (x, y, width, height) ints, pixels of the full sensor. trigger : Trigger.
    trigger_line : str or None, the input line under HARDWARE (``"Line0"``).
    max_value : int, the largest pixel value of ``pixel_format`` (saturation level).
    """

    exposure_s: float
    gain_db: float
    pixel_format: str
    roi: tuple[int, int, int, int]
    trigger: Trigger
    trigger_line: str | None = None
    max_value: int = 255


@dataclass(frozen=True)
class Frame:
    """One frame from :meth:`Camera.grab`.

    image : ndarray (rows, cols) uint8 or uint16, or None when ``status`` is TIMEOUT.
    frame_id : int, the device's frame/block id (GigE Vision: 1..65535, wrapping to 1;
        -1 when there is none). timestamp_ns : int or None, the device's time stamp of the
        exposure start (its own clock; used for spacing checks). status : FrameStatus.
    message : str, the transport's words for a failure ("" when OK).
    """

    image: np.ndarray | None
    frame_id: int
    timestamp_ns: int | None
    status: FrameStatus
    message: str = ""

    @property
    def ok(self) -> bool:
        """True when the frame is complete."""
        return self.status is FrameStatus.OK


@dataclass(frozen=True)
class ProjectorInfo:
    """Who a projector is and what it can do.

    driver, model, serial : str. width, height : int, pixels. refresh_hz : float (0 when
    unknown). bit_depth : int, levels per pixel as shown (8 for HDMI). sequencer : bool,
    it can hold a pattern sequence and trigger the camera itself (:meth:`Projector.
    load_sequence`). address : str.
    """

    driver: str
    model: str
    serial: str
    width: int
    height: int
    refresh_hz: float
    bit_depth: int = 8
    sequencer: bool = False
    address: str = ""

    @property
    def period_s(self) -> float:
        """One refresh period in seconds (0 when the rate is unknown)."""
        return 1.0 / self.refresh_hz if self.refresh_hz > 0 else 0.0


@dataclass(frozen=True)
class Shown:
    """When :meth:`Projector.show` knew its image committed, on the projector's clock.

    t_ns : int, the clock time at which the image was handed to the display (window:
        after the buffer flip completed; sim: the refresh at which it takes effect). The
        light leaves the lens a display latency later, which ``telefringe capture
        latency`` measures. refresh : int or None, the refresh (vblank) counter, when known.
    """

    t_ns: int
    refresh: int | None = None


@dataclass(frozen=True)
class SequenceSettings:
    """What a sequencer projector actually loaded (see :meth:`Projector.load_sequence`).

    count : int, patterns. period_s : float, seconds from one pattern to the next.
    exposure_s : float, seconds each pattern is lit. trigger_out : bool, it pulses its
    trigger output at each pattern start.
    """

    count: int
    period_s: float
    exposure_s: float
    trigger_out: bool = True


@dataclass(frozen=True)
class DeviceListing:
    """One device a driver found (``telefringe capture devices``).

    driver : str. address : str, what to put after ``DRIVER:``. model, serial : str.
    detail : str, anything else worth showing (size, interface).
    """

    driver: str
    address: str
    model: str = ""
    serial: str = ""
    detail: str = ""


# ----------------------------------------------------------------------------- clocks
@runtime_checkable
class Clock(Protocol):
    """A clock the capture waits on: the system's for real devices, a virtual one for the
    simulated pair (so tests never sleep)."""

    def now_ns(self) -> int:
        """The current time, integer nanoseconds (monotonic)."""

    def wait_until(self, t_ns: int) -> None:
        """Return once ``now_ns() >= t_ns`` (at once if already past)."""


class SystemClock:
    """The host's monotonic clock (``time.monotonic_ns``); waits sleep, then spin for the
    last half millisecond (sleep alone overshoots by up to a scheduler tick)."""

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def wait_until(self, t_ns: int) -> None:
        while True:
            left = t_ns - time.monotonic_ns()
            if left <= 0:
                return
            if left > 1_000_000:
                time.sleep((left - 500_000) * 1e-9)


#: the clock of every real device
SYSTEM_CLOCK = SystemClock()


# ---------------------------------------------------------------------------- protocols
@runtime_checkable
class Camera(Protocol):
    """A camera, as the capture uses it. A context manager: leaving it stops and closes.

    Life cycle: ``configure`` -> ``start`` -> (``fire`` -> ``grab``)* -> ``stop`` ->
    ``close``. Under ``Trigger.HARDWARE`` frames come on the trigger line; ``fire`` does
    nothing.

    The one rule a driver must keep: **never return a stale frame silently**. ``grab``
    returns each delivered frame once, oldest first, with the device's frame id and time
    stamp; ``start`` and ``flush`` discard whatever was queued before; a frame that did
    not arrive is a TIMEOUT frame, never the previous image again.
    """

    info: CameraInfo

    def configure(self, *, exposure_s: float, gain_db: float = 0.0,
                  pixel_format: str = "Mono8",
                  roi: tuple[int, int, int, int] | None = None,
                  trigger: Trigger = Trigger.SOFTWARE,
                  trigger_line: str | None = None) -> CameraSettings:
        """Apply settings (only while stopped); return those actually set.

        exposure_s : float, seconds. gain_db : float. pixel_format : str (a key of
        :data:`PIXEL_FORMAT_MAX`). roi : (x, y, width, height) or None for the full
        sensor. trigger : Trigger. trigger_line : input line for HARDWARE, or None for
        the device's default.
        """

    def start(self, n_buffers: int = 8) -> None:
        """Start acquisition with ``n_buffers`` buffers; discards anything queued."""

    def fire(self) -> None:
        """Software trigger: start one exposure now (no-op under HARDWARE)."""

    def grab(self, timeout_s: float) -> Frame:
        """The oldest frame not yet returned, waiting up to ``timeout_s`` seconds; a
        TIMEOUT frame (image None) when none came."""

    def flush(self) -> int:
        """Discard queued frames (after a failure, before a retry); return how many."""

    def stop(self) -> None:
        """Stop acquisition (buffers are released; settings are kept)."""

    def close(self) -> None:
        """Release the device (idempotent)."""

    def __enter__(self) -> Camera: ...

    def __exit__(self, *exc) -> None: ...


@runtime_checkable
class Projector(Protocol):
    """A projector, as the capture uses it. A context manager: leaving it closes.

    Streamed mode (any projector): :meth:`show` one image, wait, trigger the camera.
    Sequenced mode (``info.sequencer``): :meth:`load_sequence` the patterns once, then
    :meth:`start_sequence`: the projector shows them at its own pace and pulses its
    trigger output for the camera (DLP LightCrafter style). Others raise
    :class:`NotSupported` there.
    """

    info: ProjectorInfo
    clock: Clock

    def show(self, image: np.ndarray) -> Shown:
        """Show ``image`` ((height, width) uint8, or uint16 when ``info.bit_depth`` > 8)
        until the next ``show``; return when it was committed (on :attr:`clock`)."""

    def load_sequence(self, images: Sequence[np.ndarray], *, exposure_s: float,
                      period_s: float | None = None,
                      trigger_out: bool = True) -> SequenceSettings:
        """Hold ``images`` (each (height, width)) as a sequence, each lit ``exposure_s``
        every ``period_s`` (None: the shortest the device allows); return what was set."""

    def start_sequence(self, repeats: int = 1) -> Shown:
        """Run the loaded sequence ``repeats`` times; return when it started."""

    def stop_sequence(self) -> None:
        """Stop a running sequence (no-op when none runs)."""

    def close(self) -> None:
        """Blank and release the device (idempotent)."""

    def __enter__(self) -> Projector: ...

    def __exit__(self, *exc) -> None: ...


# ----------------------------------------------------------------------------- registry
@dataclass(frozen=True)
class DriverEntry:
    """A driver the registry knows.

    name : str, as written before the colon. module : str, dotted module path.
    extra : str or None, the pip extra that installs what it needs. needs : str, what it
    needs in words (shown when missing). summary : str, one line for ``--help``.
    address : str, the form of the address after the colon.
    """

    name: str
    module: str
    extra: str | None
    needs: str
    summary: str
    address: str = ""
    kinds: tuple[str, ...] = field(default=("camera",))


_D = "telefringe.acquisition.drivers."

#: camera drivers by name
CAMERA_DRIVERS: dict[str, DriverEntry] = {
    "sim": DriverEntry("sim", _D + "sim", None, "nothing", "the virtual rig's camera "
                       "(pairs with the sim projector; virtual clock)",
                       "[preset=NAME,scene=NAME,seed=N,drop=P|@I+J,...]",
                       ("camera", "projector")),
    "aravis": DriverEntry("aravis", _D + "aravis", None,
                          "the Aravis 0.8 library (Debian: apt-get install libaravis-0.8-0)",
                          "GigE Vision / USB3 Vision cameras through Aravis",
                          "IP address, serial or device id"),
    "pylon": DriverEntry("pylon", _D + "pylon", "pylon", "Basler pypylon",
                         "Basler cameras through pylon", "serial number"),
    "gentl": DriverEntry("gentl", _D + "gentl", "gentl",
                         "harvesters and a GenTL producer (.cti)",
                         "any camera with a GenTL producer, through harvesters",
                         "PATH.cti[#INDEX]"),
}

#: projector drivers by name
PROJECTOR_DRIVERS: dict[str, DriverEntry] = {
    "sim": CAMERA_DRIVERS["sim"],
    "window": DriverEntry("window", _D + "window", "window", "pyglet",
                          "a borderless full-screen window on a monitor (HDMI projectors)",
                          "MONITOR-INDEX or WIDTHxHEIGHT+X+Y", ("projector",)),
    "lightcrafter": DriverEntry("lightcrafter", _D + "lightcrafter", "lightcrafter",
                                "hidapi (PyPI 'hidapi')",
                                "TI DLP LightCrafter 4500 (DLPC350) over USB, as a sequencer",
                                "USB serial or empty for the first", ("projector",)),
}


def parse_spec(spec: str) -> tuple[str, str]:
    """Split ``"DRIVER[:ADDRESS]"`` into (driver, address); the address may hold colons.

    >>> parse_spec("aravis:127.0.0.1")
    ('aravis', '127.0.0.1')
    >>> parse_spec("sim")
    ('sim', '')
    """
    name, _, address = str(spec).strip().partition(":")
    if not name:
        raise DriverUnavailable(f"device {spec!r}: expected DRIVER[:ADDRESS], e.g. 'sim' or "
                                f"'aravis:192.168.1.10'")
    return name.lower(), address


def load_driver(name: str, kind: str):
    """Import the module of driver ``name`` for ``kind`` ("camera" or "projector").

    Raises
    ------
    DriverUnavailable
        Unknown driver (the message lists the known ones), or its package is missing (the
        message says what to install).
    """
    table = CAMERA_DRIVERS if kind == "camera" else PROJECTOR_DRIVERS
    entry = table.get(name)
    if entry is None:
        raise DriverUnavailable(f"unknown {kind} driver {name!r}; known: "
                                f"{', '.join(sorted(table))}")
    try:
        return importlib.import_module(entry.module)
    except ImportError as exc:
        missing = getattr(exc, "name", None) or ""
        if missing == entry.module or missing.startswith("telefringe."):
            raise DriverUnavailable(f"the {name} {kind} driver is not part of this "
                                    f"telefringe version") from exc
        how = (f"; install it: pip install 'telefringe[{entry.extra}]'" if entry.extra
               else "")
        raise DriverUnavailable(f"the {name} driver needs {entry.needs} "
                                f"(missing: {missing or exc}){how}") from exc


def open_projector(spec: str) -> Projector:
    """Open the projector of ``"DRIVER[:ADDRESS]"`` (see :data:`PROJECTOR_DRIVERS`)."""
    name, address = parse_spec(spec)
    mod = load_driver(name, "projector")
    return mod.open_projector(address)


def open_camera(spec: str, *, projector: Projector | None = None) -> Camera:
    """Open the camera of ``"DRIVER[:ADDRESS]"`` (see :data:`CAMERA_DRIVERS`);
    ``projector``: the one opened for the same capture (the sim camera needs it)."""
    name, address = parse_spec(spec)
    mod = load_driver(name, "camera")
    return mod.open_camera(address, projector=projector)


def list_devices(kind: str) -> dict[str, list[DeviceListing] | str]:
    """What each driver of ``kind`` ("camera" or "projector") finds: driver name ->
    list of :class:`DeviceListing`, or a one-line reason when the driver is unavailable
    or failed to enumerate."""
    table = CAMERA_DRIVERS if kind == "camera" else PROJECTOR_DRIVERS
    out: dict[str, list[DeviceListing] | str] = {}
    for name in table:
        try:
            mod = load_driver(name, kind)
            lister = getattr(mod, "list_cameras" if kind == "camera" else "list_projectors")
            out[name] = list(lister())
        except AcquisitionError as exc:
            out[name] = str(exc)
        except Exception as exc:  # a driver's enumeration failing must not hide the others
            out[name] = f"enumeration failed: {type(exc).__name__}: {exc}"
    return out
