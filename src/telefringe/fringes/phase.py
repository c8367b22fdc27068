"""N-step wrapped phase, modulation and background; pixel masks; HDR fusion; noise model.

Convention (DESIGN.md): image ``k`` (0-based) of a group with ``steps`` = N images shows
``A + B cos(phi + offset + 2 pi k / N)``. The least-squares estimate for N >= 3 equal
steps is::

    S = sum_k I_k sin(d_k + offset),  C = sum_k I_k cos(d_k + offset),  d_k = 2 pi k / N
    phi = atan2(-S, C)             in (-pi, pi]
    B   = (2 / N) sqrt(S^2 + C^2)  (modulation, DN)
    A   = mean_k I_k               (background, DN)

For N = 4 and offset 0 this is exactly ``atan2(I3 - I1, I0 - I2)`` (the paper's Eq. 2):
coefficients that are 0 or +-1 up to rounding are stored exactly.

Noise (:class:`NoiseModel`): each sample has variance ``read_noise^2 + gain * I + q^2``
(DN^2; read noise, shot noise with ``gain`` DN per electron, quantisation ``q^2 = 1/12``).
For independent samples the phase has standard deviation
``sigma_phi = sqrt(2 / N) sigma_I / B`` (first order in sigma_I / B), with ``sigma_I``
evaluated at the background level ``A`` (the mean of the samples' variances).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = [
    "WrappedPhase",
    "HdrFusion",
    "NoiseModel",
    "PhaseInputError",
    "phase_shift_coefficients",
    "wrapped_phase",
    "saturation_mask",
    "low_modulation_mask",
    "shadow_mask",
    "fuse_hdr",
    "phase_sigma",
    "wrap",
]


class PhaseInputError(ValueError):
    """Degenerate or inconsistent input to the phase computation."""


@dataclass(frozen=True)
class WrappedPhase:
    """Result of :func:`wrapped_phase` (arrays shaped like one image, float64).

    Attributes
    ----------
    phase : (rows, cols) ndarray of float64, rad, wrapped to (-pi, pi].
    modulation : (rows, cols) ndarray of float64, B in DN.
    background : (rows, cols) ndarray of float64, A in DN.
    quadrature : (rows, cols) ndarray of float64 or None, DN: the samples' mean weighted by
        their phase sensitivity, ``(2/N) sum_k I_k sin^2(phi + offset + d_k)``. The phase
        noise is ``sqrt(2/N) sigma_I / B`` with sigma_I evaluated at this level. For a pure
        sinusoid it equals A when N >= 4 and ``A - (B/2) cos(3 (phi + offset))`` when
        N = 3; a peaky, gamma-distorted fringe is darker where the phase is read, hence
        less shot noise.
    """

    phase: np.ndarray
    modulation: np.ndarray
    background: np.ndarray
    quadrature: np.ndarray | None = None


@dataclass(frozen=True)
class NoiseModel:
    """Per-sample camera noise in DN: ``var = read_noise^2 + gain * I + quantization^2``.

    Parameters
    ----------
    read_noise : float, DN (standard deviation of the signal-independent noise).
    gain : float, DN per electron: the shot-noise variance is ``gain * I`` DN^2.
    quantization : float, DN; ``1/sqrt(12)`` for integer images.

    The defaults describe a typical 8-bit machine-vision camera (full well about
    10 000 e-, i.e. 0.025 DN/e-, read noise 0.5 DN). Scale ``read_noise`` and ``gain`` by
    ``max_value / 255`` for data on another scale (see :meth:`scaled`).
    """

    read_noise: float = 0.5
    gain: float = 0.025
    quantization: float = 1.0 / np.sqrt(12.0)

    def __post_init__(self):
        for name in ("read_noise", "gain", "quantization"):
            val = getattr(self, name)
            if not (np.isfinite(val) and val >= 0):
                raise PhaseInputError(f"NoiseModel.{name} must be finite and >= 0, got {val!r}")

    def scaled(self, factor: float) -> NoiseModel:
        """The same camera with intensities multiplied by ``factor`` (e.g. 8 -> 16 bit)."""
        return NoiseModel(self.read_noise * factor, self.gain * factor, self.quantization)

    def variance(self, intensity) -> np.ndarray:
        """Variance (DN^2) of one sample of mean ``intensity`` (DN), any shape."""
        i = np.clip(np.asarray(intensity, dtype=float), 0.0, None)
        return self.read_noise ** 2 + self.quantization ** 2 + self.gain * i


def wrap(phase) -> np.ndarray:
    """Wrap angles (rad) to (-pi, pi]."""
    p = np.asarray(phase, dtype=float)
    w = np.mod(p + np.pi, 2.0 * np.pi) - np.pi
    return np.where(w <= -np.pi, w + 2.0 * np.pi, w)


def phase_shift_coefficients(steps: int, offset: float = 0.0, *,
                             harmonic: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Cosine and sine weights ``(cos(h d_k + offset), sin(h d_k + offset))``, each (steps,),
    h = ``harmonic``.

    Values within 1e-12 of 0, +-0.5 or +-1 are snapped to them, so that common step
    counts (3, 4, 6, 8, 12) with offsets that are multiples of pi/2 use exact weights.
    """
    steps = _check_steps(steps)
    if not np.isfinite(offset):
        raise PhaseInputError(f"offset must be finite, got {offset!r}")
    ang = 2.0 * np.pi * int(harmonic) * np.arange(steps) / steps + float(offset)
    cos_w, sin_w = np.cos(ang), np.sin(ang)
    for arr in (cos_w, sin_w):
        for exact in (0.0, 0.5, -0.5, 1.0, -1.0):
            arr[np.abs(arr - exact) < 1e-12] = exact
    return cos_w, sin_w


