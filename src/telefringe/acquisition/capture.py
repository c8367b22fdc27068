"""A whole scan from a camera and a projector: the pattern set, one pass per exposure,
verification, and the provenance that goes into scan.json's ``capture`` block.

Nothing here writes files: :func:`capture_scan` returns the scan in memory and the block;
the command line writes both atomically (``telefringe.io.scan_json.write_scan``).
"""

from __future__ import annotations

import datetime as _dt
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from telefringe import __version__
from telefringe.acquisition.base import Camera, CameraSettings, Projector, Trigger
from telefringe.acquisition.sequence import (
    CaptureFailed,
    PassResult,
    Policy,
    capture_sequenced,
    capture_streamed,
    check_modulation,
    round_exposure,
    to_stored,
    wait_periods,
)
from telefringe.fringes.patterns import pattern_stack
from telefringe.fringes.scan import GrayGroup, PhaseGroup, Scan, ScanManifest

__all__ = ["LatencyUsed", "CaptureResult", "capture_scan", "image_names", "pass_images"]


@dataclass(frozen=True)
class LatencyUsed:
    """The display latency a streamed capture waits for.

    latency_s : float, s, from a flip to the light (measured or given). source : str,
    "measured" (``telefringe capture latency``), "option" or "default".
    """

    latency_s: float
    source: str


@dataclass(frozen=True, eq=False)
class CaptureResult:
    """A captured scan (images as stored: uint8, or uint16 MSB-aligned) and its
    ``capture`` block (a JSON-ready dict, see docs/formats.md)."""

    scan: Scan
    capture: dict


def image_names(group, exposure: float) -> tuple[str, ...]:
    """File names of a group's images (the names ``telefringe patterns`` uses, with the
    relative exposure appended when it is not 1)."""
    exp = "" if exposure == 1.0 else f"_e{exposure:g}".replace(".", "p")
    if isinstance(group, PhaseGroup):
        off = "" if not group.offset else f"_o{group.offset:+.3f}".replace(".", "p")
        stem = f"{group.axis}_{group.periods:03d}_{group.steps}s{off}{exp}"
    else:
        stem = f"{group.axis}_gray{group.bits}{'c' if group.complementary else ''}{exp}"
    return tuple(f"{stem}_{k:02d}.png" for k in range(group.count))


def pass_images(groups: Sequence, *, width: int, height: int, white_black: bool,
                bit_depth: int = 8) -> tuple[list[np.ndarray], list[tuple], tuple | None]:
    """The projector images of one pass: every group's images, then white and black.

    Returns (images, layout for :func:`~telefringe.acquisition.sequence.check_groups`,
    (white index, black index) or None).
    """
    images: list[np.ndarray] = []
    layout: list[tuple] = []
    for g in groups:
        st = pattern_stack(g, width=width, height=height, bit_depth=bit_depth)
        images.extend(st)
        layout.append(("phase" if isinstance(g, PhaseGroup) else "gray", g))
    wb = None
    if white_black:
        top = 2 ** bit_depth - 1
        dtype = np.uint8 if bit_depth <= 8 else np.uint16
        wb = (len(images), len(images) + 1)
        images.append(np.full((height, width), top, dtype=dtype))
        images.append(np.zeros((height, width), dtype=dtype))
        layout += [("flat", None), ("flat", None)]
    return images, layout, wb


def _settings_json(s: CameraSettings) -> dict:
    return {"exposure_s": float(s.exposure_s), "gain_db": float(s.gain_db),
            "pixel_format": s.pixel_format, "roi": [int(v) for v in s.roi],
            "trigger": s.trigger.value, "trigger_line": s.trigger_line,
            "max_value": int(s.max_value)}


def _nan_none(x: float):
    return None if x is None or not math.isfinite(x) else float(x)


