"""Decode a scan: projector coordinates (u_p, v_p) seen by every camera pixel.

Per axis: N-step wrapped phase of each group (HDR sets fused per pixel), masks
(saturation, low modulation, shadow), the projector nonlinearity learned from the
ladder and removed (:mod:`telefringe.fringes.nonlinearity`), temporal unwrapping
(:mod:`telefringe.fringes.unwrap`), and the projector coordinate ``x = Phi L / (2 pi p)``.

Uncertainty: each group's phase has ``sigma_phi = sqrt(2/N) sigma_I / B`` with
``sigma_I`` from the :class:`~telefringe.phase.NoiseModel` at the background level, i.e.
``sigma_x = sigma_phi L / (2 pi p)`` in projector pixels. Once the orders are fixed, every
unwrapped group measures the same x, so the groups are combined with inverse-variance
weights; ``sigma_u_p = (sum_j sigma_x_j^-2)^-1/2``. (With the 1/8/64 ladder the finest
group carries 98% of the weight.)

Two implementations give the same result. Hierarchical ladders (HDR sets included, up to
16 groups per axis) go through one parallel, vectorised pass of a fused numba kernel
(:func:`telefringe.fringes._kernels.fused_ladder`: float32 polynomial arctangent within
1e-6 rad, float32 unwrapping, every group's absolute phase and the combination in float64;
u_p within 2e-6 rad * L / (2 pi p_fine) of the float64 path (measured <= 2e-6 px up to
L = 3840 px with 5 groups), masks and diagnostics equal, tested in
tests/test_decode_fast.py). ``decode(..., exact=True)`` and the other methods
(heterodyne, number-theoretic, Gray code) use float64 NumPy with ``numpy.arctan2``. When
the nonlinearity is learned, the fit (telefringe.fringes.nonlinearity) uses the float64
phases and the fused kernel applies the correction through its tables.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from telefringe import _recycle
from telefringe.fringes.errors import DecodeError, LadderDecodeError
from telefringe.fringes.fast import _MAX_MEMBERS, FastCoordinates, _fused, decode_axis_fast
from telefringe.fringes.noise import resolve_noise
from telefringe.fringes.nonlinearity import PhaseErrorFit, PhaseErrorModel, fit_phase_errors
from telefringe.fringes.phase import (
    NoiseModel,
    WrappedPhase,
    fuse_hdr,
    phase_sigma,
    saturation_mask,
    wrapped_phase,
)
from telefringe.fringes.scan import GrayGroup, PhaseGroup, Scan, ScanManifest
from telefringe.fringes.unwrap import (
    LadderError,
    Unwrapped,
    heterodyne_plan,
    number_theoretic_candidates,
    unwrap_gray,
    unwrap_heterodyne,
    unwrap_hierarchical,
    unwrap_number_theoretic,
    unwrap_step,
)

__all__ = [
    "DecodeError",
    "FastCoordinates",
    "decode_axis_fast",
    "AxisCoordinates",
    "ProjectorCoordinates",
    "METHODS",
    "decode",
    "decode_axis",
    "choose_method",
    "nonlinearity_kept",
]

METHODS = ("auto", "hierarchical", "heterodyne", "number-theoretic", "gray")
TWO_PI = 2.0 * np.pi


@dataclass(frozen=True)
class AxisCoordinates:
    """Decoding result of one projector axis (arrays (rows, cols)).

    Attributes
    ----------
    axis : "u" or "v".  method : str, the unwrapping method used.
    coordinate : float64, projector pixels, NaN where invalid.
    sigma : float64, projector pixels (standard uncertainty; NaN where invalid).
    valid : bool.
    modulation, background : float64, DN, of the finest group (at the exposure used).
    saturated : bool, every exposure of some group saturates.
    low_modulation : bool, some group's modulation is below the threshold.
    shadow : bool, the projector does not light the pixel.
    order_reliable : bool, the unwrapping trusts the fringe order.
    exposure : float64, exposure used for the finest group (a read-only view of one value
        where that group has a single exposure).
    periods : tuple of int, the groups used (increasing).
    phase_errors : PhaseErrorFit or None, the nonlinearity correction applied.
    """

    axis: str
    method: str
    coordinate: np.ndarray
    sigma: np.ndarray
    valid: np.ndarray
    modulation: np.ndarray
    background: np.ndarray
    saturated: np.ndarray
    low_modulation: np.ndarray
    shadow: np.ndarray
    order_reliable: np.ndarray
    exposure: np.ndarray
    periods: tuple[int, ...]
    phase_errors: PhaseErrorFit | None = None


@dataclass(frozen=True)
class ProjectorCoordinates:
    """Projector coordinates seen by each camera pixel (arrays (rows, cols)).

    Attributes
    ----------
    u_p : float64, projector column (pixels), NaN where invalid.
    v_p : float64 or None (no v fringes), projector row (pixels), NaN where invalid.
    mask : bool, u_p valid (and v_p valid where present).
    modulation : float64, DN, modulation B of the finest u group (or v when there is no u).
    sigma_u_p, sigma_v_p : float64 (or None), projector pixels, standard uncertainty from
        the noise model (NaN where invalid).
    saturated, shadow, order_reliable : bool diagnostics (any axis).
    background : float64, DN, background A of the finest u (else v) group.
    axes : dict axis -> AxisCoordinates, the full per-axis results.
    noise : telefringe.fringes.noise.NoiseChoice, the camera noise model used for the
        sigmas and where it came from.
    """

    u_p: np.ndarray | None
    v_p: np.ndarray | None
    mask: np.ndarray
    modulation: np.ndarray
    sigma_u_p: np.ndarray | None
    sigma_v_p: np.ndarray | None
    saturated: np.ndarray
    shadow: np.ndarray
    order_reliable: np.ndarray
    background: np.ndarray
    axes: dict = field(default_factory=dict)
    noise: object = None


# ----------------------------------------------------------------------------- helpers
@dataclass
class _Level:
    periods: int
    steps: int
    offset: float
    wrapped: WrappedPhase
    saturated: np.ndarray
    exposure: np.ndarray  # per pixel, exposure used
    exposure_index: np.ndarray


def _phase_sets(scan: Scan, axis: str) -> dict[int, list[tuple[PhaseGroup, np.ndarray]]]:
    """The phase groups of ``axis`` by periods (HDR sets: several exposures), checked."""
    sets: dict[int, list[tuple[PhaseGroup, np.ndarray]]] = {}
    for g, stack in zip(scan.manifest.groups, scan.stacks, strict=True):
        if isinstance(g, PhaseGroup) and g.axis == axis:
            sets.setdefault(int(g.periods), []).append((g, stack))
    for periods in sorted(sets):
        members = sets[periods]
        g0 = members[0][0]
        for g, _ in members[1:]:
            if (g.steps, g.offset) != (g0.steps, g0.offset):
                raise DecodeError(f"{scan.source}: two phase groups with {periods} periods on "
                                  f"axis {axis} differ in steps/offset ({g0.steps}, "
                                  f"{g0.offset}) vs ({g.steps}, {g.offset}); give them "
                                  "different periods or the same steps and offset")
        exps = [float(g.exposure) for g, _ in members]
        if len(set(exps)) != len(exps):
            raise DecodeError(f"{scan.source}: two phase groups with {periods} periods on axis "
                              f"{axis} have the same exposure")
        for g, stack in members:
            _check_stack_values(scan, g, stack)
    return {p: sets[p] for p in sorted(sets)}


def _levels(scan: Scan, axis: str) -> list[_Level]:
    """Wrapped phase of every phase group on ``axis``, HDR sets fused (sorted by periods)."""
    sets = _phase_sets(scan, axis)
    out = []
    for periods, members in sets.items():
        g0 = members[0][0]
        exps = [float(g.exposure) for g, _ in members]
        wps, sats = [], []
        for g, stack in members:
            wps.append(wrapped_phase(stack, steps=int(g.steps), offset=float(g.offset)))
            sats.append(saturation_mask(stack, max_value=scan.max_value))
        if len(members) == 1:
            shape = wps[0].phase.shape
            out.append(_Level(periods, int(g0.steps), float(g0.offset), wps[0], sats[0],
                              np.full(shape, exps[0]), np.zeros(shape, dtype=np.int64)))
        else:
            fused = fuse_hdr(wps, sats, exps)
            out.append(_Level(periods, int(g0.steps), float(g0.offset), fused.wrapped,
                              fused.saturated, fused.exposure, fused.exposure_index))
    return out


def _check_stack_values(scan: Scan, group, stack: np.ndarray) -> None:
    if stack.dtype.kind not in "uif":
        raise DecodeError(f"{scan.source}: group {group.key} has images of type {stack.dtype}")
    if stack.dtype.kind == "f" and not np.all(np.isfinite(stack)):
        raise DecodeError(f"{scan.source}: group {group.key} has NaN or infinite values")


def _gray_groups(scan: Scan, axis: str) -> list[tuple[GrayGroup, np.ndarray]]:
    return [(g, s) for g, s in zip(scan.manifest.groups, scan.stacks, strict=True)
            if isinstance(g, GrayGroup) and g.axis == axis]


def choose_method(periods, *, length: int, gray_bits: int | None = None,
                  method: str = "auto") -> str:
    """The unwrapping method for an axis with these phase-group periods.

    ``auto``: hierarchical when a one-period group exists, else Gray code when a Gray
    group fixes one of the groups, else heterodyne, else number-theoretic. Raises
    :class:`LadderDecodeError` (a ValueError) when the asked (or any) method cannot
    unwrap the finest group over the whole projector.
    """
    per = sorted(int(p) for p in periods)
    if method not in METHODS:
        raise DecodeError(f"unknown method {method!r}; use one of {', '.join(METHODS)}")
    if not per:
        raise LadderDecodeError("no phase group on this axis")

    def ok(m):
        if m == "hierarchical":
            return per[0] == 1
        if m == "gray":
            return gray_bits is not None and (2 ** gray_bits) in per
        if m == "heterodyne":
            try:
                heterodyne_plan(per)
                return True
            except LadderError:
                return False
        if m == "number-theoretic":
            if len(per) < 2:
                return False
            from telefringe.fringes.unwrap import _projected_separation

            cands = number_theoretic_candidates(per, length=length)
            return _projected_separation(cands, np.asarray(per, float)) > 1e-9
        return False

    if method != "auto":
        if not ok(method):
            raise LadderDecodeError(f"periods {per} cannot be unwrapped by the {method} "
                                    "method over the whole projector")
        return method
    for m in ("hierarchical", "gray", "heterodyne", "number-theoretic"):
        if ok(m):
            return m
    raise LadderDecodeError(
        f"periods {per} cannot unwrap the finest group over the whole projector: add a "
        "one-period group (ladder such as 1, 8, 64), a Gray code, or use periods whose "
        "heterodyne beat is 1 / that are coprime")


def _unwrap(method: str, levels: list[_Level], phases: list[np.ndarray], *, length: int,
            max_residual: float, gray=None, gray_threshold=None, gray_min_contrast=None):
    """Absolute phases for the levels used by ``method``; returns (indices, Unwrapped)."""
    per = [lv.periods for lv in levels]
    if method == "hierarchical":
        return list(range(len(levels))), unwrap_hierarchical(
            phases, per, length=length, max_residual=max_residual)
    if method == "heterodyne":
        return list(range(len(levels))), unwrap_heterodyne(
            phases, per, length=length, max_residual=max_residual)
    if method == "number-theoretic":
        return list(range(len(levels))), unwrap_number_theoretic(
            phases, per, length=length, max_fraction=max_residual / np.pi)
    # gray: the group with 2**bits periods, then finer groups hierarchically
    g, stack = gray
    base = per.index(2 ** g.bits)
    res = unwrap_gray(phases[base], stack, gray_threshold, bits=g.bits,
                      complementary=g.complementary, length=length,
                      min_contrast=gray_min_contrast)
    used = [base]
    absolute = [res.phases[0]]
    worst = res.residual.copy()
    reliable = res.reliable.copy()
    for j in range(base + 1, len(levels)):
        ab, r = unwrap_step(phases[j], per[j], absolute[-1], per[used[-1]])
        used.append(j)
        absolute.append(ab)
        q = np.abs(r) / max_residual
        reliable &= q <= 1.0
        np.maximum(worst, q, out=worst)
    return used, Unwrapped(tuple(absolute), reliable, worst)


def _fusable(sets) -> bool:
    """The fused kernel can decode these phase groups (one dtype, (steps, rows, cols)
    stacks of one image shape; anything else takes the exact path and its messages)."""
    pairs = [(g, s) for members in sets.values() for g, s in members]
    s0 = pairs[0][1]
    return (len(pairs) <= _MAX_MEMBERS and s0.dtype.kind in "uif" and s0.ndim == 3
            and all(s.dtype == s0.dtype and s.ndim == 3 and s.shape[0] == int(g.steps)
                    and s.shape[1:] == s0.shape[1:] for g, s in pairs))


def _given_fit(phase_errors, axis: str, sets) -> PhaseErrorFit | None:
    """The nonlinearity models given for every group of ``axis`` (keys ``(axis, periods,
    steps)``, values PhaseErrorModel), in ``sets`` order, or None when one is missing."""
    if not phase_errors:
        return None
    models = []
    for periods, members in sets.items():
        m = phase_errors.get((axis, int(periods), int(members[0][0].steps)))
        if not isinstance(m, PhaseErrorModel):
            return None
        models.append(m if m.periods == periods else
                      PhaseErrorModel(int(periods), m.harmonics, m.cos_coef, m.sin_coef))
    return PhaseErrorFit(tuple(models), float("nan"), 0)


#: pixels the nonlinearity is learned from at most (a regular subsample of the good ones)
_FIT_SAMPLES = 100_000


def _fit_from_samples(scan: Scan, axis: str, sets, *, length: int, noise: NoiseModel,
                      min_mod: float, max_residual: float) -> PhaseErrorFit | None:
    """The nonlinearity learned as :func:`decode_axis`'s exact path learns it (same pixels,
    same wrapped phases and weights), with the wrapped phases computed at the sampled
    pixels only: the good-pixel mask comes from a first pass of the fused kernel, whose
    masks equal the exact path's (tested). None when the ladder's ratios are not all
    integers (the exact path then needs a first unwrapping of every pixel)."""
    per = list(sets)
    if not all(b % a == 0 for a, b in zip(per[:-1], per[1:], strict=True)):
        return None
    first = _decode_axis_fused(scan, axis, sets, length=length, noise=noise, min_mod=min_mod,
                               max_residual=max_residual, fit=None)
    idx = np.flatnonzero((~first.saturated & ~first.low_modulation).ravel())
    if idx.size == 0:
        return PhaseErrorFit(tuple(PhaseErrorModel.zero(p) for p in per), 0.0, 0)
    if idx.size > _FIT_SAMPLES:  # the subsample fit_phase_errors itself would take
        idx = idx[np.linspace(0, idx.size - 1, _FIT_SAMPLES).astype(np.int64)]
    groups, stacks = [], []
    for p in per:
        for g, st in sets[p]:
            groups.append(g)
            stacks.append(st.reshape(st.shape[0], -1)[:, idx][:, None, :])
    sub = Scan(ScanManifest(scan.manifest.projector_width, scan.manifest.projector_height,
                            tuple(groups)), tuple(stacks), max_value=scan.max_value,
               source=scan.source)
    levels = _levels(sub, axis)
    good = np.ones((1, idx.size), dtype=bool)
    for lv in levels:
        good &= ~lv.saturated & (lv.wrapped.modulation >= min_mod)
    sigmas = [phase_sigma(lv.wrapped.modulation, lv.wrapped.quadrature, steps=lv.steps,
                          noise=noise) for lv in levels]
    return fit_phase_errors([lv.wrapped.phase for lv in levels], per,
                            steps=[lv.steps for lv in levels], mask=good, sigmas=sigmas,
                            max_samples=_FIT_SAMPLES)


def _decode_axis_fused(scan: Scan, axis: str, sets, *, length: int, noise: NoiseModel,
                       min_mod: float, max_residual: float, fit) -> AxisCoordinates:
    """:func:`decode_axis` for a hierarchical ladder (HDR sets allowed) in one pass of the
    fused kernel (see :func:`_fused`); ``fit`` is the nonlinearity correction (or None)."""
    per = list(sets)
    levels = [[(s, float(g.exposure)) for g, s in sets[p]] for p in per]
    steps = [int(sets[p][0][0].steps) for p in per]
    offsets = [float(sets[p][0][0].offset) for p in per]
    models = None if fit is None else list(fit.models)
    out = _fused(levels, per, steps, offsets, length=length, max_value=float(scan.max_value),
                 min_mod=min_mod, max_residual=max_residual, models=models, full=True,
                 noise=noise)
    if out["saturated"].all():
        raise DecodeError(f"{scan.source}: every pixel is saturated on axis {axis} (reduce "
                          "the exposure or the projector brightness)")
    shadow = out["shadow"]
    if scan.white is not None and scan.black is not None:
        shadow = (scan.white.astype(np.float64) - scan.black.astype(np.float64)) < 2 * min_mod
    return AxisCoordinates(
        axis=axis, method="hierarchical", coordinate=out["coordinate"], sigma=out["sigma"],
        valid=out["valid"], modulation=out["modulation"], background=out["background"],
        saturated=out["saturated"], low_modulation=out["low_modulation"], shadow=shadow,
        order_reliable=out["order_reliable"], exposure=out["exposure"], periods=tuple(per),
        phase_errors=fit)


def nonlinearity_kept(axes, gamma_correction: bool) -> list[str]:
    """Why the projector nonlinearity stayed in decoded coordinates although
    ``gamma_correction`` asked to remove it: one message per axis (``axes``: name ->
    :class:`AxisCoordinates`) of one period count (a lone group, or one with a Gray code:
    nothing to learn it from) without a model given (e.g. by the rig). Its periodic phase
    error is then in the coordinates and not in their sigma. Empty when none."""
    if not gamma_correction:
        return []
    out = []
    for name, ax in (axes or {}).items():
        fit = getattr(ax, "phase_errors", None)
        if len(getattr(ax, "periods", ())) == 1 and (
                fit is None or not any(m.harmonics for m in fit.models)):
            out.append(f"axis {name}: one period count ({ax.periods[0]}): the projector "
                       "nonlinearity cannot be learned from it and stays in the phase (a "
                       "systematic error sigma does not hold; fewer steps, more of it): use "
                       "a rig.json that holds it (learned at calibration), fringes of >= 2 "
                       "period counts, or no gamma correction to accept it")
    return out


def decode_axis(scan: Scan, axis: str, *, method: str = "auto", gamma_correction: bool = True,
                min_modulation: float | None = None, noise: NoiseModel | None = None,
                max_residual: float = np.pi / 2, gray_min_contrast: float | None = None,
                exact: bool = False, phase_errors=None) -> AxisCoordinates:
    """Decode one projector axis of a scan (see :func:`decode` for the parameters).

    Returns
    -------
    AxisCoordinates
    """
    if axis not in ("u", "v"):
        raise DecodeError(f"axis must be 'u' or 'v', got {axis!r}")
    sets = _phase_sets(scan, axis)
    if not sets:
        raise DecodeError(f"{scan.source}: no phase group on axis {axis}")
    length = scan.manifest.axis_length(axis)
    noise = resolve_noise(scan, noise).model  # None: the default model, scaled
    min_mod = 0.02 * float(scan.max_value) if min_modulation is None else float(min_modulation)
    if not (np.isfinite(min_mod) and min_mod >= 0):
        raise DecodeError(f"min_modulation must be finite and >= 0, got {min_modulation!r}")
    if not (np.isfinite(max_residual) and 0 < max_residual <= np.pi):
        raise DecodeError(f"max_residual must be in (0, pi], got {max_residual!r}")
    grays = _gray_groups(scan, axis)
    gray = None
    if grays:
        gray = max(grays, key=lambda gs: (gs[0].complementary, gs[0].exposure))
    method = choose_method(list(sets), length=length,
                           gray_bits=gray[0].bits if gray else None, method=method)
    fusable = not exact and method == "hierarchical" and _fusable(sets)
    given = _given_fit(phase_errors, axis, sets) if gamma_correction else None
    if fusable and (given is not None or not (gamma_correction and len(sets) >= 2)):
        fit = given
        if fit is None and (len(sets) >= 2 or gamma_correction):
            fit = PhaseErrorFit(tuple(PhaseErrorModel.zero(p) for p in sets), 0.0, 0)
        return _decode_axis_fused(scan, axis, sets, length=length, noise=noise,
                                  min_mod=min_mod, max_residual=max_residual, fit=fit)
    if fusable and given is None:  # learned from the sampled pixels only
        fit = _fit_from_samples(scan, axis, sets, length=length, noise=noise, min_mod=min_mod,
                                max_residual=max_residual)
        if fit is not None:
            return _decode_axis_fused(scan, axis, sets, length=length, noise=noise,
                                      min_mod=min_mod, max_residual=max_residual, fit=fit)
    levels = _levels(scan, axis)

    shape = levels[0].wrapped.phase.shape
    saturated = np.zeros(shape, dtype=bool)
    low_mod = np.zeros(shape, dtype=bool)
    for lv in levels:
        saturated |= lv.saturated
        low_mod |= ~(lv.wrapped.modulation >= min_mod)
    if saturated.all():
        raise DecodeError(f"{scan.source}: every pixel is saturated on axis {axis} (reduce "
                          "the exposure or the projector brightness)")
    if scan.white is not None and scan.black is not None:
        shadow = (scan.white.astype(np.float64) - scan.black.astype(np.float64)) < 2 * min_mod
    else:
        shadow = np.ones(shape, dtype=bool)
        for lv in levels:
            shadow &= ~(lv.wrapped.modulation >= min_mod)
    # (shadow is a diagnostic: an unlit pixel has no modulation in any group anyway, and
    # white/black frames of one exposure say little about the other exposures of HDR sets)
    good = ~saturated & ~low_mod
    sigmas = [phase_sigma(lv.wrapped.modulation, lv.wrapped.quadrature, steps=lv.steps,
                          noise=noise) for lv in levels]
    phases = [lv.wrapped.phase for lv in levels]

    gray_threshold = gray_min_contrast_arr = None
    if gray is not None and method == "gray":
        g, _ = gray
        if scan.white is not None and scan.black is not None:
            gray_threshold = 0.5 * (scan.white.astype(np.float64) + scan.black.astype(np.float64))
        else:
            base = [lv.periods for lv in levels].index(2 ** g.bits)
            gray_threshold = levels[base].wrapped.background
        if gray_min_contrast is None:
            gray_min_contrast_arr = 3.0 * np.sqrt(noise.variance(gray_threshold))
        else:
            gray_min_contrast_arr = float(gray_min_contrast)

    def run(phs):
        return _unwrap(method, levels, phs, length=length, max_residual=max_residual,
                       gray=gray, gray_threshold=gray_threshold,
                       gray_min_contrast=gray_min_contrast_arr)

    fit = None
    used, unw = None, None
    if given is not None:  # learned beforehand (e.g. by the calibration)
        fit = given
    elif gamma_correction and len(levels) >= 2 and good.any():
        per = [lv.periods for lv in levels]
        ratios_integer = all(b % a == 0 for a, b in zip(sorted(per)[:-1], sorted(per)[1:],
                                                         strict=True))
        absolute = None
        if not ratios_integer:
            used, unw = run(phases)
            absolute = [None] * len(levels)
            for j, ab in zip(used, unw.phases, strict=True):
                absolute[j] = ab
            learn = good & unw.reliable
        else:
            learn = good
        fit = fit_phase_errors(phases, per, steps=[lv.steps for lv in levels], mask=learn,
                               sigmas=sigmas, absolute=absolute, max_samples=_FIT_SAMPLES)
    elif len(levels) >= 2 or gamma_correction:
        fit = PhaseErrorFit(tuple(PhaseErrorModel.zero(lv.periods) for lv in levels), 0.0, 0)
    if fusable:  # the correction is learned: the final pass in the fused kernel applies it
        return _decode_axis_fused(scan, axis, sets, length=length, noise=noise,
                                  min_mod=min_mod, max_residual=max_residual, fit=fit)
    if fit is not None and any(m.harmonics for m in fit.models):
        sigmas = [s * np.abs(m.noise_factor(p))
                  for m, p, s in zip(fit.models, phases, sigmas, strict=True)]
        phases = [m.correct(p) for m, p in zip(fit.models, phases, strict=True)]
    used, unw = run(phases)

    # inverse-variance combination of the unwrapped groups (projector pixels)
    num = np.zeros(shape)
    den = np.zeros(shape)
    for j, ab in zip(used, unw.phases, strict=True):
        p = levels[j].periods
        x = ab * (length / (TWO_PI * p))
        sx = sigmas[j] * (length / (TWO_PI * p))
        with np.errstate(divide="ignore", invalid="ignore"):
            w = np.where(np.isfinite(sx) & (sx > 0), 1.0 / (sx * sx), 0.0)
        num += w * x
        den += w
    with np.errstate(divide="ignore", invalid="ignore"):
        coord = num / den
        sigma = 1.0 / np.sqrt(den)
    valid = good & unw.reliable & np.isfinite(coord) & (den > 0)
    valid &= (coord >= -0.5) & (coord <= length - 0.5)
    coord = np.where(valid, coord, np.nan)
    sigma = np.where(valid, sigma, np.nan)
    fine = levels[used[-1]]
    return AxisCoordinates(
        axis=axis, method=method, coordinate=coord, sigma=sigma, valid=valid,
        modulation=fine.wrapped.modulation, background=fine.wrapped.background,
        saturated=saturated, low_modulation=low_mod, shadow=shadow,
        order_reliable=unw.reliable, exposure=fine.exposure,
        periods=tuple(levels[j].periods for j in used), phase_errors=fit)


def decode(scan: Scan, *, method: str = "auto", gamma_correction: bool = True,
           min_modulation: float | None = None, noise: NoiseModel | None = None,
           max_residual: float = np.pi / 2,
           gray_min_contrast: float | None = None, exact: bool = False,
           phase_errors=None) -> ProjectorCoordinates:
    """Projector coordinates of every camera pixel of a scan.

    Parameters
    ----------
    scan : telefringe.scan.Scan, any number of phase groups per axis (a ladder of
        periods), HDR sets (same group, several exposures), Gray-code groups, optional
        white/black frames; 8- or 16-bit (or float) images.
    method : "auto" | "hierarchical" | "heterodyne" | "number-theoretic" | "gray".
    gamma_correction : bool, learn and remove the projector nonlinearity's periodic
        phase error from the ladder (needs >= 2 groups on the axis; no effect otherwise).
    min_modulation : float, DN; pixels whose modulation is below it in any group are
        invalid. Default ``0.02 * scan.max_value`` (5.1 DN for 8 bit).
    noise : NoiseModel, or "default" | "auto" | "scan" | "calibrated", the camera noise for
        the uncertainty (and Gray-code contrast); see
        :func:`telefringe.fringes.noise.resolve_noise` ("scan": measured from the scan's
        own phase-step residuals, N >= 4). Default None: ``NoiseModel()`` scaled by
        ``max_value / 255``, a typical camera, not necessarily this one.
    max_residual : float, rad, order-consistency tolerance of the unwrapping (pi/2).
    gray_min_contrast : float, DN, contrast below which a Gray bit counts as unread
        (default 3 sigma_I at the threshold level).
    exact : bool. False (default): hierarchical ladders (with HDR sets, any step counts,
        8/16-bit or float; a lone one-period group too) go through one pass of the fused
        kernel (float32 polynomial arctangent and unwrapping, the result assembled in
        float64; u_p within 2e-6 rad * L / (2 pi p_fine) of the exact path, tested up to
        L = 3840 px); the other methods always take the exact path. True: float64 NumPy
        throughout (``numpy.arctan2``).
    phase_errors : mapping ``(axis, periods, steps) -> PhaseErrorModel`` or None, the
        projector nonlinearity learned beforehand (e.g.
        :attr:`telefringe.calibrate.RigCalibration.phase_errors`). An axis whose every
        group has a model is corrected with them and nothing is learned from the scan
        (faster); other axes are learned as usual. Ignored when ``gamma_correction`` is
        False.

    Returns
    -------
    ProjectorCoordinates

    Raises
    ------
    DecodeError (a ValueError)
        Inconsistent groups, a period ladder that cannot unwrap the finest group, every
        pixel saturated.
    """
    if not isinstance(scan, Scan):
        raise DecodeError(f"decode needs a telefringe.scan.Scan, got {type(scan).__name__}")
    axes_present = [a for a in ("u", "v")
                    if any(isinstance(g, PhaseGroup) and g.axis == a
                           for g in scan.manifest.groups)]
    if not axes_present:
        raise DecodeError(f"{scan.source}: the scan has no phase group")
    choice = resolve_noise(scan, noise)
    res = {a: decode_axis(scan, a, method=method, gamma_correction=gamma_correction,
                          min_modulation=min_modulation, noise=choice.model,
                          max_residual=max_residual, gray_min_contrast=gray_min_contrast,
                          exact=exact, phase_errors=phase_errors)
           for a in axes_present}
    u = res.get("u")
    v = res.get("v")
    first = u if u is not None else v
    # the first axis' flags copied, then the other's combined in (recycled memory: no
    # fresh pages to map for these four planes)
    mask, saturated, shadow, reliable = (
        _recycle.empty(first.valid.shape, dtype=bool) for _ in range(4))
    np.copyto(mask, first.valid)
    np.copyto(saturated, first.saturated)
    np.copyto(shadow, first.shadow)
    np.copyto(reliable, first.order_reliable)
    for r in res.values():
        if r is not first:
            mask &= r.valid
            saturated |= r.saturated
            shadow |= r.shadow
            reliable &= r.order_reliable
    return ProjectorCoordinates(
        u_p=None if u is None else u.coordinate,
        v_p=None if v is None else v.coordinate,
        mask=mask, modulation=first.modulation,
        sigma_u_p=None if u is None else u.sigma,
        sigma_v_p=None if v is None else v.sigma,
        saturated=saturated, shadow=shadow, order_reliable=reliable,
        background=first.background, axes=res, noise=choice)
