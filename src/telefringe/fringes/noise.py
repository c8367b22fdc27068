"""The camera's noise measured from a scan's own phase steps (photon transfer per scan).

Why: the decoder's uncertainty ``sigma_phi = sqrt(2/N) sigma_I / B`` needs the camera's
per-sample noise ``sigma_I(I)``. The built-in :class:`~telefringe.fringes.phase.NoiseModel`
describes a typical 8-bit machine-vision camera, not the one that took the scan (on the
SLMaster capture in ``../shared/realdata`` it understates the noise 1.9x). An N-step group
with N >= 4 measures the noise itself: each pixel's N samples are fitted by
``A + B cos(phi + offset + 2 pi k / N)`` (3 parameters), and what is left has N - 3
degrees of freedom of pure noise, whose expected sum of squares is ``(N - 3) sigma_I^2(A)``
for equal steps (the projection's diagonal is (N - 3) / N for every sample).

How (:func:`estimate_noise`):

1. Per phase group with N >= 4 (a regular subsample of at most ``max_pixels`` pixels over
   all groups): the per-pixel fit, its residual and the background A. Pixels with a sample
   at the sensor's maximum (saturated) or at 0 (clipped black) are left out.
2. The projector's nonlinearity (gamma) adds harmonics of the fringe to every pixel, in a
   ratio to the fundamental that is the same for all pixels of a group (a pixel sees
   ``alpha f(p) + c`` of the pattern level p): these harmonics (2 to 5, those the N steps
   can tell from the fundamental and the mean) are fitted globally per group and removed
   from the residuals, and the first-order leak of the fitted phase's and modulation's
   own noise into that harmonic model is corrected per pixel. (Without this a gamma-2.2
   projector's second harmonic, 28 % of B, would dominate a 4-step residual.)
3. Pixels are pooled in bins of A (width ``max_value / 32``); each bin's variance is the
   mean of its pixels' residual sums of squares over their weights (:class:`StepResiduals`),
   leaving out the pixels beyond the chi^2 tail 1e-4 (edges and specks that do not follow
   a sinusoid) and correcting the mean for that cut, with its standard error. (A median
   would be biased by the coarse steps of 8-bit residuals.)
4. ``sigma_I^2(I) = a + b I`` (read noise and quantisation ``a``; shot noise ``b`` DN per DN)
   is fitted to the bins, each weighted by its decodable pixels at equal relative error
   (where the line cannot follow the bins, it is best where most pixels are), with
   ``a >= q^2`` (q^2 = 1/12 for integer images) and ``b >= 0``. Its uncertainty: the
   covariance of (a, b) from the bins' standard errors and, in quadrature, the misfit
   (the pixel-weighted RMS relative deviation of the bins from the line).
   The camera is the same for every group, so a group whose residuals exceed the quietest
   group's by more than 10 % carries fringe shape the harmonic model did not follow (fine
   fringes blurred unevenly across the field): it is left out (and named).

:func:`resolve_noise` chooses the model the decoder uses (``"auto"``: a calibrated model in
the scan's ``meta.camera_noise`` if present, else the scan's estimate where it can be
made, else the built-in default, saying why).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from telefringe.fringes.errors import DecodeError
from telefringe.fringes.phase import NoiseModel
from telefringe.fringes.scan import PhaseGroup, Scan

__all__ = [
    "NOISE_SOURCES",
    "NoiseEstimate",
    "NoiseEstimateError",
    "NoiseChoice",
    "estimate_noise",
    "resolve_noise",
    "step_residuals",
    "noise_from_meta",
]

#: what ``resolve_noise`` accepts as a string
NOISE_SOURCES = ("auto", "scan", "calibrated", "default")
#: pixels of a scan the estimate reads at most (over all its phase groups)
MAX_PIXELS = 24_000
#: fewest usable pixels for an estimate, and per intensity bin
MIN_PIXELS = 2_000
MIN_PER_BIN = 100
#: intensity bins across [0, max_value]
N_BINS = 32
#: pixels (per group) the global harmonic fit reads at most
_HARMONIC_PIXELS = 20_000


class NoiseEstimateError(DecodeError):
    """The scan cannot tell its camera's noise (the message says why; a DecodeError, so a
    ValueError)."""


@dataclass(frozen=True)
class NoiseEstimate:
    """The camera noise measured from a scan's phase-step residuals.

    Attributes
    ----------
    model : NoiseModel, DN of the scan's images (``read_noise^2 + quantization^2 = a``,
        ``gain = b``).
    a : float, DN^2, intercept of ``sigma_I^2(I) = a + b I`` (read noise and quantisation).
    b : float, DN per DN, slope (shot noise).
    covariance : (2, 2) ndarray, of (a, b) (DN^4, DN^3, DN^2); a parameter held at its bound
        has variance 0.
    chi2_dof : float, the line's chi^2 per degree of freedom over the bins' standard
        errors (about 1 when the model describes the data; NaN with 2 bins).
    misfit : float, the RMS relative deviation of the bins' variances from the line,
        weighted by their decodable pixels: how far a camera's noise is from read + shot
        noise (a real camera's can curve upward, e.g. with illumination flicker).
    n_pixels : int, pixels used (over all groups).
    dof : tuple of int, residual degrees of freedom per group used (N - 3).
    bin_intensity, bin_variance, bin_sigma : (n_bins,) ndarray, DN, DN^2, DN^2: the
        pooled bins (their pixels' weighted mean A, variance, its standard error).
    bounded : tuple of str, the parameters held at a bound (``"a"`` at q^2: the read noise
        is below what the data resolve; ``"b"`` at 0).
    subsampled : bool, a regular subsample of the pixels was read.
    groups : tuple of (axis, periods, steps, exposure), the phase groups used.
    excluded : tuple of the same, groups left out because their residuals exceed the
        quietest group's by more than ``GROUP_EXCESS`` (fringe shape, not noise).
    """

    model: NoiseModel
    a: float
    b: float
    covariance: np.ndarray
    chi2_dof: float
    misfit: float
    n_pixels: int
    dof: tuple[int, ...]
    bin_intensity: np.ndarray
    bin_variance: np.ndarray
    bin_sigma: np.ndarray
    bounded: tuple[str, ...] = ()
    subsampled: bool = False
    groups: tuple = ()
    excluded: tuple = ()

    def variance(self, intensity) -> np.ndarray:
        """Predicted per-sample variance (DN^2) at ``intensity`` (DN), any shape."""
        i = np.clip(np.asarray(intensity, dtype=float), 0.0, None)
        return self.a + self.b * i

    def relative_uncertainty(self, intensity) -> np.ndarray:
        """Relative standard uncertainty of the predicted ``sigma_I`` at ``intensity`` (DN):
        half the relative uncertainty of the variance, from the covariance of (a, b) and
        the line's misfit in quadrature. Any shape."""
        i = np.clip(np.asarray(intensity, dtype=float), 0.0, None)
        c = self.covariance
        u_var = np.sqrt(np.maximum(c[0, 0] + 2 * i * c[0, 1] + i * i * c[1, 1], 0.0))
        return 0.5 * np.hypot(u_var / self.variance(i), self.misfit)

    @property
    def intensity_range(self) -> tuple[float, float]:
        """(lowest, highest) bin intensity (DN): where the model was measured."""
        return float(self.bin_intensity.min()), float(self.bin_intensity.max())


@dataclass(frozen=True)
class NoiseChoice:
    """The noise model the decoder used and where it came from.

    Attributes
    ----------
    model : NoiseModel, DN of the scan's images.
    source : "scan" (estimated from the scan), "calibrated" (the scan's
        ``meta.camera_noise`` or a model passed in), or "default" (the built-in typical
        camera, scaled to the scan's max_value).
    estimate : NoiseEstimate or None (source "scan").
    note : str, why this source (e.g. why the scan could not be used); "" when asked for.
    """

    model: NoiseModel
    source: str
    estimate: NoiseEstimate | None = None
    note: str = ""

    def summary(self) -> dict:
        """A JSON-ready description (numbers in DN; see docs/formats.md, ``noise_model``)."""
        m = self.model
        out = {"source": self.source, "read_noise_dn": float(m.read_noise),
               "gain_dn_per_dn": float(m.gain), "quantization_dn": float(m.quantization)}
        e = self.estimate
        if e is not None:
            mid = float(np.median(e.bin_intensity))
            out.update({
                "a_dn2": float(e.a), "b_dn": float(e.b),
                "u_a_dn2": float(np.sqrt(e.covariance[0, 0])),
                "u_b_dn": float(np.sqrt(e.covariance[1, 1])),
                "cov_ab": float(e.covariance[0, 1]),
                "chi2_dof": None if not np.isfinite(e.chi2_dof) else float(e.chi2_dof),
                "misfit": float(e.misfit),
                "intensity_range_dn": list(e.intensity_range),
                "relative_u_sigma_at_median": float(e.relative_uncertainty(mid)),
                "n_pixels": int(e.n_pixels), "dof": list(e.dof),
                "bounded": list(e.bounded), "subsampled": bool(e.subsampled),
                "groups": [list(k) for k in e.groups],
                "excluded_groups": [list(k) for k in e.excluded]})
        if self.note:
            out["note"] = self.note
        return out


# ----------------------------------------------------------------------------- residuals
def _harmonics(steps: int, hmax: int = 5) -> list[int]:
    """Harmonics 2..hmax that N steps tell apart from the mean, the fundamental and each
    other (h = N -+ 1 alias onto the fundamental, h = N onto the mean)."""
    out, seen = [], set()
    for h in range(2, hmax + 1):
        r = h % steps
        alias = min(r, steps - r)
        if alias in (0, 1) or alias in seen:
            continue
        seen.add(alias)
        out.append(h)
    return out


@dataclass(frozen=True)
class StepResiduals:
    """Per-pixel residuals of an N-step group's sinusoid fit (arrays (n,)).

    To first order in the noise, ``E[sum_squares] = a * dof_weight + b * intensity_weight``
    for per-sample variances ``a + b I_k``: the weights hold the projection's column norms
    (``(N - 3) / N`` each without harmonics) including how the fitted phase's and
    modulation's own noise leaks into the harmonic model, and that noise's correlation with
    the residual where the variance follows the intensity (shot noise).

    Attributes
    ----------
    sum_squares : DN^2, residual sum of squares (harmonics removed).
    dof_weight : 1, ``sum_k m_k`` (N - 3 without harmonics).
    intensity_weight : DN, ``sum_k m_k I_k`` with I_k the fitted (noise-free) samples
        ((N - 3) A without harmonics).
    background : DN, A.  modulation : DN, B.
    """

    sum_squares: np.ndarray
    dof_weight: np.ndarray
    intensity_weight: np.ndarray
    background: np.ndarray
    modulation: np.ndarray

    @property
    def variance(self) -> np.ndarray:
        """DN^2, per-pixel residual variance ``sum_squares / dof_weight`` (an estimate of
        the samples' mean variance)."""
        return self.sum_squares / self.dof_weight


def step_residuals(stack, *, steps: int, offset: float = 0.0, harmonics: bool = True
                   ) -> StepResiduals:
    """Per-pixel residuals of an N-step group's sinusoid fit, for noise estimation.

    Parameters
    ----------
    stack : (N, n) array_like, DN, the N phase-shifted samples of n pixels (image k shows
        ``A + B cos(phi + offset + 2 pi k / N)``); N >= 4.
    steps : int, N.  offset : float, rad.
    harmonics : bool, fit the fringe's harmonics globally (one ratio to the fundamental
        per harmonic, from at most 20 000 of the pixels) and remove them (see the module
        notes); False leaves them in the residual.

    Returns
    -------
    StepResiduals
    """
    n_steps = int(steps)
    if n_steps < 4:
        raise NoiseEstimateError(f"{n_steps}-step groups leave no residual to measure the "
                                 "noise (N - 3 = 0 degrees of freedom); N >= 4 needed")
    I = np.asarray(stack)
    if I.ndim != 2 or I.shape[0] != n_steps:
        raise NoiseEstimateError(f"stack must be shaped ({n_steps}, n), got {I.shape}")
    hs = _harmonics(n_steps) if harmonics else []
    n = I.shape[1]
    offset = float(offset)
    single = n <= _CHUNK
    parts = _fit_parts(I, n_steps, offset, hs) if single else None
    beta = None
    if hs and n:
        fit = _subsample(n, _HARMONIC_PIXELS)
        sub = _take(parts, fit) if single else _fit_parts(I[:, fit], n_steps, offset, hs)
        X, res = sub["X"], sub["res"]
        X2 = X.reshape(-1, X.shape[-1])
        M = X2.T @ X2
        beta = np.linalg.lstsq(M, X2.T @ res.reshape(-1), rcond=1e-9)[0]
    if single:
        return StepResiduals(*_chunk_residuals(parts, n_steps, hs, beta))
    out = [np.empty(n) for _ in range(5)]
    for lo in range(0, n, _CHUNK):
        sl = slice(lo, min(n, lo + _CHUNK))
        parts = _fit_parts(I[:, sl], n_steps, offset, hs if beta is not None else [])
        for arr, val in zip(out, _chunk_residuals(parts, n_steps, hs, beta), strict=True):
            arr[sl] = val
    return StepResiduals(*out)


#: pixels per chunk of :func:`step_residuals` (bounds its memory)
_CHUNK = 65_536


def _take(parts: dict, idx) -> dict:
    """The pixels ``idx`` of :func:`_fit_parts`'s per-pixel arrays."""
    return {"X": parts["X"][:, idx], "res": parts["res"][:, idx]}


def _fit_parts(I, n_steps: int, offset: float, hs) -> dict:
    """Per-pixel sinusoid fit of (N, n) samples: residual (N, n), A, B, the fitted
    samples and, for harmonics ``hs``, cos(h theta), sin(h theta) (N, n) and the projected
    regressors X (N, n, 2 len(hs)) with their per-unit-B version."""
    I = np.asarray(I, dtype=np.float64)
    ang = offset + 2.0 * np.pi * np.arange(n_steps) / n_steps
    basis = np.stack([np.ones(n_steps), np.cos(ang), np.sin(ang)])  # orthogonal rows
    norm = np.array([n_steps, n_steps / 2.0, n_steps / 2.0])
    coef = (basis @ I) / norm[:, None]  # (3, n): A, B cos phi, -B sin phi
    model = basis.T @ coef
    B = np.hypot(coef[1], coef[2])
    out = {"res": I - model, "model": model, "A": coef[0], "B": B,
           "basis": basis, "norm": norm, "ang": ang}
    if hs:
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(B > 0, (coef[1] - 1j * coef[2]) / B, 1.0)  # exp(i phi)
        trig, cols = {}, []
        for h in hs:
            e = np.exp(1j * h * ang)[:, None] * (z ** h)[None, :]  # exp(i h theta), (N, n)
            trig[h] = (e.real, e.imag)
            cols += [e.real, -e.imag]
        unit = _project_out(np.stack(cols, axis=-1), basis, norm)
        out.update(cphi=z.real, sphi=z.imag, trig=trig, unit=unit, X=unit * B[None, :, None])
    return out


def _project_out(x, basis, norm):
    """``x`` (N, ...) minus its projection on the mean and the fundamental (axis 0)."""
    shape = x.shape
    x2 = x.reshape(shape[0], -1)
    c = (basis @ x2) / norm[:, None]
    return (x2 - basis.T @ c).reshape(shape)


def _chunk_residuals(parts, n_steps: int, hs, beta):
    """(sum_squares, dof_weight, intensity_weight, A, B) of a chunk (see StepResiduals)."""
    res = parts["res"]
    A, B = parts["A"], parts["B"]
    if beta is None:
        dof = float(n_steps - 3)
        return np.einsum("kn,kn->n", res, res), np.full(A.shape, dof), dof * A, A, B
    res = res - parts["X"] @ beta
    ss = np.einsum("kn,kn->n", res, res)
    basis, norm, ang, trig = parts["basis"], parts["norm"], parts["ang"], parts["trig"]
    # e = M n to first order, M = Pperp - G_c w_c^T - G_s w_s^T: the harmonic model moves
    # with the fitted coefficients c1 = B cos phi, c2 = -B sin phi (w_c, w_s their weights
    # on the samples); E|e|^2 = sum_k m_k var_k with m_k the squared column norms of M
    f = parts["unit"] @ beta                                   # dH/dB
    g = _project_out(sum(-h * (beta[2 * j] * trig[h][1] + beta[2 * j + 1] * trig[h][0])
                         for j, h in enumerate(hs)), basis, norm)  # dH/dphi / B
    cphi, sphi = parts["cphi"], parts["sphi"]
    gc = cphi * f - sphi * g                                   # dH/dc1
    gs = -sphi * f - cphi * g                                  # dH/dc2
    wc = (2.0 / n_steps) * np.cos(ang)[:, None]
    ws = (2.0 / n_steps) * np.sin(ang)[:, None]
    pkk = (n_steps - 3.0) / n_steps
    m = (pkk - 2.0 * (gc * wc + gs * ws) + wc * wc * np.einsum("kn,kn->n", gc, gc)
         + 2.0 * wc * ws * np.einsum("kn,kn->n", gc, gs) + ws * ws * np.einsum("kn,kn->n", gs, gs))
    fitted = parts["model"] + parts["X"] @ beta
    return ss, m.sum(axis=0), np.einsum("kn,kn->n", m, fitted), A, B


# ----------------------------------------------------------------------------- estimate
#: a pixel whose residual is beyond this chi^2 tail probability (given its bin's
#: variance) is left out as not following a sinusoid (edge, speck, motion); the bin's mean
#: is corrected for the legitimate tail cut with it
_TAIL = 1e-4


@lru_cache(maxsize=64)
def _tail(nu: int) -> tuple[float, float]:
    """(c, F_{nu+2}(c)): the chi^2_nu quantile at 1 - _TAIL and the share of the mean of
    chi^2_nu below it (scipy.special: cheaper to import than scipy.stats; for nu <= 61
    its figures from the table of :mod:`telefringe.fringes._chi2_tails`, without importing
    it)."""
    from telefringe.fringes._chi2_tails import TAIL, TAILS

    if TAIL == _TAIL and 1 <= nu <= len(TAILS):
        return TAILS[nu - 1]
    from scipy.special import gammainc, gammaincinv

    c = 2.0 * float(gammaincinv(nu / 2.0, 1.0 - _TAIL))
    return c, float(gammainc(nu / 2.0 + 1.0, c / 2.0))


def _clipped_mean(ss, u, w, nu: int):
    """Mean sum of squares, dof and intensity weights of a bin's pixels, iteratively
    leaving out pixels beyond the chi^2_nu tail ``_TAIL`` (and correcting the mean for
    that cut: E[Y; Y < c] = nu F_{nu+2}(c) for Y ~ chi^2_nu). Returns (y, sigma_y, x, n)
    in variance units: y = mean(ss) / mean(u), x = mean(w) / mean(u)."""
    c, corr = _tail(int(nu))
    keep = np.ones(ss.size, dtype=bool)
    for _ in range(4):
        v = ss[keep].sum() / u[keep].sum()
        new = ss * nu < c * v * u
        if np.array_equal(new, keep):
            break
        keep = new
    k = int(keep.sum())
    uu = u[keep].mean()
    y = ss[keep].mean() / uu / corr
    sy = ss[keep].std(ddof=1) / np.sqrt(k) / uu / corr
    return float(y), float(sy), float(w[keep].mean() / uu), k


def _fit_line(x, y, s, n, q2: float):
    """Least squares ``y = a + b x`` over the bins, each weighted by the pixels it speaks
    for (``n``) at equal relative error, with ``a >= q2`` and ``b >= 0``.

    Returns (a, b, covariance (2, 2) from the bins' standard errors ``s`` (sandwich form),
    chi2_dof of the bins against the line with those errors, misfit: the pixel-weighted
    RMS relative deviation of the bins from the line, bounded)."""
    w = n / (y * y)

    def solve(free):
        cols = [np.ones_like(x), x]
        X = np.column_stack([cols[i] for i in free])
        yy = y.copy()
        fixed = {0: q2, 1: 0.0}
        for i in (0, 1):
            if i not in free:
                yy = yy - fixed[i] * cols[i]
        M = np.linalg.inv(X.T @ (X * w[:, None]))
        p = M @ (X.T @ (w * yy))
        meat = X.T @ (X * (w * w * s * s)[:, None])
        cov = M @ meat @ M
        full, fcov = np.array([fixed[0], fixed[1]], float), np.zeros((2, 2))
        for a_, i in enumerate(free):
            full[i] = p[a_]
            for b_, j in enumerate(free):
                fcov[i, j] = cov[a_, b_]
        return full, fcov

    bounded: tuple[str, ...] = ()
    p, cov = solve((0, 1))
    if p[0] < q2:
        p, cov = solve((1,))
        bounded = ("a",)
    if p[1] < 0:
        p, cov = solve((0,))
        bounded = ("b",)
        if p[0] < q2:
            p, cov = np.array([q2, 0.0]), np.zeros((2, 2))
            bounded = ("a", "b")
    fit = p[0] + p[1] * x
    r = y - fit
    dof = x.size - (2 - len(bounded))
    chi2_dof = float(np.sum((r / s) ** 2) / dof) if dof > 0 else float("nan")
    misfit = float(np.sqrt(np.sum(n * (r / fit) ** 2) / np.sum(n)))
    return float(p[0]), float(p[1]), cov, chi2_dof, misfit, bounded


def _subsample(n: int, k: int) -> np.ndarray:
    """A regular subsample of k of n indices (all when k >= n)."""
    if k >= n:
        return np.arange(n)
    return np.linspace(0, n - 1, k).astype(np.int64)


def estimate_noise(scan: Scan, *, max_pixels: int | None = MAX_PIXELS,
                   min_pixels: int = MIN_PIXELS,
                   min_modulation: float | None = None) -> NoiseEstimate:
    """Measure the camera's noise model from a scan's phase-step residuals.

    Parameters
    ----------
    scan : telefringe.scan.Scan, with at least one phase group of N >= 4 steps.
    max_pixels : int or None, pixels read at most over all groups (a regular subsample of
        each group's pixels, equal shares); None reads every pixel.
    min_pixels : int, fewest unsaturated, unclipped pixels needed.
    min_modulation : float, DN, the decoder's modulation threshold (default
        ``0.02 * max_value``, as :func:`telefringe.fringes.decode.decode`): the line is
        fitted to the bins weighted by their pixels above it (the pixels whose sigma it
        sets), while every unclipped pixel informs its bin's variance.

    Returns
    -------
    NoiseEstimate
        ``model`` in DN of the scan's images.

    Raises
    ------
    NoiseEstimateError (a ValueError)
        Only 3-step groups (no residual), too few usable pixels (saturated, clipped at 0,
        or a tiny image), or fewer than two intensity bins with enough pixels.
    """
    groups = [(g, s) for g, s in zip(scan.manifest.groups, scan.stacks, strict=True)
              if isinstance(g, PhaseGroup)]
    if not groups:
        raise NoiseEstimateError(f"{scan.source}: no phase group to measure the noise from")
    usable = [(g, s) for g, s in groups if int(g.steps) >= 4]
    if not usable:
        raise NoiseEstimateError(
            f"{scan.source}: every phase group has 3 steps, which leave no residual "
            "(N - 3 = 0 degrees of freedom) to measure the camera's noise; use >= 4 steps "
            "or give a calibrated noise model")
    max_value = float(scan.max_value)
    npx = int(np.prod(usable[0][1].shape[1:]))
    share = npx if max_pixels is None else max(1, int(max_pixels) // len(usable))
    idx = _subsample(npx, share)
    integer = all(s.dtype.kind in "ui" for _, s in usable)
    q2 = 1.0 / 12.0 if integer else 0.0
    edges = np.linspace(0.0, max_value, N_BINS + 1)
    rows = []  # per bin: group index, x, y, sigma_y, decodable pixels, pixels
    min_mod = 0.02 * max_value if min_modulation is None else float(min_modulation)
    n_used = n_sat = 0
    npix_group, dofs = [], []
    for gi, (g, stack) in enumerate(usable):
        flat = stack.reshape(stack.shape[0], -1)[:, idx]
        ok = (flat.max(axis=0) < max_value) & (flat.min(axis=0) > 0)
        if flat.dtype.kind == "f":
            ok &= np.all(np.isfinite(flat), axis=0)
        n_sat += int(np.sum(~ok))
        npix_group.append(0)
        dofs.append(int(g.steps) - 3)
        if ok.sum() < MIN_PER_BIN:
            continue
        r = step_residuals(flat[:, ok], steps=int(g.steps), offset=float(g.offset))
        nu = int(g.steps) - 3
        npix_group[gi] = r.sum_squares.size
        A = r.background
        which = np.clip(np.searchsorted(edges, A, side="right") - 1, 0, N_BINS - 1)
        order = np.argsort(which, kind="stable")
        counts = np.bincount(which, minlength=N_BINS)
        starts = np.concatenate([[0], np.cumsum(counts)])
        for b in np.flatnonzero(counts >= MIN_PER_BIN):
            sel = order[starts[b]:starts[b + 1]]
            y, sy, x, _ = _clipped_mean(r.sum_squares[sel], r.dof_weight[sel],
                                        r.intensity_weight[sel], nu)
            rows.append((gi, x, y, sy, int(np.count_nonzero(r.modulation[sel] >= min_mod)),
                         sel.size))
    n_used = sum(npix_group)
    if n_used < min_pixels:
        why = (f"{n_sat} of the pixels read are saturated or clipped at 0"
               if n_sat else "the image is too small")
        raise NoiseEstimateError(f"{scan.source}: {n_used} usable pixels, fewer than "
                                 f"{min_pixels}, to measure the camera's noise ({why})")
    tab = np.asarray(rows, dtype=float).reshape(-1, 6)
    tab = tab[np.all(np.isfinite(tab), axis=1) & (tab[:, 2] > 0) & (tab[:, 3] > 0)]
    if not len(tab):
        raise NoiseEstimateError(f"{scan.source}: the phase steps show no noise (noise-free "
                                 "synthetic images?): nothing to measure")
    gid, xs, ys, ss, ns, nall = tab.T
    if np.unique(np.round(xs / (max_value / N_BINS))).size < 2:
        raise NoiseEstimateError(f"{scan.source}: the lit pixels span too narrow an "
                                 "intensity range to fit read and shot noise")
    if np.count_nonzero(ns) < 2:  # fewer than 2 bins of decodable pixels: all pixels
        ns = nall
    # rounding adds q2 to the variance only when the noise before it is >~ 0.5 DN: below,
    # rounded values vary less, and a group whose every bin is there (a very short
    # exposure of an HDR set, 2-3 DN) would pass as the quietest one and leave a line fitted
    # to one narrow range (gain 8x too low, measured); such groups inform nothing here
    informative = np.unique(gid[ys >= QUANTIZED_BELOW * q2]) if q2 else np.unique(gid)
    use = np.isin(gid, informative) if informative.size else np.ones(gid.size, dtype=bool)
    keep = _consistent_groups(gid[use], xs[use], ys[use], ss[use], ns[use], q2)
    sel = np.isin(gid, keep)
    if np.unique(np.round(xs[sel] / (max_value / N_BINS))).size < 2:
        raise NoiseEstimateError(
            f"{scan.source}: the phase groups whose noise agrees ({len(keep)} of "
            f"{len(usable)}) span too narrow an intensity range to fit read and shot noise")
    a, b, cov, chi2_dof, misfit, bounded = _fit_line(xs[sel], ys[sel], ss[sel], ns[sel], q2)
    q = float(np.sqrt(q2))
    model = NoiseModel(read_noise=float(np.sqrt(max(a - q2, 0.0))), gain=max(b, 0.0),
                       quantization=q)
    order = np.argsort(xs[sel])
    keys = [(g.axis, int(g.periods), int(g.steps), float(g.exposure)) for g, _ in usable]
    return NoiseEstimate(model=model, a=a, b=b, covariance=cov, chi2_dof=chi2_dof,
                         misfit=misfit, n_pixels=int(sum(npix_group[i] for i in keep)),
                         dof=tuple(dofs[i] for i in keep), bin_intensity=xs[sel][order],
                         bin_variance=ys[sel][order], bin_sigma=ss[sel][order],
                         bounded=bounded, subsampled=bool(idx.size < npx),
                         groups=tuple(keys[i] for i in keep),
                         excluded=tuple(keys[i] for i in range(len(usable))
                                        if i not in keep and npix_group[i]))


#: integer images: bins whose variance is below this many times the rounding's (1/12
#: DN^2) are dominated by the rounding (noise before it below ~0.4 DN), where the
#: variance of rounded values is not ``a + b I`` (it is less)
QUANTIZED_BELOW = 2.0

#: a group whose residuals say more than this much more variance (relative) than the
#: quietest group's is left out: the camera is the same, so the excess is fringe shape
#: the global harmonic model does not follow (fine fringes blurred unevenly across the
#: field)
GROUP_EXCESS = 0.10


def _consistent_groups(gid, xs, ys, ss, ns, q2) -> list[int]:
    """The groups whose noise level agrees with the quietest group's (see
    GROUP_EXCESS): each group's pixel-weighted mean ratio of its bins to the line fitted
    to all bins."""
    groups = [int(g) for g in np.unique(gid)]
    if len(groups) == 1:
        return groups
    a, b, *_ = _fit_line(xs, ys, ss, ns, q2)
    ratio = ys / (a + b * xs)
    level = {g: float(np.sum(ns[gid == g] * ratio[gid == g]) / max(np.sum(ns[gid == g]), 1))
             for g in groups if np.sum(ns[gid == g]) > 0}
    if not level:
        return groups
    low = min(level.values())
    return [g for g in groups if g in level and level[g] <= low * (1.0 + GROUP_EXCESS)]


# ----------------------------------------------------------------------------- choice
def noise_from_meta(scan: Scan) -> NoiseModel | None:
    """A calibrated noise model in the scan's ``meta.camera_noise`` (``read_noise_dn``,
    ``gain_dn_per_dn``, optional ``quantization_dn``; DN of the scan's images), or None.
    Raises NoiseEstimateError when the entry is malformed."""
    doc = (scan.meta or {}).get("camera_noise")
    if doc is None:
        return None
    try:
        kw = {"read_noise": float(doc["read_noise_dn"]), "gain": float(doc["gain_dn_per_dn"])}
        if "quantization_dn" in doc:
            kw["quantization"] = float(doc["quantization_dn"])
        return NoiseModel(**kw)
    except (TypeError, KeyError, ValueError) as exc:
        raise NoiseEstimateError(
            f"{scan.source}: meta.camera_noise must hold numbers read_noise_dn and "
            f"gain_dn_per_dn (>= 0), got {doc!r} ({exc})") from None


def resolve_noise(scan: Scan, spec=None) -> NoiseChoice:
    """The noise model to decode ``scan`` with.

    Parameters
    ----------
    scan : telefringe.scan.Scan
    spec : None | "default" | "auto" | "scan" | "calibrated" | NoiseModel.
        None or "default": the built-in typical camera scaled by ``max_value / 255`` (the
        decoder's historical default). "scan": :func:`estimate_noise` (raises
        NoiseEstimateError when it cannot). "calibrated": the scan's ``meta.camera_noise``
        (raises when absent). "auto": calibrated if present, else the scan's estimate,
        else the default with a note saying why. A NoiseModel: used as given
        ("calibrated").

    Returns
    -------
    NoiseChoice
    """
    if isinstance(spec, NoiseModel):
        return NoiseChoice(spec, "calibrated", note="given by the caller")
    default = NoiseModel().scaled(float(scan.max_value) / 255.0)
    if spec is None or spec == "default":
        return NoiseChoice(default, "default")
    if spec not in NOISE_SOURCES:
        raise NoiseEstimateError(f"noise must be a NoiseModel or one of "
                                 f"{', '.join(NOISE_SOURCES)}; got {spec!r}")
    if spec in ("calibrated", "auto"):
        given = noise_from_meta(scan)
        if given is not None:
            return NoiseChoice(given, "calibrated", note="scan.json meta.camera_noise")
        if spec == "calibrated":
            raise NoiseEstimateError(f"{scan.source}: no calibrated noise model "
                                     "(scan.json meta.camera_noise)")
    try:
        est = estimate_noise(scan)
    except NoiseEstimateError as exc:
        if spec == "scan":
            raise
        return NoiseChoice(default, "default", note=f"not measurable from the scan: {exc}")
    return NoiseChoice(est.model, "scan", est)