def capture_scan(camera: Camera, projector: Projector, *, groups: Sequence,
                 white_black: bool, exposure_s: float, exposures: Sequence[float] = (1.0,),
                 mode: str = "streamed", latency: LatencyUsed | None = None,
                 pixel_format: str = "Mono8", gain_db: float = 0.0,
                 roi: tuple[int, int, int, int] | None = None, whole_periods: bool = True,
                 policy: Policy = Policy(),
                 progress: Callable[[int], None] | None = None) -> CaptureResult:
    """Capture a scan: for each relative exposure one pass over the pattern set (white
    and black at the first), each frame verified and re-shot as needed.

    Parameters
    ----------
    camera, projector : open devices (the camera is configured and started here).
    groups : PhaseGroup / GrayGroup (no image names; ``exposure`` 1).
    white_black : bool, also full-on and full-off frames.
    exposure_s : float, s, the base exposure; ``exposures`` multiply it (HDR), each
        rounded to whole refresh periods when ``whole_periods`` (see
        :func:`~telefringe.acquisition.sequence.round_exposure`); the scan's ``exposure``
        fields are the applied exposures over ``exposure_s``.
    mode : "streamed" or "sequenced".
    latency : LatencyUsed, the display latency (streamed); None: 3 refresh periods.
    pixel_format, gain_db, roi : camera settings asked for.
    policy : Policy.  progress : called with 1 per accepted frame of the first attempt.

    Raises
    ------
    CaptureFailed, AcquisitionError
    """
    info_p = projector.info
    period = info_p.period_s
    if mode not in ("streamed", "sequenced"):
        raise ValueError(f"mode must be 'streamed' or 'sequenced', got {mode!r}")
    if latency is None:
        # 3 refresh periods after the flip (a common input lag is 1-2 frames)
        latency = LatencyUsed(2.5 * period if period > 0 else 0.05, "default")
    warnings: list[str] = []
    if latency.source == "default":
        warnings.append("no measured display latency: waited 3 refresh periods (run "
                        "`telefringe capture latency` once for this pair)")
    n_wait = wait_periods(latency.latency_s, period)
    wait_s = n_wait * period if period > 0 else latency.latency_s + 0.001
    passes: list[tuple[float, CameraSettings, PassResult, list]] = []
    t_start = _dt.datetime.now(_dt.UTC)
    order = sorted(range(len(exposures)), key=lambda i: -exposures[i])
    shortest = order[-1]
    for e_index, factor in enumerate(exposures):
        want = exposure_s * float(factor)
        applied_want, warn = round_exposure(want, period) if whole_periods else (want, "")
        if warn:
            warnings.append(warn)
        camera.stop()
        trig = Trigger.HARDWARE if mode == "sequenced" else Trigger.SOFTWARE
        settings = camera.configure(exposure_s=applied_want, gain_db=gain_db,
                                    pixel_format=pixel_format, roi=roi, trigger=trig)
        if e_index == 0 and abs(settings.gain_db - gain_db) > 0.05:
            warnings.append(f"the camera set gain {settings.gain_db:g} dB for {gain_db:g} dB "
                            f"asked")
        if abs(settings.exposure_s - applied_want) > 1e-3 * applied_want:
            warnings.append(f"the camera set exposure {settings.exposure_s * 1e3:.3f} ms for "
                            f"{applied_want * 1e3:.3f} ms asked")
        camera.start()
        images, layout, wb = pass_images(groups, width=info_p.width, height=info_p.height,
                                         white_black=white_black and e_index == 0,
                                         bit_depth=info_p.bit_depth)
        limit = e_index == shortest
        if mode == "streamed":
            res = capture_streamed(camera, projector, images, settings=settings, wait_s=wait_s,
                                   layout=layout, policy=policy, saturation_limit=limit,
                                   white_black=wb, progress=progress, period_s=period)
        else:
            res = capture_sequenced(camera, projector, images, settings=settings,
                                    exposure_s=settings.exposure_s, layout=layout,
                                    policy=policy, saturation_limit=limit, white_black=wb,
                                    progress=progress)
        rel = settings.exposure_s / exposure_s
        if abs(rel - float(factor)) <= 1e-3 * float(factor):
            rel = float(factor)         # the camera's own rounding (us steps) is no change
        passes.append((rel, settings, res, layout))
    camera.stop()
    # fringes must be seen somewhere (an HDR set's shortest pass may see them only on
    # highlights, its longest clip much of the field)
    check_modulation([r for p in passes for r in p[2].groups], policy)
    return _assemble(camera, projector, passes, white_black=white_black, mode=mode,
                     latency=latency, n_wait=n_wait, wait_s=wait_s, warnings=warnings,
                     t_start=t_start, base_exposure=exposure_s)


