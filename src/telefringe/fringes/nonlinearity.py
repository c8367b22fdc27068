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

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from telefringe.fringes import _nonlinearity_kernels as _k

__all__ = [
    "PhaseErrorModel",
    "PhaseErrorFit",
    "default_harmonics",
    "mean_model",
    "fit_phase_errors",
    "periodic_error",
    "ResponseCurve",
    "fit_response",
]

TWO_PI = 2.0 * np.pi

#: largest noise dilution ``m^2 tau^2 / 2`` of a harmonic whose errors-in-variables bias is
#: corrected (see :func:`_gauss_newton`): beyond, the correction's own feedback (its
#: terms grow like m^2 tau^2 times the coefficient) amplifies the noise more than the
#: bias it removes
_EIV_DILUTION = 0.1

#: largest contraction (ratio of two successive Gauss-Newton step sizes) for which the
#: remaining steps are extrapolated as a geometric series to stop early (see
#: :func:`_gauss_newton`); measured contractions are 0.03-0.1 from a subsample's solution
#: and up to 0.8 after harmonics are dropped
_MAX_CONTRACTION = 0.25

#: the contraction (ratio of two successive step sizes) beyond which :func:`_gauss_newton`
#: goes on with Newton's method (see there), for steps above _WARN_LAST_STEP standard
#: errors: Gauss-Newton then needs many more steps than it is given (at 0.5, 5 steps
#: shrink a step 32-fold); from a subsample's solution they are 0.03-0.1 (see
#: _MAX_CONTRACTION), and on the full paper scan Newton's method is never called
_SLOW_CONTRACTION = 0.5

#: the remaining distance to the Gauss-Newton fixed point (extrapolated, in standard
#: errors of each coefficient) at which :func:`_gauss_newton` stops: a model 2 % of its
#: own uncertainty away from the fixed point; the model's uncertainty moves the decoded
#: phase by about 1 % of its noise (1e5 samples, ~10 coefficients per group), so this
#: moves it by ~2e-4 of the noise (tests/test_learn_gamma.py bounds it at 1e-3)
_REMAINING = 0.02

#: the last step (in standard errors of a coefficient) beyond which a fit that ran out of
#: Gauss-Newton steps is reported as not converged: at the slowest contraction measured
#: (0.8, after harmonics are dropped) the remaining distance is then up to 4x that, about
#: the model's own uncertainty, which the decoded sigma does not hold; below it the model
#: is a fraction of its uncertainty from the fixed point (0.06 standard errors move the
#: decoded phase by ~6e-4 of its noise, see _REMAINING) and a warning would be noise
_WARN_LAST_STEP = 0.25

#: how a note of :attr:`PhaseErrorFit.warnings` saying that the fit did not converge
#: ends (:func:`fit_phase_errors` also issues those notes as a RuntimeWarning)
_NOT_CONVERGED = "(not converged)"
#: how the note of a fit that ran out of Gauss-Newton steps begins
_OUT_OF_STEPS = "Gauss-Newton took its"
#: how the note of a fit stopped for a restart (see :func:`_gauss_newton`) begins
_HALVED = "Gauss-Newton stalled, its steps halved to keep the model invertible"

#: largest move (in standard errors) of a coefficient by the linearised start of a refit
#: (see :func:`_conditioned_start`)
_MAX_SHIFT = 1.0


