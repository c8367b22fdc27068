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
@nb.njit(cache=True, nogil=True)
def _newton(x, phi, warm, d, ca, sa, k2):
    """:func:`invert_harmonic`'s iteration for one sample (same steps, same stopping):
    the true phase solving ``phi + e(phi) = x`` from ``phi`` (``warm``) or from
    ``x - e(x)``; returns (phi, ok) with ok False when ``1 + e' <= 0`` was met."""
    for it in range(62):
        e, de = _series(phi, d, ca, sa)
        if it == 0 and not warm:
            phi = x - e
            continue
        slope = 1.0 + de
        if slope <= 0.0:
            return phi, False
        step = (phi + e - x) / slope
        phi = phi - step
        lower = slope - k2 * abs(step)
        if abs(step) < 1e-14 or (lower > 0.0 and k2 * step * step < 2e-15 * lower):
            break
    return phi, True


@nb.njit(cache=True, nogil=True, parallel=True)
def ladder_residuals(measured, warm, start, dense_cos, dense_sin, divisor, kmax, sig,
                     pair_a, pair_b, ratio, absolute, ka, kb,
                     unwrapped, est, gain, res, wt, absz, bad):
    """The per-sample part of one Gauss-Newton evaluation of the ladder's phase-error fit
    (``nonlinearity._gauss_newton``), in one pass (one parallel region):

    - per group g: the true phase solving ``phi + e_g(phi) = measured[g]`` by Newton's
      method (:func:`invert_harmonic`'s iteration and stopping; from ``start[g]`` when
      ``warm[g]``, else from ``measured - e(measured)``) into ``unwrapped[g]``; ``est[g] =
      wrap(unwrapped[g])`` in [-pi, pi) (as ``np.mod(x + pi, 2 pi) - pi``) and ``gain[g] =
      1 / (1 + e_g'(est))``; ``bad[g]`` set where ``1 + e_g' <= 0`` was met;
    - per pair p of groups (a, b) = (pair_a[p], pair_b[p]) and ratio r: the residual
      ``res[p] = wrap(r phi_a - phi_b)`` (the absolute phases ``est + 2 pi k`` when
      ``absolute[p]``), its weight ``wt[p] = 1 / ((r sig_a gain_a)^2 + (sig_b gain_b)^2)``
      (0 where that variance is not finite and positive) and ``absz[p] = |res| sqrt(wt)``.

    measured, start, sig, unwrapped, est, gain : (G, n) float64 (rad; gain unitless);
    warm : (G,) bool; dense_cos, dense_sin : (G, K) float64, each group's coefficients on
    the multiples k divisor[g] of its orders' divisor, k = 0..kmax[g] (see
    :func:`_dense_coefficients`; zero-padded); divisor, kmax : (G,) int64; pair_a, pair_b :
    (P,) int64; ratio : (P,) float64; absolute : (P,) bool; ka, kb : (P, n) float64 (orders;
    read only where absolute); res, wt, absz : (P, n) float64; bad : (G,) bool (set, never
    cleared).
    """
    n_groups, n = measured.shape
    k2 = np.zeros(n_groups)
    for g in range(n_groups):
        for k in range(1, kmax[g] + 1):
            k2[g] += (k * divisor[g]) ** 2 * (abs(dense_cos[g, k]) + abs(dense_sin[g, k]))
    n_chunks = 16
    for ch in nb.prange(n_chunks):
        lo = ch * n // n_chunks
        hi = (ch + 1) * n // n_chunks
        for g in range(n_groups):
            d = divisor[g]
            ca = dense_cos[g, :kmax[g] + 1]
            sa = dense_sin[g, :kmax[g] + 1]
            for i in range(lo, hi):
                phi, ok = _newton(measured[g, i], start[g, i] if warm[g] else 0.0, warm[g],
                                  d, ca, sa, k2[g])
                if not ok:
                    bad[g] = True
                unwrapped[g, i] = phi
                w = (phi + math.pi) % TWO_PI - math.pi
                est[g, i] = w
                gain[g, i] = 1.0 / (1.0 + _series(w, d, ca, sa)[1])
        for p in range(pair_a.size):
            a = pair_a[p]
            b = pair_b[p]
            r = ratio[p]
            for i in range(lo, hi):
                if absolute[p]:
                    x = r * (est[a, i] + TWO_PI * ka[p, i]) - (est[b, i] + TWO_PI * kb[p, i])
                else:
                    x = r * est[a, i] - est[b, i]
                x = (x + math.pi) % TWO_PI - math.pi
                res[p, i] = x
                va = r * sig[a, i] * gain[a, i]
                vb = sig[b, i] * gain[b, i]
                var = va * va + vb * vb
                wgt = 1.0 / var if (math.isfinite(var) and var > 0.0) else 0.0
                wt[p, i] = wgt
                absz[p, i] = abs(x) * math.sqrt(wgt)


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