def _check_steps(steps) -> int:
    if isinstance(steps, bool) or not isinstance(steps, int | np.integer) or steps < 3:
        raise PhaseInputError(f"steps must be an integer >= 3, got {steps!r}")
    return int(steps)


def _check_stack(images, steps: int, name: str = "images") -> np.ndarray:
    images = np.asarray(images)
    if images.ndim < 2:
        raise PhaseInputError(f"{name} must be shaped (steps, rows, cols), got {images.shape}")
    if images.shape[0] != steps:
        raise PhaseInputError(f"{name} holds {images.shape[0]} images but steps = {steps}")
    if not (np.issubdtype(images.dtype, np.integer) or np.issubdtype(images.dtype, np.floating)):
        raise PhaseInputError(f"{name} must be integer or float, got dtype {images.dtype}")
    if images.dtype.kind == "f" and not np.all(np.isfinite(images)):
        raise PhaseInputError(f"{name} contains NaN or infinite values")
    return images


#: Image types whose sums :func:`wrapped_phase` computes in a compiled pass
#: (:func:`telefringe.fringes._gray_kernels.phase_sums`, bit-identical to the NumPy loop),
#: for images of at least this many pixels (smaller ones: NumPy, no compilation).
_COMPILED_DTYPES = tuple(np.dtype(t) for t in (np.uint8, np.uint16, np.float64))
_COMPILED_MIN_PIXELS = 1 << 16


