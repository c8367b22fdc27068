"""The ``window`` projector: a borderless window covering one monitor (an HDMI projector).

``--projector window:SPEC`` with SPEC one of

- a monitor index, as ``telefringe capture devices`` lists them (``window:1``);
- a monitor name (``window:HDMI-1``, or one declared with ``xrandr --setmonitor``);
- an explicit geometry ``WIDTHxHEIGHT+X+Y`` in desktop pixels (``window:912x1140+1280+0``);
- empty: the last monitor listed that is not the primary one;

followed by options ``,refresh=HZ`` (the monitor's refresh rate, when the system cannot
tell it: telefringe rounds exposures to whole refresh periods) and ``,vsync=0`` (do not
wait for the vertical blank). Without ``refresh=``, the rate of the video mode of the
output that shows the monitor is read from ``xrandr`` (0: unknown).

On X11 the monitors are RandR 1.5 monitors (``xrandr --listmonitors``: real outputs and
software monitors alike), read through libXrandr; elsewhere pyglet's screens. Needs pyglet
(``pip install 'telefringe[window]'``) and a display.

:meth:`WindowProjector.show` uploads the image as an RGB texture (grey replicated, nearest
filtering, one texel per screen pixel), draws it, swaps buffers (waiting for the vertical
blank where the driver honours vsync) and waits for the GPU to finish (``glFinish``), then
returns :class:`~telefringe.acquisition.base.Shown` with the time on the system clock. The
light leaves the lens a display latency later; ``telefringe capture latency`` measures it.
Keep the desktop (notifications, screen savers, a compositor's fades) off that monitor.
"""

from __future__ import annotations

import ctypes as C
import ctypes.util
import importlib
import os
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pyglet  # the optional package: its absence is the registry's one-line message

from telefringe.acquisition.base import (
    SYSTEM_CLOCK,
    DeviceError,
    DeviceListing,
    NotSupported,
    ProjectorInfo,
    SequenceSettings,
    Shown,
)

__all__ = ["Monitor", "list_monitors", "parse_geometry", "WindowProjector", "open_projector",
           "list_projectors"]

_GEOMETRY = re.compile(r"^(\d+)x(\d+)([+-]\d+)([+-]\d+)$")


@dataclass(frozen=True)
class Monitor:
    """A monitor of the desktop: name, geometry (pixels, desktop coordinates), primary."""

    name: str
    x: int
    y: int
    width: int
    height: int
    primary: bool = False

    @property
    def geometry(self) -> str:
        """``WIDTHxHEIGHT+X+Y``."""
        return f"{self.width}x{self.height}+{self.x}+{self.y}"


def parse_geometry(spec: str) -> tuple[int, int, int, int] | None:
    """(x, y, width, height) of ``"WIDTHxHEIGHT+X+Y"``, or None if ``spec`` is not one.

    >>> parse_geometry("912x1140+1280+0")
    (1280, 0, 912, 1140)
    >>> parse_geometry("1") is None
    True
    """
    m = _GEOMETRY.match(spec.strip())
    if not m:
        return None
    w, h, x, y = (int(g) for g in m.groups())
    if w < 1 or h < 1:
        raise ValueError(f"window geometry {spec!r}: width and height must be >= 1")
    return x, y, w, h


class _XRRMonitorInfo(C.Structure):
    _fields_ = [("name", C.c_ulong), ("primary", C.c_int), ("automatic", C.c_int),
                ("noutput", C.c_int), ("x", C.c_int), ("y", C.c_int), ("width", C.c_int),
                ("height", C.c_int), ("mwidth", C.c_int), ("mheight", C.c_int),
                ("outputs", C.c_void_p)]


