"""Capture sequences: show the patterns, trigger, grab, verify every frame, re-shoot.

Two modes (see docs/acquisition.md):

- **streamed** (any projector, software trigger): per pattern ``show`` -> wait the
  display latency rounded up to whole refresh periods after the flip -> ``fire`` ->
  ``grab``; each frame is checked at once (status, id continuity, not a repeat of the
  previous buffer) and re-shot on failure; each group is then checked as a whole
  (saturation outliers, phase steps, Gray-code mixes) and its flagged frames re-shot;
- **sequenced** (a projector that holds the patterns and triggers the camera): load the
  sequence, arm the camera on its trigger line, run it once, collect the frames; the
  count, the ids (consecutive, GigE Vision wrap 65535 -> 1) and the time stamps (one
  pattern period apart) are checked, then the groups; any failure repeats the sequence.

Retries are bounded (:class:`Policy`); past them a :class:`CaptureFailed` says what went
wrong, and the caller writes nothing.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from telefringe.acquisition import verify
from telefringe.acquisition.base import (
    AcquisitionError,
    Camera,
    CameraSettings,
    FrameStatus,
    Projector,
    Trigger,
)

__all__ = ["CaptureFailed", "Policy", "Shot", "GroupReport", "PassResult", "wait_periods",
           "round_exposure", "capture_streamed", "capture_sequenced", "check_groups",
           "to_stored", "check_modulation"]

_NS = 1_000_000_000


class CaptureFailed(AcquisitionError):
    """The capture could not get verified frames within its retries."""


@dataclass(frozen=True)
class Policy:
    """How hard a capture tries.

    timeout_s : float, s, waited for a frame beyond its exposure (and readout allowance).
    frame_retries : int, extra attempts per frame (streamed) after a failed check.
    group_rounds : int, times a group's flagged frames (streamed) or the whole sequence
        (sequenced) are re-shot after the group checks.
    total_retries : int, re-shot frames allowed in one capture pass.
    spacing_tol : float, allowed deviation of time-stamp spacing, fraction of a period.
    max_saturated : float, largest saturated fraction of an image accepted at the
        shortest exposure (longer HDR exposures saturate by design).
    background_tol : float, largest RMS difference, relative to the modulation, between
        the background of a group the phase-step check cannot judge and that of a verified
        group (or 4 times its noise, if larger). Clean groups of the virtual rig show
        0.010-0.015 (noise); a frame of the previous pattern moves it by about 0.35 for
        N = 4, a quarter of one (4 ms of a 16 ms exposure) by 0.05-0.06.
    gray_repeat : float, a Gray-code frame whose RMS difference from the frame before it,
        relative to white - black, is below this shows mostly that frame's pattern
        (consecutive bit images differ on about half the pixels: about 0.7).
    min_modulated : float, smallest fraction of pixels that must show fringes (in the
        best phase group of a pass); below it the camera does not see the projection.
    flash_factor : float, a frame whose saturated fraction exceeds its group's median by
        this factor (and 0.5 % of the image) is re-shot.
    """

    timeout_s: float = 1.0
    frame_retries: int = 3
    group_rounds: int = 3
    total_retries: int = 50
    spacing_tol: float = 0.25
    max_saturated: float = 0.05
    flash_factor: float = 3.0
    min_modulated: float = 0.01
    background_tol: float = 0.03
    gray_repeat: float = 0.3


@dataclass(frozen=True)
class Shot:
    """One accepted frame: image (rows, cols) as the camera delivered it, frame_id,
    timestamp_ns (camera clock), t_shown_ns / t_fire_ns (projector clock; None in
    sequenced mode for t_fire), attempts (1 when the first attempt passed)."""

    image: np.ndarray
    frame_id: int
    timestamp_ns: int | None
    t_shown_ns: int | None
    t_fire_ns: int | None
    attempts: int = 1


@dataclass(frozen=True)
class GroupReport:
    """What the group checks found for one group of a pass: ``kind`` ("phase", "gray",
    "flat"), ``possible`` (the phase-step check could run), ``max_step_error_rad``,
    ``min_gain``/``max_gain``, ``modulated`` (fraction of pixels with fringes),
    ``saturated`` (largest saturated fraction), ``flagged`` (frame indices still flagged),
    ``message``."""

    kind: str
    possible: bool = False
    max_step_error_rad: float = float("nan")
    gain_range: tuple[float, float] = (float("nan"), float("nan"))
    modulated: float = float("nan")
    saturated: float = 0.0
    flagged: tuple[int, ...] = ()
    message: str = ""


@dataclass(frozen=True)
class PassResult:
    """One capture pass (one camera setting): the accepted shots in pattern order, the
    group reports, the retries spent and the failures seen (one line each)."""

    shots: tuple[Shot, ...]
    groups: tuple[GroupReport, ...]
    retries: int
    events: tuple[str, ...] = field(default_factory=tuple)


def wait_periods(latency_s: float, period_s: float, *, margin_s: float = 0.001) -> int:
    """Refresh periods to wait after a flip before exposing: the display latency plus a
    margin, rounded up to whole periods (at least 1).

    >>> wait_periods(0.025, 1 / 60)
    2
    """
    if period_s <= 0:
        return 1
    return max(1, math.ceil((latency_s + margin_s) / period_s - 1e-9))


def round_exposure(exposure_s: float, period_s: float) -> tuple[float, str]:
    """An exposure rounded to whole refresh periods (a DLP builds grey levels by pulse
    width within each period: other exposures see a level that depends on their start).
    Shorter than one period it is kept, with a warning. Returns (exposure, warning or "").

    >>> round_exposure(0.02, 1 / 60)[0] == 1 / 60
    True
    """
    if period_s <= 0:
        return exposure_s, ""
    k = round(exposure_s / period_s)
    if k >= 1:
        new = k * period_s
        warn = ("" if abs(new - exposure_s) <= 1e-3 * exposure_s else
                f"exposure {exposure_s * 1e3:.3f} ms rounded to {k} refresh period(s) = "
                f"{new * 1e3:.3f} ms")
        return new, warn
    return exposure_s, (f"exposure {exposure_s * 1e3:.3f} ms is shorter than one refresh period "
                        f"({period_s * 1e3:.3f} ms): a pulse-width-modulated projector (DLP) "
                        f"gives it a level that depends on when it starts")


def to_stored(image: np.ndarray, pixel_format: str) -> np.ndarray:
    """A camera image as a scan stores it: Mono8 as uint8, deeper formats in uint16
    MSB-aligned with the top bits replicated below (full scale 65535, like the virtual
    rig's 12-bit output), so that saturation stays at the stored maximum.

    >>> int(to_stored(np.array([4095], dtype=np.uint16), "Mono12")[0])
    65535
    """
    img = np.asarray(image)
    if pixel_format == "Mono8":
        return img.astype(np.uint8, copy=False)
    bits = {"Mono10": 10, "Mono12": 12, "Mono14": 14, "Mono16": 16}[pixel_format]
    x = img.astype(np.uint32)
    if bits == 16:
        return x.astype(np.uint16)
    return ((x << (16 - bits)) | (x >> (2 * bits - 16))).astype(np.uint16)


# --------------------------------------------------------------------------- group checks
def _dark_bright(shots_by_group, layout):
    """Per-pixel dark and bright levels from the first phase group (a - b, a + b)."""
    for (kind, _group), idx in zip(layout, shots_by_group, strict=True):
        if kind == "phase" and idx:
            st = np.stack(idx).astype(float)
            n = st.shape[0]
            d = 2 * np.pi * np.arange(n) / n
            c = np.tensordot(np.cos(d), st, axes=1)
            s = np.tensordot(np.sin(d), st, axes=1)
            b = 2.0 / n * np.hypot(c, s)
            a = st.mean(axis=0)
            return a - b, a + b
    return None, None


def check_groups(images: Sequence[np.ndarray], layout: Sequence[tuple], *, max_value: float,
                 policy: Policy, saturation_limit: bool, white_black: tuple | None = None
                 ) -> tuple[list[GroupReport], set[int]]:
    """Run the group checks on one pass.

    Parameters
    ----------
    images : the pass's frames in pattern order, (rows, cols) each.
    layout : per group, (kind, group) with kind "phase", "gray" or "flat" (white/black),
        in the same order; the frames of group g are consecutive.
    max_value : float, saturation level of ``images``.
    saturation_limit : bool, enforce ``policy.max_saturated`` (the shortest exposure).
    white_black : (index of white, index of black) in ``images`` or None.

    Returns
    -------
    reports : one :class:`GroupReport` per group.
    flagged : set of frame indices (into ``images``) to re-shoot.
    """
    full = images
    # the checks are statistics over the field: a regular sample of about 40 000 pixels
    # gives them to far better than their tolerances, at a fraction of the cost
    stride = max(1, int(np.sqrt(np.asarray(images[0]).size / 40_000)))
    images = [np.asarray(im)[::stride, ::stride] for im in images]
    counts = [g.count if kind != "flat" else 1 for kind, g in layout]
    starts = np.cumsum([0, *counts[:-1]])
    per_group = [list(images[s:s + c]) for s, c in zip(starts, counts, strict=True)]
    sat = np.array([verify.saturated_fraction(im, max_value=max_value) for im in images])
    flagged: set[int] = set()
    if saturation_limit:
        # stray light saturating one fringe frame (the shortest exposure only: longer HDR
        # passes saturate by design; white and black frames are not judged this way)
        is_flat = np.zeros(len(images), dtype=bool)
        for (kind, _g), s0, c in zip(layout, starts, counts, strict=True):
            is_flat[s0:s0 + c] = kind == "flat"
        med = float(np.median(sat[~is_flat])) if (~is_flat).any() else 0.0
        flash = np.flatnonzero((sat > max(policy.flash_factor * med, med + 0.005))
                               & ~is_flat)
        flagged.update(int(i) for i in flash)
    reports = []
    dark, bright = _dark_bright(per_group, layout)
    if white_black is not None and all(i is not None for i in white_black):
        bright = np.asarray(images[white_black[0]], dtype=float)
        dark = np.asarray(images[white_black[1]], dtype=float)
    ref = None              # (background, modulation) of a verified phase group
    pending = []            # phase groups the step check could not judge
    for (kind, _g), s0, frames in zip(layout, starts, per_group, strict=True):
        gsat = float(max((sat[s0 + j] for j in range(len(frames))), default=0.0))
        if kind == "phase":
            r = verify.phase_step_check(np.stack(frames), max_value=max_value)
            bad = {int(s0 + j) for j in np.flatnonzero(r.flagged)}
            # a frame far darker or brighter than its group (the projector showed
            # nothing yet, or stray light): caught even where the step check cannot run
            if not r.possible:
                pending.append((int(s0), len(frames), r))
            elif not bad and ref is None:
                st = np.stack(frames).astype(float)
                ref = (st.mean(axis=0), _modulation_b(st),
                       float(np.sqrt(np.mean(r.residual ** 2))))
            # a frame repeating its predecessor (late by a whole pattern)
            for j in range(1, len(frames)):
                if np.array_equal(frames[j], frames[j - 1]):
                    bad.add(int(s0 + j))
            # which frame of a group is off cannot always be told (N = 4: frame k and
            # k + 2 look alike): the whole group is re-shot
            flagged |= set(range(int(s0), int(s0) + len(frames))) if bad else set()
            reports.append(GroupReport(
                "phase", r.possible,
                float(np.nanmax(np.abs(r.step_error))) if r.possible else float("nan"),
                (float(np.nanmin(r.gain)), float(np.nanmax(r.gain))) if r.possible
                else (float("nan"), float("nan")),
                r.modulated, gsat, tuple(sorted(i - int(s0) for i in bad)), r.message))
        elif kind == "gray" and dark is not None:
            contrast = 0.1 * max_value
            r = verify.gray_check(np.stack(frames), dark=dark, bright=bright,
                                  min_contrast=contrast)
            bad = {int(s0 + j) for j in np.flatnonzero(r.flagged)}
            # a frame showing mostly the pattern before it (light late by most of the
            # exposure): consecutive bit images differ on about half the pixels
            lit = (bright - dark) > contrast
            late = []
            if np.count_nonzero(lit) >= 50:
                for j in range(len(frames)):
                    if s0 + j == 0:
                        continue
                    prev = np.asarray(images[s0 + j - 1], dtype=float)
                    d = (np.asarray(frames[j], dtype=float) - prev)[lit] / (bright - dark)[lit]
                    if float(np.sqrt(np.mean(d * d))) < policy.gray_repeat:
                        late.append(j)
                        bad.add(int(s0 + j))
            msg = r.message + "".join(f"; frame {j}: mostly the previous pattern"
                                      for j in late)
            flagged |= bad
            reports.append(GroupReport("gray", True, saturated=gsat,
                                       flagged=tuple(sorted(i - int(s0) for i in bad)),
                                       message=msg.strip("; ")))
        else:
            reports.append(GroupReport(kind, False, saturated=gsat))
    # groups the step check could not judge (a coarse group seeing part of a period):
    # their background (the mean of an N-step group, independent of the phase) must be
    # the verified group's; a dark, late or mixed frame moves it by a part of B / N
    flats = None
    if white_black is not None and all(i is not None for i in white_black):
        flats = (np.asarray(images[white_black[0]], dtype=float),
                 np.asarray(images[white_black[1]], dtype=float))
    if flats is not None and float(np.mean(flats[0] - flats[1])) < 0.02 * max_value:
        flagged |= {int(white_black[0]), int(white_black[1])}
        reports[-2] = GroupReport("flat", False, saturated=reports[-2].saturated, flagged=(0,),
                                  message="the white frame is not brighter than the black one")
        flats = None
    if ref is not None and flats is not None:
        # white above and black below the fringes' range
        a_ref, b_ref, _noise = ref
        ok = b_ref > 0.05 * max_value
        if np.count_nonzero(ok) >= 50:
            wq = float(np.median((flats[0][ok] - a_ref[ok]) / b_ref[ok]))
            bq = float(np.median((a_ref[ok] - flats[1][ok]) / b_ref[ok]))
            for idx, q, name in ((white_black[0], wq, "white"), (white_black[1], bq, "black")):
                if q < 0.5:
                    flagged.add(int(idx))
                    i = len(reports) - (2 if name == "white" else 1)
                    reports[i] = GroupReport("flat", False, saturated=reports[i].saturated,
                                             flagged=(0,), message=f"the {name} frame is not "
                                             f"{name}er than the fringes ({q:+.2f} B)")
    for s0, n, _r in pending:
        st = np.stack(images[s0:s0 + n]).astype(float)
        if ref is None:
            if flats is None:
                continue
            # no verified group: the background of an N-step group is black + kappa
            # (white - black) with one kappa per group (a linear camera)
            w_, k_ = flats
            b_own = _modulation_b(st)
            ok = ((b_own > 0.05 * max_value) & np.all(st < max_value, axis=0)
                  & (w_ - k_ > 0.1 * max_value))
            if np.count_nonzero(ok) < 50:
                continue
            y = st.mean(axis=0)[ok] - k_[ok]
            x = w_[ok] - k_[ok]
            kappa = float(np.sum(x * y) / np.sum(x * x))
            dev = float(np.sqrt(np.mean((y - kappa * x) ** 2))
                        / np.sqrt(np.mean(b_own[ok] ** 2)))
            if dev > policy.background_tol:
                flagged |= set(range(s0, s0 + n))
                i = int(np.searchsorted(starts, s0))
                old = reports[i]
                reports[i] = GroupReport(old.kind, old.possible, old.max_step_error_rad,
                                         old.gain_range, old.modulated, old.saturated,
                                         tuple(range(n)), f"background not proportional to "
                                         f"white - black ({100 * dev:.0f} % of the modulation)")
            continue
        a_ref, b_ref, noise = ref
        ok = (b_ref > 0.05 * max_value) & np.all(st < max_value, axis=0)
        if np.count_nonzero(ok) < 50:
            continue
        b_rms = float(np.sqrt(np.mean(b_ref[ok] ** 2)))
        dev = float(np.sqrt(np.mean((st.mean(axis=0)[ok] - a_ref[ok]) ** 2))) / b_rms
        # both backgrounds carry noise: sqrt(1/n + 1/N_ref) of a frame's
        tol = max(policy.background_tol, 4.0 * noise * np.sqrt(2.0 / n) / b_rms)
        if dev > tol:
            flagged |= set(range(s0, s0 + n))
            i = int(np.searchsorted(starts, s0))
            old = reports[i]
            reports[i] = GroupReport(old.kind, old.possible, old.max_step_error_rad,
                                     old.gain_range, old.modulated, old.saturated,
                                     tuple(range(n)), f"background off by {100 * dev:.0f} % "
                                     f"of the modulation from the verified groups' ({old.message})")
    for a, b in verify.duplicate_frames(images):
        if np.array_equal(full[a], full[b]):
            flagged.add(int(b))
    return reports, flagged


def _modulation_b(st: np.ndarray) -> np.ndarray:
    n = st.shape[0]
    d = 2 * np.pi * np.arange(n) / n
    return 2.0 / n * np.hypot(np.tensordot(np.cos(d), st, axes=1),
                              np.tensordot(np.sin(d), st, axes=1))


# --------------------------------------------------------------------------- streamed
def _grab_timeout(settings: CameraSettings, policy: Policy) -> float:
    return settings.exposure_s + policy.timeout_s


def capture_streamed(camera: Camera, projector: Projector, images: Sequence[np.ndarray], *,
                     settings: CameraSettings, wait_s: float, layout: Sequence[tuple],
                     policy: Policy = Policy(), saturation_limit: bool = True,
                     white_black: tuple | None = None,
                     progress: Callable[[int], None] | None = None,
                     last_id: int = -1, period_s: float = 0.0) -> PassResult:
    """Capture ``images`` one by one with software triggers (the camera is started,
    configured as ``settings``); verify and re-shoot (see the module docstring).

    Parameters
    ----------
    images : projector images (height, width), in pattern order.
    wait_s : float, s from a flip to the trigger (whole refresh periods).
    layout, white_black : see :func:`check_groups`.
    progress : called with 1 per accepted frame.
    last_id : the id of the frame before this pass (-1: none).
    period_s : float, the projector's refresh period; each round of group re-shoots waits
        one more (light that comes late -- a latency that varies -- is the usual cause
        of flagged phase steps).

    Raises
    ------
    CaptureFailed
        A frame failed ``policy.frame_retries`` + 1 times, the retries ran out, or frames
        were still flagged after ``policy.group_rounds`` rounds.
    """
    clock = projector.clock
    wait = {"ns": int(round(wait_s * _NS))}
    timeout = _grab_timeout(settings, policy)
    events: list[str] = []
    retries = 0
    state = {"last_id": int(last_id), "last_image": None, "consumed": 0}

    def shoot(i: int) -> Shot:
        nonlocal retries
        failures = []
        for attempt in range(policy.frame_retries + 1):
            if attempt:
                retries += 1
                if retries > policy.total_retries:
                    raise CaptureFailed(f"more than {policy.total_retries} re-shot frames in "
                                        f"one pass; last problem: {failures[-1]}")
                camera.flush()
            shown = projector.show(images[i])
            clock.wait_until(shown.t_ns + wait["ns"])
            t_fire = clock.now_ns()
            camera.fire()
            state["consumed"] += 1
            f = camera.grab(timeout)
            why = ""
            if f.status is not FrameStatus.OK:
                why = f"{f.status.value}" + (f" ({f.message})" if f.message else "")
            elif f.image is None:
                why = "no image"
            else:
                gap = verify.id_gap(state["last_id"], f.frame_id)
                if state["last_id"] > 0 and f.frame_id > 0 and gap == 0:
                    why = f"stale frame: id {f.frame_id} again"
                elif state["last_id"] > 0 and f.frame_id > 0 and gap > state["consumed"]:
                    why = (f"id {f.frame_id} after {state['last_id']} with "
                           f"{state['consumed']} trigger(s) in between: not the frame "
                           f"just triggered")
                elif (state["last_image"] is not None
                      and np.array_equal(f.image[::7, ::7], state["last_image"][::7, ::7])
                      and np.array_equal(f.image, state["last_image"])
                      and float(np.std(f.image[::7, ::7])) >= 1.0):
                    why = "the previous image again (stuck buffer)"
            if (f.frame_id > 0 and f.status is not FrameStatus.TIMEOUT
                    and (state["last_id"] <= 0
                         or 0 < verify.id_gap(state["last_id"], f.frame_id) < 32768)):
                # ids consumed so far are counted from this frame on (an older frame
                # delivered late does not move the count back)
                state["last_id"], state["consumed"] = f.frame_id, 0
            if not why:
                state["last_image"] = f.image
                return Shot(np.asarray(f.image), f.frame_id, f.timestamp_ns, shown.t_ns,
                            t_fire, attempt + 1)
            failures.append(why)
            events.append(f"pattern {i}: {why}")
        seen: dict[str, int] = {}
        for why in failures:
            seen[why] = seen.get(why, 0) + 1
        said = "; ".join(f"{n} x {w}" if n > 1 else w for w, n in seen.items())
        raise CaptureFailed(f"pattern {i}: {policy.frame_retries + 1} attempts failed "
                            f"({said})")

    shots = []
    for i in range(len(images)):
        shots.append(shoot(i))
        if progress is not None:
            progress(1)
    reports, flagged = check_groups([s.image for s in shots], layout,
                                    max_value=settings.max_value, policy=policy,
                                    saturation_limit=saturation_limit,
                                    white_black=white_black)
    for _ in range(policy.group_rounds):
        if not flagged:
            break
        if period_s > 0:
            wait["ns"] += int(round(period_s * _NS))
        events.append(f"group checks flagged frames {sorted(flagged)}: re-shot"
                      + (f", waiting {wait['ns'] / _NS * 1e3:.1f} ms after each flip"
                         if period_s > 0 else ""))
        for i in sorted(flagged):
            retries += 1
            if retries > policy.total_retries:
                raise CaptureFailed(f"more than {policy.total_retries} re-shot frames in one "
                                    f"pass; the group checks still flag {sorted(flagged)}")
            s = shoot(i)
            shots[i] = Shot(s.image, s.frame_id, s.timestamp_ns, s.t_shown_ns, s.t_fire_ns,
                            s.attempts + shots[i].attempts)
        reports, flagged = check_groups([s.image for s in shots], layout,
                                        max_value=settings.max_value, policy=policy,
                                        saturation_limit=saturation_limit,
                                        white_black=white_black)
    if flagged:
        msgs = [r.message for r in reports if r.flagged and r.message]
        raise CaptureFailed(f"frames {sorted(flagged)} still fail the group checks after "
                            f"{policy.group_rounds} re-shoots"
                            + (f": {msgs[0]}" if msgs else "")
                            + "; if the light comes late, measure the latency again "
                              "(telefringe capture latency)")
    _check_saturation(shots, settings, policy, saturation_limit)
    return PassResult(tuple(shots), tuple(reports), retries, tuple(events))


def check_modulation(reports, policy) -> None:
    """Fail when no phase group of a scan (all passes' reports) shows fringes on at least
    ``policy.min_modulated`` of the pixels."""
    mods = [r.modulated for r in reports if r.kind == "phase" and np.isfinite(r.modulated)]
    if mods and max(mods) < policy.min_modulated:
        raise CaptureFailed(f"only {100 * max(mods):.2f} % of the pixels show fringes: the "
                            f"camera does not see the projected patterns (in view? in "
                            f"focus? lens cap? exposure?)")


def _check_saturation(shots, settings, policy, saturation_limit):
    if not saturation_limit:
        return
    sat = [verify.saturated_fraction(s.image, max_value=settings.max_value) for s in shots]
    worst = float(np.median(sat)) if sat else 0.0
    if worst > policy.max_saturated:
        raise CaptureFailed(f"{100 * worst:.1f} % of the pixels are saturated at exposure "
                            f"{settings.exposure_s * 1e3:.3f} ms (at most "
                            f"{100 * policy.max_saturated:.0f} % accepted): shorten the "
                            f"exposure, or add a shorter one (--exposures)")


# --------------------------------------------------------------------------- sequenced
def capture_sequenced(camera: Camera, projector: Projector, images: Sequence[np.ndarray], *,
                      settings: CameraSettings, exposure_s: float, layout: Sequence[tuple],
                      period_s: float | None = None, policy: Policy = Policy(),
                      saturation_limit: bool = True, white_black: tuple | None = None,
                      progress: Callable[[int], None] | None = None) -> PassResult:
    """Let a sequencer projector run ``images`` and trigger the camera (configured with
    ``Trigger.HARDWARE`` as ``settings``, started); check and repeat the whole sequence on
    any failure (see the module docstring).

    Raises
    ------
    CaptureFailed
        Still failing after ``policy.group_rounds`` + 1 runs.
    """
    if not projector.info.sequencer:
        raise CaptureFailed(f"the {projector.info.driver} projector has no sequencer: use the "
                            f"streamed mode")
    if settings.trigger is not Trigger.HARDWARE:
        raise CaptureFailed("sequenced mode needs the camera on its hardware trigger")
    if period_s is None:
        # the camera must finish its exposure and readout before the next trigger: a
        # whole refresh period beyond the exposure ("waste one refresh period")
        rp = projector.info.period_s
        period_s = ((math.ceil(settings.exposure_s / rp - 1e-9) + 1) * rp if rp > 0
                    else 1.25 * settings.exposure_s + 0.002)
    # each pattern stays lit for its whole period; the camera's exposure sits inside it
    seq = projector.load_sequence(images, exposure_s=max(exposure_s, period_s),
                                  period_s=period_s)
    events: list[str] = []
    retries = 0
    last = "no run"
    for run in range(policy.group_rounds + 1):
        if run:
            retries += len(images)
            camera.flush()
        projector.start_sequence(1)
        frames = []
        problems = []
        for i in range(seq.count):
            f = camera.grab(seq.period_s + settings.exposure_s + policy.timeout_s)
            if f.status is FrameStatus.TIMEOUT:
                problems.append(f"{seq.count - i} of {seq.count} frames missing (timeout "
                                f"after frame {i - 1})")
                break
            if f.status is not FrameStatus.OK:
                problems.append(f"frame {i}: {f.status.value} {f.message}".strip())
            frames.append(f)
            if progress is not None and run == 0:
                progress(1)
        projector.stop_sequence()
        if len(frames) == seq.count:
            ids = verify.check_ids([f.frame_id for f in frames])
            if not ids.ok:
                problems.append(f"ids: {ids.message}")
            sp = verify.check_spacing([f.timestamp_ns for f in frames], period_s=seq.period_s,
                                      tolerance=policy.spacing_tol)
            if not sp.ok:
                problems.append(f"time stamps: {sp.message}")
        if not problems:
            imgs = [np.asarray(f.image) for f in frames]
            reports, flagged = check_groups(imgs, layout, max_value=settings.max_value,
                                            policy=policy, saturation_limit=saturation_limit,
                                            white_black=white_black)
            if not flagged:
                shots = tuple(Shot(im, f.frame_id, f.timestamp_ns, None, None, run + 1)
                              for im, f in zip(imgs, frames, strict=True))
                _check_saturation(shots, settings, policy, saturation_limit)
                return PassResult(shots, tuple(reports), retries, tuple(events))
            problems.append(f"group checks flagged frames {sorted(flagged)}")
        last = "; ".join(problems)
        events.append(f"sequence run {run + 1}: {last}")
    raise CaptureFailed(f"the pattern sequence failed {policy.group_rounds + 1} times; "
                        f"last: {last}")
