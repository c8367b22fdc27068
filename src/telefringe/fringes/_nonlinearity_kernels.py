"""Numba kernels of the projector-nonlinearity model (private; used by
:mod:`telefringe.fringes.nonlinearity`). No fastmath; ``cache=True``.

Harmonics ``cos(m phi), sin(m phi)`` come from the complex recurrence
``exp(i m phi) = exp(i (m-1) phi) exp(i phi)`` (one sin/cos per sample; rounding error grows
like m * 1e-16, below 1e-14 for the orders used here, m <= 48).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

TWO_PI = 2.0 * math.pi


@nb.njit(cache=True, nogil=True)
def _gcd(harmonics):
    """Greatest common divisor of the orders (1 for none)."""
    d = 0
    for m in range(harmonics.size):
        a, b = d, harmonics[m]
        while b:
            a, b = b, a % b
        d = a
    return max(d, 1)


@nb.njit(cache=True, nogil=True)
def _dense_coefficients(harmonics, cos_coef, sin_coef):
    """The orders' common divisor d and the coefficients on the dense axis of multiples
    k d, k = 0..max(harmonics) / d (zeros between), so that the recurrence steps by d."""
    d = _gcd(harmonics)
    kmax = 0
    for m in range(harmonics.size):
        kmax = max(kmax, harmonics[m] // d)
    ca = np.zeros(kmax + 1)
    sa = np.zeros(kmax + 1)
    for m in range(harmonics.size):
        ca[harmonics[m] // d] += cos_coef[m]
        sa[harmonics[m] // d] += sin_coef[m]
    return d, ca, sa


@nb.njit(cache=True, nogil=True, inline="always")
def _series(phi, d, ca, sa):
    """e(phi) and e'(phi) of the dense series (see :func:`_dense_coefficients`)."""
    c1 = math.cos(d * phi)
    s1 = math.sin(d * phi)
    c = 1.0
    s = 0.0
    e = 0.0
    de = 0.0
    for k in range(1, ca.size):
        c, s = c * c1 - s * s1, s * c1 + c * s1
        e += ca[k] * c + sa[k] * s
        de += (k * d) * (sa[k] * c - ca[k] * s)
    return e, de


@nb.njit(cache=True, nogil=True, parallel=True)
def harmonic_sum(phase, harmonics, cos_coef, sin_coef, out):
    """``out[i] = sum_m cos_coef[m] cos(h_m phase[i]) + sin_coef[m] sin(h_m phase[i])``.

    phase, out : (n,) float64, rad; harmonics : (k,) int64 orders >= 1; cos_coef, sin_coef :
    (k,) float64, rad.
    """
    d, ca, sa = _dense_coefficients(harmonics, cos_coef, sin_coef)
    for i in nb.prange(phase.size):
        out[i] = _series(phase[i], d, ca, sa)[0]


@nb.njit(cache=True, nogil=True, parallel=True)
def invert_harmonic(measured, harmonics, cos_coef, sin_coef, start, out):
    """Solve ``phi + e(phi) = measured`` per sample by Newton's method, where
    ``e(phi) = sum_m cos_coef[m] cos(h_m phi) + sin_coef[m] sin(h_m phi)``.

    measured, out : (n,) float64, rad. start : (n,) float64 starting values (rad), or an
    empty array to start at ``measured - e(measured)``. Each sample stops when Newton's
    error bound after its last step is below 1e-15 rad, or the step below 1e-14 rad (at
    most 60 steps). Returns False when ``1 + e'(phi) <= 0`` is met (the
    model is not invertible there), True otherwise.
    """
    n = measured.size
    d, ca, sa = _dense_coefficients(harmonics, cos_coef, sin_coef)
    kmax = ca.size - 1
    # Newton's error bound: after a step s the error is <= K2 / (2 min(1 + e')) s^2 with
    # K2 = sum (k d)^2 (|a| + |b|) >= |e''|; stop once that is below 1e-15 rad (or when
    # the step itself is below 1e-14 rad)
    k2 = 0.0
    for k in range(1, kmax + 1):
        k2 += (k * d) ** 2 * (abs(ca[k]) + abs(sa[k]))
    warm = start.size == n
    bad = np.zeros(n, dtype=np.bool_)
    for i in nb.prange(n):
        x = measured[i]
        phi = start[i] if warm else x
        for it in range(62):
            e, de = _series(phi, d, ca, sa)
            if it == 0 and not warm:
                phi = x - e  # the start, as e is evaluated at the measured phase
                continue
            slope = 1.0 + de
            if slope <= 0.0:
                bad[i] = True
                break
            step = (phi + e - x) / slope
            phi = phi - step
            # (1 + e' >= slope - K2 |step| near the root)
            lower = slope - k2 * abs(step)
            if abs(step) < 1e-14 or (lower > 0.0 and k2 * step * step < 2e-15 * lower):
                break
        out[i] = phi
    for i in range(n):
        if bad[i]:
            return False
    return True


@nb.njit(cache=True, nogil=True, inline="always")
def _harmonic_row(phase, scale, harm, d, out, i, start):
    """out[i, start + 2m], out[i, start + 2m + 1] = scale (cos, sin)(harm[m] phase)."""
    c1 = math.cos(d * phase)
    s1 = math.sin(d * phase)
    c = 1.0
    s = 0.0
    h = 0
    for m in range(harm.size):
        target = harm[m] // d
        while h < target:
            c, s = c * c1 - s * s1, s * c1 + c * s1
            h += 1
        out[i, start + 2 * m] = scale * c
        out[i, start + 2 * m + 1] = scale * s