@nb.njit(cache=True, nogil=True)
def _group_stein(w, g, curv, cp, sp, harm, nh, sel, d, acc):
    """Add one sample's Stein's-lemma terms of one group (see :func:`stein_sums`; weight
    ``w``, gain ``g``, dgain = -g^2 curv) to ``acc`` (2 per order, cos/sin)."""
    wd = w * -(g * g) * curv
    wg = w * g
    for j in range(nh):
        if sel[j]:
            k = harm[j] // d
            mk = harm[j]
            acc[2 * j] += wd * cp[k] - wg * mk * sp[k]
            acc[2 * j + 1] += wd * sp[k] + wg * mk * cp[k]


@nb.njit(cache=True, nogil=True, parallel=True)
def ladder_normal_equations(est, gain, sig, pair_a, pair_b, ratio, res, wk, s2, harm,
                            nharm, sel, fix_cos, fix_sin, divisor, kmax, ata, atb, stein,
                            with_gram):
    """Every pair's normal equations of an errors-in-variables Gauss-Newton step in one
    pass (one parallel region; what ``nonlinearity._gauss_newton`` does), over the samples
    with weight ``wk > 0``. For pair p of groups (a, b) and ratio r:

    - per group g of the pair: ``tau2 = s2 (sig_g gain_g)^2`` and the damped curvature
      ``curv_g`` (:func:`damped_curvature` of the dense coefficients ``fix_cos[g]``,
      ``fix_sin[g]`` of the harmonics whose bias is corrected, zero elsewhere);
    - the target ``-(res - mean_bias)``, ``mean_bias = s2 / 2 (r sig_a^2 (-gain_a^3
      curv_a) - sig_b^2 (-gain_b^3 curv_b))``;
    - the rows ``J = [-r gain_a h_a(est_a), gain_b h_b(est_b)]`` (h: cos and sin of each
      order of ``harm[g][:nharm[g]]``): ``ata[p] = sum wk J^T J`` and ``atb[p] = sum wk
      J^T target`` (the first 2 (nharm[a] + nharm[b]) rows and columns; zero beyond);
    - Stein's sums (:func:`stein_sums`) of the orders with ``sel`` set, weights ``wk r^2
      (sig_a gain_a)^2`` and ``wk (sig_b gain_b)^2``, into ``stein[p, 0]`` (group a) and
      ``stein[p, 1]`` (group b), 2 per order (cos/sin; 0 for orders not selected).

    est, gain, sig : (G, n) float64; pair_a, pair_b : (P,) int64; ratio : (P,) float64;
    res, wk : (P, n) float64; s2 : float; harm : (G, H) int64 sorted orders, nharm : (G,)
    int64 how many; sel : (G, H) bool; fix_cos, fix_sin : (G, K) float64 on the multiples
    of divisor[g], k = 0..kmax[g]; divisor, kmax : (G,) int64; ata : (P, W, W) float64,
    W >= 2 (nharm[a] + nharm[b]); atb : (P, W); stein : (P, 2, 2 H). Outputs are
    overwritten. Sums are taken in a fixed number of chunks (deterministic whatever the
    thread count). ``with_gram`` False leaves out ``ata`` (set to zero; the costly part,
    O(W^2) per sample): ``atb`` and ``stein`` are the same, bit for bit (same sums in the
    same order).
    """
    n_pairs = pair_a.size
    n = est.shape[1]
    width = ata.shape[2]
    h2 = stein.shape[2]
    kk = fix_cos.shape[1]
    n_chunks = 16
    part = np.zeros((n_chunks, n_pairs, 2, h2))
    part_ata = np.zeros((n_chunks, n_pairs, width, width))
    part_atb = np.zeros((n_chunks, n_pairs, width))
    for ch in nb.prange(n_chunks):
        lo = ch * n // n_chunks
        hi = (ch + 1) * n // n_chunks
        acc = np.zeros((n_pairs, 2, h2))
        gram = np.zeros((n_pairs, width, width))
        rhs = np.zeros((n_pairs, width))
        row = np.zeros(width)
        cpa = np.empty(kk)
        spa = np.empty(kk)
        cpb = np.empty(kk)
        spb = np.empty(kk)
        for p in range(n_pairs):
            a = pair_a[p]
            b = pair_b[p]
            r = ratio[p]
            da = divisor[a]
            db = divisor[b]
            nha = nharm[a]
            nhb = nharm[b]
            na = 2 * nha
            ca_fix = fix_cos[a, :kmax[a] + 1]
            sa_fix = fix_sin[a, :kmax[a] + 1]
            cb_fix = fix_cos[b, :kmax[b] + 1]
            sb_fix = fix_sin[b, :kmax[b] + 1]
            npar = na + 2 * nhb
            gp = gram[p]
            rp = rhs[p]
            for i in range(lo, hi):
                w = wk[p, i]
                if not w > 0.0:
                    continue
                ga = gain[a, i]
                gb = gain[b, i]
                _powers(est[a, i], da, kmax[a], cpa, spa)
                _powers(est[b, i], db, kmax[b], cpb, spb)
                sa2 = sig[a, i] * sig[a, i]
                sb2 = sig[b, i] * sig[b, i]
                curv_a = _damped_curv(cpa, spa, da, kmax[a], ca_fix, sa_fix,
                                      s2 * sa2 * ga * ga)
                curv_b = _damped_curv(cpb, spb, db, kmax[b], cb_fix, sb_fix,
                                      s2 * sb2 * gb * gb)
                mean_bias = 0.5 * s2 * (r * sa2 * -(ga * ga * ga) * curv_a
                                        - sb2 * -(gb * gb * gb) * curv_b)
                tgt = -(res[p, i] - mean_bias)
                sc_a = -r * ga
                for j in range(nha):
                    k = harm[a, j] // da
                    row[2 * j] = sc_a * cpa[k]
                    row[2 * j + 1] = sc_a * spa[k]
                for j in range(nhb):
                    k = harm[b, j] // db
                    row[na + 2 * j] = gb * cpb[k]
                    row[na + 2 * j + 1] = gb * spb[k]
                for u in range(npar):
                    wu = w * row[u]
                    rp[u] += wu * tgt
                    if with_gram:
                        gu = gp[u]
                        for v in range(u, npar):
                            gu[v] += wu * row[v]
                _group_stein(w * r * r * sa2 * ga * ga, ga, curv_a, cpa, spa, harm[a], nha,
                             sel[a], da, acc[p, 0])
                _group_stein(w * sb2 * gb * gb, gb, curv_b, cpb, spb, harm[b], nhb, sel[b],
                             db, acc[p, 1])
        part[ch] = acc
        part_ata[ch] = gram
        part_atb[ch] = rhs
    for p in range(n_pairs):
        for u in range(width):
            t = 0.0
            for ch in range(n_chunks):
                t += part_atb[ch, p, u]
            atb[p, u] = t
            for v in range(u, width):
                t = 0.0
                for ch in range(n_chunks):
                    t += part_ata[ch, p, u, v]
                ata[p, u, v] = t
                ata[p, v, u] = t
        for s in range(2):
            for j in range(h2):
                t = 0.0
                for ch in range(n_chunks):
                    t += part[ch, p, s, j]
                stein[p, s, j] = t