@dataclass(frozen=True)
class PhaseErrorModel:
    """A periodic phase error as a function of the true wrapped phase phi (rad)::

        measured = phi + e(phi),   e(phi) = sum_m a_m cos(m phi) + b_m sin(m phi)

    (the forward form: gamma errors have a short harmonic series in the true phase; as a
    function of the measured phase the series is much longer).

    Attributes
    ----------
    periods : int, the fringe group it belongs to.
    harmonics : tuple of int, orders m >= 1.
    cos_coef, sin_coef : (n_harmonics,) ndarray of float64, rad.

    :meth:`correct` inverts the mapping with a table of the correction ``e(phi)`` against
    the measured phase (solved by Newton's method on a regular grid), linearly
    interpolated; the grid is refined until the interpolation error, checked against the
    exact inverse at every mid-point, is below 1e-8 rad (:attr:`table_error`).
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
        """The error e(phi) (rad) at true wrapped phase(s) phi (rad), any shape."""
        phase = np.asarray(phase, dtype=np.float64)
        out = np.zeros(phase.shape)
        if self.harmonics:
            _k.harmonic_sum(np.ascontiguousarray(phase).ravel(),
                            np.asarray(self.harmonics, dtype=np.int64),
                            np.asarray(self.cos_coef, dtype=np.float64),
                            np.asarray(self.sin_coef, dtype=np.float64), out.reshape(-1))
        return out

    def slope(self, phase) -> np.ndarray:
        """de/dphi at true phase(s) phi. The corrected phase's noise is
        ``1 / (1 + slope)`` times the measured phase's."""
        m = np.asarray(self.harmonics, dtype=float)
        deriv = PhaseErrorModel(self.periods, self.harmonics, m * self.sin_coef,
                                -m * self.cos_coef)
        return deriv.error(phase)

    def _invert(self, measured: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
        """True phase (unwrapped near ``measured``) solving phi + e(phi) = measured
        (Newton's method per sample, to 1e-14 rad), from ``start`` (same shape, e.g. the
        solution for a nearby model) when given."""
        measured = np.asarray(measured, dtype=np.float64)
        if not self.harmonics:
            return measured.copy()
        out = np.empty(measured.size)
        first = (np.empty(0) if start is None
                 else np.ascontiguousarray(start, dtype=np.float64).ravel())
        ok = _k.invert_harmonic(np.ascontiguousarray(measured).ravel(),
                                np.asarray(self.harmonics, dtype=np.int64),
                                np.asarray(self.cos_coef, dtype=np.float64),
                                np.asarray(self.sin_coef, dtype=np.float64), first, out)
        if not ok:
            raise ValueError("phase error model is not invertible (slope <= -1)")
        return out.reshape(measured.shape)

    def correction_table(self, n: int) -> tuple[np.ndarray, float]:
        """The correction e(phi) against the measured phase at ``-pi + 2 pi j / n``,
        (n,) rad, and the largest error of its linear interpolation (checked at every
        mid-point against the exact inverse), rad."""
        n = int(n)
        if not self.harmonics:
            return np.zeros(n), 0.0
        grid = -np.pi + TWO_PI * np.arange(n) / n
        g = grid - self._invert(grid)
        mid = grid + np.pi / n
        gm = mid - self._invert(mid)
        interp = 0.5 * (g + np.roll(g, -1))
        return g, float(np.max(np.abs(interp - gm)))

    @cached_property
    def _tables(self) -> tuple[np.ndarray, float, np.ndarray, float]:
        """The correction table (see :meth:`correction_table`) on the coarsest grid of
        4096 * 2^k points whose interpolation error is <= 1e-8 rad (checked at every
        mid-point against the exact inverse), its error, the noise factor
        ``1 / (1 + e'(phi))`` on the same grid and its largest relative interpolation
        error. Refined grids start Newton's method from the coarser solution."""
        if not self.harmonics:
            return np.zeros(1), 0.0, np.ones(1), 0.0
        n = 4096
        grid = -np.pi + TWO_PI * np.arange(n) / n
        phi = self._invert(grid)
        while True:
            nxt = np.append(phi[1:], phi[0] + TWO_PI)
            mid = grid + np.pi / n
            phi_mid = self._invert(mid, 0.5 * (phi + nxt))
            g, g_mid = grid - phi, mid - phi_mid
            err = float(np.max(np.abs(0.5 * (g + np.append(g[1:], g[0])) - g_mid)))
            if err <= 1e-8 or n >= 2 ** 20:
                break
            # linear interpolation error falls as 1 / n^2: go to the predicted size
            factor = 2 ** int(np.ceil(np.log2(np.sqrt(err / 1e-8) * 1.05)))
            factor = max(2, min(factor, 2 ** 20 // n))
            known = np.empty(2 * n + 1)
            known[0:2 * n:2], known[1:2 * n:2], known[2 * n] = phi, phi_mid, phi[0] + TWO_PI
            n *= factor
            grid = -np.pi + TWO_PI * np.arange(n) / n
            start = np.interp(grid, -np.pi + np.pi * np.arange(known.size) / (known.size // 2),
                              known)
            phi = self._invert(grid, start)
        f = 1.0 / (1.0 + self.slope(phi))
        f_mid = 1.0 / (1.0 + self.slope(phi_mid))
        f_err = float(np.max(np.abs(0.5 * (f + np.append(f[1:], f[0])) / f_mid - 1.0)))
        return g, err, f, f_err

    @property
    def _table(self) -> tuple[np.ndarray, float]:
        return self._tables[0], self._tables[1]

    @property
    def _noise_table(self) -> tuple[np.ndarray, float]:
        return self._tables[2], self._tables[3]

    @property
    def invertible(self) -> bool:
        """The measured phase is a monotonic function of the true phase (1 + e' > 0),
        proven: on a grid of spacing h, ``1 + e'`` at the grid's minimum less ``K2 h / 2``
        (``K2 = sum m^2 (|a_m| + |b_m|) >= |e''|``) bounds it everywhere. The grid is
        refined until that bound is positive or a grid point is <= 0; a model still
        undecided at 2^22 points counts as not invertible (its Newton inversion and its
        noise factor ``1 / (1 + e')`` would not be usable anyway). A sampled check alone
        passed models that dip below 0 between its points, whose inversion then failed."""
        if not self.harmonics:
            return True
        m = np.asarray(self.harmonics, dtype=float)
        k2 = float(np.sum(m * m * (np.abs(self.cos_coef) + np.abs(self.sin_coef))))
        n = 64 * max(self.harmonics)
        while True:
            grid = np.linspace(-np.pi, np.pi, n, endpoint=False)
            if n <= 2 ** 16:  # short grid: one thread (see slope_serial)
                slope = np.empty(n)
                _k.slope_serial(grid, np.asarray(self.harmonics, dtype=np.int64),
                                np.asarray(self.cos_coef, dtype=np.float64),
                                np.asarray(self.sin_coef, dtype=np.float64), slope)
            else:
                slope = self.slope(grid)
            low = float(np.min(1.0 + slope))
            if low <= 0.0:
                return False
            if low - k2 * (np.pi / n) > 0.0:
                return True
            if n >= 2 ** 22:
                return False
            n *= 4

    @property
    def table_error(self) -> float:
        """Largest interpolation error of the inverse table (rad), checked at mid-points."""
        return self._table[1]

    def correct(self, phase) -> np.ndarray:
        """True wrapped phase (in (-pi, pi]) of measured wrapped phase(s), any shape
        (NaN stays NaN); error <= :attr:`table_error`."""
        phase = np.asarray(phase, dtype=np.float64)
        if not self.harmonics:
            return phase.copy()
        out = np.empty(phase.shape)
        _k.table_interp(np.ascontiguousarray(phase).ravel(), self._table[0], True,
                        out.reshape(-1))
        return out

    def noise_factor(self, phase) -> np.ndarray:
        """d(true phase)/d(measured phase) at measured phase(s): ``1 / (1 + e'(phi))``,
        any shape, interpolated from a table (relative error <= :attr:`noise_table_error`).
        """
        phase = np.asarray(phase, dtype=np.float64)
        if not self.harmonics:
            return np.ones(phase.shape)
        out = np.empty(phase.shape)
        _k.table_interp(np.ascontiguousarray(phase).ravel(), self._noise_table[0], False,
                        out.reshape(-1))
        return out

    @property
    def noise_table_error(self) -> float:
        """Largest relative interpolation error of :meth:`noise_factor` (mid-points)."""
        return self._noise_table[1]

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
    coverage : tuple of float, one per group (input order): the fraction of the 36
        10-degree bins of the circle its measured phase occupies over the pixels used
        (empty when nothing was fitted).
    warnings : tuple of str, what a person should read: harmonics the data could not
        decide (too uneven a coverage, a singular covariance, aliasing) and solver
        fallbacks (a zero start, a stalled iteration). Empty when the fit is clean.
    """

    models: tuple[PhaseErrorModel, ...]
    residual_rms: float
    n_samples: int
    coverage: tuple[float, ...] = ()
    warnings: tuple[str, ...] = ()


def mean_model(models: Sequence[PhaseErrorModel]) -> PhaseErrorModel:
    """The mean of several fits of one group's error (e.g. one per calibration pose): the
    union of their harmonics, each coefficient averaged over all fits (0 where a fit left
    the harmonic out as insignificant). Raises ValueError for fits of different periods.
    """
    models = list(models)
    if not models:
        raise ValueError("mean_model needs at least one model")
    per = {int(m.periods) for m in models}
    if len(per) != 1:
        raise ValueError(f"mean_model: models of different periods {sorted(per)}")
    harm = sorted({int(h) for m in models for h in m.harmonics})
    cos = np.zeros(len(harm))
    sin = np.zeros(len(harm))
    for m in models:
        for h, c, s_ in zip(m.harmonics, m.cos_coef, m.sin_coef, strict=True):
            cos[harm.index(int(h))] += c
            sin[harm.index(int(h))] += s_
    return PhaseErrorModel(per.pop(), tuple(harm), cos / len(models), sin / len(models))


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
                     reject: float = 4.0, significance: float = 13.8,
                     max_inflation: float = 100.0) -> PhaseErrorFit:
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
    max_inflation : float, largest variance inflation of a harmonic's coefficients (their
        variance over what it would be with a basis orthogonal to the other harmonics, as
        on an even phase coverage). On an uneven coverage a harmonic's basis functions are
        nearly a combination of the others (and of the unobservable common shift), so the
        data cannot tell it apart: it is left out, worst first, and the result's
        ``warnings`` say so. ``inf`` keeps every harmonic. Where Gauss-Newton on every
        harmonic stalls with steps halved to keep the models invertible, the inflations
        are first judged at a fit of each group's two lowest orders, the higher orders
        added lowest first while within ``max_inflation``, and the fit goes on from there
        (Newton's method on every harmonic where that does not converge either).

    Returns
    -------
    PhaseErrorFit; a single group (nothing to compare with) gets the zero model.
    ``coverage`` gives each group's phase coverage; ``warnings`` every harmonic left out
    for a reason other than its significance, and every fallback of the solver.
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
    notes: list[str] = []
    coverage = tuple(_coverage(x) for x in samp)
    # a harmonic needs the phases to cover the circle: with K distinct (equally spaced)
    # values, orders m and K - m alias; keep m < K / 4 (K counted in 4096 bins)
    for g in range(n):
        occupied = np.count_nonzero(np.bincount(
            np.clip(((samp[g] + np.pi) * (4096 / TWO_PI)).astype(np.int64), 0, 4095),
            minlength=4096))
        left = [m for m in harm[g] if 4 * m >= occupied]
        if left:
            notes.append(f"periods {per[g]}: harmonics {left} not fitted, the phase takes "
                         f"only {occupied} of 4096 values (orders would alias)")
        harm[g] = [m for m in harm[g] if 4 * m < occupied]
    sig = None if sigmas is None else [np.asarray(s, dtype=np.float64).ravel()[idx]
                                       for s in sigmas]
    absol = None if absolute is None else [None if x is None else
                                           np.asarray(x, dtype=np.float64).ravel()[idx]
                                           for x in absolute]
    pairs = []
    ones = np.ones(idx.size)
    for a, b in zip(order[:-1], order[1:], strict=True):
        r = per[b] / per[a]
        ka = kb = None
        if abs(r - round(r)) >= 1e-12:
            if absol is None or absol[b] is None or (per[a] != 1 and absol[a] is None):
                raise ValueError(f"fit_phase_errors: periods {per[a]} -> {per[b]} is not an "
                                 "integer ratio; pass the absolute phases of a first "
                                 "unwrapping")
            ka = (np.zeros(idx.size) if per[a] == 1
                  else np.round((absol[a] - samp[a]) / TWO_PI))
            kb = np.round((absol[b] - samp[b]) / TWO_PI)
        sa = ones if sig is None else sig[a]
        sb = ones if sig is None else sig[b]
        pairs.append((a, b, r, sa, sb, ka, kb))

    final_notes = len(notes)  # where the notes of the fit whose models are the result begin
    # where Gauss-Newton stalls with steps it had to halve to keep the models invertible,
    # harmonics the data cannot tell apart at the solution are in (see _continuation):
    # they are left out, judged at a fit of the lowest orders, and the rest fitted from
    # there; where that fails too, or Gauss-Newton stalls otherwise, Newton's method
    first: list[str] = []
    models, rms, nkeep, cov = _solve(samp, per, harm, pairs, iterations, reject,
                                     notes=first, restart=bool(np.isfinite(max_inflation)))
    if not any(x.startswith(_HALVED) for x in first):
        notes += first
    else:
        notes += [x for x in first if not x.startswith(_HALVED)]
        low = _continuation(samp, per, harm, pairs, iterations, reject, max_inflation)
        refit: list[str] = []
        if low is not None:
            pruned, left, start = low
            fit = _solve(samp, per, pruned, pairs, iterations, reject, start=start,
                         notes=refit)
        if low is not None and not any(x.endswith(_NOT_CONVERGED) for x in refit):
            for g, m, vif in left:
                notes.append(f"periods {per[g]}: harmonic {m} not learned: Gauss-Newton on "
                             "every harmonic stalled, and at the fit of the lowest orders "
                             f"{[h[:2] for h in harm]} the phase covers {coverage[g]:.0%} "
                             "of its circle (10-degree bins) too unevenly to tell it from "
                             f"the lower harmonics (variance inflation {vif:.3g} > "
                             f"{max_inflation:g})")
            harm = pruned
            final_notes = len(notes)
            notes += refit
            models, rms, nkeep, cov = fit
        else:
            final_notes = len(notes)
            models, rms, nkeep, cov = _solve(samp, per, harm, pairs, iterations, reject,
                                             notes=notes)
    if cov is not None and np.isfinite(max_inflation):
        pruned, worst = _identifiable(cov, harm, max_inflation)
        for g, m, vif in worst:
            notes.append(f"periods {per[g]}: harmonic {m} not learned, the phase covers "
                         f"{coverage[g]:.0%} of its circle (10-degree bins) too unevenly "
                         f"to tell it from the other harmonics (variance inflation "
                         f"{vif:.3g} > {max_inflation:g})")
        if pruned != harm:
            start = _conditioned_start(models, cov, harm, pruned)
            harm = pruned
            final_notes = len(notes)
            models, rms, nkeep, cov = _solve(samp, per, harm, pairs, iterations, reject,
                                             start=start, notes=notes)
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
                    notes.append(f"periods {per[g]}: harmonic {m} dropped, its covariance "
                                 "is singular (the data cannot decide it)")
                    continue
                if chi2 > significance:
                    kept.append(m)
            pruned.append(kept)
        if pruned != harm:
            final_notes = len(notes)
            models, rms, nkeep, _ = _solve(samp, per, pruned, pairs, iterations, reject,
                                           start=_conditioned_start(models, cov, harm,
                                                                    pruned), notes=notes)
    # a refit's start may come from a fit that ran out of steps (common when harmonics are
    # then dropped): only the iteration of the fit that gave the result counts
    stalled = [x for x in notes[final_notes:] if x.endswith(_NOT_CONVERGED)]
    notes[:final_notes] = [x for x in notes[:final_notes] if not x.startswith(_OUT_OF_STEPS)]
    if stalled:
        warnings.warn(f"fit_phase_errors (periods {per}): " + "; ".join(stalled),
                      RuntimeWarning, stacklevel=2)
    return PhaseErrorFit(tuple(models), rms, nkeep, coverage=coverage,
                         warnings=tuple(dict.fromkeys(notes)))


def _conditioned_start(models, cov, harm, kept):
    """Starting models for a refit with the harmonics ``kept`` (per group, a subset of
    ``harm``): the kept coefficients moved to where the linearised fit puts them once the
    dropped ones are zero, ``c_K - C_KD C_DD^-1 c_D`` (C: the covariance of the fit of
    ``models``, ordered as :func:`_solve` orders the coefficients). The refit then starts
    near its solution. The models as they are (pruned) when that system is singular or
    moves a coefficient by more than ``_MAX_SHIFT`` standard errors (measured: <= 0.45 on
    well covered scans; 3.4 on a tiny plane covering 6 % of the circle, where that start
    led Gauss-Newton astray)."""
    coef = np.concatenate([np.column_stack([m.cos_coef, m.sin_coef]).ravel()
                           for m in models])
    cols = [(g, m) for g, h in enumerate(harm) for m in h for _ in (0, 1)]
    keep = np.array([m in kept[g] for g, m in cols], dtype=bool)
    new = coef.copy()
    if (~keep).any() and keep.any():
        c_kd = cov[np.ix_(keep, ~keep)]
        c_dd = cov[np.ix_(~keep, ~keep)]
        try:
            new[keep] = coef[keep] - c_kd @ np.linalg.solve(c_dd, coef[~keep])
        except np.linalg.LinAlgError:
            new = coef
        # only a modest move (within _MAX_SHIFT standard errors): a larger one says the
        # dropped harmonics were entangled with the kept ones (an uneven phase coverage),
        # where the linearisation is not to be trusted
        se = np.sqrt(np.abs(np.diag(cov)))
        if not (np.all(np.isfinite(new))
                and np.all(np.abs(new - coef)[keep] <= _MAX_SHIFT * se[keep])):
            new = coef
    out, i = [], 0
    for g, (m, h) in enumerate(zip(models, harm, strict=True)):
        c, s_ = new[i:i + 2 * len(h):2], new[i + 1:i + 2 * len(h):2]
        i += 2 * len(h)
        sel = [j for j, order in enumerate(h) if order in kept[g]]
        out.append(PhaseErrorModel(m.periods, tuple(h[j] for j in sel), c[sel].copy(),
                                   s_[sel].copy()))
    return out


def _continuation(samp, per, harm, pairs, iterations, reject, max_inflation):
    """A restart for a fit of the harmonics ``harm`` (per group) where Gauss-Newton
    stalled with halved steps: fits each group's two lowest orders (the bulk of a gamma
    error, N and 2N), then, with the normal matrix of the ladder at that fit (the other
    harmonics zero), adds the higher orders lowest first, each kept when every variance
    inflation (as in :func:`_identifiable`) stays within ``max_inflation`` with it.
    Returns (harmonics per group kept, [(group, order, inflation)] left out, the
    low-order models: the refit's start), or None when the low-order fit is all of
    ``harm`` or did not converge itself.

    Why: the inflation depends on where it is taken. The true phases and gains come from
    the model, and a strong error (a 3-step scan's, slopes 1 + e' down to 0.33) reshapes
    them: on a 120 x 100 px crop whose 1-period phase covers 28 % of its circle, that
    group's orders 3-18 have inflations 8e3-7e6 near the solution but all below 100 at the
    linear start (:func:`_initial`). The fit of every harmonic then takes steps along
    those nearly collinear combinations that would make the model non-invertible (its
    slope down to -36), halved 2^7-fold and more; Newton's method after it wandered where
    the 1-period model was nearly non-invertible (gains up to 20, residual RMS 0.54 rad,
    5x the noise) and the equations are not smooth on the scale of a standard error, and
    ran out of steps (the pruning after it, judged on that iterate, then dropped the
    finest group's well-determined harmonic 3, and the refit stalled in turn). Adding
    orders lowest first keeps the ones that carry the error (dropping the worst-inflated
    one first, as :func:`_identifiable` does, dropped order 6 here, whose coefficient
    is 0.03-0.05 rad, and the refit did not converge)."""
    low = [list(h[:2]) for h in harm]
    if low == [list(h) for h in harm]:
        return None
    scratch: list[str] = []
    start, _, _, cov = _solve(samp, per, low, pairs, iterations, reject, notes=scratch)
    if cov is None or any(x.endswith(_NOT_CONVERGED) for x in scratch):
        return None
    offs = np.cumsum([0] + [2 * len(h) for h in harm])
    n_par = int(offs[-1])
    harm_arr = [np.asarray(h, dtype=np.int64) for h in harm]
    coef = _start_coefficients(start, harm, offs, per)
    ev = _Ladder(samp, per, harm, harm_arr, offs, pairs).evaluate(coef, reject, True)
    normal = ev.ata + 1e-9 * np.trace(ev.ata) / n_par * np.eye(n_par)
    cols = [(g, m) for g, h in enumerate(harm) for m in h for _ in (0, 1)]
    live = np.array([m in low[g] for g, m in cols], dtype=bool)
    left = []
    # the higher orders in increasing order (a gamma error's series falls off with the
    # order), each kept when every inflation stays within max_inflation with it
    for m, g in sorted((m, g) for g, h in enumerate(harm) for m in h if m not in low[g]):
        trial = live | np.array([c == (g, m) for c in cols], dtype=bool)
        sub = normal[np.ix_(trial, trial)]
        try:
            vif = float(np.max(np.diag(np.linalg.inv(sub)) * np.diag(sub)))
        except np.linalg.LinAlgError:
            vif = np.inf
        if vif <= max_inflation:
            live = trial
        else:
            left.append((g, m, vif))
    kept = [[m for m in h if (g, m) not in {(a, b) for a, b, _ in left}]
            for g, h in enumerate(harm)]
    return kept, left, start


def _coverage(phase) -> float:
    """Fraction of the 36 10-degree bins of the circle that hold a sample of ``phase``."""
    if phase.size == 0:
        return 0.0
    k = np.clip(((phase + np.pi) * (36 / TWO_PI)).astype(np.int64), 0, 35)
    return float(np.count_nonzero(np.bincount(k, minlength=36))) / 36.0


def _identifiable(cov, harm, limit):
    """Harmonics left after removing, one at a time, the worst-determined one while its
    variance inflation exceeds ``limit``; returns (harmonics per group, [(group, order,
    inflation)] removed). The inflation of a coefficient is ``C_jj (C^-1)_jj`` (1 for a
    basis orthogonal to the other columns, as on an even phase coverage; the larger of a
    harmonic's cos and sin is used), computed from the normal matrix ``C^-1`` restricted
    to the harmonics still in."""
    cols = [(g, m, k) for g, h in enumerate(harm) for m in h for k in (0, 1)]
    normal = np.linalg.pinv(cov)
    normal = 0.5 * (normal + normal.T)
    live = np.ones(len(cols), dtype=bool)
    removed = []
    while live.any():
        sub = normal[np.ix_(live, live)]
        try:
            inv = np.linalg.inv(sub)
            vif = np.diag(inv) * np.diag(sub)
        except np.linalg.LinAlgError:
            vif = np.full(sub.shape[0], np.inf)
        where = np.flatnonzero(live)
        j = int(np.argmax(vif))
        if not vif[j] > limit:
            break
        g, m, _ = cols[where[j]]
        removed.append((g, m, float(vif[j])))
        for i, (gg, mm, _) in enumerate(cols):
            if gg == g and mm == m:
                live[i] = False
    kept = [[m for m in h if (g, m) not in {(a, b) for a, b, _ in removed}]
            for g, h in enumerate(harm)]
    return kept, removed


def _wrap(x):
    return np.mod(x + np.pi, TWO_PI) - np.pi


def _pair_normal_equations(phase_a, phase_b, scale_a, scale_b, harm_a, harm_b, off_a, off_b,
                           target, weight, ata, atb):
    """Add the weighted normal equations ``J^T W J`` and ``J^T W target`` of one pair to
    ``ata`` (n_par, n_par) and ``atb`` (n_par,), in place. Rows ``J = [scale_a h_a(phase_a),
    scale_b h_b(phase_b)]`` (h: cos and sin of each sorted harmonic order) go to the
    parameters at offsets ``off_a`` and ``off_b``; samples with weight <= 0 are skipped.
    All per-sample arrays (n,) float64."""
    keep = np.flatnonzero(weight > 0)
    na, nb_ = 2 * harm_a.size, 2 * harm_b.size
    if keep.size == 0 or na + nb_ == 0:
        return
    root = np.sqrt(weight[keep])  # rows scaled by sqrt(w): J^T W J = R^T R
    rows = np.empty((keep.size, na + nb_))
    _k.design_rows(phase_a[keep], phase_b[keep],
                   np.broadcast_to(scale_a, weight.shape)[keep] * root,
                   np.broadcast_to(scale_b, weight.shape)[keep] * root, harm_a, harm_b, rows)
    loc = rows.T @ rows
    locb = rows.T @ (target[keep] * root)
    index = np.concatenate([off_a + np.arange(na), off_b + np.arange(nb_)])
    ata[np.ix_(index, index)] += loc
    atb[index] += locb


def _initial(samp, per, harm, harm_arr, offs, pairs, notes=None):
    """Starting forward coefficients: the linear fit of the errors as functions of the
    measured phases (inverse form), turned into true-phase estimates, to which each
    group's forward harmonics are then fitted. Scaled down if not invertible; after 20
    halvings the start is zero, and a line saying so goes to ``notes`` (a list)."""
    n = len(per)
    n_par = int(offs[-1])
    ata = np.zeros((n_par, n_par))
    atb = np.zeros(n_par)
    for a, b, r, sig_a, sig_b, ka, kb in pairs:
        if ka is None:
            w = _wrap(r * samp[a] - samp[b])
        else:
            w = _wrap(r * (samp[a] + TWO_PI * ka) - (samp[b] + TWO_PI * kb))
        var = (r * sig_a) ** 2 + sig_b ** 2
        with np.errstate(divide="ignore", invalid="ignore"):
            wt = np.where(np.isfinite(var) & (var > 0), 1.0 / var, 0.0)
        one = np.ones(w.size)
        _pair_normal_equations(samp[a], samp[b], r * one, -one, harm_arr[a], harm_arr[b],
                                 int(offs[a]), int(offs[b]), w, wt, ata, atb)
    ridge = 1e-9 * np.trace(ata) / max(n_par, 1) + 1e-300
    inv_coef = np.linalg.solve(ata + ridge * np.eye(n_par), atb)
    coef = np.zeros(n_par)
    for g in range(n):
        if not harm[g]:
            continue
        m = PhaseErrorModel(per[g], tuple(harm[g]), inv_coef[offs[g]:offs[g + 1]:2],
                            inv_coef[offs[g] + 1:offs[g + 1]:2])
        est = _wrap(samp[g] - m.error(samp[g]))
        d = _wrap(samp[g] - est)
        # least squares on at most ~20,000 samples, by its normal equations (a small
        # well-conditioned system: orders of one group on a covered circle), compiled
        stride = max(1, est.size // 20000)
        h = harm_arr[g]
        ata_g, atb_g = np.empty((2 * h.size, 2 * h.size)), np.empty(2 * h.size)
        _k.harmonic_normal_equations(np.ascontiguousarray(est[::stride]),
                                     np.ascontiguousarray(d[::stride]), h, ata_g, atb_g)
        try:
            coef[offs[g]:offs[g + 1]] = np.linalg.solve(ata_g, atb_g)
        except np.linalg.LinAlgError:
            coef[offs[g]:offs[g + 1]] = np.linalg.lstsq(ata_g, atb_g, rcond=None)[0]
    return _invertible_start(coef, per, harm, offs, notes, "the linear fit")


def _invertible_start(coef, per, harm, offs, notes, what):
    """``coef`` halved until every group's model is invertible (at most 20 halvings, then
    zero, reported in ``notes``): Gauss-Newton inverts the models from its first step."""
    for _ in range(20):
        if all(m.invertible for m in _models(per, harm, offs, coef)):
            return coef
        coef = 0.5 * coef
    if notes is not None:
        notes.append(f"starting values: {what} stayed non-invertible after 20 "
                     "halvings; Gauss-Newton started from zero")
    return np.zeros(int(offs[-1]))


def _solve(samp, per, harm, pairs, iterations, reject, start=None, notes=None,
           restart=False):
    """Gauss-Newton fit of the forward models; returns (models, rms, samples kept,
    covariance of the coefficients or None).

    With phi_g(c) the true phase the model c implies for each measured phase (its
    inverse), a pair's residual is the inconsistency ``r Phi_a(c) - Phi_b(c)`` (wrapped;
    with absolute phases when r is not an integer), whose derivative with respect to a
    coefficient of group g is ``-/+ h(phi_g) / (1 + e_g'(phi_g))``. The residuals are
    weighted by their variance from the phase noise (updated every iteration); samples
    beyond ``reject`` robust standard deviations are left out.

    The iterations first run on a regular subsample of about 20,000 samples (cheap), then
    continue on every sample until the step is below 1e-7 rad: the path is shortened, the
    fixed point (the least-squares solution over all samples) is the same. ``start``
    (one PhaseErrorModel per group, e.g. a fit with more harmonics) gives the starting
    coefficients of the harmonics it has. Fallbacks (a zero start, a stalled step) are
    reported as lines appended to ``notes`` (a list) when given. ``restart``: see
    :func:`_gauss_newton`.
    """
    offs = np.cumsum([0] + [2 * len(h) for h in harm])
    n_par = int(offs[-1])
    harm_arr = [np.asarray(h, dtype=np.int64) for h in harm]
    if n_par == 0:
        return [PhaseErrorModel.zero(p) for p in per], 0.0, 0, None
    max_it = max(2, iterations + 2)
    # (a start from a fit with more harmonics is already close: no subsample phase)
    stride = max(1, samp[0].size // 20_000) if start is None else 1
    if stride > 1:
        sub = [np.ascontiguousarray(x[::stride]) for x in samp]
        sub_pairs = [(a, b, r, *(None if v is None else
                                 np.ascontiguousarray(np.asarray(v)[::stride])
                                 for v in rest)) for a, b, r, *rest in pairs]
        coef = (_initial(sub, per, harm, harm_arr, offs, sub_pairs, notes) if start is None
                else _start_coefficients(start, harm, offs, per, notes))
        coef = _gauss_newton(sub, per, harm, harm_arr, offs, sub_pairs, coef, max_it, reject,
                             tol=1e-6, reject_first=False, notes=notes)[0]
    else:
        coef = (_initial(samp, per, harm, harm_arr, offs, pairs, notes) if start is None
                else _start_coefficients(start, harm, offs, per, notes))
    # (a subsample's solution or a start from another fit is good: reject from the first
    # iteration on)
    good_start = stride > 1 or start is not None
    coef, rms, total_keep, ata, chi2 = _gauss_newton(samp, per, harm, harm_arr, offs, pairs,
                                                     coef, max_it, reject, tol=1e-7,
                                                     reject_first=good_start, notes=notes,
                                                     final=True, restart=restart)
    models = _models(per, harm, offs, coef)
    s2 = chi2 / max(total_keep - n_par, 1)
    ridge = 1e-9 * np.trace(ata) / n_par + 1e-300
    cov = s2 * np.linalg.inv(ata + ridge * np.eye(n_par))
    return models, rms, total_keep, cov


def _start_coefficients(models, harm, offs, per, notes=None):
    """Coefficient vector for harmonics ``harm`` (per group) taken from ``models``, made
    invertible (dropping harmonics from an invertible model can leave one that is not)."""
    coef = np.zeros(int(offs[-1]))
    for g, (m, h) in enumerate(zip(models, harm, strict=True)):
        for j, order in enumerate(h):
            if order in m.harmonics:
                k = m.harmonics.index(order)
                coef[offs[g] + 2 * j] = m.cos_coef[k]
                coef[offs[g] + 2 * j + 1] = m.sin_coef[k]
    return _invertible_start(coef, per, harm, offs, notes, "the pruned fit")


def _models(per, harm, offs, coef):
    return [PhaseErrorModel(per[g], tuple(harm[g]), coef[offs[g]:offs[g + 1]:2].copy(),
                            coef[offs[g] + 1:offs[g + 1]:2].copy()) for g in range(len(per))]


@dataclass(frozen=True)
class _Evaluation:
    """One evaluation of the ladder's estimating equations at coefficients ``coef``:
    the normal matrix ``ata`` (n_par, n_par), the right-hand side ``atb`` (n_par,) (the
    Gauss-Newton step is ``ata^-1 atb``), the weighted sum of squares ``chi2`` over the
    samples kept, their weighted RMS residual ``rms`` (rad) and count ``n_keep``, the
    samples kept (P, n) bool, the true phases found (G, n) rad (a warm start) and the
    harmonics whose errors-in-variables bias is corrected (one bool array per group)."""

    coef: np.ndarray
    ata: np.ndarray
    atb: np.ndarray
    chi2: float
    rms: float
    n_keep: int
    keep: np.ndarray
    unwrapped: np.ndarray
    fix: list


class _Ladder:
    """The samples of a ladder laid out for the compiled passes of :func:`_gauss_newton`
    (each group's sigma from the pairs it is in, the pairs' groups, ratios and orders),
    and :meth:`evaluate`, one evaluation of the estimating equations."""

    def __init__(self, samp, per, harm, harm_arr, offs, pairs):
        self.per, self.harm, self.harm_arr, self.offs, self.pairs = per, harm, harm_arr, offs, pairs
        self.n_par = int(offs[-1])
        n_groups, n = len(per), samp[0].size
        self.n = n
        self.meas = np.ascontiguousarray(np.stack([np.asarray(x, dtype=np.float64)
                                                   for x in samp]))
        self.sig2d = np.ones((n_groups, n))
        for a, b, _, sig_a, sig_b, *_ in pairs:
            self.sig2d[a], self.sig2d[b] = sig_a, sig_b
        self.pair_a = np.array([p[0] for p in pairs], dtype=np.int64)
        self.pair_b = np.array([p[1] for p in pairs], dtype=np.int64)
        self.ratio = np.array([float(p[2]) for p in pairs])
        self.absolute = np.array([p[5] is not None for p in pairs], dtype=bool)
        self.ka2d, self.kb2d = np.zeros((len(pairs), n)), np.zeros((len(pairs), n))
        for j, (*_, ka, kb) in enumerate(pairs):
            if ka is not None:
                self.ka2d[j], self.kb2d[j] = ka, kb
        self.h_max = max(1, max(h.size for h in harm_arr))
        self.harm2d = np.zeros((n_groups, self.h_max), dtype=np.int64)
        self.nharm = np.array([h.size for h in harm_arr], dtype=np.int64)
        for g, h in enumerate(harm_arr):
            self.harm2d[g, :h.size] = h
        self.width = max(1, max(2 * (harm_arr[a].size + harm_arr[b].size)
                                for a, b, *_ in pairs))
        self.sig_g = {}
        for a, b, _, sig_a, sig_b, *_ in pairs:
            self.sig_g[a], self.sig_g[b] = sig_a, sig_b
        self.start = None  # true phases of the last evaluation (a warm start for the next)

    def evaluate(self, coef, reject, reject_now, keep=None, fix=None, with_gram=True):
        """The estimating equations at ``coef`` (an :class:`_Evaluation`). Samples beyond
        ``reject`` robust standard deviations of their pair are left out when
        ``reject_now``; ``keep`` (P, n) bool, when given, is the set of samples used
        instead, and ``fix`` (one bool array per group), when given, the harmonics whose
        errors-in-variables bias is corrected (else chosen by their noise dilution).
        ``with_gram`` False leaves the normal matrix out (``ata`` zero; the right-hand side
        ``atb`` is the same bit for bit, at a fraction of the cost: what Newton's matrix by
        differences and its step acceptance need). Raises ValueError where a model is not
        invertible."""
        per, harm_arr, offs, pairs = self.per, self.harm_arr, self.offs, self.pairs
        n_groups, n, n_par, h_max = len(per), self.n, self.n_par, self.h_max
        models = _models(per, self.harm, offs, coef)
        warm = np.full(n_groups, self.start is not None)
        start = np.zeros((n_groups, n)) if self.start is None else self.start
        unw = np.empty((n_groups, n))
        # one compiled pass: true-phase estimates by Newton on the samples themselves (no
        # table needed), each started from the previous evaluation's solution, wrapped,
        # their gains 1 / (1 + e'), and every pair's residuals and weights
        dense_c, dense_s, divisor, kmax = _dense_ladder(models)
        est, gain = np.empty((n_groups, n)), np.empty((n_groups, n))
        res_all, wt_all = np.empty((len(pairs), n)), np.empty((len(pairs), n))
        absz_all = np.empty((len(pairs), n))
        bad = np.zeros(n_groups, dtype=bool)
        _k.ladder_residuals(self.meas, warm, start, dense_c, dense_s, divisor, kmax,
                            self.sig2d, self.pair_a, self.pair_b, self.ratio, self.absolute,
                            self.ka2d, self.kb2d, unw, est, gain, res_all, wt_all, absz_all,
                            bad)
        if bad.any():
            raise ValueError("phase error model is not invertible (slope <= -1)")
        self.start = unw
        ata = np.zeros((n_par, n_par))
        atb = np.zeros(n_par)
        num = den = 0.0
        total_keep = 0
        keeps = np.zeros((len(pairs), n), dtype=bool)
        wk_all = np.zeros((len(pairs), n))
        for j in range(len(pairs)):
            res, wt, absz = res_all[j], wt_all[j], absz_all[j]
            use = wt > 0
            if keep is not None:
                kp = use & keep[j]
            elif reject_now:
                scale = 1.4826 * float(np.median(absz[use])) if use.any() else 0.0
                kp = use & (absz <= reject * max(scale, 1e-12))
            else:
                kp = use
            keeps[j] = kp
            wk_all[j] = np.where(kp, wt, 0.0)
            num += float(np.dot(wk_all[j], res * res))
            den += float(np.sum(wk_all[j]))
            total_keep += int(np.count_nonzero(kp))
        chi2 = num  # (the weighted sum of squares: z^2 = w res^2)
        rms = float(np.sqrt(num / den)) if den > 0 else 0.0
        # errors in variables (see _gauss_newton): each group's noise variance as a true
        # phase, tau^2 (the model's sigmas times the variance scale the residuals measure),
        # and the harmonics whose dilution m^2 tau^2 / 2 is small enough to correct
        s2 = chi2 / max(total_keep - n_par, 1)
        if fix is None:
            fix = [0.5 * harm_arr[g].astype(float) ** 2
                   * (float(np.median(s2 * (self.sig_g[g] * gain[g]) ** 2))
                      if g in self.sig_g else 0.0)
                   <= _EIV_DILUTION for g in range(n_groups)]
        # one compiled pass over every pair: the damped curvatures, the mean of the
        # inversion of a noisy phase taken out of the residual, the normal equations'
        # rows and Stein's sums (E[J^T res] = -tau^2 E[F'] per sample, taken out of J^T res)
        sel = np.zeros((n_groups, h_max), dtype=bool)
        fix_c, fix_s = np.zeros_like(dense_c), np.zeros_like(dense_s)
        for g in range(n_groups):
            sel[g, :harm_arr[g].size] = fix[g]
            for j, order in enumerate(harm_arr[g]):
                if fix[g][j]:
                    fix_c[g, order // divisor[g]] += models[g].cos_coef[j]
                    fix_s[g, order // divisor[g]] += models[g].sin_coef[j]
        pair_ata = np.empty((len(pairs), self.width, self.width))
        pair_atb = np.empty((len(pairs), self.width))
        stein = np.empty((len(pairs), 2, 2 * h_max))
        _k.ladder_normal_equations(est, gain, self.sig2d, self.pair_a, self.pair_b,
                                   self.ratio, res_all, wk_all, float(s2), self.harm2d,
                                   self.nharm, sel, fix_c, fix_s, divisor, kmax, pair_ata,
                                   pair_atb, stein, with_gram)
        for j, (a, b, *_) in enumerate(pairs):
            na, nb_ = 2 * harm_arr[a].size, 2 * harm_arr[b].size
            loc = pair_ata[j, :na + nb_, :na + nb_]
            locb = pair_atb[j, :na + nb_]
            index = np.concatenate([offs[a] + np.arange(na), offs[b] + np.arange(nb_)])
            ata[np.ix_(index, index)] += loc
            atb[index] += locb
            atb[offs[a]:offs[a + 1]] -= s2 * stein[j, 0, :na]
            atb[offs[b]:offs[b + 1]] -= s2 * stein[j, 1, :nb_]
        return _Evaluation(np.array(coef, dtype=np.float64), ata, atb, chi2, rms, total_keep,
                           keeps, unw, fix)


def _newton_matrix(lad, ev, h):
    """Newton's matrix ``-dU/dc`` (n_par, n_par) of the estimating equations ``U`` (the
    right-hand side ``atb`` of :meth:`_Ladder.evaluate`) at ``ev.coef``, by forward
    differences of steps ``h`` (n_par,) with the samples of ``ev`` and its choice of the
    harmonics whose bias is corrected held (both are discrete): every dependence
    on the coefficients (the phases' inversion, gains, weights, the errors-in-variables
    corrections), which Gauss-Newton's ``J^T W J`` leaves out but for the first."""
    n_par = ev.coef.size
    out = np.empty((n_par, n_par))
    for i in range(n_par):
        c = ev.coef.copy()
        c[i] += h[i]
        out[:, i] = -(lad.evaluate(c, 0.0, False, keep=ev.keep, fix=ev.fix,
                                   with_gram=False).atb - ev.atb) / h[i]
    return out


def _accept_newton(lad, back, jac, full, lam, per, harm, offs):
    """Whether the Newton step ``lam * back[3]`` from the iterate ``back[0]`` (evaluation
    ``back[1]``, standard errors ``back[2]``) passes the natural monotonicity test
    (Deuflhard): the model is invertible and the simplified step from the new iterate,
    ``jac^-1 U`` with the old Newton matrix ``jac`` and the old iterate's samples, is at
    most ``(1 - lam / 4)`` times the full step's size ``full`` (in standard errors).
    Returns the new iterate's evaluation (with the old samples) when it passes, else
    None."""
    coef = back[0] + lam * back[3]
    if not all(m.invertible for m in _models(per, harm, offs, coef)):
        return None
    trial = lad.evaluate(coef, 0.0, False, keep=back[1].keep, fix=back[1].fix,
                         with_gram=False)
    bar = float(np.max(np.abs(np.linalg.solve(jac, trial.atb)) / back[2]))
    return trial if bar <= (1.0 - 0.25 * lam) * full else None


def _gauss_newton(samp, per, harm, harm_arr, offs, pairs, coef, max_it, reject, *, tol,
                  reject_first, notes=None, final=False, restart=False):
    """Iterations of :func:`_solve` from ``coef``; returns (coef, rms, samples kept, normal
    matrix, chi2) of the last evaluated iterate. Outliers are rejected from the first
    iteration on when ``reject_first`` (a good start), else from the second. With
    ``final`` (the pass whose iterate is the result), running out of the ``max_it - 1``
    steps with the last one above :data:`_WARN_LAST_STEP` standard errors, or a step no
    halving keeps invertible, is reported in ``notes`` as a line ending with
    :data:`_NOT_CONVERGED`.

    Errors in variables: the regressors are evaluated at the true-phase estimates, which
    carry the very noise that is in the residual. Least squares then learns the
    conditional mean of the phase given its noisy measurement (a shrinkage towards where
    the phases are dense, ``sigma^2 d log p / dphi``), which is not a property of the
    projector: zero on an even phase coverage, but up to tens of mrad on an uneven one.
    The estimating equation is made unbiased to second order in the noise: by Stein's
    lemma ``E[F(phi + tau nu) tau nu] = tau^2 E[F'(phi + tau nu)]`` (F the derivative of
    a phase with respect to a coefficient, :func:`_stein_sum`), and the mean of the
    inversion of a noisy phase, ``E[phi_est - phi] = -tau^2 g^3 e'' / 2`` (g = 1 /
    (1 + e')), is taken out of the residual. The noise variances are the model's
    (``sigmas``) times the scale the residuals measure (their chi-square per degree of
    freedom), so a mis-scaled noise model does not bias the correction. Harmonics whose
    noise dilution ``m^2 tau^2 / 2`` (median over the samples) exceeds ``_EIV_DILUTION``
    are left uncorrected: there the correction's terms, which grow like ``m^2 tau^2``
    times the coefficients, would feed back and amplify the noise (measured: sigma_phi
    = 0.05 rad, m = 24 drove the finest group's 24th harmonic to 0.04 rad).

    Newton's method: those corrections depend on the coefficients (through the curvature
    e'', the gains, the phases), which the Gauss-Newton matrix ``J^T W J`` leaves out. On
    an even coverage that costs a little speed; on a narrow one the harmonics of the
    coarsest group are nearly collinear, ``J^T W J`` is small along their combination and
    the left-out terms are not: the iteration's map can then have an eigenvalue beyond
    -1 (measured -1.0 on a 200 px BGA window of the paper rig whose 1-period phase covers
    17 % of its circle: a 2-cycle between models 78 standard errors apart, whatever the
    number of steps). Where a Gauss-Newton step is larger than ``_SLOW_CONTRACTION``
    times the previous one (and above ``_WARN_LAST_STEP`` standard errors), the iteration
    goes on with Newton's method on the same estimating equations (same fixed point):
    the matrix ``-dU/dc`` by forward differences (:func:`_newton_matrix`; the samples and
    the corrected harmonics held), then Broyden's updates while the steps shrink by
    ``_MAX_CONTRACTION`` or more, anew by differences otherwise, each step damped until
    it passes the natural monotonicity test (:func:`_accept_newton`); a step no damping
    accepts returns to Gauss-Newton. Newton's method gets ``max_it - 1`` steps of its own;
    its convergence tests take the full (undamped) step: a damped step is short because it
    is damped (a 3-step scan's fit 60 standard errors from its root passed them with steps
    damped to 0.1 %).
    On the BGA window it reaches the root (one more step from the result: 0.0006 standard
    errors). A matrix by differences costs one evaluation of the equations per
    coefficient (~20): the window's two fits took 10 and 36 s of CPU (2.6 and 4.3 s when
    Gauss-Newton ran out of steps), only where Gauss-Newton stalls (on the full paper scan
    measured it never does: the same iterates as before, bit for bit).

    ``restart`` (with ``final``): where Gauss-Newton stalls as above after steps it had to
    halve to keep the model invertible, it stops instead, with a note beginning
    :data:`_HALVED` (and ending :data:`_NOT_CONVERGED`): the sign of harmonics the data
    cannot tell apart at the solution, which :func:`fit_phase_errors` then leaves out
    (:func:`_continuation`) rather than take Newton's method into them. A halved step's
    convergence tests take its size before halving."""
    n_par = int(offs[-1])
    lad = _Ladder(samp, per, harm, harm_arr, offs, pairs)
    rms = chi2 = 0.0
    total_keep = 0
    ata = np.eye(n_par)
    last = 0.0  # the previous step's size in standard errors (0: none yet)
    # the last step's size undamped (Newton's full step where it was damped), in standard
    # errors, and the one before: what the convergence tests take
    gap = last_full = 0.0
    newton = None
    taken = 0  # steps taken
    budget = max_it - 1  # steps allowed (Newton's method gets max_it - 1 of its own)
    jac = None  # Newton's matrix -dU/dc once the iteration is switched to it, else None
    lam, full, back = 1.0, 0.0, None  # Newton's damping, its full step's size, way back
    allow = True  # Newton's method may be switched to
    halved = 0  # Gauss-Newton's steps halved to keep the model invertible (halvings)
    ev = lad.evaluate(coef, reject, reject_first)
    while True:
        ata, atb, chi2, rms, total_keep = ev.ata, ev.atb, ev.chi2, ev.rms, ev.n_keep
        # a tiny ridge keeps poorly covered harmonics (partial phase coverage) bounded
        ridge = 1e-9 * np.trace(ata) / n_par + 1e-300
        s2 = chi2 / max(total_keep - n_par, 1)
        se = np.sqrt(np.abs(s2 * np.diag(np.linalg.inv(ata + ridge * np.eye(n_par)))))
        se = np.maximum(se, 1e-300)
        if taken >= budget:
            if final and notes is not None and gap > _WARN_LAST_STEP:
                notes.append(f"{_OUT_OF_STEPS} {taken} steps without meeting a "
                             f"convergence test (the last, undamped, moved a coefficient by "
                             f"{gap:.3g} of its standard errors, converged is <= "
                             f"{_REMAINING:g}); the "
                             f"model is the last iterate {_NOT_CONVERGED}")
            break
        step = np.linalg.solve(ata + ridge * np.eye(n_par), atb)
        size = float(np.max(np.abs(step) / se))
        if (allow and jac is None and last > 0 and size > _SLOW_CONTRACTION * last
                and size > _WARN_LAST_STEP):
            # Gauss-Newton contracts too slowly or not at all: on to Newton's method
            if restart and halved and final:
                # (or, its steps having been halved to stay invertible, to a restart)
                if notes is not None:
                    notes.append(f"{_HALVED} ({halved} halvings in {taken} steps; the next "
                                 f"moves a coefficient by {size:.3g} of its standard "
                                 f"errors) {_NOT_CONVERGED}")
                break
            jac, budget = np.empty(0), taken + max_it - 1
        if jac is not None:
            try:
                if jac.size == 0:  # (just switched: Newton's matrix by differences)
                    jac = _newton_matrix(lad, ev, 1e-2 * se) + ridge * np.eye(n_par)
                newton = np.linalg.solve(jac, atb)
            except (ValueError, np.linalg.LinAlgError):
                newton = None
            if newton is None or not np.all(np.isfinite(newton)):
                jac = None  # (no Newton's matrix here: the Gauss-Newton step)
                if notes is not None:
                    notes.append("Newton's matrix could not be formed; back to Gauss-Newton")
            else:
                full = float(np.max(np.abs(newton) / se))
                back = (coef, ev, se, newton)
                step = lam * newton
        whole = step  # (the step before any halving)
        for _ in range(20):  # keep the model invertible (halve the step if need be)
            trial = _models(per, harm, offs, coef + step)
            if all(m.invertible for m in trial):
                break
            step = 0.5 * step
            if jac is not None:
                lam *= 0.5
            else:
                halved += 1
        else:
            if notes is not None:
                notes.append(f"Gauss-Newton stopped at iteration {taken + 1}: no step kept "
                             "the model invertible after 20 halvings "
                             + (_NOT_CONVERGED if final else "(a later pass goes on)"))
            break
        coef = coef + step
        taken += 1
        # converged: the step is below tol, or below _REMAINING of every coefficient's
        # standard error (the steps still to come are a fraction q of it; further steps
        # would not change the result materially), or the steps shrink fast enough that
        # all the steps still to come, bounded by the geometric series of the last
        # contraction q (in standard errors), q / (1 - q) |step|, are below _REMAINING
        size = float(np.max(np.abs(step) / se))
        q = size / last if last > 0 else np.inf
        # (a damped Newton step is short because it is damped, not because the root is
        # near: the test takes the full step, and its contraction from the last full step;
        # so for a Gauss-Newton step halved to keep the model invertible: a 3-step crop's
        # fit, its steps halved 2^7-2^26-fold, passed the tests 50 standard errors from
        # its root)
        damped = jac is not None and newton is not None and lam < 1.0
        if damped:
            gap, move = full, float(np.max(np.abs(newton)))
        else:
            gap = float(np.max(np.abs(whole) / se))
            move = float(np.max(np.abs(whole)))
        cq = np.inf
        if last_full > 0:
            cq = gap / last_full
        last, last_full = size, gap
        if (move < tol or gap <= _REMAINING
                or (cq <= _MAX_CONTRACTION and cq / (1.0 - cq) * gap <= _REMAINING)):
            break
        if jac is not None:
            # Newton's step acceptance (natural monotonicity): halve the step from the
            # old iterate until the simplified step from the new one is short enough
            trial = _accept_newton(lad, back, jac, full, lam, per, harm, offs)
            while trial is None and lam >= 2.0 ** -10:
                lam *= 0.5
                coef = back[0] + lam * back[3]
                trial = _accept_newton(lad, back, jac, full, lam, per, harm, offs)
            if trial is None:
                # no damping reduced the next step (e.g. a far start on a nearly singular
                # problem): back to the old iterate and on with Gauss-Newton (the out-of-
                # steps test below still says whether the result converged; the contraction
                # tests start anew: measured from Newton's full step, a Gauss-Newton step
                # of 1.06 standard errors passed them, 222 being far larger)
                coef, jac, allow = back[0], None, False
                ev = back[1]
                last = last_full = 0.0
                continue
            if q > _MAX_CONTRACTION:  # slow: Newton's matrix anew, by differences
                jac = np.empty(0)
            else:
                # Broyden's update of Newton's matrix (the secant condition of the step
                # taken, on the old iterate's samples; least change in standard-error
                # units): one evaluation per step instead of a matrix of differences
                moved = coef - back[0]
                scaled = moved / back[2] ** 2
                jac = jac + np.outer(-(trial.atb - back[1].atb) - jac @ moved,
                                     scaled) / float(moved @ scaled)
            lam = min(1.0, 2.0 * lam)
        ev = lad.evaluate(coef, reject, True)
    return coef, rms, total_keep, ata, chi2


#: an empty array: no absolute phases (kernels take arrays, not None)
_NONE = np.empty(0)


def _dense_ladder(models):
    """Every group's coefficients on the dense axis of multiples of its orders' divisor
    (as :func:`telefringe.fringes._nonlinearity_kernels.ladder_residuals` takes them):
    cos, sin (G, K) zero-padded, divisor (G,) and kmax (G,) int64 (1 and 0 for a group
    without harmonics)."""
    divisor = np.ones(len(models), dtype=np.int64)
    kmax = np.zeros(len(models), dtype=np.int64)
    for g, m in enumerate(models):
        if m.harmonics:
            h = np.asarray(m.harmonics, dtype=np.int64)
            divisor[g] = max(int(np.gcd.reduce(h)), 1)
            kmax[g] = int(h.max()) // divisor[g]
    cos = np.zeros((len(models), int(kmax.max()) + 1))
    sin = np.zeros_like(cos)
    for g, m in enumerate(models):
        for order, c, s_ in zip(m.harmonics, m.cos_coef, m.sin_coef, strict=True):
            cos[g, int(order) // divisor[g]] += c
            sin[g, int(order) // divisor[g]] += s_
    return cos, sin, divisor, kmax


def _curvature(model, x, tau2, fix):
    """The curvature e''(x) of the model's harmonics selected by ``fix`` (bool, one per
    harmonic), each damped by ``exp(-m^2 tau2 / 2)``: the mean of ``cos(m (x + tau nu))``
    over Gaussian noise of variance ``tau2`` (scalar or one per sample). (n,) like x.
    (Compiled: :func:`telefringe.fringes._nonlinearity_kernels.damped_curvature`.)"""
    x = np.ascontiguousarray(x, dtype=np.float64)
    out = np.zeros(x.shape)
    sel = np.asarray(fix, dtype=bool)
    if not sel.any() or x.size == 0:
        return out
    harm = np.asarray(model.harmonics, dtype=np.int64)[sel]
    t = np.ascontiguousarray(np.broadcast_to(np.asarray(tau2, dtype=np.float64), x.shape))
    _k.damped_curvature(x.ravel(), t.ravel(), harm,
                        np.asarray(model.cos_coef, dtype=np.float64)[sel],
                        np.asarray(model.sin_coef, dtype=np.float64)[sel], out.reshape(-1))
    return out


def _stein_sum(model, x, gain, curv, weight, fix):
    """``sum_i weight_i F'(x_i)`` with ``F(x) = h(x) / (1 + e'(x))`` (h: cos and sin of
    each harmonic of ``model``, interleaved as the coefficients), ``gain`` = 1 / (1 + e')
    and ``curv`` = e'' (see :func:`_curvature`) at x; (2 n_harmonics,), zero for the
    harmonics not selected by ``fix``. (Compiled:
    :func:`telefringe.fringes._nonlinearity_kernels.stein_sums`.)"""
    harm = np.asarray(model.harmonics, dtype=np.int64)
    out = np.zeros(2 * harm.size)
    sel = np.asarray(fix, dtype=bool)
    x = np.ascontiguousarray(x, dtype=np.float64).ravel()
    if not sel.any() or x.size == 0:
        return out
    shape = x.shape
    g = np.ascontiguousarray(np.broadcast_to(np.asarray(gain, dtype=np.float64), shape))
    dgain = np.ascontiguousarray(-g * g * np.broadcast_to(curv, shape))
    w = np.ascontiguousarray(np.broadcast_to(np.asarray(weight, dtype=np.float64), shape))
    part = np.empty(2 * int(sel.sum()))
    _k.stein_sums(x, dgain, g, w, harm[sel], part)
    idx = np.flatnonzero(sel)
    out[2 * idx] = part[0::2]
    out[2 * idx + 1] = part[1::2]
    return out


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
