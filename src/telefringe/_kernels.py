"""Numba kernels of the decoder (private). No fastmath anywhere; ``cache=True``."""

from __future__ import annotations

import math

import numba as nb
import numpy as np

TWO_PI = 2.0 * math.pi
INV_TWO_PI = 1.0 / TWO_PI


@nb.njit(cache=True, nogil=True)
def harmonic_sum(phase, harmonics, cos_coef, sin_coef, out):
    """out[i] = sum_m cos_coef[m] cos(h_m phase[i]) + sin_coef[m] sin(h_m phase[i]).

    ``phase`` and ``out`` are 1-D float64; harmonics int64 (n,), any orders >= 1. The
    powers of exp(i phase) come from a complex recurrence (error ~ order * 1e-16).
    """
    n = phase.size
    hmax = 0
    for m in range(harmonics.size):
        if harmonics[m] > hmax:
            hmax = harmonics[m]
    ca = np.zeros(hmax + 1)
    sa = np.zeros(hmax + 1)
    for m in range(harmonics.size):
        ca[harmonics[m]] += cos_coef[m]
        sa[harmonics[m]] += sin_coef[m]
    for i in range(n):
        c1 = math.cos(phase[i])
        s1 = math.sin(phase[i])
        c = 1.0
        s = 0.0
        acc = 0.0
        for h in range(1, hmax + 1):
            c, s = c * c1 - s * s1, s * c1 + c * s1
            acc += ca[h] * c + sa[h] * s
        out[i] = acc


@nb.njit(cache=True, nogil=True)
def _features(phase, harmonics, scale, out, start):
    c1 = math.cos(phase)
    s1 = math.sin(phase)
    c = 1.0
    s = 0.0
    h = 0
    j = 0
    for m in range(harmonics.size):
        target = harmonics[m]
        while h < target:
            c, s = c * c1 - s * s1, s * c1 + c * s1
            h += 1
        out[start + 2 * j] = scale * c
        out[start + 2 * j + 1] = scale * s
        j += 1


@nb.njit(cache=True, nogil=True)
def pair_normal_equations(phase_a, phase_b, scale_a, scale_b, harm_a, harm_b, off_a, off_b,
                          target, weight, ata, atb):
    """Accumulate weighted normal equations ``ata += J^T W J``, ``atb += J^T W target`` for
    rows ``J = [scale_a h_a(phase_a), scale_b h_b(phase_b)]``, h the (cos, sin) harmonics
    (sorted orders) placed at parameter offsets off_a, off_b. Per-sample scales and
    weights; samples with weight <= 0 are skipped.
    """
    na = 2 * harm_a.size
    nbb = 2 * harm_b.size
    nf = na + nbb
    f = np.empty(nf)
    loc = np.zeros((nf, nf))
    locb = np.zeros(nf)
    for i in range(phase_a.size):
        w = weight[i]
        if w <= 0.0:
            continue
        _features(phase_a[i], harm_a, scale_a[i], f, 0)
        _features(phase_b[i], harm_b, scale_b[i], f, na)
        t = target[i]
        for p in range(nf):
            fp = f[p] * w
            locb[p] += fp * t
            for q in range(p, nf):
                loc[p, q] += fp * f[q]
    for p in range(nf):
        ip = off_a + p if p < na else off_b + p - na
        atb[ip] += locb[p]
        for q in range(p, nf):
            iq = off_a + q if q < na else off_b + q - na
            ata[ip, iq] += loc[p, q]
            if iq != ip:
                ata[iq, ip] += loc[p, q]


@nb.njit(cache=True, nogil=True)
def table_correct(phase, table, out):
    """out = wrap(phase - g(phase)), g linearly interpolated from ``table`` sampled at
    -pi + 2 pi j / M (periodic). 1-D float64 arrays; result in (-pi, pi]."""
    m = table.size
    scale = m / TWO_PI
    for i in range(phase.size):
        p = phase[i]
        t = (p + math.pi) * scale
        j = int(math.floor(t))
        f = t - j
        j0 = j % m
        j1 = (j0 + 1) % m
        g = table[j0] * (1.0 - f) + table[j1] * f
        q = p - g
        if q > math.pi:
            q -= TWO_PI
        elif q <= -math.pi:
            q += TWO_PI
        out[i] = q


