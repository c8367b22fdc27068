"""The ``pylon`` camera driver: Basler cameras (GigE, USB3, CoaXPress) through pypylon.

``--camera pylon:SERIAL`` (empty: the first camera). Needs ``pip install
'telefringe[pylon]'`` (Basler's pypylon wheel, about 90 MB, with the proprietary pylon
runtime inside). Setting ``PYLON_CAMEMU=N`` in the environment adds N emulated cameras
(pylon's camera emulation), which the tests use.

Same rules as the aravis driver: configure returns what the camera reports back; under
``Trigger.SOFTWARE`` a frame that arrives while no trigger is outstanding is discarded, a
frame whose id does not follow the last is INCOMPLETE, a failed buffer is INCOMPLETE with
pylon's words, and after a timed-out grab the next ``fire``/``flush`` restarts grabbing so
that a late frame cannot answer a new trigger.
"""

from __future__ import annotations

import warnings

import numpy as np

with warnings.catch_warnings():
    # pypylon's SWIG types warn on import, and a warning turned into an error there
    # crashes the interpreter (-W error; pytest's filterwarnings = error)
    warnings.filterwarnings("ignore", message="builtin type .* has no __module__",
                            category=DeprecationWarning)
    from pypylon import genicam, pylon  # the optional package

from telefringe.acquisition.base import (
    PIXEL_FORMAT_MAX,
    CameraInfo,
    CameraSettings,
    DeviceError,
    DeviceListing,
    Frame,
    FrameStatus,
    NotSupported,
    Trigger,
)
from telefringe.acquisition.drivers._ids import id_gap
from telefringe.acquisition.drivers._settings import check_configure, full_roi
from telefringe.acquisition.drivers._trigger import SoftwareTriggerBook

__all__ = ["PylonCamera", "open_camera", "list_cameras"]


def list_cameras() -> list[DeviceListing]:
    """The cameras pylon finds (and its emulated ones when PYLON_CAMEMU is set)."""
    return [DeviceListing("pylon", d.GetSerialNumber(), model=d.GetModelName(),
                          serial=d.GetSerialNumber(), detail=d.GetDeviceClass())
            for d in pylon.TlFactory.GetInstance().EnumerateDevices()]


def open_camera(address: str, *, projector=None) -> PylonCamera:
    """Open the camera with serial ``address`` ("" for the first); ``projector`` unused."""
    del projector
    return PylonCamera(address)


def _avail(node) -> bool:
    return node is not None and genicam.IsAvailable(node)


