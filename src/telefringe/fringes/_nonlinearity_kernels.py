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


# ------------------------------------------------------------------ learning (fused passes)
@nb.njit(cache=True, nogil=True, parallel=True)
def invert_wrap_gain(measured, harmonics, cos_coef, sin_coef, start, unwrapped, est, gain):
    """One group's true-phase estimates for the fit, in one pass: :func:`invert_harmonic`
    (``start`` as there), then ``est = wrap(unwrapped)`` in [-pi, pi) (as ``np.mod(x + pi,
    2 pi) - pi``) and ``gain = 1 / (1 + e'(est))``.

    measured, start (or empty), unwrapped, est, gain : (n,) float64 (rad; gain unitless).
    Returns False when ``1 + e' <= 0`` was met (the model is not invertible there).
    """
    ok = invert_harmonic(measured, harmonics, cos_coef, sin_coef, start, unwrapped)
    d, ca, sa = _dense_coefficients(harmonics, cos_coef, sin_coef)
    for i in nb.prange(measured.size):
        w = (unwrapped[i] + math.pi) % TWO_PI - math.pi
        est[i] = w
        gain[i] = 1.0 / (1.0 + _series(w, d, ca, sa)[1])
    return ok


@nb.njit(cache=True, nogil=True, parallel=True)
def pair_residuals(est_a, est_b, gain_a, gain_b, sig_a, sig_b, r, ka, kb, res, wt, absz):
    """A pair's residual ``res = wrap(r phi_a - phi_b)`` (with the absolute phases
    ``phi + 2 pi k`` when ``ka``, ``kb`` are given, else they are empty), its weight
    ``wt = 1 / ((r sig_a gain_a)^2 + (sig_b gain_b)^2)`` (0 where that variance is not
    finite and positive) and ``absz = |res| sqrt(wt)``.

    All (n,) float64 (rad, 1/rad^2, unitless); r : float, the period ratio.
    """
    absolute = ka.size == est_a.size
    for i in nb.prange(est_a.size):
        if absolute:
            x = r * (est_a[i] + TWO_PI * ka[i]) - (est_b[i] + TWO_PI * kb[i])
        else:
            x = r * est_a[i] - est_b[i]
        x = (x + math.pi) % TWO_PI - math.pi
        res[i] = x
        va = r * sig_a[i] * gain_a[i]
        vb = sig_b[i] * gain_b[i]
        var = va * va + vb * vb
        w = 1.0 / var if (math.isfinite(var) and var > 0.0) else 0.0
        wt[i] = w
        absz[i] = abs(x) * math.sqrt(w)


@nb.njit(cache=True, nogil=True, inline="always")
def _powers(phase, d, kmax, c_out, s_out):
    """c_out[k], s_out[k] = cos, sin(k d phase), k = 0..kmax (one sin/cos)."""
    c1 = math.cos(d * phase)
    s1 = math.sin(d * phase)
    c = 1.0
    s = 0.0
    c_out[0] = 1.0
    s_out[0] = 0.0
    for k in range(1, kmax + 1):
        c, s = c * c1 - s * s1, s * c1 + c * s1
        c_out[k] = c
        s_out[k] = s


@nb.njit(cache=True, nogil=True, inline="always")
def _damped_curv(cp, sp, d, kmax, cfix, sfix, tau2):
    """-sum_k (k d)^2 exp(-(k d)^2 tau2 / 2) (cfix[k] cos + sfix[k] sin)(k d x), from the
    powers of :func:`_powers` (as :func:`damped_curvature`)."""
    q = math.exp(-0.5 * d * d * tau2)
    damp = 1.0
    step = q
    acc = 0.0
    for k in range(1, kmax + 1):
        damp *= step
        step *= q * q
        mk = k * d
        acc -= mk * mk * damp * (cfix[k] * cp[k] + sfix[k] * sp[k])
    return acc


