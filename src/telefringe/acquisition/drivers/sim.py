"""The ``sim`` driver: a camera + projector pair backed by the virtual rig, on a virtual
clock (nothing sleeps), with seeded faults.

Timing model (all on one :class:`VirtualClock`, integer nanoseconds):

- the projector refreshes every ``1 / refresh`` s; :meth:`SimProjector.show` returns at
  the next refresh (the flip, :attr:`Shown.t_ns`) and its light appears ``latency`` s
  later (the display's input lag; ``telefringe capture latency`` measures it), plus the
  seeded ``jitter`` / ``late`` faults;
- a camera exposure opened at ``t`` (a software trigger plus ``trigger_delay``, or a
  hardware trigger from the sim projector's sequencer) integrates what the projector
  shows during ``[t, t + exposure]``: a pattern change inside it mixes the two patterns
  in proportion to their times; the frame is delivered ``readout`` s after the exposure
  ends; a trigger arriving while the camera is still busy is lost (as on real cameras);
- the image is the virtual rig's render (:mod:`telefringe.simulate.render`): the
  pattern-independent geometry once per scene, one noise-free signal per projector
  pattern, then exposure, shot and read noise, quantisation and saturation per frame.
  ``exposure_ref`` seconds give the renderer's exposure 1 (about 200 DN on the plate's
  light areas at 8 bits). Gain is fixed at 0 dB (the renderer has no analogue gain;
  ``configure`` says so by returning 0).

Address options (``--projector sim:KEY=VALUE,...``, ``--camera sim:KEY=VALUE,...``):

projector (and the rig): ``preset`` (fast, paper, mixed, macro), ``crop`` (``WxH+X+Y``:
read out only that window of the virtual camera's sensor, for small fast rigs), ``bin``
(N: the camera's pixels binned N x N, the field unchanged; applied before ``crop``),
``scene`` (plate, steps, sphere, bga, tilted-plane, calibration), ``z`` (mm), ``poses``
(calibration poses), ``seed``,
``refresh`` (Hz), ``latency`` (s), ``jitter`` (s, uniform extra latency per show),
``late`` (shows whose light comes one refresh period late);
camera: ``drop`` (frames that never arrive), ``incomplete`` (buffers with lost packets),
``stuck`` (the previous image again under a new id), ``missed`` (triggers ignored),
``flash`` (stray light saturating a frame), ``id_start`` (first frame id; GigE Vision
ids wrap from 65535 to 1), ``readout`` (s).

A fault's value is a probability (``drop=0.05``) or the 0-based indices at which it
strikes, after ``@`` and joined by ``+`` (``drop=@3+7``: the camera's 4th and 8th
triggers). Camera fault indices count triggers received, projector ones count shows.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from telefringe.acquisition.base import (
    PIXEL_FORMAT_MAX,
    CameraInfo,
    CameraSettings,
    DeviceError,
    DeviceListing,
    Frame,
    FrameStatus,
    NotSupported,
    ProjectorInfo,
    SequenceSettings,
    Shown,
    Trigger,
)

__all__ = ["VirtualClock", "Fault", "SimConfig", "SimRig", "SimProjector", "SimCamera",
           "parse_address", "open_camera", "open_projector", "list_cameras",
           "list_projectors", "next_frame_id"]

_NS = 1_000_000_000
_PROJECTOR_KEYS = {"preset", "scene", "z", "poses", "seed", "refresh", "latency", "jitter",
                   "late", "crop", "bin"}
_CAMERA_KEYS = {"drop", "incomplete", "stuck", "missed", "flash", "id_start", "readout"}


def next_frame_id(frame_id: int) -> int:
    """The GigE Vision (GEV 1.x) block id after ``frame_id``: 65535 wraps to 1 (0 is
    never used).

    >>> next_frame_id(65535), next_frame_id(7)
    (1, 8)
    """
    return 1 if frame_id >= 65535 else frame_id + 1


class VirtualClock:
    """A clock that only moves when someone waits on it (nanoseconds; starts at 1 s)."""

    def __init__(self, start_ns: int = _NS):
        self._t = int(start_ns)

    def now_ns(self) -> int:
        return self._t

    def wait_until(self, t_ns: int) -> None:
        self._t = max(self._t, int(t_ns))


@dataclass(frozen=True)
class Fault:
    """When a seeded fault strikes: with ``probability`` per event, or at ``at`` (0-based
    event indices)."""

    probability: float = 0.0
    at: frozenset = frozenset()

    def strikes(self, index: int, rng: np.random.Generator) -> bool:
        """Whether event ``index`` is hit (draws from ``rng`` only for a probability)."""
        if index in self.at:
            return True
        return bool(self.probability > 0 and rng.random() < self.probability)

    @staticmethod
    def parse(key: str, text: str) -> Fault:
        text = text.strip()
        if text.startswith("@"):
            try:
                at = frozenset(int(x) for x in text[1:].split("+") if x)
            except ValueError:
                raise DeviceError(f"sim: {key}={text!r}: expected @INDEX[+INDEX...]") from None
            if any(i < 0 for i in at):
                raise DeviceError(f"sim: {key}={text!r}: indices must be >= 0")
            return Fault(at=at)
        try:
            p = float(text)
        except ValueError:
            raise DeviceError(f"sim: {key}={text!r}: expected a probability in [0, 1] or "
                              f"@INDEX[+INDEX...]") from None
        if not 0.0 <= p <= 1.0:
            raise DeviceError(f"sim: {key}={text!r}: a probability must be in [0, 1]")
        return Fault(probability=p)


@dataclass(frozen=True)
class SimConfig:
    """Everything the sim pair is made of (see the module docstring for the keys).

    Times in seconds. ``exposure_ref``: the exposure that gives the renderer's exposure 1.
    """

    preset: str = "fast"
    crop: str = ""
    bin: int = 1
    scene: str = "plate"
    z: float = 0.0
    poses: int = 8
    seed: int = 0
    refresh: float = 60.0
    latency: float = 0.025
    jitter: float = 0.0
    late: Fault = Fault()
    drop: Fault = Fault()
    incomplete: Fault = Fault()
    stuck: Fault = Fault()
    missed: Fault = Fault()
    flash: Fault = Fault()
    id_start: int = 1
    readout: float = 0.005
    trigger_delay: float = 20e-6
    exposure_ref: float = 2.0 / 60.0


def parse_address(address: str, *, kind: str, base: SimConfig | None = None) -> SimConfig:
    """Parse a sim address ``KEY=VALUE,...`` for ``kind`` ("camera" or "projector") on
    top of ``base``.

    >>> parse_address("drop=@3,id_start=65534", kind="camera").id_start
    65534
    """
    cfg = base or SimConfig()
    allowed = _CAMERA_KEYS if kind == "camera" else _PROJECTOR_KEYS
    changes: dict = {}
    for item in (s.strip() for s in address.split(",")):
        if not item:
            continue
        key, eq, value = item.partition("=")
        key = key.strip().replace("-", "_")
        if not eq:
            raise DeviceError(f"sim {kind}: {item!r}: expected KEY=VALUE")
        if key not in allowed:
            other = _PROJECTOR_KEYS if kind == "camera" else _CAMERA_KEYS
            where = (f"; it belongs to the sim {'projector' if kind == 'camera' else 'camera'}"
                     if key in other else "")
            raise DeviceError(f"sim {kind}: unknown option {key!r}{where}; known: "
                              f"{', '.join(sorted(allowed))}")
        try:
            if key in ("late", "drop", "incomplete", "stuck", "missed", "flash"):
                changes[key] = Fault.parse(key, value)
            elif key in ("preset", "scene", "crop"):
                changes[key] = value.strip()
            elif key in ("poses", "seed", "id_start", "bin"):
                changes[key] = int(value)
            else:
                changes[key] = float(value)
        except ValueError:
            raise DeviceError(f"sim {kind}: {key}={value!r} is not a number") from None
    cfg = replace(cfg, **changes)
    if not 1 <= cfg.id_start <= 65535:
        raise DeviceError(f"sim camera: id_start must be 1..65535, got {cfg.id_start}")
    if not 1.0 <= cfg.refresh <= 10_000.0:
        raise DeviceError(f"sim projector: refresh must be 1..10000 Hz, got {cfg.refresh}")
    for key in ("latency", "jitter", "readout"):
        v = getattr(cfg, key)
        if not (math.isfinite(v) and 0 <= v <= 10):
            raise DeviceError(f"sim: {key} must be 0..10 s, got {v}")
    if not 1 <= cfg.bin <= 64:
        raise DeviceError(f"sim projector: bin must be 1..64, got {cfg.bin}")
    if cfg.poses < 4 and cfg.scene == "calibration":
        raise DeviceError(f"sim projector: poses must be >= 4, got {cfg.poses}")
    return cfg


# --------------------------------------------------------------------------- the rig
def _image_line(image: np.ndarray, shape: tuple[int, int]) -> tuple[str, np.ndarray]:
    """A projector image that is constant along rows or columns -> (axis, 1-D levels)."""
    img = np.asarray(image)
    if img.shape != shape:
        raise DeviceError(f"sim projector: image is {img.shape[1] if img.ndim > 1 else '?'}"
                          f" x {img.shape[0]}, the panel {shape[1]} x {shape[0]}")
    if img.dtype != np.uint8:
        raise DeviceError(f"sim projector: images must be uint8 (8-bit panel), got {img.dtype}")
    if np.all(img == img[:1, :]):
        return "u", img[0].copy()
    if np.all(img == img[:, :1]):
        return "v", img[:, 0].copy()
    raise NotSupported("sim projector: the virtual rig renders fringe images only (each "
                       "row or each column constant), not this 2-D image")


class SimRig:
    """The state the sim pair shares: virtual clock, virtual rig, scene, and the
    projector's timeline (what light it emits from when).

    Parameters
    ----------
    config : SimConfig
    """

    def __init__(self, config: SimConfig):
        from telefringe.simulate.calibration import simulate_calibration_poses
        from telefringe.simulate.presets import get_preset

        self.config = config
        self.clock = VirtualClock()
        try:
            self.vrig = get_preset(config.preset)
            if config.bin > 1:
                from telefringe.simulate.presets import bin_camera_any

                self.vrig = bin_camera_any(self.vrig, config.bin)
            if config.crop:
                from telefringe.simulate.presets import crop_camera

                size, _, rest = config.crop.partition("+")
                w, h = (int(v) for v in size.lower().split("x"))
                x, y = (int(v) for v in rest.split("+"))
                self.vrig = crop_camera(self.vrig, col0=x, row0=y, width=w, height=h)
        except ValueError as exc:
            raise DeviceError(f"sim: {exc} (crop is WIDTHxHEIGHT+X+Y)" if config.crop
                              else f"sim: {exc}") from None
        self.poses = ()
        if config.scene == "calibration":
            try:
                self.poses = simulate_calibration_poses(self.vrig, n_poses=config.poses,
                                                        seed=config.seed)
            except ValueError as exc:  # e.g. a crop too small for the plate
                raise DeviceError(f"sim: {exc}") from None
        self.pose_index = 0
        self.scene = self._make_scene(0)
        self._geom = None
        self._signals: dict = {}
        proj = self.vrig.projector.intrinsics
        self.panel_shape = (int(proj.height), int(proj.width))
        # timeline: sorted (t_ns, key) with key = (axis, bytes of the line) or None (dark)
        self.timeline: list[tuple[int, tuple | None]] = [(0, None)]
        self._lines: dict = {}
        self.camera: SimCamera | None = None
        self.noise_rng = np.random.default_rng(np.random.SeedSequence([config.seed, 1]))
        self.fault_rng = np.random.default_rng(np.random.SeedSequence([config.seed, 2]))

    # scenes -------------------------------------------------------------------------
    def _make_scene(self, k: int):
        from telefringe.simulate.scenes import CirclePlate, make_scene

        if self.poses:
            p = self.poses[k]
            t = self.vrig.target
            return CirclePlate(R_world_target=p.R_world_target,
                               t_world_target=p.t_world_target, rows=t.rows, cols=t.cols,
                               pitch=t.pitch_mm, diameter=t.diameter_mm)
        try:
            return make_scene(self.config.scene, z=self.config.z, seed=self.config.seed)
        except ValueError as exc:
            raise DeviceError(f"sim: {exc}") from None

    def move_to_pose(self, k: int) -> None:
        """Put the calibration plate at pose ``k`` (a ``scene=calibration`` rig only)."""
        if not self.poses:
            raise NotSupported("sim: only scene=calibration has poses")
        if not 0 <= k < len(self.poses):
            raise DeviceError(f"sim: pose {k} is not one of the {len(self.poses)} poses")
        self.pose_index = k
        self.scene = self._make_scene(k)
        self._geom = None
        self._signals.clear()

    # light --------------------------------------------------------------------------
    def emit(self, t_ns: int, image: np.ndarray | None) -> None:
        """From ``t_ns`` on, the projector emits ``image`` (None: dark)."""
        key = None
        if image is not None:
            axis, line = _image_line(image, self.panel_shape)
            key = (axis, line.tobytes())
            self._lines.setdefault(key, (axis, line))
        # a later event set before this one (a sequence being cut short) is superseded
        self.timeline = [e for e in self.timeline if e[0] < t_ns]
        self.timeline.append((int(t_ns), key))

    def _signal(self, key) -> np.ndarray:
        """Noise-free camera signal (8-bit DN at exposure 1, padded grid) of a line."""
        from telefringe.simulate import render

        if self._geom is None:
            self._geom = render.trace_geometry(self.vrig, self.scene)
        if key not in self._signals:
            if key is None:
                line, axis = np.zeros(self.panel_shape[1], dtype=np.uint8), "u"
                # a dark projector still emits its black level: the renderer's level 0
            else:
                axis, line = self._lines[key]
            self._signals[key] = render._integrate_many(self._geom, self.vrig, axis, [line])[0]
        return self._signals[key]

    def weights(self, t0_ns: int, t1_ns: int) -> list[tuple[float, tuple | None]]:
        """What the projector emitted during ``[t0, t1]``: (fraction of the time, key)."""
        out = []
        span = max(1, t1_ns - t0_ns)
        tl = self.timeline
        for i, (t, key) in enumerate(tl):
            t_next = tl[i + 1][0] if i + 1 < len(tl) else None
            a = max(t, t0_ns)
            b = t1_ns if t_next is None else min(t_next, t1_ns)
            if b > a:
                out.append(((b - a) / span, key))
        return out

    def render(self, t0_ns: int, t1_ns: int, *, pixel_format: str = "Mono8",
               gain: float = 1.0) -> np.ndarray:
        """The camera image of an exposure ``[t0, t1]`` (ns on the virtual clock): the
        time-weighted mix of what the projector showed, through the virtual camera.

        Returns (rows, cols) uint8 for Mono8, uint16 LSB-aligned for Mono12/Mono16.
        ``gain`` multiplies the light (a stray flash), not the noise-free signal's SNR.
        """
        from telefringe.simulate import render

        sig = None
        for w, key in self.weights(t0_ns, t1_ns):
            s = self._signal(key) * w
            sig = s if sig is None else sig + s
        if sig is None:
            sig = self._signal(None)
        bits = {"Mono8": 8, "Mono12": 12, "Mono16": 16}[pixel_format]
        vr = self.vrig if self.vrig.photometry.bit_depth == bits else \
            self.vrig.with_photometry(bit_depth=bits)
        exposure = (t1_ns - t0_ns) / _NS / self.config.exposure_ref * gain
        img = render._sensor(sig, vr, exposure, self.noise_rng, self._geom.pad)
        if bits == 12:           # the renderer stores 12 bits MSB-aligned; cameras LSB
            img = img >> 4
        return img


# --------------------------------------------------------------------------- projector
class SimProjector:
    """The virtual rig's projector (streamed and sequenced modes). See the module
    docstring for the timing."""

    def __init__(self, rig: SimRig, address: str = ""):
        self.rig = rig
        self.clock = rig.clock
        h, w = rig.panel_shape
        cfg = rig.config
        self.info = ProjectorInfo(driver="sim", model=f"virtual projector ({cfg.preset} rig)",
                                  serial=f"SIMP-{cfg.seed:04d}", width=w, height=h,
                                  refresh_hz=float(cfg.refresh), bit_depth=8, sequencer=True,
                                  address=address)
        self._period_ns = int(round(_NS / cfg.refresh))
        self._shows = 0
        self._sequence: tuple | None = None
        self._closed = False

    def _next_vsync(self) -> int:
        now = self.clock.now_ns()
        return (now // self._period_ns + 1) * self._period_ns

    def show(self, image: np.ndarray) -> Shown:
        self._check_open()
        cfg = self.rig.config
        _image_line(image, self.rig.panel_shape)          # refuse bad images up front
        t_flip = self._next_vsync()
        self.clock.wait_until(t_flip)
        extra = 0.0
        if cfg.jitter > 0:
            extra += float(self.rig.fault_rng.uniform(0.0, cfg.jitter))
        if cfg.late.strikes(self._shows, self.rig.fault_rng):
            extra += 1.0 / cfg.refresh
        self._shows += 1
        self.rig.emit(t_flip + int(round((cfg.latency + extra) * _NS)), image)
        return Shown(t_ns=t_flip, refresh=t_flip // self._period_ns)

    def load_sequence(self, images: Sequence[np.ndarray], *, exposure_s: float,
                      period_s: float | None = None, trigger_out: bool = True
                      ) -> SequenceSettings:
        self._check_open()
        imgs = [np.asarray(i) for i in images]
        if not imgs:
            raise DeviceError("sim projector: an empty sequence")
        for i in imgs:
            _image_line(i, self.rig.panel_shape)
        period = 1.0 / self.rig.config.refresh if period_s is None else float(period_s)
        period = round(period * 1e6) / 1e6
        exposure = min(round(float(exposure_s) * 1e6) / 1e6, period)
        if exposure <= 0:
            raise DeviceError(f"sim projector: exposure must be > 0, got {exposure_s}")
        self._sequence = (imgs, exposure, period, bool(trigger_out))
        return SequenceSettings(count=len(imgs), period_s=period, exposure_s=exposure,
                                trigger_out=bool(trigger_out))

    def start_sequence(self, repeats: int = 1) -> Shown:
        self._check_open()
        if self._sequence is None:
            raise DeviceError("sim projector: no sequence loaded")
        imgs, exposure, period, trig = self._sequence
        t0 = self.clock.now_ns() + 1_000_000           # the sequencer starts 1 ms later
        p_ns, e_ns = int(round(period * _NS)), int(round(exposure * _NS))
        n = 0
        for _ in range(int(repeats)):
            for img in imgs:
                t = t0 + n * p_ns
                self.rig.emit(t, img)
                if e_ns < p_ns:
                    self.rig.emit(t + e_ns, None)
                if trig and self.rig.camera is not None:
                    self.rig.camera._hardware_trigger(t)
                n += 1
        self.rig.emit(t0 + n * p_ns, None)
        return Shown(t_ns=t0)

    def stop_sequence(self) -> None:
        if self.rig.camera is not None:
            self.rig.camera._cancel_after(self.clock.now_ns())
        self.rig.emit(self.clock.now_ns(), None)

    def _check_open(self):
        if self._closed:
            raise DeviceError("sim projector: closed")

    def close(self) -> None:
        if not self._closed:
            self.rig.emit(self.clock.now_ns(), None)
        self._closed = True

    def __enter__(self) -> SimProjector:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# --------------------------------------------------------------------------- camera
@dataclass
class _Exposure:
    index: int
    t0: int
    t1: int
    deliver: int
    frame_id: int
    faults: set = field(default_factory=set)


class SimCamera:
    """The virtual rig's camera. See the module docstring for timing and faults."""

    def __init__(self, rig: SimRig, config: SimConfig, address: str = ""):
        self.rig = rig
        self.config = config
        k = rig.vrig.camera.intrinsics
        rows, cols = int(k.height), int(k.width)
        self.info = CameraInfo(driver="sim", model=f"virtual camera ({config.preset} rig)",
                               serial=f"SIMC-{config.seed:04d}", vendor="telefringe",
                               width=int(cols), height=int(rows),
                               pixel_formats=("Mono8", "Mono12", "Mono16"), address=address)
        self.settings = CameraSettings(exposure_s=config.exposure_ref, gain_db=0.0,
                                       pixel_format="Mono8", roi=(0, 0, int(cols), int(rows)),
                                       trigger=Trigger.SOFTWARE, max_value=255)
        self._started = False
        self._closed = False
        self._queue: list[_Exposure] = []
        self._triggers = 0
        self._next_id = config.id_start
        self._busy_until = 0
        self._last_image: np.ndarray | None = None
        rig.camera = self

    # settings -----------------------------------------------------------------------
    def configure(self, *, exposure_s: float, gain_db: float = 0.0,
                  pixel_format: str = "Mono8", roi: tuple[int, int, int, int] | None = None,
                  trigger: Trigger = Trigger.SOFTWARE,
                  trigger_line: str | None = None) -> CameraSettings:
        self._check_open()
        if self._started:
            raise DeviceError("sim camera: stop acquisition before changing settings")
        if pixel_format not in self.info.pixel_formats:
            raise NotSupported(f"sim camera: pixel format {pixel_format!r} not offered; "
                               f"use one of {', '.join(self.info.pixel_formats)}")
        if not (math.isfinite(exposure_s) and exposure_s > 0):
            raise DeviceError(f"sim camera: exposure must be > 0 s, got {exposure_s}")
        exposure = min(max(round(exposure_s * 1e6) / 1e6, 10e-6), 10.0)
        W, H = self.info.width, self.info.height
        if roi is None:
            roi = (0, 0, W, H)
        x, y, w, h = (int(v) for v in roi)
        if not (0 <= x and 0 <= y and w >= 1 and h >= 1 and x + w <= W and y + h <= H):
            raise DeviceError(f"sim camera: ROI {w} x {h} at ({x}, {y}) is not inside the "
                              f"{W} x {H} sensor")
        line = None
        if trigger is Trigger.HARDWARE:
            line = trigger_line or "Line0"
        self.settings = CameraSettings(exposure_s=exposure, gain_db=0.0,
                                       pixel_format=pixel_format, roi=(x, y, w, h),
                                       trigger=trigger, trigger_line=line,
                                       max_value=PIXEL_FORMAT_MAX[pixel_format])
        del gain_db     # no analogue gain in the virtual camera: 0 dB is what is set
        return self.settings

    # acquisition --------------------------------------------------------------------
    def start(self, n_buffers: int = 8) -> None:
        self._check_open()
        if self.settings.trigger is Trigger.FREE_RUN:
            raise NotSupported("sim camera: free-run is not simulated; use a trigger")
        self._queue.clear()
        self._started = True

    def stop(self) -> None:
        self._started = False
        self._queue.clear()

    def flush(self) -> int:
        now = self.rig.clock.now_ns()
        n = sum(1 for e in self._queue if e.deliver <= now and "drop" not in e.faults)
        self._queue = [e for e in self._queue if e.deliver > now]
        return n

    def _expose(self, t_trigger: int) -> None:
        cfg, rng = self.config, self.rig.fault_rng
        idx = self._triggers
        self._triggers += 1
        t0 = t_trigger + int(round(cfg.trigger_delay * _NS))
        if cfg.missed.strikes(idx, rng) or t0 < self._busy_until:
            return                              # ignored trigger (or one while busy)
        t1 = t0 + int(round(self.settings.exposure_s * _NS))
        deliver = t1 + int(round(cfg.readout * _NS))
        self._busy_until = deliver
        faults = {name for name in ("drop", "incomplete", "stuck", "flash")
                  if getattr(cfg, name).strikes(idx, rng)}
        self._queue.append(_Exposure(idx, t0, t1, deliver, self._next_id, faults))
        self._next_id = next_frame_id(self._next_id)

    def _hardware_trigger(self, t_ns: int) -> None:
        if self._started and self.settings.trigger is Trigger.HARDWARE:
            self._expose(t_ns)

    def _cancel_after(self, t_ns: int) -> None:
        self._queue = [e for e in self._queue if e.t0 <= t_ns]

    def fire(self) -> None:
        self._check_open()
        if not self._started:
            raise DeviceError("sim camera: fire() before start()")
        if self.settings.trigger is Trigger.SOFTWARE:
            self._expose(self.rig.clock.now_ns())

    def grab(self, timeout_s: float) -> Frame:
        self._check_open()
        if not self._started:
            raise DeviceError("sim camera: grab() before start()")
        clock = self.rig.clock
        deadline = clock.now_ns() + int(round(float(timeout_s) * _NS))
        self._queue.sort(key=lambda e: e.deliver)
        while self._queue and self._queue[0].deliver <= deadline:
            e = self._queue.pop(0)
            if "drop" in e.faults:
                continue                     # lost on the wire: never delivered
            clock.wait_until(e.deliver)
            return self._frame(e)
        clock.wait_until(deadline)
        return Frame(image=None, frame_id=-1, timestamp_ns=None, status=FrameStatus.TIMEOUT,
                     message=f"no frame within {timeout_s:.3g} s")

    def _frame(self, e: _Exposure) -> Frame:
        s = self.settings
        if "stuck" in e.faults and self._last_image is not None:
            img = self._last_image.copy()
        else:
            img = self.rig.render(e.t0, e.t1, pixel_format=s.pixel_format,
                                  gain=8.0 if "flash" in e.faults else 1.0)
            x, y, w, h = s.roi
            img = np.ascontiguousarray(img[y:y + h, x:x + w])
        status, msg = FrameStatus.OK, ""
        if "incomplete" in e.faults:
            img = img.copy()
            lost = int(self.rig.fault_rng.integers(1, max(2, img.shape[0] // 2)))
            img[-lost:] = 0
            status, msg = FrameStatus.INCOMPLETE, f"{lost} lines lost (missing packets)"
        self._last_image = img
        return Frame(image=img, frame_id=e.frame_id, timestamp_ns=e.t0, status=status,
                     message=msg)

    # sim-only: move the calibration plate (``telefringe capture calibration`` calls it
    # after the user's Enter when the camera has it)
    def move_to_pose(self, k: int) -> None:
        """Move the virtual calibration plate to pose ``k`` (sim only)."""
        self.rig.move_to_pose(k)

    @property
    def n_poses(self) -> int:
        """Poses the virtual plate can take (0 unless ``scene=calibration``)."""
        return len(self.rig.poses)

    def _check_open(self):
        if self._closed:
            raise DeviceError("sim camera: closed")

    def close(self) -> None:
        self.stop()
        self._closed = True

    def __enter__(self) -> SimCamera:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# --------------------------------------------------------------------------- registry
def open_projector(address: str) -> SimProjector:
    """The sim projector (and the virtual rig it shares with the sim camera)."""
    cfg = parse_address(address, kind="projector")
    return SimProjector(SimRig(cfg), address)


def open_camera(address: str, *, projector=None) -> SimCamera:
    """The sim camera of the sim ``projector`` opened for the same capture."""
    if not isinstance(projector, SimProjector):
        raise NotSupported("the sim camera renders what the sim projector shows: use "
                           "--projector sim with --camera sim")
    if projector.rig.camera is not None and not projector.rig.camera._closed:
        raise DeviceError("sim: this sim projector already has a camera")
    cfg = parse_address(address, kind="camera", base=projector.rig.config)
    return SimCamera(projector.rig, cfg, address)


def list_cameras() -> list[DeviceListing]:
    from telefringe.simulate.presets import PRESETS, get_preset

    out = []
    for name in PRESETS:
        k = get_preset(name).camera.intrinsics
        out.append(DeviceListing("sim", f"preset={name}", f"virtual camera ({name} rig)",
                                 "SIMC-0000", f"{k.width} x {k.height}, Mono8/12/16; pairs "
                                 f"with --projector sim:preset={name}"))
    return out


def list_projectors() -> list[DeviceListing]:
    from telefringe.simulate.presets import PRESETS, get_preset

    out = []
    for name in PRESETS:
        k = get_preset(name).projector.intrinsics
        out.append(DeviceListing("sim", f"preset={name}", f"virtual projector ({name} rig)",
                                 "SIMP-0000", f"{k.width} x {k.height}, 60 Hz, sequencer"))
    return out