def wrapped_phase(images, *, steps: int, offset: float = 0.0) -> WrappedPhase:
    """Least-squares wrapped phase, modulation and background of an N-step group.

    Parameters
    ----------
    images : (steps, ...) array_like of int or float, DN. Image k is shifted by
        ``2 pi k / steps`` (see the module docstring); trailing axes are any image shape.
    steps : int >= 3, the number of equal phase steps.
    offset : float, rad, the group's phase offset (removed from the result).

    Returns
    -------
    WrappedPhase
        ``phase`` in (-pi, pi] (rad), ``modulation`` B and ``background`` A (DN), each
        shaped ``images.shape[1:]``, float64. The input is not modified.

    Examples
    --------
    >>> import numpy as np
    >>> x = np.linspace(0, 1, 5)
    >>> imgs = np.stack([100 + 50 * np.cos(2 * np.pi * x + np.pi / 2 * k) for k in range(4)])
    >>> wp = wrapped_phase(imgs, steps=4)
    >>> np.allclose(wp.phase, np.angle(np.exp(2j * np.pi * x)))
    True
    >>> np.allclose(wp.modulation, 50), np.allclose(wp.background, 100)
    (True, True)
    """
    steps = _check_steps(steps)
    images = _check_stack(images, steps)
    cos_w, sin_w = phase_shift_coefficients(steps, offset)
    cos2_w, sin2_w = phase_shift_coefficients(steps, 2.0 * offset, harmonic=2)
    shape = images.shape[1:]
    s = np.zeros(shape, dtype=np.float64)
    c = np.zeros(shape, dtype=np.float64)
    a = np.zeros(shape, dtype=np.float64)
    s2 = np.zeros(shape, dtype=np.float64)
    c2 = np.zeros(shape, dtype=np.float64)
    if images.dtype in _COMPILED_DTYPES and s.size >= _COMPILED_MIN_PIXELS:
        # one parallel compiled pass, bit-identical sums (no float64 copies of the images)
        from telefringe.fringes._gray_kernels import phase_sums

        phase_sums(np.ascontiguousarray(images).reshape(steps, -1), sin_w, cos_w, sin2_w,
                   cos2_w, s.reshape(-1), c.reshape(-1), s2.reshape(-1), c2.reshape(-1),
                   a.reshape(-1))
        steps_loop = 0
    else:
        steps_loop = steps
    for k in range(steps_loop):
        img = images[k].astype(np.float64)
        if sin_w[k]:
            s += sin_w[k] * img
        if cos_w[k]:
            c += cos_w[k] * img
        if sin2_w[k]:
            s2 += sin2_w[k] * img
        if cos2_w[k]:
            c2 += cos2_w[k] * img
        a += img
    phase = np.arctan2(-s, c)
    phase[phase <= -np.pi] = np.pi
    modulation = np.hypot(s, c)
    modulation *= 2.0 / steps
    a /= steps
    # (2/N) sum I_k sin^2(theta_k) = A - (1/N) sum I_k cos(2 theta_k)
    quad = a - (np.cos(2.0 * phase) * c2 - np.sin(2.0 * phase) * s2) / steps
    return WrappedPhase(phase=phase, modulation=modulation, background=a, quadrature=quad)


def saturation_mask(images, *, max_value: float) -> np.ndarray:
    """True where any sample of the stack reaches ``max_value`` (the sensor maximum).

    Parameters
    ----------
    images : (n, ...) array_like, DN.  max_value : float, DN (255 for 8 bit).

    Returns
    -------
    (...) ndarray of bool.
    """
    images = np.asarray(images)
    if images.ndim < 2:
        raise PhaseInputError(f"images must be shaped (n, rows, cols), got {images.shape}")
    out = np.zeros(images.shape[1:], dtype=bool)
    for img in images:
        out |= img >= max_value
    return out


def low_modulation_mask(modulation, *, min_modulation: float) -> np.ndarray:
    """True where the modulation B (DN) is below ``min_modulation`` (DN), or not finite."""
    m = np.asarray(modulation, dtype=float)
    return ~(m >= float(min_modulation))


def shadow_mask(*, background=None, white=None, black=None, min_contrast: float) -> np.ndarray:
    """True where the projector does not light the pixel.

    With ``white`` and ``black`` frames: ``white - black < min_contrast``. Without them,
    from the phase background A: ``A < min_contrast`` (a shadowed pixel sees only ambient
    light). ``min_contrast`` in DN.

    Returns
    -------
    (rows, cols) ndarray of bool.
    """
    if white is not None and black is not None:
        w = np.asarray(white, dtype=float)
        b = np.asarray(black, dtype=float)
        if w.shape != b.shape:
            raise PhaseInputError(f"white {w.shape} and black {b.shape} differ in shape")
        return (w - b) < min_contrast
    if background is None:
        raise PhaseInputError("shadow_mask needs white and black frames, or the background")
    return np.asarray(background, dtype=float) < min_contrast


