"""The ``gentl`` camera driver: any camera with a GenTL producer (.cti), through harvesters.

``--camera gentl:PATH.cti[#WHICH]`` with WHICH a device index (default 0), serial number
or device id; ``gentl:#WHICH`` (or ``gentl:``) searches every producer on the standard
``GENICAM_GENTL64_PATH`` (vendors' SDKs set it: Basler, Allied Vision, Baumer, IDS, The
Imaging Source, Teledyne FLIR, MATRIX VISION...). Needs ``pip install
'telefringe[gentl]'`` (harvesters) and the vendor's producer.

Features are set by their SFNC names (ExposureTime in microseconds, Gain, PixelFormat,
Width/Height/OffsetX/OffsetY, TriggerSelector/TriggerMode/TriggerSource/TriggerSoftware).
A device that lacks exposure or trigger control can only free-run (enumeration and
focusing; a capture refuses it: :class:`~telefringe.acquisition.base.NotSupported`).

Stale frames: under ``Trigger.SOFTWARE`` a frame that arrives while no trigger is
outstanding is discarded; an id that does not follow the last one returns the frame as
INCOMPLETE; after a timed-out grab the next ``fire``/``flush`` restarts acquisition so that
a late frame cannot answer a new trigger (as in the aravis driver).
"""

from __future__ import annotations

import glob
import math
import os
import sys

import numpy as np
from harvesters.core import Harvester  # the optional package

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
from telefringe.acquisition.drivers._settings import check_configure
from telefringe.acquisition.drivers._trigger import SoftwareTriggerBook

__all__ = ["GentlCamera", "open_camera", "list_cameras", "producers"]


def producers(path: str = "") -> list[str]:
    """The .cti files to load: ``path`` itself, or every .cti in the directories of
    ``GENICAM_GENTL64_PATH`` (``GENICAM_GENTL32_PATH`` on 32-bit Pythons)."""
    if path:
        if not os.path.isfile(path):
            raise DeviceError(f"no GenTL producer file {path!r}")
        return [path]
    var = "GENICAM_GENTL64_PATH" if sys.maxsize > 2 ** 32 else "GENICAM_GENTL32_PATH"
    found = []
    for d in filter(None, os.environ.get(var, "").split(os.pathsep)):
        found += sorted(glob.glob(os.path.join(d, "*.cti")))
    if not found:
        raise DeviceError(f"no GenTL producer: give gentl:PATH.cti, or install the camera "
                          f"vendor's SDK (it sets {var})")
    return found


def _harvester(path: str) -> Harvester:
    h = Harvester()
    for f in producers(path):
        h.add_file(f, check_existence=True, check_validity=True)
    h.update()
    return h


def list_cameras(path: str = "") -> list[DeviceListing]:
    """The devices the producers find (``path``: one .cti, else GENICAM_GENTL64_PATH);
    DeviceError saying what is missing when there is no producer."""
    h = _harvester(path)
    try:
        return [DeviceListing("gentl", f"{path}#{i}" if path else f"#{i}",
                              model=str(d.model), serial=str(d.serial_number),
                              detail=f"{d.vendor} {d.tl_type} id {d.id_}")
                for i, d in enumerate(h.device_info_list)]
    finally:
        h.reset()


def open_camera(address: str, *, projector=None) -> GentlCamera:
    """Open ``PATH.cti[#WHICH]`` (see the module docstring); ``projector`` unused."""
    del projector
    path, _, which = address.partition("#")
    return GentlCamera(path, which)


def _node(nm, name):
    return getattr(nm, name) if nm.has_node(name) else None


def _set(node, value) -> None:
    try:
        node.value = value
    except Exception as exc:
        name = getattr(getattr(node, "node", None), "name", "a feature")
        raise DeviceError(f"cannot set {name} to {value!r}: {exc}") from exc