# ------------------------------------------------------------------- fused fast decoding
#: atan(a) = a P(a^2) on [0, 1]: Chebyshev least-squares fit of degree 10 in a^2, power
#: basis. Largest error 1.3e-9 rad (tests/test_decode_fast.py checks <= 1e-6 densely).
ATAN_COEF = (0.9999999997078739, -0.3333332567970671, 0.1999966704637836,
             -0.1428001870079002, 0.1106046634753856, -0.08822430509150758,
             0.06772961148703784, -0.04519965252518872, 0.023025548295370343,
             -0.007569207294537762, 0.0011682799386918791)
_A0, _A1, _A2, _A3, _A4, _A5, _A6, _A7, _A8, _A9, _A10 = ATAN_COEF
_HALF_PI = 0.5 * math.pi


@nb.njit(inline="always", error_model="numpy")
def atan2_poly(y, x):
    """atan2(y, x) in (-pi, pi] from a polynomial arctangent (branch-free)."""
    ax = abs(x)
    ay = abs(y)
    mx = max(ax, ay)
    mn = min(ax, ay)
    a = mn / mx if mx > 0.0 else 0.0
    s = a * a
    p = _A10
    p = p * s + _A9
    p = p * s + _A8
    p = p * s + _A7
    p = p * s + _A6
    p = p * s + _A5
    p = p * s + _A4
    p = p * s + _A3
    p = p * s + _A2
    p = p * s + _A1
    p = p * s + _A0
    r = a * p
    r = _HALF_PI - r if ay > ax else r
    r = math.pi - r if x < 0.0 else r
    r = -r if y < 0.0 else r
    return math.pi if r <= -math.pi else r


_F32 = np.float32
_B0, _B1, _B2, _B3, _B4, _B5, _B6, _B7, _B8, _B9, _B10 = (np.float32(c) for c in ATAN_COEF)
_HALF_PI32 = np.float32(0.5 * math.pi)
_PI32 = np.float32(math.pi)
_ZERO32 = np.float32(0.0)


@nb.njit(inline="always", error_model="numpy")
def atan2_poly32(y, x):
    """float32 :func:`atan2_poly` (for exact float32 inputs; error <= 1e-6 rad, tested)."""
    ax = abs(x)
    ay = abs(y)
    mx = max(ax, ay)
    mn = min(ax, ay)
    a = mn / mx if mx > _ZERO32 else _ZERO32
    s = a * a
    p = _B10
    p = p * s + _B9
    p = p * s + _B8
    p = p * s + _B7
    p = p * s + _B6
    p = p * s + _B5
    p = p * s + _B4
    p = p * s + _B3
    p = p * s + _B2
    p = p * s + _B1
    p = p * s + _B0
    r = a * p
    r = _HALF_PI32 - r if ay > ax else r
    r = _PI32 - r if x < _ZERO32 else r
    r = -r if y < _ZERO32 else r
    return _PI32 if r <= -_PI32 else r


@nb.njit(cache=True, error_model="numpy")
def atan2_poly32_array(y, x, out):
    """Vectorised :func:`atan2_poly32` over 1-D float32 arrays (for tests)."""
    for i in range(y.size):
        out[i] = atan2_poly32(y[i], x[i])


@nb.njit(cache=True, error_model="numpy")
def atan2_poly_array(y, x, out):
    """Vectorised :func:`atan2_poly` over 1-D arrays (for tests)."""
    for i in range(y.size):
        out[i] = atan2_poly(y[i], x[i])


@nb.njit(inline="always")
def _accumulate4(row0, row1, row2, row3, a0, a1, a2, a3, b0, b1, b2, b3, j0, j1, s_acc,
                 c_acc, top):
    """Add 4 steps' weighted samples of columns j0..j1 to the sums (vectorised over j)."""
    for j in range(j0, j1):
        v0 = float(row0[j])
        v1 = float(row1[j])
        v2 = float(row2[j])
        v3 = float(row3[j])
        s_acc[j - j0] += (a0 * v0 + a1 * v1) + (a2 * v2 + a3 * v3)
        c_acc[j - j0] += (b0 * v0 + b1 * v1) + (b2 * v2 + b3 * v3)
        top[j - j0] = max(top[j - j0], max(max(v0, v1), max(v2, v3)))