def _assemble(camera, projector, passes, *, white_black, mode, latency, n_wait, wait_s,
              warnings, t_start, base_exposure) -> CaptureResult:
    out_groups, stacks, frames = [], [], []
    white = black = None
    wb_frames = []
    max_value = 255.0
    for rel, settings, res, layout in passes:
        rel = float(f"{rel:.4g}")
        fmt = settings.pixel_format
        max_value = 255.0 if fmt == "Mono8" else 65535.0
        pos = 0
        for kind, g in layout:
            if kind == "flat":
                sh = res.shots[pos]
                img = to_stored(sh.image, fmt)
                rec = _frame_json(sh, rel)
                if white is None:
                    white, wb_frames = img, [*wb_frames, {"image": "white.png", **rec}]
                else:
                    black, wb_frames = img, [*wb_frames, {"image": "black.png", **rec}]
                pos += 1
                continue
            g2 = replace(g, exposure=rel, images=image_names(g, rel))
            shots = res.shots[pos:pos + g.count]
            pos += g.count
            out_groups.append(g2)
            stacks.append(np.stack([to_stored(s.image, fmt) for s in shots]))
            frames += [{"image": n, **_frame_json(s, rel)}
                       for n, s in zip(g2.images, shots, strict=True)]
    frames += wb_frames
    ip, ic = projector.info, camera.info
    man = ScanManifest(projector_width=int(ip.width), projector_height=int(ip.height),
                       groups=tuple(out_groups), white="white.png" if white is not None
                       else None, black="black.png" if black is not None else None)
    scan = Scan(manifest=man, stacks=tuple(stacks), white=white, black=black,
                max_value=max_value, source=f"capture {ic.driver}:{ic.address}")
    checks = []
    for rel, _s, res, layout in passes:
        for (kind, g), rep in zip(layout, res.groups, strict=True):
            if kind == "flat":
                continue
            d = {"group": _group_label(g, rel), "kind": rep.kind,
                 "phase_step_check": bool(rep.possible),
                 "max_step_error_rad": _nan_none(rep.max_step_error_rad),
                 "saturated_fraction": float(rep.saturated)}
            if rep.kind == "phase":
                d["modulated_fraction"] = _nan_none(rep.modulated)
            if rep.message and not rep.possible:
                d["note"] = rep.message
            checks.append(d)
    block = {
        "version": 1,
        "software": f"telefringe {__version__}",
        "started_utc": t_start.isoformat(timespec="seconds"),
        "mode": mode,
        "camera": {"driver": ic.driver, "address": ic.address, "vendor": ic.vendor,
                   "model": ic.model, "serial": ic.serial},
        "projector": {"driver": ip.driver, "address": ip.address, "model": ip.model,
                      "serial": ip.serial, "width": int(ip.width), "height": int(ip.height),
                      "refresh_hz": float(ip.refresh_hz)},
        "settings": [_settings_json(s) for _r, s, _p, _l in passes],
        "base_exposure_s": float(base_exposure),
        "latency": {"latency_s": float(latency.latency_s), "source": latency.source,
                    "wait_periods": int(n_wait), "wait_s": float(wait_s)},
        "stored": "uint8" if max_value == 255.0 else "uint16, MSB-aligned",
        "retries": int(sum(p[2].retries for p in passes)),
        "events": [e for p in passes for e in p[2].events],
        "checks": checks,
        "warnings": warnings,
        "frames": frames,
    }
    return CaptureResult(scan=scan, capture=block)


def _group_label(g, rel) -> str:
    if isinstance(g, GrayGroup):
        return f"gray {g.axis} {g.bits} bits, exposure {rel:g}"
    return f"phase {g.axis} {g.periods} periods {g.steps} steps, exposure {rel:g}"


def _frame_json(s, rel) -> dict:
    return {"id": int(s.frame_id), "timestamp_ns": None if s.timestamp_ns is None
            else int(s.timestamp_ns), "attempts": int(s.attempts), "exposure": rel}


__all__ += ["CaptureFailed"]