@nb.njit(cache=True, nogil=True)
def slope_serial(phase, harmonics, cos_coef, sin_coef, out):
    """``out[i] = e'(phase[i])`` of the series of :func:`harmonic_sum`, on one thread (for
    the short grids of the invertibility check, where a parallel region costs more than
    the work). phase, out : (n,) float64, rad and unitless."""
    d, ca, sa = _dense_coefficients(harmonics, cos_coef, sin_coef)
    for i in range(phase.size):
        out[i] = _series(phase[i], d, ca, sa)[1]


@nb.njit(cache=True, nogil=True)
def harmonic_normal_equations(phase, target, harmonics, ata, atb):
    """Normal equations of the unweighted least-squares fit of ``target`` by the harmonics
    ``cos, sin(m phase)`` (interleaved per order m of ``harmonics``), on one thread (a
    small fit: no parallel region, no BLAS threads): ``ata = H^T H``, ``atb = H^T target``.

    phase, target : (n,) float64 (rad); harmonics : (k,) int64 sorted orders >= 1; ata :
    (2 k, 2 k), atb : (2 k,) float64, overwritten.
    """
    nh = harmonics.size
    d = _gcd(harmonics)
    kmax = 0
    for j in range(nh):
        kmax = max(kmax, harmonics[j] // d)
    npar = 2 * nh
    cp = np.empty(kmax + 1)
    sp = np.empty(kmax + 1)
    row = np.empty(npar)
    ata[:, :] = 0.0
    atb[:] = 0.0
    for i in range(phase.size):
        _powers(phase[i], d, kmax, cp, sp)
        for j in range(nh):
            row[2 * j] = cp[harmonics[j] // d]
            row[2 * j + 1] = sp[harmonics[j] // d]
        y = target[i]
        for u in range(npar):
            atb[u] += row[u] * y
            for v in range(u, npar):
                ata[u, v] += row[u] * row[v]
    for u in range(npar):
        for v in range(u):
            ata[u, v] = ata[v, u]