class PylonCamera(SoftwareTriggerBook):
    """A Basler camera through pypylon (the :class:`Camera` protocol)."""

    def __init__(self, serial: str = ""):
        tl = pylon.TlFactory.GetInstance()
        devs = [d for d in tl.EnumerateDevices() if not serial or d.GetSerialNumber() == serial]
        if not devs:
            found = ", ".join(d.GetSerialNumber() for d in tl.EnumerateDevices()) or "none"
            raise DeviceError(f"no Basler camera {serial or ''} found (found: {found})")
        d = devs[0]
        try:
            self._cam = pylon.InstantCamera(tl.CreateDevice(d))
            self._cam.Open()
        except Exception as exc:
            raise DeviceError(f"cannot open Basler camera {d.GetSerialNumber()}: {exc}") from exc
        self._gige = d.GetDeviceClass() == "BaslerGigE"
        c = self._cam
        formats = tuple(f for f in c.PixelFormat.Symbolics if f in PIXEL_FORMAT_MAX)
        self.info = CameraInfo(driver="pylon", model=d.GetModelName(),
                               serial=d.GetSerialNumber(), vendor=d.GetVendorName(),
                               width=int(c.Width.Max), height=int(c.Height.Max),
                               pixel_formats=formats, address=serial)
        self.settings: CameraSettings | None = None
        self.discarded = 0
        self.restarts = 0
        self._n_buffers = 8
        self._reset_counts()

    def _acquiring(self) -> bool:
        return bool(self._cam.IsGrabbing())

    def feature(self, name: str):
        """The GenICam node ``name`` of the camera (for features telefringe does not set,
        e.g. the emulator's ``ImageFilename``); set ``.Value`` while stopped."""
        node = getattr(self._cam, name, None)
        if not _avail(node):
            raise NotSupported(f"camera {self.info.model} has no feature {name}")
        return node

    def configure(self, *, exposure_s: float, gain_db: float = 0.0,
                  pixel_format: str = "Mono8",
                  roi: tuple[int, int, int, int] | None = None,
                  trigger: Trigger = Trigger.SOFTWARE,
                  trigger_line: str | None = None) -> CameraSettings:
        """Apply settings while stopped; return those read back (see the Camera protocol).
        Exposure through ``ExposureTime`` (or ``ExposureTimeAbs``), microseconds; gain
        through ``Gain`` in dB (a camera with raw gain units only accepts gain 0)."""
        c = self._cam
        check_configure(self.info, pixel_format, acquiring=c.IsGrabbing())
        c.PixelFormat.Value = pixel_format
        x, y, w, h = full_roi(roi, self.info)
        c.OffsetX.Value = 0
        c.OffsetY.Value = 0
        c.Width.Value = w
        c.Height.Value = h
        c.OffsetX.Value = x
        c.OffsetY.Value = y
        for auto in ("ExposureAuto", "GainAuto"):
            n = getattr(c, auto, None)
            if _avail(n) and genicam.IsWritable(n):
                n.Value = "Off"
        exp = next((getattr(c, n) for n in ("ExposureTime", "ExposureTimeAbs")
                    if _avail(getattr(c, n, None))), None)
        if exp is None:
            raise NotSupported(f"camera {self.info.model} has no ExposureTime feature")
        exp.Value = float(np.clip(exposure_s * 1e6, exp.Min, exp.Max))
        gain = getattr(c, "Gain", None)
        if _avail(gain):
            gain.Value = float(np.clip(gain_db, gain.Min, gain.Max))
            gain_applied = float(gain.Value)
        elif gain_db != 0:
            raise NotSupported(f"camera {self.info.model} has no Gain in dB; use gain 0")
        else:
            gain_applied = 0.0
        c.TriggerSelector.Value = "FrameStart"
        line = None
        if trigger is Trigger.FREE_RUN:
            c.TriggerMode.Value = "Off"
        else:
            c.TriggerMode.Value = "On"
            if trigger is Trigger.SOFTWARE:
                c.TriggerSource.Value = "Software"
            else:
                line = trigger_line or "Line1"
                c.TriggerSource.Value = line
        if _avail(getattr(c, "AcquisitionMode", None)):
            c.AcquisitionMode.Value = "Continuous"
        applied = str(c.PixelFormat.Value)
        self.settings = CameraSettings(
            exposure_s=float(exp.Value) * 1e-6, gain_db=gain_applied, pixel_format=applied,
            roi=(int(c.OffsetX.Value), int(c.OffsetY.Value), int(c.Width.Value),
                 int(c.Height.Value)),
            trigger=trigger, trigger_line=line,
            max_value=PIXEL_FORMAT_MAX.get(applied, PIXEL_FORMAT_MAX[pixel_format]))
        return self.settings

    def start(self, n_buffers: int = 8) -> None:
        """Start grabbing, oldest frame first, with ``n_buffers`` buffers."""
        if self.settings is None:
            raise DeviceError("configure() the camera before start()")
        self.stop()
        self._n_buffers = max(2, int(n_buffers))
        self._cam.MaxNumBuffer.Value = self._n_buffers
        self._cam.StartGrabbing(pylon.GrabStrategy_OneByOne)
        self._reset_counts()
        self.discarded = 0

    def _restart(self) -> None:
        self._cam.StopGrabbing()
        self._cam.StartGrabbing(pylon.GrabStrategy_OneByOne)
        self._reset_counts()
        self.restarts += 1

    def fire(self) -> None:
        """Software trigger (no-op unless configured with Trigger.SOFTWARE)."""
        if not self._fire_ready():
            return
        if not self._cam.WaitForFrameTriggerReady(1000, pylon.TimeoutHandling_Return):
            raise DeviceError("the camera did not become ready for a trigger within 1 s")
        self._cam.ExecuteSoftwareTrigger()
        self._owed += 1

    def grab(self, timeout_s: float) -> Frame:
        """The oldest frame not yet returned, within ``timeout_s`` seconds."""
        if not self._cam.IsGrabbing():
            raise DeviceError("start() the camera before grab()")
        software = self.settings.trigger is Trigger.SOFTWARE
        while True:
            r = self._cam.RetrieveResult(max(0, int(timeout_s * 1000)),
                                         pylon.TimeoutHandling_Return)
            if r is None or not r.IsValid():
                if software and self._owed:
                    self._desync = True
                return Frame(None, -1, None, FrameStatus.TIMEOUT,
                             f"no frame within {timeout_s:.3g} s")
            try:
                ok = r.GrabSucceeded()
                fid = int(r.GetBlockID())
                ts = int(r.GetTimeStamp()) or None
                msg = "" if ok else f"pylon: {r.ErrorDescription} (error 0x{r.ErrorCode:x})"
                image = np.array(r.Array, copy=True) if ok else None
            finally:
                r.Release()
            if software:
                if self._owed <= 0:
                    self.discarded += 1
                    continue
                self._owed -= 1
            if not ok:
                self._last_id = fid
                return Frame(None, fid, ts, FrameStatus.INCOMPLETE, msg)
            if self._last_id is not None:
                gap = id_gap(self._last_id, fid, wrap16=self._gige)
                if gap != 1:
                    self._last_id = fid
                    return Frame(image, fid, ts, FrameStatus.INCOMPLETE,
                                 f"frame id jumped by {gap} to {fid}")
            self._last_id = fid
            return Frame(image, fid, ts, FrameStatus.OK)

    def flush(self) -> int:
        """Discard queued frames (restarting grabbing when a frame is overdue)."""
        if not self._cam.IsGrabbing():
            return 0
        n = 0
        while self._cam.GetGrabResultWaitObject().Wait(0):
            r = self._cam.RetrieveResult(0, pylon.TimeoutHandling_Return)
            if r is None or not r.IsValid():
                break
            r.Release()
            n += 1
        return self._flushed(n)

    def stop(self) -> None:
        if self._cam is not None and self._cam.IsGrabbing():
            self._cam.StopGrabbing()

    def close(self) -> None:
        """Stop and release the camera (idempotent)."""
        if self._cam is None:
            return
        try:
            self.stop()
            self._cam.Close()
        finally:
            self._cam.DestroyDevice()
            self._cam = None

    def __enter__(self) -> PylonCamera:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