@nb.njit(inline="always")
def _accumulate4_32(row0, row1, row2, row3, a0, a1, a2, a3, b0, b1, b2, b3, j0, j1, s_acc,
                    c_acc, top):
    """float32 :func:`_accumulate4` (exact when the weights are 0 or +-1)."""
    for j in range(j0, j1):
        v0 = _F32(row0[j])
        v1 = _F32(row1[j])
        v2 = _F32(row2[j])
        v3 = _F32(row3[j])
        s_acc[j - j0] += (a0 * v0 + a1 * v1) + (a2 * v2 + a3 * v3)
        c_acc[j - j0] += (b0 * v0 + b1 * v1) + (b2 * v2 + b3 * v3)
        top[j - j0] = max(top[j - j0], max(max(v0, v1), max(v2, v3)))


@nb.njit(inline="always", error_model="numpy")
def _phase32(s_acc, c_acc, m2, ph, nj):
    for j in range(nj):
        s = s_acc[j]
        c = c_acc[j]
        m2[j] = s * s + c * c
        ph[j] = atan2_poly32(-s, c)


@nb.njit(inline="always", error_model="numpy")
def _widen(src32, dst64, nj):
    for j in range(nj):
        dst64[j] = float(src32[j])


@nb.njit(inline="always", error_model="numpy")
def _unit_phase(ph, phi_abs, cut, nj):
    for j in range(nj):
        q = ph[j] + cut
        phi_abs[j] = q - TWO_PI * np.floor(q * INV_TWO_PI) - cut


@nb.njit(inline="always", error_model="numpy")
def _unwrap_step(ph, phi_abs, ratio, max_res, res_ok, nj):
    for j in range(nj):
        pred = phi_abs[j] * ratio
        full = ph[j] + TWO_PI * np.floor((pred - ph[j]) * INV_TWO_PI + 0.5)
        phi_abs[j] = full
        res_ok[j] = abs(pred - full) <= max_res


@nb.njit(inline="always", error_model="numpy")
def _mask_first(m2, top, thr, max_value, ok, nj):
    for j in range(nj):
        ok[j] = (m2[j] >= thr) & (top[j] < max_value)


@nb.njit(inline="always", error_model="numpy")
def _mask_next(m2, top, res_ok, thr, max_value, ok, nj):
    for j in range(nj):
        ok[j] = ok[j] & res_ok[j] & (m2[j] >= thr) & (top[j] < max_value)


@nb.njit(inline="always", error_model="numpy")
def _weigh_first(phi_abs, m2, wscale, xscale, num, den, nj):
    for j in range(nj):
        w = wscale * m2[j]
        num[j] = w * (phi_abs[j] * xscale)
        den[j] = w


@nb.njit(inline="always", error_model="numpy")
def _weigh_next(phi_abs, m2, wscale, xscale, num, den, nj):
    for j in range(nj):
        w = wscale * m2[j]
        num[j] += w * (phi_abs[j] * xscale)
        den[j] += w