def _x11_monitors(display_name: str | None) -> list[Monitor] | None:
    """RandR 1.5 monitors through libXrandr, or None when that is not available."""
    x11_path = ctypes.util.find_library("X11")
    xrr_path = ctypes.util.find_library("Xrandr")
    if not x11_path or not xrr_path:
        return None
    x11, xrr = C.CDLL(x11_path), C.CDLL(xrr_path)
    if not hasattr(xrr, "XRRGetMonitors"):
        return None
    x11.XOpenDisplay.restype = C.c_void_p
    x11.XOpenDisplay.argtypes = [C.c_char_p]
    x11.XDefaultRootWindow.restype = C.c_ulong
    x11.XDefaultRootWindow.argtypes = [C.c_void_p]
    x11.XGetAtomName.restype = C.c_void_p
    x11.XGetAtomName.argtypes = [C.c_void_p, C.c_ulong]
    x11.XFree.argtypes = [C.c_void_p]
    x11.XCloseDisplay.argtypes = [C.c_void_p]
    xrr.XRRGetMonitors.restype = C.POINTER(_XRRMonitorInfo)
    xrr.XRRGetMonitors.argtypes = [C.c_void_p, C.c_ulong, C.c_int, C.POINTER(C.c_int)]
    xrr.XRRFreeMonitors.argtypes = [C.POINTER(_XRRMonitorInfo)]
    dpy = x11.XOpenDisplay(display_name.encode() if display_name else None)
    if not dpy:
        raise DeviceError(f"cannot open the X display {display_name or os.environ.get('DISPLAY')!r}"
                          f" (is DISPLAY set and the server running?)")
    try:
        n = C.c_int()
        arr = xrr.XRRGetMonitors(dpy, x11.XDefaultRootWindow(dpy), 1, C.byref(n))
        out = []
        if arr:
            for i in range(n.value):
                m = arr[i]
                p = x11.XGetAtomName(dpy, m.name)
                name = C.string_at(p).decode("utf-8", "replace") if p else f"monitor{i}"
                if p:
                    x11.XFree(p)
                out.append(Monitor(name, m.x, m.y, m.width, m.height, bool(m.primary)))
            xrr.XRRFreeMonitors(arr)
        return out
    finally:
        x11.XCloseDisplay(dpy)


def list_monitors() -> list[Monitor]:
    """The desktop's monitors (RandR 1.5 monitors on X11, else pyglet's screens)."""
    if sys.platform.startswith("linux"):
        if not os.environ.get("DISPLAY"):
            raise DeviceError("no display: DISPLAY is not set (the window projector needs an "
                              "X server with the projector as a monitor)")
        mons = _x11_monitors(os.environ.get("DISPLAY"))
        if mons is not None:
            return mons
    display = pyglet.display.get_display()
    return [Monitor(f"screen{i}", s.x, s.y, s.width, s.height, i == 0)
            for i, s in enumerate(display.get_screens())]


def parse_address(address: str) -> tuple[str, dict]:
    """Split ``"SPEC[,refresh=HZ][,vsync=0|1]"`` into the monitor SPEC and options.

    >>> parse_address("PROJECTOR,refresh=60")
    ('PROJECTOR', {'refresh': 60.0})
    """
    spec, *rest = [p.strip() for p in address.split(",")]
    opts: dict = {}
    for item in rest:
        key, eq, value = item.partition("=")
        try:
            if key == "refresh" and eq:
                opts["refresh"] = float(value)
                if not 1.0 <= opts["refresh"] <= 1000.0:
                    raise ValueError
            elif key == "vsync" and eq and value in ("0", "1"):
                opts["vsync"] = value == "1"
            else:
                raise KeyError
        except KeyError:
            raise DeviceError(f"window:{address}: unknown option {item!r}; expected "
                              f"refresh=HZ or vsync=0|1") from None
        except ValueError:
            raise DeviceError(f"window:{address}: refresh must be 1..1000 Hz, got "
                              f"{value!r}") from None
    return spec, opts


_XRANDR_OUTPUT = re.compile(r"^(\S+) connected (?:primary )?(\d+)x(\d+)\+(\d+)\+(\d+)")
_XRANDR_RATE = re.compile(r"(\d+(?:\.\d+)?)\*")