@dataclass(frozen=True)
class HdrFusion:
    """Result of :func:`fuse_hdr`.

    Attributes
    ----------
    wrapped : WrappedPhase, per pixel from the chosen exposure (modulation and background
        in DN of that exposure).
    exposure_index : (rows, cols) ndarray of int, index (into the inputs) of the exposure
        used; the longest one when every exposure saturates.
    exposure : (rows, cols) ndarray of float, that exposure's value.
    saturated : (rows, cols) ndarray of bool, every exposure saturates at this pixel.
    """

    wrapped: WrappedPhase
    exposure_index: np.ndarray
    exposure: np.ndarray
    saturated: np.ndarray


def fuse_hdr(phases: Sequence[WrappedPhase], saturated: Sequence[np.ndarray],
             exposures: Sequence[float]) -> HdrFusion:
    """Fuse groups that differ only in exposure: per pixel, the longest exposure with no
    saturated sample.

    With shot- and read-noise-limited sensors the phase noise ``sqrt(2/N) sigma_I / B``
    falls with exposure (B grows linearly, sigma_I at most as its square root), so the
    longest unsaturated exposure is the best single choice per pixel.

    Parameters
    ----------
    phases : sequence of WrappedPhase, one per exposure, same shapes.
    saturated : sequence of (rows, cols) bool, per exposure (see :func:`saturation_mask`).
    exposures : sequence of float > 0, relative exposure of each.

    Returns
    -------
    HdrFusion
    """
    n = len(phases)
    if n == 0 or len(saturated) != n or len(exposures) != n:
        raise PhaseInputError("fuse_hdr needs as many phases, saturation masks and exposures "
                              f"(got {len(phases)}, {len(saturated)}, {len(exposures)})")
    exposures = [float(e) for e in exposures]
    if not all(np.isfinite(e) and e > 0 for e in exposures):
        raise PhaseInputError(f"exposures must be finite and > 0, got {exposures}")
    if len(set(exposures)) != n:
        raise PhaseInputError(f"exposures must differ, got {exposures}")
    shape = phases[0].phase.shape
    for p, s in zip(phases, saturated, strict=True):
        if p.phase.shape != shape or np.shape(s) != shape:
            raise PhaseInputError("fuse_hdr inputs differ in shape")
    order = np.argsort(exposures)  # shortest first: later (longer) ones overwrite
    idx = np.full(shape, order[-1], dtype=np.int64)
    all_sat = np.ones(shape, dtype=bool)
    for j in order:
        ok = ~np.asarray(saturated[j], dtype=bool)
        idx[ok] = j
        all_sat &= ~ok
    idx[all_sat] = order[-1]
    out = {}
    names = ["phase", "modulation", "background"]
    if all(p.quadrature is not None for p in phases):
        names.append("quadrature")
    for name in names:
        arr = np.empty(shape, dtype=np.float64)
        for j in range(n):
            sel = idx == j
            arr[sel] = getattr(phases[j], name)[sel]
        out[name] = arr
    exp_arr = np.asarray(exposures)[idx]
    return HdrFusion(wrapped=WrappedPhase(**out), exposure_index=idx, exposure=exp_arr,
                     saturated=all_sat)


def phase_sigma(modulation, background, *, steps: int, noise: NoiseModel) -> np.ndarray:
    """Standard uncertainty of the wrapped phase (rad): ``sqrt(2/N) sigma_I(A) / B``.

    Parameters
    ----------
    modulation, background : array_like, DN (same shape). Pass
        :attr:`WrappedPhase.quadrature` as ``background`` for the exact first-order
        propagation of intensity-dependent (shot) noise.
    steps : int, N.  noise : NoiseModel.

    Returns
    -------
    ndarray of float, rad; ``inf`` where B <= 0.
    """
    steps = _check_steps(steps)
    b = np.asarray(modulation, dtype=float)
    sig_i = np.sqrt(noise.variance(background))
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.sqrt(2.0 / steps) * sig_i / b
    return np.where(b > 0, out, np.inf)