@nb.njit(parallel=True, cache=True, error_model="numpy")
def fused_hierarchical(stacks, cw, sw, cw32, sw32, exact32, nsteps, periods, length, tables,
                       has_table, max_value, min_mod2, max_res, block_rows, out_u, out_mask,
                       out_mod):
    """One pass over the images of a hierarchical ladder (coarse to fine, first group one
    period): per pixel the N-step sums of every group, the phase (polynomial atan2),
    optional nonlinearity correction (table), hierarchical unwrapping with the residual
    check, inverse-variance combination (weights (p B)^2: equal sigma_I per pixel), the
    modulation of the finest group, saturation and low-modulation masks.

    Works on tiles of TILE columns of one row so the running sums stay in L1; the steps
    are summed four at a time (cw/sw padded with zero weights to a multiple of 4).

    stacks : tuple of (N_l, rows, cols) uint8/uint16 arrays, one per group.
    cw, sw : (L, Nmax4) cos / sin weights (zero-padded).  nsteps, periods : (L,).
    cw32, sw32 : the same in float32; exact32 : (L,) bool, the group's weights are all
    0 or +-1 and its samples integers below 2^16, so float32 sums are exact.
    tables : (L, M) correction tables (see telefringe.gamma), has_table : (L,) bool.
    min_mod2 : (L,) thresholds on S^2 + C^2.  out_* : (rows, cols) outputs.
    """
    tile = 256
    n_lev = nsteps.size
    rows = out_u.shape[0]
    cols = out_u.shape[1]
    m_tab = tables.shape[1]
    tab_scale = m_tab / TWO_PI
    cut = math.pi / length
    n_blocks = (rows + block_rows - 1) // block_rows
    for blk in nb.prange(n_blocks):
        s_acc = np.empty(tile)
        c_acc = np.empty(tile)
        top = np.empty(tile)
        phi_abs = np.empty(tile)
        num = np.empty(tile)
        den = np.empty(tile)
        ok = np.empty(tile, dtype=np.bool_)
        m2 = np.empty(tile)
        ph = np.empty(tile)
        res_ok = np.empty(tile, dtype=np.bool_)
        s32 = np.empty(tile, dtype=np.float32)
        c32 = np.empty(tile, dtype=np.float32)
        top32 = np.empty(tile, dtype=np.float32)
        m232 = np.empty(tile, dtype=np.float32)
        ph32 = np.empty(tile, dtype=np.float32)
        r0 = blk * block_rows
        r1 = min(rows, r0 + block_rows)
        for r in range(r0, r1):
            for j0 in range(0, cols, tile):
                j1 = min(cols, j0 + tile)
                nj = j1 - j0
                for lev in range(n_lev):
                    st = stacks[lev]
                    n_k = nsteps[lev]
                    if exact32[lev]:
                        # integer sums: exact in float32 (weights 0/+-1, |S| < 2^24), so
                        # the phase can use 8-lane float32 arithmetic
                        for j in range(nj):
                            s32[j] = 0.0
                            c32[j] = 0.0
                            top32[j] = 0.0
                        for k in range(0, n_k, 4):
                            k1 = min(k + 1, n_k - 1)
                            k2 = min(k + 2, n_k - 1)
                            k3 = min(k + 3, n_k - 1)
                            _accumulate4_32(st[k, r], st[k1, r], st[k2, r], st[k3, r],
                                            sw32[lev, k], sw32[lev, k + 1], sw32[lev, k + 2],
                                            sw32[lev, k + 3], cw32[lev, k], cw32[lev, k + 1],
                                            cw32[lev, k + 2], cw32[lev, k + 3], j0, j1, s32,
                                            c32, top32)
                        _phase32(s32, c32, m232, ph32, nj)
                        _widen(ph32, ph, nj)
                        _widen(m232, m2, nj)
                        _widen(top32, top, nj)
                    else:
                        for j in range(nj):
                            s_acc[j] = 0.0
                            c_acc[j] = 0.0
                            top[j] = 0.0
                        for k in range(0, n_k, 4):
                            k1 = min(k + 1, n_k - 1)
                            k2 = min(k + 2, n_k - 1)
                            k3 = min(k + 3, n_k - 1)
                            _accumulate4(st[k, r], st[k1, r], st[k2, r], st[k3, r],
                                         sw[lev, k], sw[lev, k + 1], sw[lev, k + 2],
                                         sw[lev, k + 3], cw[lev, k], cw[lev, k + 1],
                                         cw[lev, k + 2], cw[lev, k + 3], j0, j1, s_acc, c_acc,
                                         top)
                        for j in range(nj):  # phase and squared modulation (vectorised)
                            s = s_acc[j]
                            c = c_acc[j]
                            m2[j] = s * s + c * c
                            ph[j] = atan2_poly(-s, c)
                    p = periods[lev]
                    inv_n = 2.0 / n_k
                    wscale = p * p * inv_n * inv_n
                    xscale = length / (TWO_PI * p)
                    ratio = p / periods[lev - 1] if lev > 0 else 1.0
                    thr = min_mod2[lev]
                    use_tab = has_table[lev]
                    last = lev == n_lev - 1
                    if use_tab:  # nonlinearity correction: table look-up (gather)
                        for j in range(nj):
                            t = (ph[j] + math.pi) * tab_scale
                            i0 = int(t)
                            f = t - i0
                            i0 = min(max(i0, 0), m_tab - 1)
                            i1 = i0 + 1 if i0 + 1 < m_tab else 0
                            q = ph[j] - (tables[lev, i0] * (1.0 - f) + tables[lev, i1] * f)
                            q = q - TWO_PI if q > math.pi else q
                            ph[j] = q + TWO_PI if q <= -math.pi else q
                    # (short loops over few arrays: each one vectorises)
                    if lev == 0:
                        _unit_phase(ph, phi_abs, cut, nj)
                        _mask_first(m2, top, thr, max_value, ok, nj)
                        _weigh_first(phi_abs, m2, wscale, xscale, num, den, nj)
                    else:
                        _unwrap_step(ph, phi_abs, ratio, max_res, res_ok, nj)
                        _mask_next(m2, top, res_ok, thr, max_value, ok, nj)
                        _weigh_next(phi_abs, m2, wscale, xscale, num, den, nj)
                    if last:
                        for j in range(nj):
                            out_mod[r, j0 + j] = inv_n * math.sqrt(m2[j])
                for j in range(nj):
                    x = num[j] / den[j]
                    valid = ok[j] & (x >= -0.5) & (x <= length - 0.5)
                    out_u[r, j0 + j] = x if valid else np.nan
                    out_mask[r, j0 + j] = valid