def refresh_from_xrandr(text: str, box: tuple[int, int, int, int]) -> float:
    r"""The refresh rate (Hz) of the current mode of the output (in ``xrandr --query``
    output ``text``) whose area contains ``box`` = (x, y, width, height); 0 if none.

    >>> txt = "HDMI-1 connected 912x1140+1920+0 (normal) 0mm x 0mm\n   912x1140  60.00*+"
    >>> refresh_from_xrandr(txt, (1920, 0, 912, 1140))
    60.0
    """
    rate, current = 0.0, None
    for line in text.splitlines():
        m = _XRANDR_OUTPUT.match(line)
        if m:
            w, h, x, y = (int(g) for g in m.groups()[1:])
            bx, by, bw, bh = box
            current = x <= bx and y <= by and bx + bw <= x + w and by + bh <= y + h
            continue
        if line[:1].isspace() and current:
            r = _XRANDR_RATE.search(line)
            if r and float(r.group(1)) > 0:
                rate = float(r.group(1))
                current = None
        elif not line[:1].isspace():
            current = None
    return rate


def _refresh_of(box: tuple[int, int, int, int]) -> float:
    """The refresh rate of the output showing ``box``, read from xrandr (0: unknown)."""
    import shutil
    import subprocess

    if not sys.platform.startswith("linux") or shutil.which("xrandr") is None:
        return 0.0
    try:
        out = subprocess.run(["xrandr", "--query"], capture_output=True, text=True,
                             timeout=5, check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return 0.0
    return refresh_from_xrandr(out, box)


def _choose(spec: str) -> tuple[tuple[int, int, int, int], str]:
    """((x, y, width, height), description) of a projector SPEC (see the module)."""
    geo = parse_geometry(spec) if spec else None
    if geo is not None:
        return geo, spec
    mons = list_monitors()
    if not mons:
        raise DeviceError("the display reports no monitor")
    known = "; ".join(f"{i}: {m.name} {m.geometry}" for i, m in enumerate(mons))
    if not spec:
        others = [m for m in mons if not m.primary] or mons
        m = others[-1]
    elif spec.isdigit():
        if int(spec) >= len(mons):
            raise DeviceError(f"no monitor {spec}; monitors: {known}")
        m = mons[int(spec)]
    else:
        named = [m for m in mons if m.name == spec]
        if not named:
            raise DeviceError(f"no monitor named {spec!r}; monitors: {known}")
        m = named[0]
    return (m.x, m.y, m.width, m.height), f"{m.name} {m.geometry}"


def list_projectors() -> list[DeviceListing]:
    """One listing per monitor (the address is its index)."""
    return [DeviceListing("window", str(i), model=m.name, detail=m.geometry
                          + (" primary" if m.primary else ""))
            for i, m in enumerate(list_monitors())]


def open_projector(address: str) -> WindowProjector:
    """Open a window projector on the monitor ``address`` names (see the module)."""
    spec, opts = parse_address(address)
    return WindowProjector(spec, refresh_hz=opts.get("refresh"),
                           vsync=opts.get("vsync", True), address=address)


class WindowProjector:
    """A borderless window covering one monitor (the :class:`Projector` protocol).

    Parameters
    ----------
    spec : str
        Monitor index or name, ``WIDTHxHEIGHT+X+Y``, or "" (see the module docstring).
    refresh_hz : float or None
        The monitor's refresh rate, reported in ``info``; None: read it from xrandr
        (0 when unknown).
    vsync : bool
        Swap buffers at the vertical blank (recommended; the driver may ignore it).
    address : str
        What to report as ``info.address`` (default ``spec``).
    """

    def __init__(self, spec: str = "", *, refresh_hz: float | None = None,
                 vsync: bool = True, address: str | None = None):
        (x, y, w, h), where = _choose(spec)
        if refresh_hz is None:
            refresh_hz = _refresh_of((x, y, w, h))
        pyglet.options["shadow_window"] = False     # no hidden window of pyglet's own
        try:
            gl = importlib.import_module("pyglet.gl")
            pwindow = importlib.import_module("pyglet.window")
            self._image = importlib.import_module("pyglet.image")
        except Exception as exc:  # no display, no GL
            raise DeviceError(f"cannot open a window for the projector: {exc}") from exc
        self._gl = gl
        try:
            self._win = pwindow.Window(
                width=w, height=h, style=pwindow.Window.WINDOW_STYLE_BORDERLESS,
                vsync=vsync, visible=False, caption="telefringe projector")
        except Exception as exc:
            raise DeviceError(f"cannot open a window for the projector: {exc}") from exc
        self._win.set_location(x, y)
        self._win.set_mouse_visible(False)
        self._win.set_visible(True)
        self._win.dispatch_events()
        if tuple(self._win.get_location()) != (x, y):
            got = self._win.get_location()
            self._win.close()
            raise DeviceError(f"the window manager put the projector window at {got}, not "
                              f"at ({x}, {y}): keep panels and docks off the projector's "
                              f"monitor, or give its geometry as WxH+X+Y")
        self._tex = self._image.Texture.create(w, h, min_filter=gl.GL_NEAREST,
                                                mag_filter=gl.GL_NEAREST)
        self._rgb = np.empty((h, w, 3), dtype=np.uint8)
        self.clock = SYSTEM_CLOCK
        self.info = ProjectorInfo(driver="window", model=where, serial="", width=w, height=h,
                                  refresh_hz=float(refresh_hz), bit_depth=8, sequencer=False,
                                  address=spec if address is None else address)
        self._refresh = 0
        self.show(np.zeros((h, w), dtype=np.uint8))

    def show(self, image: np.ndarray) -> Shown:
        """Show ``image`` ((height, width) uint8; bool is taken as 0/255) until the next
        call; return once the swap completed and the GPU finished drawing."""
        if self._win is None:
            raise DeviceError("the projector window is closed")
        img = np.asarray(image)
        if img.dtype == bool:
            img = img.astype(np.uint8) * 255
        want = (self.info.height, self.info.width)
        if img.shape != want:
            raise ValueError(f"the projector shows {want[1]} x {want[0]} images (height, width "
                             f"= {want}), got shape {img.shape}")
        if img.dtype != np.uint8:
            raise ValueError(f"the window projector shows 8-bit images (uint8), got {img.dtype}")
        return self._draw(img[::-1, :, None])       # GL's rows run bottom-up

    def show_rgb(self, image: np.ndarray) -> Shown:
        """Show a colour frame ((height, width, 3) uint8, R, G, B), e.g. three 8-bit
        patterns packed for a DLP controller in video pattern mode."""
        if self._win is None:
            raise DeviceError("the projector window is closed")
        img = np.asarray(image)
        want = (self.info.height, self.info.width, 3)
        if img.shape != want or img.dtype != np.uint8:
            raise ValueError(f"show_rgb takes {want} uint8, got {img.shape} {img.dtype}")
        return self._draw(img[::-1])

    def _draw(self, rgb_bottom_up: np.ndarray) -> Shown:
        gl = self._gl
        self._win.switch_to()
        self._win.dispatch_events()
        self._rgb[...] = rgb_bottom_up
        data = self._image.ImageData(self.info.width, self.info.height, "RGB",
                                      self._rgb.tobytes(), pitch=self.info.width * 3)
        self._tex.blit_into(data, 0, 0, 0)
        self._win.clear()
        self._tex.blit(0, 0)
        self._win.flip()
        gl.glFinish()
        self._refresh += 1
        return Shown(self.clock.now_ns(), None)

    def load_sequence(self, images: Sequence[np.ndarray], *, exposure_s: float,
                      period_s: float | None = None,
                      trigger_out: bool = True) -> SequenceSettings:
        raise NotSupported("the window projector has no sequencer: capture in streamed mode "
                           "(software trigger), or use a projector driver that holds "
                           "sequences (lightcrafter)")

    def start_sequence(self, repeats: int = 1) -> Shown:
        raise NotSupported("the window projector has no sequencer")

    def stop_sequence(self) -> None:
        return None

    def close(self) -> None:
        """Blank the window and close it (idempotent)."""
        if self._win is None:
            return
        try:
            self.show(np.zeros((self.info.height, self.info.width), dtype=np.uint8))
        except Exception:
            pass
        finally:
            self._win.close()
            self._win = None

    def __enter__(self) -> WindowProjector:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