@nb.njit(cache=True, nogil=True, parallel=True)
def design_rows(phase_a, phase_b, scale_a, scale_b, harm_a, harm_b, out):
    """Rows of the pair design matrix: ``out[i] = [scale_a[i] h_a(phase_a[i]),
    scale_b[i] h_b(phase_b[i])]`` with ``h(phi) = (cos m phi, sin m phi)`` for each order m
    of the (sorted) harmonics.

    phase_*, scale_* : (n,) float64; harm_* : (k_*,) int64 sorted; out : (n, 2 (k_a + k_b)).
    """
    na = 2 * harm_a.size
    da = _gcd(harm_a)
    db = _gcd(harm_b)
    for i in nb.prange(phase_a.size):
        _harmonic_row(phase_a[i], scale_a[i], harm_a, da, out, i, 0)
        _harmonic_row(phase_b[i], scale_b[i], harm_b, db, out, i, na)


@nb.njit(cache=True, nogil=True, parallel=True)
def table_interp(phase, table, wrap_difference, out):
    """Periodic linear interpolation of ``table`` (sampled at ``-pi + 2 pi j / M``) at each
    phase (rad). With ``wrap_difference`` the result is ``wrap(phase - interp)`` in
    (-pi, pi] (the correction of a measured phase), else ``interp`` itself.

    phase, out : (n,) float64; table : (M,) float64. NaN phases give NaN.
    """
    m = table.size
    scale = m / TWO_PI
    for i in nb.prange(phase.size):
        p = phase[i]
        if not math.isfinite(p):
            out[i] = np.nan
            continue
        t = (p + math.pi) * scale
        j = int(math.floor(t))
        f = t - j
        j0 = j % m
        j1 = (j0 + 1) % m
        g = table[j0] * (1.0 - f) + table[j1] * f
        if wrap_difference:
            q = p - g
            if q > math.pi:
                q -= TWO_PI
            elif q <= -math.pi:
                q += TWO_PI
            out[i] = q
        else:
            out[i] = g


@nb.njit(cache=True, nogil=True, parallel=True)
def damped_curvature(phase, tau2, harmonics, cos_coef, sin_coef, out):
    """``out[i] = -sum_m m^2 exp(-m^2 tau2[i] / 2) (cos_coef[m] cos(m phase[i])
    + sin_coef[m] sin(m phase[i]))``: the curvature e'' of the series, each harmonic damped
    by the mean of ``cos(m nu)`` over Gaussian noise nu of variance ``tau2[i]``.

    phase, tau2, out : (n,) float64 (rad, rad^2). The damping ``q^(k^2)`` of the k-th
    multiple of the orders' divisor d (q = exp(-d^2 tau2 / 2)) is carried by the
    recurrence ``q^((k+1)^2) = q^(k^2) q^(2k+1)``: one exp per sample.
    """
    d, ca, sa = _dense_coefficients(harmonics, cos_coef, sin_coef)
    for i in nb.prange(phase.size):
        q = math.exp(-0.5 * d * d * tau2[i])
        c1 = math.cos(d * phase[i])
        s1 = math.sin(d * phase[i])
        c = 1.0
        s = 0.0
        damp = 1.0
        step = q
        acc = 0.0
        for k in range(1, ca.size):
            c, s = c * c1 - s * s1, s * c1 + c * s1
            damp *= step
            step *= q * q
            mk = k * d
            acc -= mk * mk * damp * (ca[k] * c + sa[k] * s)
        out[i] = acc


@nb.njit(cache=True, nogil=True, parallel=True)
def stein_sums(phase, dgain, gain, weight, harmonics, out):
    """``out[2 j] = sum_i weight_i (dgain_i cos(m_j x_i) - gain_i m_j sin(m_j x_i))`` and
    ``out[2 j + 1] = sum_i weight_i (dgain_i sin(m_j x_i) + gain_i m_j cos(m_j x_i))`` for
    the orders m_j of ``harmonics`` (x = phase): the derivative sums of Stein's lemma.

    phase, dgain, gain, weight : (n,) float64; harmonics : (k,) int64; out : (2 k,) float64.
    Summed in a fixed number of chunks (deterministic whatever the thread count).
    """
    nh = harmonics.size
    d = _gcd(harmonics)
    kmax = 0
    for j in range(nh):
        kmax = max(kmax, harmonics[j] // d)
    n = phase.size
    n_chunks = 16
    part_c = np.zeros((n_chunks, kmax + 1))
    part_s = np.zeros((n_chunks, kmax + 1))
    for ch in nb.prange(n_chunks):
        lo = ch * n // n_chunks
        hi = (ch + 1) * n // n_chunks
        acc_c = np.zeros(kmax + 1)
        acc_s = np.zeros(kmax + 1)
        for i in range(lo, hi):
            w = weight[i]
            if w == 0.0:
                continue
            c1 = math.cos(d * phase[i])
            s1 = math.sin(d * phase[i])
            c = 1.0
            s = 0.0
            wd = w * dgain[i]
            wg = w * gain[i]
            for k in range(1, kmax + 1):
                c, s = c * c1 - s * s1, s * c1 + c * s1
                mk = k * d
                acc_c[k] += wd * c - wg * mk * s
                acc_s[k] += wd * s + wg * mk * c
        part_c[ch] = acc_c
        part_s[ch] = acc_s
    for j in range(nh):
        k = harmonics[j] // d
        tc = 0.0
        ts = 0.0
        for ch in range(n_chunks):
            tc += part_c[ch, k]
            ts += part_s[ch, k]
        out[2 * j] = tc
        out[2 * j + 1] = ts
