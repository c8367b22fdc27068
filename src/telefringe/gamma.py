"""Projector nonlinearity (gamma) correction from the fringe data alone.

A nonlinear projector response adds harmonics to the sinusoidal fringes; the N-step
estimate then carries a phase error that depends only on the wrapped phase,
``phi' = phi + e(phi)`` (for an even distortion, harmonics of order N, 2N, ...). The error
is the same function at every camera pixel (it does not depend on A or B), so it can be
learned from the scan itself:

A multi-frequency scan measures the same projector coordinate several times. For groups
i (coarser) and j (finer) with ratio ``r = p_j / p_i``, the true absolute phases satisfy
``r Phi_i = Phi_j``, so the measured wrapped phases satisfy::

    wrap(r Phi'_i - phi'_j) = wrap(r e_i(phi'_i) - e_j(phi'_j))

with ``e_g(phi')`` each group's error written as a function of its measured phase (so
no inversion is needed: ``phi = phi' - e(phi')`` exactly). Writing every ``e_g`` as a
sum of harmonics of ``phi'_g`` makes this linear in the coefficients; all consecutive
pairs of the ladder are fitted jointly by weighted least squares over the pixels (the
weights from the noise model), with outliers (wrong orders) rejected iteratively. When
r is an integer the wrapped phase of group i is enough (``r phi_i = r Phi_i`` mod 2 pi);
otherwise the absolute phase of a first unwrapping is used.

Identifiability: a constant error common to the ladder cannot be observed (it would be a
shift of the projector image); gamma errors have zero mean, so constants are not fitted.
A harmonic ``m`` of the coarser group equal to ``r`` times a harmonic of the finer one is
not separable from it; such harmonics of the coarser group are left out.

The pre-compensation path (a measured response, inverted before projecting) is in
:func:`telefringe.patterns.precompensate` and :func:`fit_response`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from . import _kernels as _k

__all__ = [
    "PhaseErrorModel",
    "PhaseErrorFit",
    "default_harmonics",
    "fit_phase_errors",
    "periodic_error",
    "ResponseCurve",
    "fit_response",
]

TWO_PI = 2.0 * np.pi


@dataclass(frozen=True)
class PhaseErrorModel:
    """A periodic phase error ``e(phi') = sum_m a_m cos(m phi') + b_m sin(m phi')`` (rad).

    Attributes
    ----------
    periods : int, the fringe group it belongs to.
    harmonics : tuple of int, orders m >= 1.
    cos_coef, sin_coef : (n_harmonics,) ndarray of float64, rad.
    """

    periods: int
    harmonics: tuple[int, ...]
    cos_coef: np.ndarray
    sin_coef: np.ndarray

    @classmethod
    def zero(cls, periods: int) -> PhaseErrorModel:
        """The identity correction."""
        return cls(int(periods), (), np.zeros(0), np.zeros(0))

    def error(self, phase) -> np.ndarray:
        """The error e(phi') (rad) at measured wrapped phase(s) phi' (rad), any shape."""
        phase = np.asarray(phase, dtype=np.float64)
        out = np.zeros(phase.shape)
        if self.harmonics:
            _k.harmonic_sum(np.ascontiguousarray(phase).ravel(),
                            np.asarray(self.harmonics, dtype=np.int64),
                            np.asarray(self.cos_coef, dtype=np.float64),
                            np.asarray(self.sin_coef, dtype=np.float64), out.reshape(-1))
        return out

    def slope(self, phase) -> np.ndarray:
        """de/dphi' at measured phase(s) phi' (the corrected phase's noise is
        ``|1 - slope|`` times the measured phase's)."""
        m = np.asarray(self.harmonics, dtype=float)
        deriv = PhaseErrorModel(self.periods, self.harmonics, m * self.sin_coef,
                                -m * self.cos_coef)
        return deriv.error(phase)

    def correct(self, phase) -> np.ndarray:
        """Corrected wrapped phase ``wrap(phi' - e(phi'))`` in (-pi, pi]."""
        phase = np.asarray(phase, dtype=np.float64)
        if not self.harmonics:
            return phase.copy()
        p = phase - self.error(phase)
        p = np.mod(p + np.pi, TWO_PI) - np.pi
        p[p <= -np.pi] = np.pi
        return p

    @property
    def rms(self) -> float:
        """RMS of e over a period (rad)."""
        return float(np.sqrt(0.5 * (np.sum(self.cos_coef ** 2) + np.sum(self.sin_coef ** 2))))

    @property
    def peak(self) -> float:
        """Largest |e| over a period (rad), evaluated on a fine grid."""
        if not self.harmonics:
            return 0.0
        grid = np.linspace(-np.pi, np.pi, 8 * max(self.harmonics) * 16, endpoint=False)
        return float(np.abs(self.error(grid)).max())


@dataclass(frozen=True)
class PhaseErrorFit:
    """Result of :func:`fit_phase_errors`.

    Attributes
    ----------
    models : tuple of PhaseErrorModel, one per input group (input order).
    residual_rms : float, rad, weighted RMS of the pair residuals after the fit.
    n_samples : int, pixels used (after outlier rejection), summed over pairs.
    """

    models: tuple[PhaseErrorModel, ...]
    residual_rms: float
    n_samples: int


def default_harmonics(steps: int, *, max_order: int = 24) -> tuple[int, ...]:
    """Orders an N-step group's gamma error lives on: multiples of N up to ``max_order``
    (at least two of them)."""
    steps = int(steps)
    top = max(max_order, 2 * steps)
    return tuple(range(steps, top + 1, steps))


def periodic_error(measured, truth, *, harmonics: Sequence[int]) -> PhaseErrorModel:
    """Least-squares harmonic fit of ``wrap(measured - truth)`` against ``measured``
    (an evaluation tool: the periodic part of a phase error when the truth is known).

    Parameters
    ----------
    measured, truth : (...) array_like, rad (wrapped or absolute, same shape).
    harmonics : sequence of int >= 1.

    Returns
    -------
    PhaseErrorModel (periods 0)
    """
    m = np.asarray(measured, dtype=np.float64).ravel()
    t = np.asarray(truth, dtype=np.float64).ravel()
    ok = np.isfinite(m) & np.isfinite(t)
    m, t = m[ok], t[ok]
    d = np.mod(m - t + np.pi, TWO_PI) - np.pi
    h = tuple(int(x) for x in harmonics)
    cols = [np.ones_like(m)]
    for order in h:
        cols += [np.cos(order * m), np.sin(order * m)]
    a = np.stack(cols, axis=1)
    coef, *_ = np.linalg.lstsq(a, d, rcond=None)
    return PhaseErrorModel(0, h, coef[1::2].copy(), coef[2::2].copy())


def fit_phase_errors(phases: Sequence, periods: Sequence[int], *, steps: Sequence[int],
                     mask=None, sigmas: Sequence | None = None,
                     absolute: Sequence | None = None,
                     harmonics: Sequence[Sequence[int]] | None = None,
                     max_samples: int = 100_000, iterations: int = 4,
                     reject: float = 4.0, significance: float = 13.8) -> PhaseErrorFit:
    """Learn each group's periodic phase error from a multi-frequency ladder (see the
    module docstring).

    Parameters
    ----------
    phases : sequence of (rows, cols) array_like, rad, measured wrapped phases.
    periods : sequence of int, distinct, one per phase.
    steps : sequence of int, N of each group (chooses the default harmonics).
    mask : (rows, cols) bool, pixels to learn from (valid modulation, not saturated).
    sigmas : sequence of (rows, cols) array_like, rad, phase standard deviations (weights);
        equal weights when None.
    absolute : sequence of (rows, cols) array_like or None, rad, absolute phases from a
        first unwrapping; needed for pairs whose period ratio is not an integer.
    harmonics : sequence (one per group) of sequences of int; default
        :func:`default_harmonics` of each group's steps.
    max_samples : int, pixels used at most (a regular subsample, deterministic).
    iterations : int, reweighting passes (outliers beyond ``reject`` robust sigmas are
        dropped).
    significance : float, chi-square (2 degrees of freedom) a harmonic's (cos, sin) pair
        must exceed to be kept (13.8: p = 0.001); insignificant harmonics are dropped and
        the rest refitted, so that a linear projector does not get noise added to its
        phase. 0 keeps every harmonic.

    Returns
    -------
    PhaseErrorFit; a single group (nothing to compare with) gets the zero model.
    """
    ph = [np.asarray(p, dtype=np.float64) for p in phases]
    per = [int(p) for p in periods]
    n = len(ph)
    if len(per) != n or len(steps) != n:
        raise ValueError("fit_phase_errors: phases, periods and steps differ in length")
    if len(set(per)) != n:
        raise ValueError(f"fit_phase_errors: periods must differ, got {per}")
    zero = PhaseErrorFit(tuple(PhaseErrorModel.zero(p) for p in per), 0.0, 0)
    if n < 2:
        return zero
    shape = ph[0].shape
    valid = np.ones(shape, dtype=bool) if mask is None else np.asarray(mask, dtype=bool).copy()
    for p in ph:
        valid &= np.isfinite(p)
    if harmonics is None:
        harm = [list(default_harmonics(s)) for s in steps]
    else:
        if len(harmonics) != n:
            raise ValueError("fit_phase_errors: give one harmonics list per group")
        harm = [sorted({int(m) for m in h}) for h in harmonics]
        if any(m < 1 for h in harm for m in h):
            raise ValueError("fit_phase_errors: harmonic orders must be >= 1")
    order = list(np.argsort(per))
    # leave out harmonics of the coarser group that alias onto the finer group's
    for a, b in zip(order[:-1], order[1:], strict=True):
        r = per[b] / per[a]
        if abs(r - round(r)) < 1e-12:
            r = int(round(r))
            harm[a] = [m for m in harm[a] if not (m % r == 0 and (m // r) in harm[b])]
    idx = np.flatnonzero(valid.ravel())
    if idx.size == 0:
        return zero
    if idx.size > max_samples:  # regular subsample (deterministic)
        idx = idx[np.linspace(0, idx.size - 1, max_samples).astype(np.int64)]
    samp = [p.ravel()[idx] for p in ph]
    # a harmonic needs the phases to cover the circle: with K distinct (equally spaced)
    # values, orders m and K - m alias; keep m < K / 4 (K counted in 4096 bins)
    for g in range(n):
        occupied = np.count_nonzero(np.bincount(
            np.clip(((samp[g] + np.pi) * (4096 / TWO_PI)).astype(np.int64), 0, 4095),
            minlength=4096))
        harm[g] = [m for m in harm[g] if 4 * m < occupied]
    sig = None if sigmas is None else [np.asarray(s, dtype=np.float64).ravel()[idx]
                                       for s in sigmas]
    absol = None if absolute is None else [None if x is None else
                                           np.asarray(x, dtype=np.float64).ravel()[idx]
                                           for x in absolute]
    pairs = []
    for a, b in zip(order[:-1], order[1:], strict=True):
        r = per[b] / per[a]
        if abs(r - round(r)) < 1e-12:
            coarse = samp[a]
        elif per[a] == 1:
            coarse = samp[a]  # a one-period phase is its own absolute phase (mod 2 pi)
        elif absol is not None and absol[a] is not None:
            coarse = absol[a]
        else:
            raise ValueError(f"fit_phase_errors: periods {per[a]} -> {per[b]} is not an "
                             "integer ratio; pass the absolute phases of a first unwrapping")
        w = np.mod(r * coarse - samp[b] + np.pi, TWO_PI) - np.pi
        if sig is None:
            wt = np.ones(w.size)
        else:
            var = (r * sig[a]) ** 2 + sig[b] ** 2
            with np.errstate(divide="ignore", invalid="ignore"):
                wt = np.where(np.isfinite(var) & (var > 0), 1.0 / var, 0.0)
        pairs.append((a, b, r, w, wt))

    models, rms, nkeep, cov = _solve(samp, per, harm, pairs, iterations, reject)
    if significance > 0 and cov is not None:
        offs = np.cumsum([0] + [2 * len(h) for h in harm])
        pruned = []
        for g in range(n):
            kept = []
            for j, m in enumerate(harm[g]):
                i0 = offs[g] + 2 * j
                c = cov[i0:i0 + 2, i0:i0 + 2]
                v = np.array([models[g].cos_coef[j], models[g].sin_coef[j]])
                try:
                    chi2 = float(v @ np.linalg.solve(c, v))
                except np.linalg.LinAlgError:
                    chi2 = 0.0
                if chi2 > significance:
                    kept.append(m)
            pruned.append(kept)
        if pruned != harm:
            models, rms, nkeep, _ = _solve(samp, per, pruned, pairs, iterations, reject)
    return PhaseErrorFit(tuple(models), rms, nkeep)


def _solve(samp, per, harm, pairs, iterations, reject):
    """Iteratively reweighted least squares of the pair equations; returns
    (models, rms, samples kept, covariance of the coefficients or None)."""
    n = len(per)
    offs = np.cumsum([0] + [2 * len(h) for h in harm])
    n_par = int(offs[-1])
    harm_arr = [np.asarray(h, dtype=np.int64) for h in harm]
    models = [PhaseErrorModel(per[g], tuple(harm[g]), np.zeros(len(harm[g])),
                              np.zeros(len(harm[g]))) for g in range(n)]
    if n_par == 0:
        return models, 0.0, 0, None
    cov = None
    rms = 0.0
    total_keep = 0
    last = max(1, iterations)
    for it in range(last + 1):
        ata = np.zeros((n_par, n_par))
        atb = np.zeros(n_par)
        num = den = chi2 = 0.0
        total_keep = 0
        for a, b, r, w, wt in pairs:
            pred = r * models[a].error(samp[a]) - models[b].error(samp[b])
            resid = np.mod(w - pred + np.pi, TWO_PI) - np.pi
            z = resid * np.sqrt(wt)
            use = wt > 0
            scale = 1.4826 * np.median(np.abs(z[use])) if use.any() else 0.0
            keep = use & (np.abs(z) <= reject * max(scale, 1e-12)) if it else use
            num += float(np.sum(wt[keep] * resid[keep] ** 2))
            chi2 += float(np.sum(z[keep] ** 2))
            den += float(np.sum(wt[keep]))
            total_keep += int(keep.sum())
            _k.pair_normal_equations(samp[a], samp[b], float(r), harm_arr[a], harm_arr[b],
                                     int(offs[a]), int(offs[b]), pred + resid,
                                     np.where(keep, wt, 0.0), ata, atb)
        rms = float(np.sqrt(num / den)) if den > 0 else 0.0
        # a tiny ridge keeps poorly covered harmonics (partial phase coverage) bounded
        ridge = 1e-9 * np.trace(ata) / n_par + 1e-300
        lhs = ata + ridge * np.eye(n_par)
        if it == last:
            s2 = chi2 / max(total_keep - n_par, 1)
            cov = s2 * np.linalg.inv(lhs)
            break
        coef = np.linalg.solve(lhs, atb)
        models = [PhaseErrorModel(per[g], tuple(harm[g]), coef[offs[g]:offs[g + 1]:2].copy(),
                                  coef[offs[g] + 1:offs[g + 1]:2].copy()) for g in range(n)]
    return models, rms, total_keep, cov


# --------------------------------------------------------------- measured response (bonus)
@dataclass(frozen=True)
class ResponseCurve:
    """A projector's measured response: relative output (0..1) versus relative input.

    Attributes
    ----------
    levels : (n,) ndarray, increasing relative input levels in [0, 1].
    output : (n,) ndarray, relative captured intensity (0 at input 0, 1 at input 1),
        made non-decreasing.
    """

    levels: np.ndarray
    output: np.ndarray

    def __call__(self, x) -> np.ndarray:
        return np.interp(np.asarray(x, dtype=float), self.levels, self.output)

    def inverse(self, y) -> np.ndarray:
        """Input level giving relative output y (piecewise linear inverse)."""
        out = self.output + np.arange(self.output.size) * 1e-12  # strictly increasing
        return np.interp(np.asarray(y, dtype=float), out, self.levels)


def fit_response(levels, captured) -> ResponseCurve:
    """Response curve from uniform frames: ``captured[i]`` is the mean camera value (DN)
    over lit pixels when the projector shows uniform level ``levels[i]`` (relative,
    0..1; include 0 and 1).

    Returns
    -------
    ResponseCurve, normalised so that levels 0 and 1 map to 0 and 1.
    """
    lv = np.asarray(levels, dtype=float)
    cap = np.asarray(captured, dtype=float)
    if lv.ndim != 1 or lv.shape != cap.shape or lv.size < 3:
        raise ValueError("fit_response needs >= 3 levels and as many captured means")
    o = np.argsort(lv)
    lv, cap = lv[o], cap[o]
    if lv[0] != 0.0 or lv[-1] != 1.0:
        raise ValueError("fit_response: levels must include 0 and 1")
    span = cap[-1] - cap[0]
    if not span > 0:
        raise ValueError("fit_response: the capture at level 1 is not brighter than at 0")
    out = np.maximum.accumulate((cap - cap[0]) / span)
    return ResponseCurve(lv, np.clip(out, 0.0, 1.0))