@nb.njit(cache=True, nogil=True, parallel=True)
def pair_rows(est_a, est_b, gain_a, gain_b, sig_a, sig_b, r, res, wk, s2,
              harm_a, cfix_a, sfix_a, sel_a, harm_b, cfix_b, sfix_b, sel_b,
              rows, target, stein_a, stein_b):
    """One pair's weighted rows of an errors-in-variables Gauss-Newton step, in one pass
    over the samples (what ``nonlinearity._gauss_newton`` does), for samples with weight
    ``wk > 0`` (the others get zero rows):

    - per group g of the pair: ``tau2 = s2 (sig_g gain_g)^2`` and the damped curvature
      ``curv_g`` (:func:`damped_curvature` of the dense coefficients ``cfix_g``,
      ``sfix_g`` of the harmonics whose bias is corrected, zero elsewhere);
    - ``target = sqrt(wk) (-(res - mean_bias))`` with ``mean_bias = s2 / 2 (r sig_a^2
      (-gain_a^3 curv_a) - sig_b^2 (-gain_b^3 curv_b))``;
    - ``rows = sqrt(wk) [-r gain_a h_a(est_a), gain_b h_b(est_b)]`` (h: cos and sin of each
      sorted order of ``harm_g``), so that ``rows^T rows`` and ``rows^T target`` are the
      normal equations;
    - Stein's sums (:func:`stein_sums`) of the orders with ``sel_g`` set, weights ``wk r^2
      (sig_a gain_a)^2`` and ``wk (sig_b gain_b)^2``, into ``stein_a`` and ``stein_b``
      (2 per order, interleaved cos/sin; 0 for the orders not selected).

    Per-sample arrays (n,) float64; r, s2 : float; harm_g : (k_g,) int64 sorted orders;
    cfix_g, sfix_g : (kmax_g + 1,) float64 dense coefficients on multiples of the orders'
    divisor (rad); sel_g : (k_g,) bool; rows : (n, 2 (k_a + k_b)); target : (n,); stein_g :
    (2 k_g,). Outputs are overwritten. The sums are taken in a fixed number of chunks
    (deterministic whatever the thread count).
    """
    na = 2 * harm_a.size
    nb_ = 2 * harm_b.size
    npar = na + nb_
    da = _gcd(harm_a)
    db = _gcd(harm_b)
    ka_max = cfix_a.size - 1
    kb_max = cfix_b.size - 1
    n = est_a.size
    n_chunks = 16
    p_sa = np.zeros((n_chunks, max(na, 1)))
    p_sb = np.zeros((n_chunks, max(nb_, 1)))
    for ch in nb.prange(n_chunks):
        lo = ch * n // n_chunks
        hi = (ch + 1) * n // n_chunks
        acc_sa = np.zeros(max(na, 1))
        acc_sb = np.zeros(max(nb_, 1))
        cpa = np.empty(ka_max + 1)
        spa = np.empty(ka_max + 1)
        cpb = np.empty(kb_max + 1)
        spb = np.empty(kb_max + 1)
        for i in range(lo, hi):
            w = wk[i]
            if not w > 0.0:
                for p in range(npar):
                    rows[i, p] = 0.0
                target[i] = 0.0
                continue
            root = math.sqrt(w)
            ga = gain_a[i]
            gb = gain_b[i]
            _powers(est_a[i], da, ka_max, cpa, spa)
            _powers(est_b[i], db, kb_max, cpb, spb)
            sa2 = sig_a[i] * sig_a[i]
            sb2 = sig_b[i] * sig_b[i]
            curv_a = _damped_curv(cpa, spa, da, ka_max, cfix_a, sfix_a, s2 * sa2 * ga * ga)
            curv_b = _damped_curv(cpb, spb, db, kb_max, cfix_b, sfix_b, s2 * sb2 * gb * gb)
            mean_bias = 0.5 * s2 * (r * sa2 * -(ga * ga * ga) * curv_a
                                    - sb2 * -(gb * gb * gb) * curv_b)
            target[i] = -(res[i] - mean_bias) * root
            sc_a = -r * ga * root
            for j in range(harm_a.size):
                k = harm_a[j] // da
                rows[i, 2 * j] = sc_a * cpa[k]
                rows[i, 2 * j + 1] = sc_a * spa[k]
            sc_b = gb * root
            for j in range(harm_b.size):
                k = harm_b[j] // db
                rows[i, na + 2 * j] = sc_b * cpb[k]
                rows[i, na + 2 * j + 1] = sc_b * spb[k]
            # Stein's lemma sums (dgain = -gain^2 curv)
            fa = w * r * r * sa2 * ga * ga
            wd = fa * -(ga * ga) * curv_a
            wg = fa * ga
            for j in range(harm_a.size):
                if sel_a[j]:
                    k = harm_a[j] // da
                    mk = harm_a[j]
                    acc_sa[2 * j] += wd * cpa[k] - wg * mk * spa[k]
                    acc_sa[2 * j + 1] += wd * spa[k] + wg * mk * cpa[k]
            fb = w * sb2 * gb * gb
            wd = fb * -(gb * gb) * curv_b
            wg = fb * gb
            for j in range(harm_b.size):
                if sel_b[j]:
                    k = harm_b[j] // db
                    mk = harm_b[j]
                    acc_sb[2 * j] += wd * cpb[k] - wg * mk * spb[k]
                    acc_sb[2 * j + 1] += wd * spb[k] + wg * mk * cpb[k]
        p_sa[ch] = acc_sa
        p_sb[ch] = acc_sb
    for j in range(na):
        t = 0.0
        for ch in range(n_chunks):
            t += p_sa[ch, j]
        stein_a[j] = t
    for j in range(nb_):
        t = 0.0
        for ch in range(n_chunks):
            t += p_sb[ch, j]
        stein_b[j] = t
