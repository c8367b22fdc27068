"""Frame verification: is every captured frame the pattern it claims to be?

Numerics only (arrays in, frozen dataclasses out). The capture (``sequence.py``) calls
these after each frame and each group and re-shoots what they flag.

Checks
------
- transport: the frame's status (complete buffer) -- in the sequence itself;
- ids: :func:`check_ids`, each id follows the previous one (GigE Vision ids wrap from
  65535 to 1, 0 is never used), allowing for as many skipped ids as failed attempts;
- time stamps: :func:`check_spacing`, in a hardware-triggered sequence consecutive frames
  are one pattern period apart (a missed trigger leaves a gap of two);
- duplicates: :func:`duplicate_frames`, a frame bit-identical to another one is a stale
  buffer (a real exposure always carries fresh noise);
- saturation: :func:`saturated_fraction` per frame; a frame far above its group's
  median is a flash (re-shot); a scan whose shortest exposure still saturates a large part
  of the image is refused;
- modulation: :func:`phase_step_check` reports the fraction of pixels with fringe
  contrast; no fringes at all means the projector is not seen;
- phase steps: :func:`phase_step_check` fits the N-step model per pixel to the group's
  other frames (leave one out, N >= 4) and then, over the modulated pixels, each frame's
  own phase step and gain. A frame that mixes two patterns, or shows the previous or the
  next one, has a step off by a sizeable part of 2 pi / N even when ids and time stamps
  are perfect. With N = 3 the model leaves no redundancy: the check is not possible and
  the result says so;
- Gray code: :func:`gray_check`, a mixed Gray-code frame has many mid-grey pixels, a late
  one repeats its predecessor (:func:`duplicate_frames` with a tolerance).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["IdCheck", "check_ids", "id_gap", "SpacingCheck", "check_spacing",
           "saturated_fraction", "duplicate_frames", "StepCheck", "phase_step_check",
           "GrayCheck", "gray_check", "similar_to_previous"]


# ----------------------------------------------------------------------------- ids
def id_gap(prev: int, cur: int, *, wrap: int = 65535) -> int:
    """How many ids from ``prev`` to ``cur`` (1 for consecutive), for ids running
    1..``wrap`` and wrapping to 1 (GigE Vision); ids <= 0 (no id) give 0.

    >>> id_gap(65535, 1), id_gap(65534, 2), id_gap(7, 7)
    (1, 3, 0)
    """
    if prev <= 0 or cur <= 0:
        return 0
    if cur > wrap or prev > wrap:    # a camera with wider ids: plain difference
        return cur - prev
    return (cur - prev) % wrap


@dataclass(frozen=True)
class IdCheck:
    """Result of :func:`check_ids`.

    ok : bool. gaps : (n - 1,) ndarray of int, id steps between consecutive frames.
    bad : (n,) ndarray of bool, frames whose id does not follow (the later of a pair).
    message : str, what is wrong ("" when ok).
    """

    ok: bool
    gaps: np.ndarray
    bad: np.ndarray
    message: str = ""


def check_ids(ids: Sequence[int], *, allowed_extra: Sequence[int] | None = None,
              wrap: int = 65535) -> IdCheck:
    """Check that frame ids follow each other.

    Parameters
    ----------
    ids : (n,) ints, frame ids in capture order.
    allowed_extra : (n,) ints or None; frame i may come ``1 + allowed_extra[i]`` ids after
        frame i - 1 at most (the failed attempts in between consumed ids). None: 0.
    wrap : int, the largest id (65535 for GigE Vision).
    """
    ids = [int(i) for i in ids]
    n = len(ids)
    extra = np.zeros(n, dtype=int) if allowed_extra is None else np.asarray(allowed_extra)
    gaps = np.array([id_gap(ids[i - 1], ids[i], wrap=wrap) for i in range(1, n)], dtype=int)
    bad = np.zeros(n, dtype=bool)
    msgs = []
    for i in range(1, n):
        if ids[i] <= 0 or ids[i - 1] <= 0:
            continue
        g = gaps[i - 1]
        if g == 0:
            bad[i] = True
            msgs.append(f"frame {i} repeats id {ids[i]}")
        elif g > 1 + int(extra[i]):
            bad[i] = True
            msgs.append(f"frame {i} has id {ids[i]} after {ids[i - 1]}: "
                        f"{g - 1 - int(extra[i])} frame(s) missing")
    return IdCheck(ok=not bad.any(), gaps=gaps, bad=bad, message="; ".join(msgs[:3]))


# ----------------------------------------------------------------------------- time
@dataclass(frozen=True)
class SpacingCheck:
    """Result of :func:`check_spacing`: ok, the spacings (s), frames whose spacing to the
    previous one is off (bool (n,)), and a message."""

    ok: bool
    spacing_s: np.ndarray
    bad: np.ndarray
    message: str = ""


def check_spacing(timestamps_ns: Sequence[int | None], *, period_s: float,
                  tolerance: float = 0.25) -> SpacingCheck:
    """Consecutive time stamps must be ``period_s`` apart within ``tolerance`` x period.

    Frames without a time stamp (None) are not judged.
    """
    ts = list(timestamps_ns)
    n = len(ts)
    sp = np.full(max(0, n - 1), np.nan)
    bad = np.zeros(n, dtype=bool)
    msgs = []
    for i in range(1, n):
        if ts[i] is None or ts[i - 1] is None:
            continue
        d = (int(ts[i]) - int(ts[i - 1])) * 1e-9
        sp[i - 1] = d
        if abs(d - period_s) > tolerance * period_s:
            bad[i] = True
            msgs.append(f"frame {i} came {d * 1e3:.2f} ms after frame {i - 1}, expected "
                        f"{period_s * 1e3:.2f} ms")
    return SpacingCheck(ok=not bad.any(), spacing_s=sp, bad=bad, message="; ".join(msgs[:3]))


# ----------------------------------------------------------------------------- pixels
def saturated_fraction(image: np.ndarray, *, max_value: float) -> float:
    """Fraction of pixels at or above ``max_value`` in one image."""
    img = np.asarray(image)
    return float(np.count_nonzero(img >= max_value)) / max(1, img.size)


def duplicate_frames(images: Sequence[np.ndarray], *, min_std: float = 1.0) -> list[tuple]:
    """Pairs (i, j), i < j, of bit-identical frames. Frames with less spread than
    ``min_std`` (DN; black or blank frames, where identity can be honest) are skipped."""
    seen: dict = {}
    out = []
    for j, img in enumerate(images):
        a = np.asarray(img)
        if a.size == 0 or float(a.std()) < min_std:
            continue
        key = (a.shape, a.dtype.str, hash(a.tobytes()))
        for i in seen.get(key, ()):
            if np.array_equal(np.asarray(images[i]), a):
                out.append((i, j))
        seen.setdefault(key, []).append(j)
    return out


def similar_to_previous(prev: np.ndarray, cur: np.ndarray, *, noise_dn: float,
                        mask: np.ndarray | None = None, k: float = 3.0) -> bool:
    """Whether ``cur`` shows the same light as ``prev`` (their RMS difference is within
    ``k`` times what noise alone gives, sqrt(2) ``noise_dn``): a late frame."""
    a = np.asarray(prev, dtype=float)
    b = np.asarray(cur, dtype=float)
    d = (b - a) if mask is None else (b - a)[mask]
    if d.size == 0:
        return False
    return bool(np.sqrt(np.mean(d * d)) < k * np.sqrt(2.0) * max(noise_dn, 0.5))


# ----------------------------------------------------------------------------- phase steps
@dataclass(frozen=True)
class StepCheck:
    """Result of :func:`phase_step_check` for one group of N frames.

    possible : bool, False for N = 3 or too few modulated pixels (see ``message``).
    step_error : (N,) float, rad, each frame's fitted phase step minus the nominal one.
    gain : (N,) float, each frame's fringe amplitude relative to the others' model.
    residual : (N,) float, DN, RMS of the frame minus the fitted model of it.
    noise_dn : float, the noise level of the residuals of the good frames (median).
    modulated : float, fraction of pixels with fringe contrast used.
    flagged : (N,) bool, frames off in step or gain.
    message : str
    """

    possible: bool
    step_error: np.ndarray
    gain: np.ndarray
    residual: np.ndarray
    noise_dn: float
    modulated: float
    flagged: np.ndarray
    message: str = ""


#: smallest phase-step tolerance (rad)
_STEP_FLOOR = 0.002


def _modulation(stack: np.ndarray, steps: int):
    d = 2.0 * np.pi * np.arange(steps) / steps
    c = np.tensordot(np.cos(d), stack, axes=1)
    s = np.tensordot(np.sin(d), stack, axes=1)
    return 2.0 / steps * np.hypot(c, s), stack.mean(axis=0)


def phase_step_check(stack: np.ndarray, *, max_value: float, step_tol: float | None = None,
                     gain_tol: float | None = None, min_modulation: float | None = None,
                     min_coverage: float = 0.95,
                     harmonics: int = 5, max_pixels: int = 20000, seed: int = 0) -> StepCheck:
    """Fit the N-step model to a group and find the frames that are not their step.

    The wrapped phase ``phi``, background ``a`` and modulation ``b`` of each pixel come
    from all N frames (the N-step estimate, blind to the harmonics a nonlinear projector
    adds, except orders N +- 1). Over the modulated pixels (modulation above
    ``min_modulation``, no clipped sample) each frame's normalised signal
    ``(I_k - a) / b`` is then fitted by a Fourier series in ``phi`` of order
    ``harmonics`` (which absorbs the gamma's harmonics even when the pixels do not cover
    every phase). Its first harmonic gives the frame's own phase step ``delta_k`` and
    fringe gain ``g_k``: a frame showing its own pattern has ``delta_k = 2 pi k / N`` and
    ``g_k = 1``; a frame mixing patterns k and k - 1 in proportions 1 - w and w, or
    showing pattern k - 1 (w = 1), has its step pulled toward the previous one by a
    sizeable part of ``atan2(w sin(2 pi / N), 1 - w + w cos(2 pi / N))`` (the rest goes
    into ``phi``), and its gain below 1.

    Parameters
    ----------
    stack : (N, rows, cols) array, the group's frames in step order (DN).
    max_value : float, saturation level (DN); pixels reaching it in any frame are left out.
    step_tol : float, rad; default the larger of 2 mrad and 6 standard deviations of the
        fitted step (from the residuals). A clean group of the virtual rig shows < 1 mrad;
        a frame with 4 % of its predecessor's light (1.3 ms of a 33 ms exposure) moves
        by about 9 mrad, the rest of the mix going into the fitted phase.
    gain_tol : float, relative; default the larger of 0.02 and 6 standard deviations.
    min_coverage : float, the fraction of 64 phase bins the modulated pixels must fill
        (each with at least 0.1 % of them); below it (a 1-period group seen by part of
        the field) the Fourier series cannot be told from a wrong step and the check is
        not possible (said in ``message``).
    min_modulation : float, DN; default 5 % of ``max_value``.
    harmonics : int, order of the Fourier series per frame.
    max_pixels : int, pixels sampled (seeded) for the fit (its precision is then far below
        the tolerances).

    Returns
    -------
    StepCheck
    """
    st = np.asarray(stack, dtype=float)
    n = st.shape[0]
    nan = np.full(n, np.nan)
    if min_modulation is None:
        min_modulation = 0.05 * max_value
    flat = st.reshape(n, -1)
    d = 2.0 * np.pi * np.arange(n) / n
    c = np.tensordot(np.cos(d), flat, axes=1)
    s = np.tensordot(np.sin(d), flat, axes=1)
    b_all = 2.0 / n * np.hypot(c, s)
    # (pixels reading 0 are kept: a frame taken in the dark must show, not hide)
    ok = (b_all > min_modulation) & np.all(flat < max_value, axis=0)
    frac = float(np.count_nonzero(ok)) / max(1, ok.size)
    if n < 4:
        return StepCheck(False, nan, nan, nan, np.nan, frac, np.zeros(n, dtype=bool),
                         f"{n} steps leave no redundancy: the phase-step check needs >= 4")
    idx = np.flatnonzero(ok)
    if idx.size < 50:
        return StepCheck(False, nan, nan, nan, np.nan, frac, np.zeros(n, dtype=bool),
                         f"only {idx.size} pixels show fringes: no phase-step check")
    if idx.size > max_pixels:
        idx = np.sort(np.random.default_rng(seed).choice(idx, max_pixels, replace=False))
    x = flat[:, idx]
    phi = np.arctan2(-s[idx], c[idx])
    hist = np.bincount(((phi + np.pi) / (2 * np.pi) * 64).astype(int).clip(0, 63),
                       minlength=64)
    coverage = float(np.mean(hist >= max(1.0, 1e-3 * idx.size)))
    if coverage < min_coverage:
        return StepCheck(False, nan, nan, nan, np.nan, frac, np.zeros(n, dtype=bool),
                         f"the modulated pixels see {100 * coverage:.0f} % of a fringe period: "
                         "no phase-step check (ids, time stamps and repeats still checked)")
    a = x.mean(axis=0)
    b = b_all[idx]
    h_max = max(1, int(harmonics))
    cols = [np.ones_like(phi)]
    for h in range(1, h_max + 1):
        cols += [np.cos(h * phi), np.sin(h * phi)]
    M = np.stack(cols, axis=1)                                    # (P, 1 + 2H)
    y = ((x - a) / b).T                                            # (P, N)
    # normal equations (11 x 11): the basis is well conditioned once the phases cover a
    # whole period (checked above), and this is 100 x cheaper than an SVD
    MtM = M.T @ M
    coef = np.linalg.solve(MtM, M.T @ y)                           # (1 + 2H, N)
    # y_k ~ g cos(phi + delta) = g cos(delta) cos(phi) - g sin(delta) sin(phi)
    delta = np.arctan2(-coef[2], coef[1])
    gain = np.hypot(coef[1], coef[2])
    step_err = np.angle(np.exp(1j * (delta - d)))
    res = y - M @ coef
    resid = np.sqrt(np.mean((res * b[:, None]) ** 2, axis=0))
    # standard deviations of the fitted first harmonic (least squares, per frame)
    cov = np.linalg.inv(MtM)
    sd = np.sqrt(np.mean(res ** 2, axis=0) * max(cov[1, 1], cov[2, 2]))
    sd_step = sd / np.maximum(gain, 1e-6)
    if step_tol is None:
        step_tol = max(_STEP_FLOOR, 6.0 * float(np.median(sd_step)))
    if gain_tol is None:
        gain_tol = max(0.02, 6.0 * float(np.median(sd)))
    flagged = (np.abs(step_err) > step_tol) | (np.abs(gain - 1.0) > gain_tol)
    msgs = [f"frame {k}: step off by {np.degrees(step_err[k]):+.1f} deg, fringe gain "
            f"{gain[k]:.2f}" for k in np.flatnonzero(flagged)]
    noise = float(np.median(resid[~flagged])) if (~flagged).any() else float("nan")
    return StepCheck(True, step_err, gain, resid, noise, frac, flagged, "; ".join(msgs))


# ----------------------------------------------------------------------------- gray code
@dataclass(frozen=True)
class GrayCheck:
    """Result of :func:`gray_check`: mid-grey fraction per frame, flagged frames, message."""

    mid_fraction: np.ndarray
    flagged: np.ndarray
    message: str = ""


def gray_check(stack: np.ndarray, *, dark: np.ndarray, bright: np.ndarray,
               min_contrast: float, max_mid: float = 0.08) -> GrayCheck:
    """Flag Gray-code frames that mix two patterns: many pixels halfway between dark and
    bright.

    Parameters
    ----------
    stack : (n, rows, cols), the Gray-code frames. dark, bright : (rows, cols), what an
        unlit and a lit pixel read (black and white frames, or the phase group's
        background -/+ modulation).
    min_contrast : float, DN; pixels with less ``bright - dark`` are not judged.
    max_mid : float, largest fraction of judged pixels in the middle third of
        [dark, bright] (the blurred bit edges of a sharp frame: a few %; a frame mixing two
        bit patterns: about a quarter to a half).
    """
    st = np.asarray(stack, dtype=float)
    lo = np.asarray(dark, dtype=float)
    hi = np.asarray(bright, dtype=float)
    ok = (hi - lo) > min_contrast
    n = st.shape[0]
    mid = np.zeros(n)
    if ok.any():
        for j in range(n):
            r = (st[j][ok] - lo[ok]) / (hi[ok] - lo[ok])
            mid[j] = float(np.mean((r > 1 / 3) & (r < 2 / 3)))
    flagged = mid > max_mid
    msg = "; ".join(f"frame {j}: {100 * mid[j]:.0f} % of pixels mid-grey (a mix of two bit "
                    f"patterns)" for j in np.flatnonzero(flagged))
    return GrayCheck(mid, flagged, msg)
