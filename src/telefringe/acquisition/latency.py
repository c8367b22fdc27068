"""Display-to-camera latency: measure it once per projector + camera pair, keep it.

Measurement (:func:`measure_latency`): the projector shows black long enough to settle,
then white; the camera is triggered ``d`` after the white image's flip with a short
exposure ``e``, for increasing ``d``. The mean level of each frame, normalised between
the settled black and white levels, is the fraction of the exposure that saw the new
image: ``f(d) = clip((d + e - L) / e, 0, 1)`` for an ideal step at latency ``L`` (a slow
panel rounds the corners). The latency kept is the smallest delay after which an
exposure sees the new image only: the first delay measured with ``f >= 0.98`` (so it
errs long by less than one delay step, never short), which the streamed
capture rounds up to whole refresh periods.

Storage (:func:`load_latency`, :func:`save_latency`): a small JSON file keyed by the pair
(driver and serial of each), at ``$TELEFRINGE_LATENCY_FILE`` if set, else
``$XDG_CONFIG_HOME/telefringe/latency.json`` (``~/.config/telefringe/latency.json``).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from telefringe.acquisition.base import AcquisitionError, Camera, FrameStatus, Projector

__all__ = ["LatencyMeasurement", "measure_latency", "fit_latency", "latency_file",
           "pair_key", "load_latency", "save_latency", "ENV_LATENCY_FILE"]

ENV_LATENCY_FILE = "TELEFRINGE_LATENCY_FILE"
_NS = 1_000_000_000


@dataclass(frozen=True)
class LatencyMeasurement:
    """Result of :func:`measure_latency`.

    latency_s : float, s, from a flip to an exposure that sees only the new image.
    half_s : float, s, the 50 % point plus half the exposure (the step's own latency for
        an instant panel). exposure_s : float, s. delays_s, fraction : (n,) arrays, the
        measured curve. dark, bright : float, DN, settled levels.
    """

    latency_s: float
    half_s: float
    exposure_s: float
    delays_s: np.ndarray
    fraction: np.ndarray
    dark: float
    bright: float


def fit_latency(delays_s, fraction, *, exposure_s: float, level: float = 0.98
                ) -> tuple[float, float]:
    """(first delay measured at ``level``, interpolated 50 % point + exposure / 2) from a
    measured curve.

    Parameters
    ----------
    delays_s : (n,) increasing, s. fraction : (n,), the normalised levels.

    Raises
    ------
    AcquisitionError
        The curve never reaches ``level`` (the delays are too short) or starts above it
        (the latency is shorter than the first delay: nothing to measure).
    """
    d = np.asarray(delays_s, dtype=float)
    f = np.asarray(fraction, dtype=float)

    def crossing(lv, interpolate=True):
        above = np.flatnonzero(f >= lv)
        if above.size == 0:
            raise AcquisitionError(f"the camera never saw the white image within "
                                   f"{d[-1] * 1e3:.1f} ms of the flip: is the camera looking "
                                   f"at the projected light? (or raise --max-delay)")
        i = int(above[0])
        if i == 0 or not interpolate:
            return float(d[i])
        f0, f1 = f[i - 1], f[i]
        return float(d[i - 1] + (lv - f0) / (f1 - f0) * (d[i] - d[i - 1]))

    # the wait must not be short: the first delay measured at ``level`` (no interpolation
    # toward shorter ones), exact to one delay step
    return crossing(level, interpolate=False), crossing(0.5) + exposure_s / 2


def measure_latency(camera: Camera, projector: Projector, *, exposure_s: float,
                    max_delay_s: float = 0.2, step_s: float | None = None,
                    timeout_s: float = 1.0, progress=None) -> LatencyMeasurement:
    """Measure the display latency (the camera is configured and started by the caller
    with a software trigger and ``exposure_s``; see the module docstring).

    Parameters
    ----------
    exposure_s : float, s, short (a quarter of a refresh period resolves the step well).
    max_delay_s : float, s, longest delay tried; also the settling time of each frame.
    step_s : float, s, delay step (default exposure / 2).
    """
    clock = projector.clock
    h, w = projector.info.height, projector.info.width
    top = 2 ** projector.info.bit_depth - 1
    dtype = np.uint8 if projector.info.bit_depth <= 8 else np.uint16
    black = np.zeros((h, w), dtype=dtype)
    white = np.full((h, w), top, dtype=dtype)
    step = exposure_s / 2 if step_s is None else step_s
    delays = np.arange(0.0, max_delay_s + 1e-12, step)
    settle = int(round((max_delay_s + exposure_s) * _NS))

    def level(img, delay_ns):
        shown = projector.show(img)
        clock.wait_until(shown.t_ns + delay_ns)
        camera.fire()
        f = camera.grab(exposure_s + timeout_s)
        if f.status is not FrameStatus.OK or f.image is None:
            f2 = None
            for _ in range(3):            # a lost frame: try again
                camera.flush()
                shown = projector.show(img)
                clock.wait_until(shown.t_ns + delay_ns)
                camera.fire()
                f2 = camera.grab(exposure_s + timeout_s)
                if f2.status is FrameStatus.OK and f2.image is not None:
                    break
            if f2 is None or f2.status is not FrameStatus.OK:
                raise AcquisitionError(f"latency: no good frame ({f.status.value})")
            f = f2
        return float(np.mean(f.image))

    projector.show(black)
    dark = level(black, settle)
    bright = level(white, settle)
    if bright - dark < 2.0:
        raise AcquisitionError(f"latency: white reads {bright:.1f} and black {dark:.1f}: the "
                               f"camera does not see the projector's light")
    frac = []
    for d in delays:
        level(black, settle)
        frac.append((level(white, int(round(d * _NS))) - dark) / (bright - dark))
        if progress is not None:
            progress(1)
    frac = np.array(frac)
    lat, half = fit_latency(delays, frac, exposure_s=exposure_s)
    return LatencyMeasurement(lat, half, exposure_s, delays, frac, dark, bright)


# --------------------------------------------------------------------------- storage
def latency_file() -> Path:
    """Where measured latencies are kept (see the module docstring)."""
    env = os.environ.get(ENV_LATENCY_FILE)
    if env:
        return Path(env)
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "telefringe" / "latency.json"


def pair_key(camera_info, projector_info) -> str:
    """The key of a projector + camera pair: ``projector DRIVER/SERIAL -> camera
    DRIVER/SERIAL``."""
    return (f"{projector_info.driver}/{projector_info.serial} -> "
            f"{camera_info.driver}/{camera_info.serial}")


def load_latency(key: str, path: Path | None = None) -> dict | None:
    """The stored entry of ``key`` ({"latency_s": ..., ...}) or None. A damaged file is an
    :class:`AcquisitionError` naming it."""
    path = latency_file() if path is None else Path(path)
    if not path.exists():
        return None
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise AcquisitionError(f"{path}: cannot read the stored latencies ({exc}); fix or "
                               f"remove it") from None
    entry = doc.get("pairs", {}).get(key) if isinstance(doc, dict) else None
    if entry is None:
        return None
    lat = entry.get("latency_s") if isinstance(entry, dict) else None
    if not isinstance(lat, int | float) or not 0 <= lat < 10:
        raise AcquisitionError(f"{path}: the entry {key!r} has no valid latency_s")
    return dict(entry)


def save_latency(key: str, entry: dict, path: Path | None = None) -> Path:
    """Store ``entry`` under ``key`` (other pairs kept), atomically; return the path."""
    from telefringe.io.atomic import write_json_atomic

    path = latency_file() if path is None else Path(path)
    doc = {"format": "telefringe-latency", "version": 1, "pairs": {}}
    if path.exists():
        try:
            old = json.loads(path.read_text(encoding="utf-8"))
            if isinstance(old, dict) and isinstance(old.get("pairs"), dict):
                doc["pairs"] = old["pairs"]
        except (OSError, ValueError):
            pass            # a damaged file is replaced
    doc["pairs"][key] = entry
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(path, doc, force=True)
    return path
