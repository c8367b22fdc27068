"""The ``aravis`` camera driver: GigE Vision and USB3 Vision cameras through Aravis 0.8.

``--camera aravis:ADDRESS`` with ADDRESS an IP address, a serial number, an Aravis device
id (``telefringe capture devices`` lists them) or empty for the first camera found.
Needs the Aravis 0.8 C library (Debian/Ubuntu: ``apt-get install libaravis-0.8-0``), bound
through ctypes (:mod:`._arvlib`); nothing from PyPI.

How a frame is proven to be the one asked for
---------------------------------------------
Under ``Trigger.SOFTWARE`` the driver counts the triggers it fired and not yet answered,
and follows the device's frame ids (GigE Vision 1.x: 16 bits, 65535 wraps to 1, 0 is never
used). A frame is returned OK only when it completed, its id directly follows the last
frame's (or, first after start, it arrived after the trigger), and its leader reached the
host after the trigger that it answers was sent. A frame arriving while no trigger is
outstanding is discarded and counted (:attr:`AravisCamera.discarded`); an id jump returns
the frame as INCOMPLETE with the jump in its message. After a grab timed out, the frame of
that trigger may still arrive later: the next :meth:`~AravisCamera.fire` or
:meth:`~AravisCamera.flush` then restarts the stream on a new port first, so a late frame
can never be taken for the answer to a new trigger. An INCOMPLETE frame carries no image
(its missing packets would be garbage), only its id, time stamp and Aravis's words.
"""

from __future__ import annotations

import ctypes as C
import ipaddress
import time

import numpy as np

from telefringe.acquisition.base import (
    PIXEL_FORMAT_MAX,
    CameraInfo,
    CameraSettings,
    DeviceError,
    DeviceListing,
    Frame,
    FrameStatus,
    Trigger,
)
from telefringe.acquisition.drivers import _arvlib as _a
from telefringe.acquisition.drivers._ids import id_gap
from telefringe.acquisition.drivers._settings import check_configure, full_roi
from telefringe.acquisition.drivers._trigger import SoftwareTriggerBook

__all__ = ["AravisCamera", "open_camera", "list_cameras", "id_gap"]

_ACQUISITION_CONTINUOUS = 1
_AUTO_OFF = 0
_CODE_TO_NAME = {code: name for name, (code, _) in _a.PIXEL_FORMATS.items()}


def list_cameras() -> list[DeviceListing]:
    """The cameras Aravis finds (GigE Vision on every interface, USB3 Vision)."""
    lib = _a.lib
    lib.arv_update_device_list()
    out = []
    for i in range(lib.arv_get_n_devices()):
        def s(fn, i=i):
            v = getattr(lib, fn)(i)
            return v.decode("utf-8", "replace") if v else ""
        address = s("arv_get_device_address") or s("arv_get_device_id")
        out.append(DeviceListing("aravis", address, model=s("arv_get_device_model"),
                                 serial=s("arv_get_device_serial_nbr"),
                                 detail=f"{s('arv_get_device_protocol')} "
                                        f"{s('arv_get_device_vendor')} id "
                                        f"{s('arv_get_device_id')}".strip()))
    return out


def _resolve(address: str) -> str:
    """The Aravis name to open for ``address`` (IP, serial, device id, or "" for first)."""
    address = address.strip()
    lib = _a.lib
    lib.arv_update_device_list()
    n = lib.arv_get_n_devices()
    for i in range(n):
        fields = [getattr(lib, fn)(i) for fn in ("arv_get_device_id", "arv_get_device_address",
                                                 "arv_get_device_serial_nbr")]
        fields = [f.decode("utf-8", "replace") if f else "" for f in fields]
        if not address or address in fields:
            return fields[0]
    try:
        ipaddress.ip_address(address)
        return address          # not discovered by broadcast: Aravis will ask it directly
    except ValueError:
        pass
    found = ", ".join(d.address for d in list_cameras()) or "none"
    if not address:
        raise DeviceError("no Aravis camera found (GigE Vision or USB3 Vision); check the "
                          "cable, the network interface and its MTU")
    raise DeviceError(f"no Aravis camera {address!r}; found: {found}")


def open_camera(address: str, *, projector=None) -> AravisCamera:
    """Open the camera at ``address`` (see the module docstring); ``projector`` unused."""
    del projector
    return AravisCamera(address)


def _str(b) -> str:
    return b.decode("utf-8", "replace") if b else ""