@nb.njit(parallel=True, cache=True)
def read_floor(stack):
    """Sum of all samples of a (n, rows, cols) integer stack, read once (parallel over
    rows): the benchmark's memory floor."""
    total = 0
    for r in nb.prange(stack.shape[1]):
        acc = 0
        for k in range(stack.shape[0]):
            row = stack[k, r]
            for j in range(row.size):
                acc += row[j]
        total += acc
    return total


@nb.njit(cache=True, nogil=True, parallel=True)
def invert_harmonic(measured, harmonics, cos_coef, sin_coef, out):
    """Solve ``phi + e(phi) = measured`` per sample by Newton's method, where
    ``e(phi) = sum_m cos_coef[m] cos(h_m phi) + sin_coef[m] sin(h_m phi)``.

    ``measured`` and ``out`` are 1-D float64. Each sample starts at
    ``measured - e(measured)`` and stops when its step is below 1e-14 rad (at most 60
    steps). Returns False when ``1 + e'(phi) <= 0`` is met (the model is not invertible
    there), True otherwise.
    """
    n = measured.size
    hmax = 0
    for m in range(harmonics.size):
        if harmonics[m] > hmax:
            hmax = harmonics[m]
    ca = np.zeros(hmax + 1)
    sa = np.zeros(hmax + 1)
    for m in range(harmonics.size):
        ca[harmonics[m]] += cos_coef[m]
        sa[harmonics[m]] += sin_coef[m]
    bad = np.zeros(n, dtype=np.bool_)
    for i in nb.prange(n):
        x = measured[i]
        phi = x
        for it in range(61):
            c1 = math.cos(phi)
            s1 = math.sin(phi)
            c = 1.0
            s = 0.0
            e = 0.0
            de = 0.0
            for h in range(1, hmax + 1):
                c, s = c * c1 - s * s1, s * c1 + c * s1
                e += ca[h] * c + sa[h] * s
                de += h * (sa[h] * c - ca[h] * s)
            if it == 0:
                phi = x - e  # the start, as e is evaluated at the measured phase
                continue
            d = 1.0 + de
            if d <= 0.0:
                bad[i] = True
                break
            step = (phi + e - x) / d
            phi = phi - step
            if abs(step) < 1e-14:
                break
        out[i] = phi
    for i in range(n):
        if bad[i]:
            return False
    return True
