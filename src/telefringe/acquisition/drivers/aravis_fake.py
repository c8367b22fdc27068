"""Aravis's fake GigE Vision camera, serving images that Python supplies.

libaravis contains ``ArvGvFakeCamera``: a complete GigE Vision device (GVCP control and
GVSP streaming on UDP port 3956) built on a register-level camera model. This module
starts one in-process on a loopback address and replaces its test pattern with the image a
Python callable returns for each frame, so that a capture can be exercised against the
real protocol stack (discovery, GenICam features, software trigger, packetised streaming,
packet loss, 16-bit frame ids) with images telefringe knows the truth of.

It is a test instrument: it listens only on a loopback address and stops when closed,
garbage-collected, or when the process ends. One fake camera per address and port (a
second one on the same address does not start: :class:`FakeGigECamera` then raises).
"""

from __future__ import annotations

import ctypes as C
import ipaddress
import threading
import weakref
from collections.abc import Callable

import numpy as np

from telefringe.acquisition.base import DeviceError
from telefringe.acquisition.drivers import _arvlib as _a

__all__ = ["FakeGigECamera", "FillFunction"]

#: fill(width, height, pixel_format, exposure_s, gain) -> (height, width) uint8/uint16 image,
#: or None for a black frame
FillFunction = Callable[[int, int, str, float, float], "np.ndarray | None"]

_FILL = C.CFUNCTYPE(None, C.c_void_p, C.c_void_p, C.c_uint32, C.c_uint32, C.c_uint32)
_CODE_TO_NAME = {code: name for name, (code, _) in _a.PIXEL_FORMATS.items()}


class FakeGigECamera:
    """A fake GigE Vision camera on loopback whose frames come from ``fill``.

    Parameters
    ----------
    fill : callable or None
        ``fill(width, height, pixel_format, exposure_s, gain) -> ndarray``, called in the
        camera's streaming thread once per frame, with the region and pixel format the
        client configured (``"Mono8"`` or ``"Mono16"``). It returns a (height, width)
        array (cast to the format's integer type; a mismatched shape is an error recorded
        in :attr:`errors` and sent as a black frame). None: Aravis's own test pattern.
    address : str
        A loopback IPv4 address (default 127.0.0.1): the camera never listens elsewhere.
    serial : str
        The device's serial number (its Aravis id is ``Aravis-Fake-SERIAL``).
    loss_ratio : float
        Fraction in [0, 1] of GVSP packets dropped at random (the fake does not resend).
    trigger_hz : float
        How often the fake looks for a pending trigger (Aravis's default is 25 Hz, i.e. up
        to 40 ms from trigger to frame).

    Attributes
    ----------
    frames_served : int, frames filled so far. errors : list of str, exceptions raised by
    ``fill`` (each frame that failed went out black).
    """

    def __init__(self, fill: FillFunction | None = None, *, address: str = "127.0.0.1",
                 serial: str = "TF001", loss_ratio: float = 0.0, trigger_hz: float = 200.0):
        if not ipaddress.ip_address(address).is_loopback:
            raise ValueError(f"the fake camera listens on loopback only, not {address!r}")
        self.address = address
        self.serial = serial
        self.frames_served = 0
        self.errors: list[str] = []
        self._fill = fill
        self._lock = threading.Lock()
        gv = _a.lib.arv_gv_fake_camera_new(address.encode(), serial.encode())
        if not gv:
            raise DeviceError(f"could not create the fake camera on {address}")
        self._gv = gv
        self._finalizer = weakref.finalize(self, _a.gobject.g_object_unref, gv)
        if not _a.lib.arv_gv_fake_camera_is_running(gv):
            self.close()
            raise DeviceError(f"the fake GigE Vision camera could not listen on {address}:3956 "
                              f"(another one already there?)")
        self._cb = None
        cam = _a.lib.arv_gv_fake_camera_get_fake_camera(gv)
        _a.lib.arv_fake_camera_set_trigger_frequency(cam, float(trigger_hz))
        if fill is not None:
            self._cb = _FILL(self._on_fill)      # kept alive as long as the server
            _a.lib.arv_fake_camera_set_fill_pattern(cam, C.cast(self._cb, C.c_void_p), None)
        self.set_loss_ratio(loss_ratio)

    @property
    def device_id(self) -> str:
        """The id Aravis lists the camera under (``Aravis-Fake-SERIAL``)."""
        return f"Aravis-Fake-{self.serial}"

    def set_loss_ratio(self, ratio: float) -> None:
        """Drop this fraction (0..1) of GVSP packets from now on."""
        ratio = float(ratio)
        if not 0.0 <= ratio <= 1.0:
            raise ValueError(f"loss_ratio must be in [0, 1], got {ratio!r}")
        if self._gv is None:
            raise DeviceError("the fake camera is closed")
        _a.set_double_property(self._gv, "gvsp-lost-ratio", ratio)

    def _on_fill(self, buf, _data, exposure_us, gain, pixel_format):
        # runs in libaravis's streaming thread (ctypes takes the GIL); never raise out of it
        try:
            w = _a.lib.arv_buffer_get_image_width(buf)
            h = _a.lib.arv_buffer_get_image_height(buf)
            name = _CODE_TO_NAME.get(int(pixel_format))
            dtype = np.uint8 if name == "Mono8" else np.uint16
            nbytes = w * h * np.dtype(dtype).itemsize
            ptr = _a.lib.arv_buffer_get_data(buf, None)
            out = np.zeros((h, w), dtype=dtype)
            try:
                if name is None:
                    raise DeviceError(f"pixel format 0x{int(pixel_format):08x} is not "
                                      f"monochrome")
                img = self._fill(w, h, name, exposure_us * 1e-6, float(gain))
                if img is not None:
                    img = np.asarray(img)
                    if img.shape != (h, w):
                        raise ValueError(f"fill returned {img.shape}, the camera's region "
                                         f"is {(h, w)}")
                    out[...] = img
            except Exception as exc:  # recorded; the frame goes out black
                with self._lock:
                    self.errors.append(f"{type(exc).__name__}: {exc}")
            if ptr:
                C.memmove(ptr, out.ctypes.data, nbytes)
            with self._lock:
                self.frames_served += 1
        except Exception as exc:  # pragma: no cover - last resort inside a C callback
            self.errors.append(f"{type(exc).__name__}: {exc}")

    def close(self) -> None:
        """Stop the camera (joins its threads; idempotent)."""
        if self._gv is not None:
            self._finalizer()
            self._gv = None

    def __enter__(self) -> FakeGigECamera:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ------------------------------------------------------------------ a virtual rig server