class GentlCamera(SoftwareTriggerBook):
    """A GenTL camera through harvesters (the :class:`Camera` protocol).

    Parameters
    ----------
    path : str, a .cti file or "" for GENICAM_GENTL64_PATH. which : str, device index,
    serial number or id ("" for the first).
    """

    def __init__(self, path: str = "", which: str = ""):
        self._h = _harvester(path)
        infos = self._h.device_info_list
        if not infos:
            self._h.reset()
            raise DeviceError("the GenTL producer finds no device")
        idx = None
        if which == "":
            idx = 0
        elif which.isdigit() and int(which) < len(infos):
            idx = int(which)
        else:
            for i, d in enumerate(infos):
                if which in (str(d.serial_number), str(d.id_)):
                    idx = i
        if idx is None:
            names = ", ".join(f"{i}: {d.id_} ({d.serial_number})" for i, d in enumerate(infos))
            self._h.reset()
            raise DeviceError(f"no GenTL device {which!r}; found {names}")
        try:
            self._ia = self._h.create(idx)
        except Exception as exc:
            self._h.reset()
            raise DeviceError(f"cannot open GenTL device {idx}: {exc}") from exc
        d = infos[idx]
        nm = self._ia.remote_device.node_map
        pf = _node(nm, "PixelFormat")
        formats = tuple(f for f in (pf.symbolics if pf is not None else ())
                        if f in PIXEL_FORMAT_MAX)
        wmax = _node(nm, "WidthMax") or _node(nm, "Width")
        hmax = _node(nm, "HeightMax") or _node(nm, "Height")
        self.info = CameraInfo(driver="gentl", model=str(d.model), serial=str(d.serial_number),
                               vendor=str(d.vendor), width=int(wmax.value) if wmax else 0,
                               height=int(hmax.value) if hmax else 0, pixel_formats=formats,
                               address=f"{path}#{which}" if which else path)
        self.settings: CameraSettings | None = None
        self.discarded = 0
        self.restarts = 0
        self._started = False
        self._reset_counts()

    def _acquiring(self) -> bool:
        return self._started

    @property
    def _nm(self):
        return self._ia.remote_device.node_map

    def configure(self, *, exposure_s: float, gain_db: float = 0.0,
                  pixel_format: str = "Mono8",
                  roi: tuple[int, int, int, int] | None = None,
                  trigger: Trigger = Trigger.SOFTWARE,
                  trigger_line: str | None = None) -> CameraSettings:
        """Apply settings while stopped; return those read back (see the Camera protocol).
        A device without ExposureTime (or trigger control) can only FREE_RUN; its
        exposure is then reported as NaN (unknown)."""
        check_configure(self.info, pixel_format, acquiring=self._started)
        nm = self._nm
        nm.PixelFormat.value = pixel_format
        if roi is not None:
            x, y, w, h = (int(v) for v in roi)
            for name, v in (("OffsetX", 0), ("OffsetY", 0), ("Width", w), ("Height", h),
                            ("OffsetX", x), ("OffsetY", y)):
                n = _node(nm, name)
                if n is None:
                    if v:
                        raise NotSupported(f"camera {self.info.model} has no {name}")
                    continue
                n.value = v
        exp = _node(nm, "ExposureTime")
        if exp is None and trigger is not Trigger.FREE_RUN:
            raise NotSupported(f"camera {self.info.model} has no ExposureTime feature: "
                               f"telefringe cannot control its exposure")
        for auto in ("ExposureAuto", "GainAuto"):
            n = _node(nm, auto)
            if n is not None and n.value != "Off":
                _set(n, "Off")
        if exp is not None:
            exp.value = float(np.clip(exposure_s * 1e6, exp.min, exp.max))
        gain = _node(nm, "Gain")
        if gain is not None:
            gain.value = float(np.clip(gain_db, gain.min, gain.max))
        mode = _node(nm, "TriggerMode")
        line = None
        if trigger is Trigger.FREE_RUN:
            if mode is not None:
                nm.TriggerSelector.value = "FrameStart"
                mode.value = "Off"
        else:
            if mode is None:
                raise NotSupported(f"camera {self.info.model} has no trigger control")
            nm.TriggerSelector.value = "FrameStart"
            mode.value = "On"
            if trigger is Trigger.SOFTWARE:
                nm.TriggerSource.value = "Software"
            else:
                line = trigger_line or "Line0"
                nm.TriggerSource.value = line
        acq = _node(nm, "AcquisitionMode")
        if acq is not None and acq.value != "Continuous":
            _set(acq, "Continuous")
        w, h = int(nm.Width.value), int(nm.Height.value)
        ox = _node(nm, "OffsetX")
        oy = _node(nm, "OffsetY")
        applied = str(nm.PixelFormat.value)
        self.settings = CameraSettings(
            exposure_s=float(exp.value) * 1e-6 if exp is not None else math.nan,
            gain_db=float(gain.value) if gain is not None else 0.0, pixel_format=applied,
            roi=(int(ox.value) if ox else 0, int(oy.value) if oy else 0, w, h),
            trigger=trigger, trigger_line=line,
            max_value=PIXEL_FORMAT_MAX.get(applied, PIXEL_FORMAT_MAX[pixel_format]))
        return self.settings

    def start(self, n_buffers: int = 8) -> None:
        """Start acquiring (nothing queued from before)."""
        if self.settings is None:
            raise DeviceError("configure() the camera before start()")
        if self._started:
            self.stop()
        self._ia.num_buffers = max(self._ia.min_num_buffers, int(n_buffers))
        self._ia.start()
        self._started = True
        self._reset_counts()
        self.discarded = 0

    def _restart(self) -> None:
        self._ia.stop()
        self._ia.start()
        self._reset_counts()
        self.restarts += 1

    def fire(self) -> None:
        """Software trigger (no-op unless configured with Trigger.SOFTWARE)."""
        if not self._fire_ready():
            return
        self._nm.TriggerSoftware.execute()
        self._owed += 1

    def grab(self, timeout_s: float) -> Frame:
        """The oldest frame not yet returned, within ``timeout_s`` seconds."""
        if not self._started:
            raise DeviceError("start() the camera before grab()")
        software = self.settings.trigger is Trigger.SOFTWARE
        while True:
            try:
                buf = self._ia.fetch(timeout=max(1e-3, float(timeout_s)))
            except Exception as exc:  # harvesters raises on timeout
                if software and self._owed:
                    self._desync = True
                return Frame(None, -1, None, FrameStatus.TIMEOUT,
                             f"no frame within {timeout_s:.3g} s ({type(exc).__name__})")
            with buf:
                m = buf.module
                fid = int(m.frame_id)
                complete = bool(m.is_complete())
                try:
                    ts = int(buf.timestamp_ns) or None
                except Exception:
                    ts = None
                image = None
                if complete:
                    c = buf.payload.components[0]
                    image = np.array(c.data, copy=True).reshape(c.height, c.width)
            if software:
                if self._owed <= 0:
                    self.discarded += 1
                    continue
                self._owed -= 1
            if not complete:
                self._last_id = fid
                return Frame(None, fid, ts, FrameStatus.INCOMPLETE,
                             "GenTL: incomplete buffer")
            if self._last_id is not None and fid != self._last_id + 1:
                gap = fid - self._last_id
                self._last_id = fid
                return Frame(image, fid, ts, FrameStatus.INCOMPLETE,
                             f"frame id jumped by {gap} to {fid}")
            self._last_id = fid
            return Frame(image, fid, ts, FrameStatus.OK)

    def flush(self) -> int:
        """Discard queued frames (restarting acquisition); return how many."""
        if not self._started:
            return 0
        n = 0
        while True:
            try:
                buf = self._ia.try_fetch(timeout=1e-3)
            except Exception:
                buf = None
            if buf is None:
                break
            buf.queue()
            n += 1
        return self._flushed(n)

    def stop(self) -> None:
        if self._started:
            self._ia.stop()
            self._started = False

    def close(self) -> None:
        """Stop and release the device and the producers (idempotent)."""
        if self._ia is None:
            return
        try:
            self.stop()
            self._ia.destroy()
        finally:
            self._ia = None
            self._h.reset()

    def __enter__(self) -> GentlCamera:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