class AravisCamera(SoftwareTriggerBook):
    """A GigE Vision / USB3 Vision camera through Aravis (the :class:`Camera` protocol).

    Parameters
    ----------
    address : str
        IP address, serial number, Aravis device id, or "" for the first camera.

    Attributes
    ----------
    info : CameraInfo
    settings : CameraSettings or None, what :meth:`configure` applied last.
    discarded : int, frames thrown away since :meth:`start` because they could not be the
        answer to a trigger (late, unasked for, or flushed).
    resyncs : int, stream restarts after a grab timed out.
    """

    def __init__(self, address: str = ""):
        name = _resolve(address)
        self._cam = _a.call("arv_camera_new", name.encode())
        if not self._cam:
            raise DeviceError(f"Aravis could not open camera {address or name!r}")
        self._stream = None
        self._started = False
        self._n_buffers = 8
        self.settings: CameraSettings | None = None
        self.discarded = 0
        self.resyncs = 0
        self._reset_counts()
        w, h = C.c_int(), C.c_int()
        _a.call("arv_camera_get_sensor_size", self._cam, C.byref(w), C.byref(h))
        self._gv = bool(_a.lib.arv_camera_is_gv_device(self._cam))
        self.info = CameraInfo(
            driver="aravis",
            model=_str(_a.call("arv_camera_get_model_name", self._cam)),
            serial=_str(_a.call("arv_camera_get_device_serial_number", self._cam)),
            vendor=_str(_a.call("arv_camera_get_vendor_name", self._cam)),
            width=int(w.value), height=int(h.value),
            pixel_formats=self._available_formats(), address=address or name)

    # -------------------------------------------------------------------- helpers
    def _available_formats(self) -> tuple[str, ...]:
        n = C.c_uint()
        arr = _a.call("arv_camera_dup_available_pixel_formats_as_strings", self._cam,
                      C.byref(n))
        if not arr:
            return ()
        try:
            names = [_str(arr[i]) for i in range(n.value)]
        finally:
            _a.g_free(C.cast(arr, C.c_void_p))
        return tuple(f for f in names if f in PIXEL_FORMAT_MAX)

    def _reset_counts(self) -> None:
        super()._reset_counts()
        self._t_fire_ns = 0         # wall clock (ns) of the last trigger

    def _acquiring(self) -> bool:
        return self._started

    def _restart(self) -> None:
        self._resync()

    def _require_open(self) -> None:
        if self._cam is None:
            raise DeviceError("the camera is closed")

    # -------------------------------------------------------------------- protocol
    def configure(self, *, exposure_s: float, gain_db: float = 0.0,
                  pixel_format: str = "Mono8",
                  roi: tuple[int, int, int, int] | None = None,
                  trigger: Trigger = Trigger.SOFTWARE,
                  trigger_line: str | None = None) -> CameraSettings:
        """Apply settings while stopped; return those the camera reports back.

        exposure_s : seconds (clipped to the camera's range). gain_db : the camera's
        ``Gain`` (dB on SFNC cameras; clipped). pixel_format : one of ``info.pixel_formats``.
        roi : (x, y, width, height) pixels, or None for the full sensor. trigger :
        SOFTWARE, HARDWARE (on ``trigger_line``, default ``"Line0"``) or FREE_RUN.
        """
        self._require_open()
        check_configure(self.info, pixel_format, acquiring=self._started,
                        unknown_formats_ok=True)
        if not (np.isfinite(exposure_s) and exposure_s > 0):
            raise ValueError(f"exposure_s must be a positive number of seconds, got "
                             f"{exposure_s!r}")
        cam = self._cam
        _a.call("arv_camera_set_acquisition_mode", cam, _ACQUISITION_CONTINUOUS)
        _a.call("arv_camera_set_pixel_format_from_string", cam, pixel_format.encode())
        _a.call("arv_camera_set_region", cam, *full_roi(roi, self.info))
        for fn in ("arv_camera_set_exposure_time_auto", "arv_camera_set_gain_auto"):
            try:
                _a.call(fn, cam, _AUTO_OFF)
            except DeviceError:
                pass                       # no auto mode on this camera: nothing to switch off
        lo, hi = C.c_double(), C.c_double()
        _a.call("arv_camera_get_exposure_time_bounds", cam, C.byref(lo), C.byref(hi))
        _a.call("arv_camera_set_exposure_time", cam,
                float(np.clip(exposure_s * 1e6, lo.value, hi.value)))
        _a.call("arv_camera_get_gain_bounds", cam, C.byref(lo), C.byref(hi))
        _a.call("arv_camera_set_gain", cam, float(np.clip(gain_db, lo.value, hi.value)))
        line = None
        if trigger is Trigger.SOFTWARE:
            _a.call("arv_camera_set_trigger", cam, b"Software")
        elif trigger is Trigger.HARDWARE:
            line = trigger_line or "Line0"
            _a.call("arv_camera_set_trigger", cam, line.encode())
        else:
            _a.call("arv_camera_clear_triggers", cam)
        rx, ry, rw, rh = C.c_int(), C.c_int(), C.c_int(), C.c_int()
        _a.call("arv_camera_get_region", cam, C.byref(rx), C.byref(ry), C.byref(rw),
                C.byref(rh))
        applied = _str(_a.call("arv_camera_get_pixel_format_as_string", cam))
        self.settings = CameraSettings(
            exposure_s=_a.call("arv_camera_get_exposure_time", cam) * 1e-6,
            gain_db=float(_a.call("arv_camera_get_gain", cam)),
            pixel_format=applied, roi=(rx.value, ry.value, rw.value, rh.value),
            trigger=trigger, trigger_line=line,
            max_value=PIXEL_FORMAT_MAX.get(applied, PIXEL_FORMAT_MAX[pixel_format]))
        return self.settings

    def _open_stream(self) -> None:
        if self._gv:
            try:
                _a.call("arv_camera_gv_auto_packet_size", self._cam)
            except DeviceError:
                pass                      # keep the camera's packet size
        stream = _a.call("arv_camera_create_stream", self._cam, None, None)
        if not stream:
            raise DeviceError("Aravis could not open a stream from the camera")
        payload = _a.call("arv_camera_get_payload", self._cam)
        for _ in range(self._n_buffers):
            _a.lib.arv_stream_push_buffer(stream, _a.lib.arv_buffer_new_allocate(payload))
        self._stream = stream
        self._payload = payload

    def _close_stream(self) -> None:
        if self._stream is not None:
            _a.gobject.g_object_unref(self._stream)   # frees the buffers it holds
            self._stream = None

    def start(self, n_buffers: int = 8) -> None:
        """Start acquiring into ``n_buffers`` buffers (a fresh stream: nothing queued)."""
        self._require_open()
        if self.settings is None:
            raise DeviceError("configure() the camera before start()")
        if self._started:
            self.stop()
        self._n_buffers = max(2, int(n_buffers))
        self._open_stream()
        self._reset_counts()
        self.discarded = 0
        self.resyncs = 0
        _a.call("arv_camera_start_acquisition", self._cam)
        self._started = True

    def _resync(self) -> None:
        """Restart the stream on a new port: frames still in flight go to the old one."""
        _a.call("arv_camera_stop_acquisition", self._cam)
        self._close_stream()
        self._open_stream()
        self._reset_counts()
        _a.call("arv_camera_start_acquisition", self._cam)
        self.resyncs += 1

    def fire(self) -> None:
        """Send a software trigger (no-op unless configured with Trigger.SOFTWARE)."""
        if not self._fire_ready():
            return
        self._t_fire_ns = time.time_ns()    # Aravis stamps arrivals with the wall clock
        _a.call("arv_camera_software_trigger", self._cam)
        self._owed += 1

    def _copy(self, buf) -> np.ndarray | None:
        if _a.lib.arv_buffer_get_payload_type(buf) != 1:      # no image leader received
            return None
        size = C.c_size_t()
        ptr = _a.lib.arv_buffer_get_image_data(buf, C.byref(size))
        w = _a.lib.arv_buffer_get_image_width(buf)
        h = _a.lib.arv_buffer_get_image_height(buf)
        name = _CODE_TO_NAME.get(int(_a.lib.arv_buffer_get_image_pixel_format(buf)))
        if not ptr or name is None or w <= 0 or h <= 0:
            return None
        bpp = _a.PIXEL_FORMATS[name][1]
        n = w * h * bpp
        if size.value < n:
            return None
        raw = np.frombuffer(C.string_at(ptr, n), dtype=np.uint8 if bpp == 1 else "<u2")
        return raw.reshape(h, w).astype(np.uint8 if bpp == 1 else np.uint16)

    def grab(self, timeout_s: float) -> Frame:
        """The oldest frame not yet returned, within ``timeout_s`` seconds (see the module
        docstring for when a frame is OK, INCOMPLETE, discarded, or a TIMEOUT)."""
        if not self._started:
            raise DeviceError("start() the camera before grab()")
        software = self.settings.trigger is Trigger.SOFTWARE
        deadline = time.monotonic() + max(0.0, float(timeout_s))
        while True:
            left = deadline - time.monotonic()
            buf = (_a.lib.arv_stream_timeout_pop_buffer(self._stream, int(left * 1e6))
                   if left > 0 else _a.lib.arv_stream_try_pop_buffer(self._stream))
            if not buf:
                if software and self._owed:
                    self._desync = True        # its frame may still come: resync first
                return Frame(None, -1, None, FrameStatus.TIMEOUT,
                             f"no frame within {timeout_s:.3g} s")
            try:
                status = _a.lib.arv_buffer_get_status(buf)
                fid = int(_a.lib.arv_buffer_get_frame_id(buf))
                ts = int(_a.lib.arv_buffer_get_timestamp(buf))
                arrived = int(_a.lib.arv_buffer_get_system_timestamp(buf))
                image = self._copy(buf) if status == 0 else None   # no garbage
            finally:
                _a.lib.arv_stream_push_buffer(self._stream, buf)
            frame = self._judge(status, fid, ts, arrived, image, software)
            if frame is not None:
                return frame

    def _judge(self, status, fid, ts, arrived, image, software) -> Frame | None:
        """The frame to return for one popped buffer, or None to discard it."""
        what = _a.BUFFER_STATUS.get(status, f"status {status}")
        ts = ts or None
        if not software:
            if status != 0:
                return Frame(image, fid if fid else -1, ts, FrameStatus.INCOMPLETE,
                             f"Aravis: {what} (frame id {fid})")
            msg = ""
            if self._last_id is not None and id_gap(self._last_id, fid, wrap16=self._gv) != 1:
                msg = f"frame id jumped from {self._last_id} to {fid}"
            self._last_id = fid
            return Frame(image, fid, ts, FrameStatus.OK, msg)
        if self._owed <= 0:
            self.discarded += 1              # not asked for: never returned
            return None
        before_fire = 0 < arrived < self._t_fire_ns      # 0: the stream did not say
        if status != 0:
            # a buffer whose leader was lost keeps the id and arrival time of its last
            # use: only trust them when the arrival is after the trigger
            self._owed -= 1
            self._last_id = fid if (fid and not before_fire) else None
            return Frame(image, fid if (fid and not before_fire) else -1, ts,
                         FrameStatus.INCOMPLETE, f"Aravis: {what} (frame id {fid})")
        if self._last_id is None:
            if before_fire and self._owed == 1:
                self.discarded += 1          # began arriving before the trigger it would answer
                return None
            gap = 1
        else:
            gap = id_gap(self._last_id, fid, wrap16=self._gv)
        if gap <= 0:
            self.discarded += 1              # an id already seen: a duplicate or an old frame
            return None
        self._last_id = fid
        if gap == 1 and not (before_fire and self._owed == 1):
            self._owed -= 1
            return Frame(image, fid, ts, FrameStatus.OK)
        self._owed = max(0, self._owed - gap)
        if gap == 1:
            return Frame(image, fid, ts, FrameStatus.INCOMPLETE,
                         f"frame {fid} began arriving before the trigger it would answer")
        return Frame(image, fid, ts, FrameStatus.INCOMPLETE,
                     f"frame id jumped by {gap} to {fid}: frames were lost or not triggered "
                     f"by us")

    def flush(self) -> int:
        """Discard queued frames (and restart the stream if a frame is overdue); return how
        many were discarded."""
        if not self._started:
            return 0
        n = 0
        while True:
            buf = _a.lib.arv_stream_try_pop_buffer(self._stream)
            if not buf:
                break
            _a.lib.arv_stream_push_buffer(self._stream, buf)
            n += 1
        return self._flushed(n)

    def statistics(self) -> dict:
        """Aravis's stream counters: completed buffers, failures, underruns (since start)."""
        if self._stream is None:
            return {"completed": 0, "failures": 0, "underruns": 0}
        a, b, c = C.c_uint64(), C.c_uint64(), C.c_uint64()
        _a.lib.arv_stream_get_statistics(self._stream, C.byref(a), C.byref(b), C.byref(c))
        return {"completed": a.value, "failures": b.value, "underruns": c.value}

    def stop(self) -> None:
        """Stop acquiring and release the buffers (settings are kept)."""
        if self._started:
            try:
                _a.call("arv_camera_stop_acquisition", self._cam)
            finally:
                self._close_stream()
                self._started = False

    def close(self) -> None:
        """Stop and release the camera (idempotent)."""
        if self._cam is None:
            return
        try:
            self.stop()
        finally:
            _a.gobject.g_object_unref(self._cam)
            self._cam = None

    def __enter__(self) -> AravisCamera:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):  # a camera left open would keep its stream thread running
        try:
            self.close()
        except Exception:
            pass