def _rig_fill(region: tuple[int, int, int, int], preset: str, scene: str, seed: int):
    """A fill function: the virtual rig's camera image of what the X display shows in
    ``region`` (x, y, width, height): a virtual camera looking at a virtual plate lit by
    whatever a projector window shows there."""
    import mss

    from telefringe.acquisition.drivers.sim import SimConfig, SimRig

    rig = SimRig(SimConfig(preset=preset, scene=scene, seed=seed))
    x, y, w, h = region
    if (h, w) != rig.panel_shape:
        raise ValueError(f"the watched region is {w} x {h}; the {preset} rig's projector is "
                         f"{rig.panel_shape[1]} x {rig.panel_shape[0]}")
    grabber = mss.MSS()
    cam = rig.vrig.camera.intrinsics
    rig.render(0, 1)                # trace the scene now, not during the first frame

    def fill(width, height, pixel_format, exposure_s, gain):
        if (height, width) != (cam.height, cam.width):
            raise ValueError(f"configure the camera's region to {cam.width} x {cam.height} "
                             f"(the rig's camera), not {width} x {height}")
        shot = np.asarray(grabber.grab({"left": x, "top": y, "width": w, "height": h}))
        rig.emit(0, np.ascontiguousarray(shot[..., 1]))      # BGRA: the green channel
        return rig.render(0, int(exposure_s * 1e9), pixel_format=pixel_format)

    return fill


def main(argv=None) -> int:
    """``python -m telefringe.acquisition.drivers.aravis_fake``: serve a fake GigE Vision
    camera on loopback until killed or ``--lifetime`` seconds pass.

    With ``--watch X,Y,W,H`` (or ``--monitor NAME``) its frames are the virtual rig's
    camera view of what that part of the X display shows: point a ``window`` projector
    at it and ``telefringe capture scan OUT --camera aravis:127.0.0.1 --projector
    window:NAME`` runs the whole capture through an X server and GigE Vision.
    """
    import argparse
    import sys
    import time

    ap = argparse.ArgumentParser(prog="python -m telefringe.acquisition.drivers.aravis_fake",
                                 description=main.__doc__.split("\n\n")[0])
    ap.add_argument("--address", default="127.0.0.1", help="loopback address to listen on")
    ap.add_argument("--serial", default="TF001")
    ap.add_argument("--loss", type=float, default=0.0, help="fraction of packets dropped")
    ap.add_argument("--watch", help="X,Y,WIDTH,HEIGHT of the display the camera sees")
    ap.add_argument("--monitor", help="or the RandR monitor it sees")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--scene", default="plate")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lifetime", type=float, default=600.0,
                    help="stop after this many seconds (default 600)")
    a = ap.parse_args(argv)
    fill = None
    if a.watch or a.monitor:
        if a.watch:
            region = tuple(int(v) for v in a.watch.split(","))
        else:
            from telefringe.acquisition.drivers.window import list_monitors

            m = {m.name: m for m in list_monitors()}[a.monitor]
            region = (m.x, m.y, m.width, m.height)
        fill = _rig_fill(region, a.preset, a.scene, a.seed)
    with FakeGigECamera(fill, address=a.address, serial=a.serial, loss_ratio=a.loss) as cam:
        print(f"ready {cam.device_id} on {a.address}", flush=True)
        end = time.monotonic() + a.lifetime
        try:
            while time.monotonic() < end:
                time.sleep(0.2)
        except KeyboardInterrupt:
            pass
        if cam.errors:
            print(f"{len(cam.errors)} frames failed: {cam.errors[-1]}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
