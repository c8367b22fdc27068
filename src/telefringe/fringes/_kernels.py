"""Numba kernels of the decoder (private; the phase-error model's are in
:mod:`telefringe.fringes._nonlinearity_kernels`). ``cache=True``; no fastmath except FMA
contraction in the fused kernel (bounded by tests)."""

from __future__ import annotations

import math

import numba as nb
import numpy as np

TWO_PI = 2.0 * math.pi
INV_TWO_PI = 1.0 / TWO_PI


# ------------------------------------------------------------------- fused fast decoding
# Written so that LLVM vectorises every inner loop (checked in the assembly, see
# tests/test_decode_fast.py): straight loops over contiguous 1-D scratch rows, float32
# where it is exact or bounded, float32 constants only in float32 maths, selects instead
# of branches, error_model="numpy" (no division checks). No reassociation: the only
# fastmath flag is FMA contraction (one rounding instead of two), where tests bound the
# result against the exact float64 path.
# The helpers are ordinary compiled functions (LLVM inlines them), not numba's IR inlining
# (inline="always"), which copied their IR into the fused kernel at every call site: the
# kernel's compilation fell from 74 to 41 s CPU per input dtype, its output bit for bit the
# same. Only the helpers that take a function argument (``cast``) stay IR-inlined, inside
# the four _acc4* wrappers (a function passed as a value cannot be cached).

#: atan(a) = a P(a^2) on [0, 1]: degree 7 in a^2, near-minimax (iteratively reweighted
#: least squares). Largest error 3.7e-8 rad in exact arithmetic, 1.4e-7 rad evaluated in
#: float32; tests/test_decode_fast.py checks atan2 <= 1e-6 rad (float32 inputs).
ATAN_COEF = (0.9999993354078233, -0.3332986012082683, 0.19946558251138288,
             -0.13908593381142703, 0.09642106969730993, -0.05591112162408767,
             0.02186214122736897, -0.004054346256421718)
_C0, _C1, _C2, _C3, _C4, _C5, _C6, _C7 = (np.float32(c) for c in ATAN_COEF)
_F32 = np.float32
_HALF_PI32 = np.float32(0.5 * math.pi)
_PI32 = np.float32(math.pi)
_TWO_PI32 = np.float32(TWO_PI)
_ZERO32 = np.float32(0.0)
_ONE32 = np.float32(1.0)


@nb.njit(error_model="numpy", fastmath={"contract"})
def atan2_poly32(y, x):
    """atan2(y, x) in (-pi, pi] of float32 y, x by a polynomial (branch-free; the
    atan2(-0.0, x < 0) = -pi case, like every -pi, is returned as pi)."""
    ax = abs(x)
    ay = abs(y)
    swap = ay > ax
    mx = ay if swap else ax
    mn = ax if swap else ay
    a = mn / (mx if mx > _ZERO32 else _ONE32)
    s = a * a
    p = _C7
    p = p * s + _C6
    p = p * s + _C5
    p = p * s + _C4
    p = p * s + _C3
    p = p * s + _C2
    p = p * s + _C1
    p = p * s + _C0
    r = a * p
    r = _HALF_PI32 - r if swap else r
    r = _PI32 - r if x < _ZERO32 else r
    r = -r if y < _ZERO32 else r
    return _PI32 if r <= -_PI32 else r


@nb.njit(cache=True, error_model="numpy", fastmath={"contract"})
def atan2_poly32_array(y, x, out):
    """:func:`atan2_poly32` over 1-D float32 arrays (for tests)."""
    for i in range(y.size):
        out[i] = atan2_poly32(y[i], x[i])


@nb.njit(error_model="numpy", fastmath={"contract"})
def _cell(p, tscale, top):
    """Cell index i (0..top) and float32 fraction of float32 phase p in (-pi32, pi32] on
    the grid -pi + 2 pi j / M (tscale = M / (2 pi), top = M), in float64. p + pi > 0: the
    float32 above -pi32 nearest to it, -pi32 + ulp, is above -pi; p <= pi32 puts t at most
    1.4e-8 M above M (cell M: the table's padding)."""
    t = (float(p) + math.pi) * tscale
    i = np.int64(t)  # t > 0: truncation is the floor
    i = i if i < top else top
    return i, _F32(t - float(i))


@nb.njit(error_model="numpy", fastmath={"contract"})
def _table_correct32(ph, tab, nft, tscale, nj, with_nf, fac):
    """ph = wrap(ph - g(ph)) in place, g linearly interpolated in the float32 table ``tab``
    (M + 2 samples g(-pi + 2 pi j / M), j = 0..M + 1: the last two are the first two, one
    period on); with ``with_nf`` also the noise factor 1 - g'(ph) (the measured phase's)
    interpolated in ``nft`` (same grid) into ``fac``. tscale = M / (2 pi) (float64): the
    cell and its fraction in float64, the interpolation in float32."""
    top = tab.size - 2
    if with_nf:
        for j in range(nj):
            p = ph[j]
            i, f = _cell(p, tscale, top)
            g0 = tab[i]
            n0 = nft[i]
            fac[j] = n0 + f * (nft[i + 1] - n0)
            q = p - (g0 + f * (tab[i + 1] - g0))
            q = q - _TWO_PI32 if q > _PI32 else q
            ph[j] = q + _TWO_PI32 if q <= -_PI32 else q
    else:
        for j in range(nj):
            p = ph[j]
            i, f = _cell(p, tscale, top)
            g0 = tab[i]
            q = p - (g0 + f * (tab[i + 1] - g0))
            q = q - _TWO_PI32 if q > _PI32 else q
            ph[j] = q + _TWO_PI32 if q <= -_PI32 else q


@nb.njit(cache=True, error_model="numpy", fastmath={"contract"})
def table_correct32_array(phase, table, nf_table, out, fac):
    """The fused kernel's table correction over 1-D float32 arrays (for tests): out =
    wrap(phase - g(phase)) and fac = the noise factor, from the padded float32 tables
    ``table``, ``nf_table`` (M + 2 samples, see :func:`_table_correct32`)."""
    out[:] = phase
    _table_correct32(out, table, nf_table, (table.size - 2) / TWO_PI, out.size, True, fac)


#: the kernel's coefficient rows of the correction's series are zero-padded to a multiple of
#: this (:func:`_series_correct32` sums them 8, or in its first pass 4, at a time)
SERIES_BLOCK = 4


@nb.njit(error_model="numpy", fastmath={"contract"})
def _clenshaw8(x2, k, b1, b2):
    """Eight steps of Clenshaw's recurrence b_t = k_t + x2 b_{t+1} - b_{t+2} (coefficients
    k[7], k[6], ..., k[0] in that order) from b_{t+1} = b1, b_{t+2} = b2; returns the last
    two. Evaluated as x2 b_{t+1} + (k_t - b_{t+2}): the subtraction does not wait for
    b_{t+1}, so each step adds one multiply-add's latency to the chain, not two
    operations'."""
    b2 = x2 * b1 + (k[7] - b2)
    b1 = x2 * b2 + (k[6] - b1)
    b2 = x2 * b1 + (k[5] - b2)
    b1 = x2 * b2 + (k[4] - b1)
    b2 = x2 * b1 + (k[3] - b2)
    b1 = x2 * b2 + (k[2] - b1)
    b2 = x2 * b1 + (k[1] - b2)
    b1 = x2 * b2 + (k[0] - b1)
    return b1, b2


@nb.njit(error_model="numpy", fastmath={"contract"})
def _clenshaw4(x2, k, b1, b2):
    """:func:`_clenshaw8` with four coefficients k[3], ..., k[0]."""
    b2 = x2 * b1 + (k[3] - b2)
    b1 = x2 * b2 + (k[2] - b1)
    b2 = x2 * b1 + (k[1] - b2)
    b1 = x2 * b2 + (k[0] - b1)
    return b1, b2


@nb.njit(error_model="numpy", fastmath={"contract"})
def _coef4(a, t):
    return (a[t], a[t + 1], a[t + 2], a[t + 3])


@nb.njit(error_model="numpy", fastmath={"contract"})
def _coef8(a, t):
    return (a[t], a[t + 1], a[t + 2], a[t + 3], a[t + 4], a[t + 5], a[t + 6], a[t + 7])


@nb.njit(error_model="numpy", fastmath={"contract"})
def _wrap32(q):
    q = q - _TWO_PI32 if q > _PI32 else q
    return q + _TWO_PI32 if q <= -_PI32 else q


@nb.njit(error_model="numpy", fastmath={"contract"})
def _series_angles32(s, c, m2, d, sc, nj):
    """cos(d phi), sin(d phi) of the measured phase into sc[0], sc[1] (float32), from the
    sums: exp(i phi) = (C - i S) / R, then its d-th power (in one pass up to d = 4, then
    multiplied in). 0 where S = C = 0. Uses sc[2], sc[3] as scratch. For d = 2 and 4 (the
    4-step ladders' gamma: harmonics of 4 phi) without the square root: exp(2 i phi) =
    (C - i S)^2 / R^2, one division."""
    x = sc[0]
    y = sc[1]
    zr = sc[2]
    zi = sc[3]
    if d == 2 or d == 4:
        m_two = _F32(-2.0)
        for j in range(nj):
            r2 = m2[j]
            inv = _ONE32 / (r2 if r2 > _ZERO32 else _ONE32)
            inv = inv if r2 > _ZERO32 else _ZERO32
            cj = c[j]
            sj = s[j]
            br = (cj * cj - sj * sj) * inv
            bi = (m_two * cj * sj) * inv
            dr = br * br - bi * bi
            di = br * bi + bi * br
            x[j] = br if d == 2 else dr
            y[j] = bi if d == 2 else di
        return
    for j in range(nj):
        r2 = m2[j]
        inv = _ONE32 / math.sqrt(r2 if r2 > _ZERO32 else _ONE32)
        inv = inv if r2 > _ZERO32 else _ZERO32
        ar = c[j] * inv
        ai = -s[j] * inv
        zr[j] = ar
        zi[j] = ai
        br = ar * ar - ai * ai
        bi = ar * ai + ai * ar
        cr = br * ar - bi * ai
        ci = br * ai + bi * ar
        dr = cr * ar - ci * ai
        di = cr * ai + ci * ar
        xr = ar if d == 1 else (br if d == 2 else (cr if d == 3 else dr))
        xi = ai if d == 1 else (bi if d == 2 else (ci if d == 3 else di))
        x[j] = xr
        y[j] = xi
    for _ in range(d - 4):
        for j in range(nj):
            a = x[j]
            b = y[j]
            x[j] = a * zr[j] - b * zi[j]
            y[j] = a * zi[j] + b * zr[j]


@nb.njit(error_model="numpy", fastmath={"contract"})
def _series_sum32(x, y, ca, cb, n, sc, out, nj):
    """out[j] = sum_{t=1..n} ca[t-1] cos(t theta) + cb[t-1] sin(t theta), float32, from
    x = cos theta, y = sin theta (1-D scratch rows), by Clenshaw's recurrence in x:
    b_t = a_t + 2 x b_{t+1} - b_{t+2} from t = n down to 1, then sum_t a_t cos(t theta) =
    x b_1 - b_2 and, with the sine coefficients' own chain, sum_t b_t sin(t theta) =
    sin(theta) b_1: one multiply-add and one subtraction per term and chain. Eight terms
    per pass over the row (four in the first pass when n is 4 more than a multiple of 8),
    the chains' state in registers within a pass and in sc[2..5] between passes. n is a
    multiple of SERIES_BLOCK, ca and cb hold at least n coefficients; n = 0 gives 0."""
    p1 = sc[2]
    p2 = sc[3]
    q1 = sc[4]
    q2 = sc[5]
    z = _ZERO32
    t = n
    top = True
    while t > 0:
        wide = t % 8 == 0
        t -= 8 if wide else 4
        last = t == 0
        if not wide:
            ka4 = _coef4(ca, t)
            kb4 = _coef4(cb, t)
            if last:  # (n = 4: top and last)
                for j in range(nj):
                    xj = x[j]
                    pa, pb = _clenshaw4(xj + xj, ka4, z, z)
                    qa, _ = _clenshaw4(xj + xj, kb4, z, z)
                    out[j] = (pa * xj - pb) + qa * y[j]
            else:
                for j in range(nj):
                    xj = x[j]
                    p1[j], p2[j] = _clenshaw4(xj + xj, ka4, z, z)
                    q1[j], q2[j] = _clenshaw4(xj + xj, kb4, z, z)
            top = False
            continue
        ka = _coef8(ca, t)
        kb = _coef8(cb, t)
        if top and last:
            for j in range(nj):
                xj = x[j]
                pa, pb = _clenshaw8(xj + xj, ka, z, z)
                qa, _ = _clenshaw8(xj + xj, kb, z, z)
                out[j] = (pa * xj - pb) + qa * y[j]
        elif top:
            for j in range(nj):
                xj = x[j]
                p1[j], p2[j] = _clenshaw8(xj + xj, ka, z, z)
                q1[j], q2[j] = _clenshaw8(xj + xj, kb, z, z)
        elif last:
            for j in range(nj):
                xj = x[j]
                pa, pb = _clenshaw8(xj + xj, ka, p1[j], p2[j])
                qa, _ = _clenshaw8(xj + xj, kb, q1[j], q2[j])
                out[j] = (pa * xj - pb) + qa * y[j]
        else:
            for j in range(nj):
                xj = x[j]
                p1[j], p2[j] = _clenshaw8(xj + xj, ka, p1[j], p2[j])
                q1[j], q2[j] = _clenshaw8(xj + xj, kb, q1[j], q2[j])
        top = False
    if n <= 0:
        for j in range(nj):
            out[j] = _ZERO32


@nb.njit(cache=True, error_model="numpy", fastmath={"contract"})
def _series_correct32(ph, s, c, m2, ca, cb, c0, d, ng, sc, nj, with_nf, da, db, nnf, fac):
    """ph = wrap(ph - g(ph)) in place, g(phi) = c0 + sum_{t=1..ng} ca[t-1] cos(t d phi) +
    cb[t-1] sin(t d phi) (float32), the measured phase's cos(d phi), sin(d phi) from the
    sums (:func:`_series_angles32`) and the series by :func:`_series_sum32`: no table
    look-up and no trigonometric function, the loops vectorise. Where S = C = 0 (no phase)
    g is c0. With ``with_nf``, also the noise factor d(true)/d(measured) = 1 - g'(phi) into
    ``fac`` from the derivative's series, its first ``nnf`` terms: g' = sum_t da[t-1]
    cos(t d phi) + db[t-1] sin(t d phi), da = t d cb, db = -t d ca (set up in
    telefringe.fringes.fast, which chooses ng and nnf, multiples of SERIES_BLOCK, for the
    accuracy asked: see the fused kernel). ``sc`` : (8, >= nj) float32 scratch.

    Accuracy with every term (float32, against the exact inverse;
    tests/test_decode_fast.py): the correction within 4.1e-7 rad (the polynomial
    arctangent's error included), the noise factor within 3.5e-7 relative (2.7e-7 for the
    paper rig's 27 terms: 5.3e-7 when exp(4 i phi) came through a square root)."""
    x = sc[0]
    y = sc[1]
    _series_angles32(s, c, m2, d, sc, nj)
    g = sc[6]
    _series_sum32(x, y, ca, cb, ng, sc, g, nj)
    for j in range(nj):
        ok = m2[j] > _ZERO32
        ph[j] = _wrap32(ph[j] - (c0 + (g[j] if ok else _ZERO32)))
    if with_nf:
        gd = sc[7]
        _series_sum32(x, y, da, db, nnf, sc, gd, nj)
        for j in range(nj):
            ok = m2[j] > _ZERO32
            fac[j] = _ONE32 - gd[j] if ok else _ONE32


@nb.njit(cache=True, error_model="numpy", fastmath={"contract"})
def series_correct32_array(s, c, ca, cb, c0, d, n, out, da=None, db=None, fac=None):
    """The fused kernel's phase and series correction over 1-D float32 sums S, C (for
    tests): out = wrap(atan2(-S, C) - g), g as in :func:`_series_correct32` with every one
    of the n terms of ca, cb (padded here); with da, db (float32, like ca, cb) also the
    noise factor from all of their n terms into ``fac`` (float32, like out)."""
    nj = s.size
    m2 = np.empty(nj, dtype=np.float32)
    _phase32(s, c, out, m2, nj)
    sc = np.empty((8, nj), dtype=np.float32)
    npad = (n + SERIES_BLOCK - 1) // SERIES_BLOCK * SERIES_BLOCK
    pa = np.zeros(npad, dtype=np.float32)
    pb = np.zeros(npad, dtype=np.float32)
    pa[:n] = ca[:n]
    pb[:n] = cb[:n]
    if fac is None:
        _series_correct32(out, s, c, m2, pa, pb, c0, d, npad, sc, nj, False, pa, pb, 0,
                          sc[0])
    else:
        pda = np.zeros(npad, dtype=np.float32)
        pdb = np.zeros(npad, dtype=np.float32)
        pda[:n] = da[:n]
        pdb[:n] = db[:n]
        _series_correct32(out, s, c, m2, pa, pb, c0, d, npad, sc, nj, True, pda, pdb, npad,
                          fac)


@nb.njit(inline="always")
def _as32(v):
    return _F32(v)


@nb.njit(inline="always")
def _as64(v):
    return float(v)


@nb.njit(error_model="numpy", fastmath={"contract"})
def _zero(a, b, c, nj):
    for j in range(nj):
        a[j] = 0
        b[j] = 0
        c[j] = 0


@nb.njit(inline="always")
def _sum4(cast, v0, v1, v2, v3, a0, a1, a2, a3, b0, b1, b2, b3, s, c, top, j):
    """Sample j of 4 steps (v0..v3, input dtype) into the sums s[j], c[j] (weights a, b;
    ``cast`` gives the sums' type) and the running maximum top[j]: the shared body of
    :func:`_acc4` and :func:`_acc4_full`."""
    f0 = cast(v0)
    f1 = cast(v1)
    f2 = cast(v2)
    f3 = cast(v3)
    s[j] += (a0 * f0 + a1 * f1) + (a2 * f2 + a3 * f3)
    c[j] += (b0 * f0 + b1 * f1) + (b2 * f2 + b3 * f3)
    m01 = v0 if v0 > v1 else v1
    m23 = v2 if v2 > v3 else v3
    m = m01 if m01 > m23 else m23
    t = top[j]
    top[j] = m if m > t else t


@nb.njit(inline="always")
def _acc4(cast, r0, r1, r2, r3, a0, a1, a2, a3, b0, b1, b2, b3, nj, s, c, top):
    """Add 4 steps' weighted samples of columns j0..j0+nj to the sums s, c and the running
    maximum ``top`` (input dtype; started at 0, which only serves the saturation test
    ``top < max_value``, max_value > 0, so negative samples change nothing). ``cast``
    (:func:`_as32` or :func:`_as64`) gives the samples the sums' type: float32 where the
    sums are exact (weights 0, +-1/2, +-1 and integer samples), else float64."""
    for j in range(nj):
        v0 = r0[j]
        v1 = r1[j]
        v2 = r2[j]
        v3 = r3[j]
        _sum4(cast, v0, v1, v2, v3, a0, a1, a2, a3, b0, b1, b2, b3, s, c, top, j)


@nb.njit(inline="always")
def _acc4_full(cast, r0, r1, r2, r3, sw, cw, s2w, c2w, ew, mem, k, nj, s, c, top, s2, c2, sa):
    """:func:`_acc4` and, in the same pass over the samples, the full decode's float32 sums
    of the second harmonic (weights p, q) and of the samples (weights e: 1, or 0 for the
    padding steps), step by step in order: ``s2 += p_k v_k``, ``c2 += q_k v_k``, ``sa +=
    e_k v_k`` (float32: the background, exact for integer samples below 2^16 and N <= 256;
    the second-harmonic sums only serve the noise level). The weights of steps k to k + 3
    are row ``mem`` of sw, cw (the sums' type), s2w, c2w, ew (float32). (Fewer than 31
    arguments: Python passes more as *args, which numba cannot inline.)"""
    a0, a1, a2, a3 = sw[mem, k], sw[mem, k + 1], sw[mem, k + 2], sw[mem, k + 3]
    b0, b1, b2, b3 = cw[mem, k], cw[mem, k + 1], cw[mem, k + 2], cw[mem, k + 3]
    p0, p1, p2, p3 = s2w[mem, k], s2w[mem, k + 1], s2w[mem, k + 2], s2w[mem, k + 3]
    q0, q1, q2, q3 = c2w[mem, k], c2w[mem, k + 1], c2w[mem, k + 2], c2w[mem, k + 3]
    e0, e1, e2, e3 = ew[mem, k], ew[mem, k + 1], ew[mem, k + 2], ew[mem, k + 3]
    for j in range(nj):
        v0 = r0[j]
        v1 = r1[j]
        v2 = r2[j]
        v3 = r3[j]
        _sum4(cast, v0, v1, v2, v3, a0, a1, a2, a3, b0, b1, b2, b3, s, c, top, j)
        g0 = _F32(v0)
        g1 = _F32(v1)
        g2 = _F32(v2)
        g3 = _F32(v3)
        x = s2[j]
        x += p0 * g0
        x += p1 * g1
        x += p2 * g2
        x += p3 * g3
        s2[j] = x
        y = c2[j]
        y += q0 * g0
        y += q1 * g1
        y += q2 * g2
        y += q3 * g3
        c2[j] = y
        z = sa[j]
        z += e0 * g0
        z += e1 * g1
        z += e2 * g2
        z += e3 * g3
        sa[j] = z


@nb.njit(error_model="numpy", fastmath={"contract"})
def _acc4_32(r0, r1, r2, r3, a0, a1, a2, a3, b0, b1, b2, b3, nj, s, c, top):
    """:func:`_acc4` with float32 sums."""
    _acc4(_as32, r0, r1, r2, r3, a0, a1, a2, a3, b0, b1, b2, b3, nj, s, c, top)


@nb.njit(error_model="numpy", fastmath={"contract"})
def _acc4_64(r0, r1, r2, r3, a0, a1, a2, a3, b0, b1, b2, b3, nj, s, c, top):
    """:func:`_acc4` with float64 sums."""
    _acc4(_as64, r0, r1, r2, r3, a0, a1, a2, a3, b0, b1, b2, b3, nj, s, c, top)


@nb.njit(error_model="numpy", fastmath={"contract"})
def _acc4_full32(r0, r1, r2, r3, sw, cw, s2w, c2w, ew, mem, k, nj, s, c, top, s2, c2, sa):
    """:func:`_acc4_full` with float32 sums."""
    _acc4_full(_as32, r0, r1, r2, r3, sw, cw, s2w, c2w, ew, mem, k, nj, s, c, top, s2, c2, sa)


@nb.njit(error_model="numpy", fastmath={"contract"})
def _acc4_full64(r0, r1, r2, r3, sw, cw, s2w, c2w, ew, mem, k, nj, s, c, top, s2, c2, sa):
    """:func:`_acc4_full` with float64 sums."""
    _acc4_full(_as64, r0, r1, r2, r3, sw, cw, s2w, c2w, ew, mem, k, nj, s, c, top, s2, c2, sa)


@nb.njit(error_model="numpy", fastmath={"contract"})
def _to32(s64, c64, s, c, nj):
    for j in range(nj):
        s[j] = _F32(s64[j])
        c[j] = _F32(c64[j])


@nb.njit(error_model="numpy", fastmath={"contract"})
def _phase32(s, c, ph, m2, nj):
    """Phase (polynomial atan2) and squared modulation sum S^2 + C^2, float32."""
    for j in range(nj):
        a = s[j]
        b = c[j]
        m2[j] = a * a + b * b
        ph[j] = atan2_poly32(-a, b)


@nb.njit(error_model="numpy", fastmath={"contract"})
def _share_max(wl, rden, buf, nj):
    """max_j wl[j] * rden[j] (>= 0, finite; 0 for nj = 0): a level's largest share of
    the combination's weight in a tile, rden holding 1 / the weights' sum (0 where the
    pixel does not count). The products go through ``buf`` (float32) and their maximum
    is taken on their bit patterns as int32 (the same order for floats >= 0): an integer
    maximum, which vectorises, where a float one would not without fast-math flags."""
    for j in range(nj):
        buf[j] = wl[j] * rden[j]
    bits = buf.view(np.int32)
    top = np.int32(0)
    for j in range(nj):
        b = bits[j]
        top = b if b > top else top
    buf[0] = _ZERO32
    bits[0] = top
    return buf[0]


@nb.njit(error_model="numpy", fastmath={"contract"})
def _terms(tail, scale, tol, n_max):
    """The fewest terms n (a multiple of SERIES_BLOCK, at most n_max) with
    scale * tail[n] <= tol; n_max where none is."""
    n = 0
    while n < n_max and scale * tail[n] > tol:
        n += SERIES_BLOCK
    return n


@nb.njit(parallel=True, cache=True, error_model="numpy", fastmath={"contract"})
def fused_ladder(stacks, lev_first, exposure, exact32, nsteps, sw32, cw32, sw, cw, s2w, c2w, ew,
                 periods, length, tables, nf_tables, has_table, ser_a, ser_b,
                 ser_c0, ser_d, ser_n, has_series, ser_da, ser_db, ser_tg, ser_tn, wbound,
                 tol_x, tol_next, tol_nf, top_lim, top_all, min_mod2,
                 max_res, full, noise_c, noise_gain, small_sums, block_rows, tile,
                 out_u, out_mask, out_mod,
                 out_sigma, out_bg, out_exp, out_sat, out_low, out_shadow, out_rel):
    """One pass over the images of a hierarchical ladder (coarse to fine, the first level
    one period), per camera pixel: each level's N-step sums, HDR choice between its
    exposures, phase (polynomial atan2), optional nonlinearity correction (series or
    table), hierarchical unwrapping with the residual check, inverse-variance combination,
    masks (saturation, low modulation, residual, range).

    Precision: sums exact in float32 where ``exact32`` (else float64, then rounded to
    float32); phase, S^2 + C^2 and unwrapping in float32; every level's absolute phase
    ``ph + 2 pi k``, its coordinate x_l and the combination ``x = sum_l w_l x_l / sum_l
    w_l`` in float64 (the weights w_l in float32).

    The corrections' series are cut per tile of pixels to what the result needs (the
    dropped terms bounded by the tails ``ser_tg``, ``ser_tn``): level l's correction
    error e_l (rad) moves x by at most s_l e_l L / (2 pi p_l), s_l its largest share
    w_l / sum_k w_k of the combination in the tile (bounded before the correction with
    the noise factors' range ``wbound``), and the next level's order prediction by
    e_l p_{l+1} / p_l; its noise factor's relative error f_l moves the weights by 2 f_l
    and sigma by at most s_l f_l. The kernel keeps s_l e_l L / (2 pi p_l) <= tol_x (px),
    e_l p_{l+1} / p_l <= tol_next (rad) and s_l f_l <= tol_nf, or uses every term.

    Levels and members: level ``l`` is made of the stacks ``lev_first[l]`` to
    ``lev_first[l + 1] - 1`` of ``stacks`` (its exposures, longest first); per pixel the
    longest exposure with no sample at ``max_value`` is used (the longest when all are).

    stacks : tuple of (N, rows, cols) arrays (one dtype).  exposure : (members,) float64.
    exact32 : (members,) bool: integer samples and weights in {0, +-1/2, +-1}: the float32
        sums are exact.  nsteps : (L,) int64.
    sw32, cw32, sw, cw : (members, K) sin / cos weights (float32, float64), K a multiple
        of 4, zero-padded.  s2w, c2w : (members, K) float32, second-harmonic weights.
    ew : (members, K) float32, 1 for each step and 0 for the padding (the background sum).
    periods : (L,) float64.  length : float, projector pixels.
    tables, nf_tables : (L, M + 2) float32, the correction g and the noise factor
        d(true)/d(measured) = 1 - g' against the measured phase at -pi + 2 pi j / M (j = 0
        .. M + 1, periodic), linearly interpolated (:func:`_table_correct32`) where
        has_table (L,) bool (which takes precedence over the series).
    ser_a, ser_b : (L, T) float32, ser_c0 : (L,) float32, ser_d, ser_n : (L,) int64: the
        correction as a Fourier series (see :func:`_series_correct32`), where has_series;
        T a multiple of SERIES_BLOCK, zero beyond each level's ser_n terms.
    ser_da, ser_db : (L, T) float32: its derivative's series; the noise factor (full
        only) is 1 - g' from it (no table look-up: where has_series and not has_table).
    ser_tg, ser_tn : (L, T + 1) float64: bounds of what the terms after the first n drop
        (n = 0..T): of the correction (rad) and of the noise factor (relative).
    wbound : (L, 2) float32: the factor 1 / nf^2 of a level's weight lies within
        [wbound[l, 1], wbound[l, 0]] (1, 1 without a correction).
    tol_x : float, px; tol_next, tol_nf : float (see above).
    top_lim : (1,) array of the stacks' dtype, top_all : bool: a sample v is below the
        saturation level max_value exactly when ``v < top_lim[0] or top_all``
        (telefringe.fringes.fast._top_limit): the test in the samples' own type, which
        vectorises on integers without widening them to float64.
    min_mod2 : (L,) float32, thresholds on S^2 + C^2 (rounded up to float32).
    max_res : float, rad.
    full : bool. False: weights (p B)^2 and only out_u, out_mask, out_mod (B of the
        finest level) are written. True: weights 1 / sigma_x^2 from the noise model
        var = noise_c + noise_gain * max(quadrature level, 0) and every output.
    small_sums : bool, every sum below 2^25 in magnitude (integer samples below 2^16,
        N <= 256): the full decode's weights in one division instead of two (the
        products of three sums stay inside float32).
    out_* : (rows, cols) arrays (the unused ones may be (1, 1)): out_u, out_mod, out_sigma,
        out_bg, out_exp float64; out_mask, out_sat, out_low, out_shadow, out_rel bool.
        out_exp is written only where the finest level has several exposures (else it is
        that level's one exposure everywhere: the caller fills it).

    ``stacks`` may hold more arrays than ``lev_first[-1]`` (padding, so that one compiled
    signature serves every ladder: see telefringe.decode._fused).
    """
    n_lev = nsteps.size
    rows = out_u.shape[0]
    cols = out_u.shape[1]
    tscale = (tables.shape[1] - 2) / TWO_PI
    cut32 = _F32(math.pi / length)
    inv2pi32 = _F32(INV_TWO_PI)
    half32 = _F32(0.5)
    max_res32 = _F32(max_res)
    n_blocks = (rows + block_rows - 1) // block_rows
    dt = stacks[0].dtype
    lim = top_lim[0]
    # the exposure map is written only where the finest level has several exposures
    hdr_last = lev_first[n_lev] - lev_first[n_lev - 1] > 1
    for blk in nb.prange(n_blocks):
        # per level: the chosen (HDR) sums, phase, S^2 + C^2, weight before the noise
        # factor, and whether a sample-free exposure was found
        lv_s = np.empty((n_lev, tile), dtype=np.float32)
        lv_c = np.empty((n_lev, tile), dtype=np.float32)
        lv_ph = np.empty((n_lev, tile), dtype=np.float32)
        lv_m2 = np.empty((n_lev, tile), dtype=np.float32)
        lv_w = np.empty((n_lev, tile), dtype=np.float32)
        lv_found = np.empty((n_lev, tile), dtype=np.bool_)
        n_g = np.empty(n_lev, dtype=np.int64)
        n_nf = np.empty(n_lev, dtype=np.int64)
        top = np.empty(tile, dtype=dt)
        ms32 = np.empty(tile, dtype=np.float32)
        mc32 = np.empty(tile, dtype=np.float32)
        mtop = np.empty(tile, dtype=dt)
        s64 = np.empty(tile)
        c64 = np.empty(tile)
        sel = np.empty(tile, dtype=np.bool_)
        pv = np.empty(tile, dtype=np.bool_)
        phi_abs = np.empty(tile, dtype=np.float32)
        kk = np.empty(tile, dtype=np.float32)
        w32 = np.empty(tile, dtype=np.float32)
        wden = np.empty(tile, dtype=np.float32)
        num = np.empty(tile)  # float64: sum_l w_l x_l of the coarse levels
        den64 = np.empty(tile)
        den = np.empty(tile, dtype=np.float32)  # (sigma: float32 is enough)
        ok = np.empty(tile, dtype=np.bool_)
        res_ok = np.empty(tile, dtype=np.bool_)
        # full decode only
        sa = np.empty(tile, dtype=np.float32)
        s2 = np.empty(tile, dtype=np.float32)
        c2 = np.empty(tile, dtype=np.float32)
        msa = np.empty(tile, dtype=np.float32)
        ms2 = np.empty(tile, dtype=np.float32)
        mc2 = np.empty(tile, dtype=np.float32)
        expo = np.empty(tile)
        sat = np.empty(tile, dtype=np.bool_)
        low = np.empty(tile, dtype=np.bool_)
        shadow = np.empty(tile, dtype=np.bool_)
        rel = np.empty(tile, dtype=np.bool_)
        # nonlinearity correction by series
        ser_sc = np.empty((8, tile), dtype=np.float32)
        nfac = np.empty(tile, dtype=np.float32)
        r0 = blk * block_rows
        r1 = min(rows, r0 + block_rows)
        for r in range(r0, r1):
            for j0 in range(0, cols, tile):
                j1 = min(cols, j0 + tile)
                nj = j1 - j0
                o_u = out_u[r, j0:j1]
                o_mask = out_mask[r, j0:j1]
                o_mod = out_mod[r, j0:j1]
                # ---- every level's sums, phase and weight (before the correction)
                for lev in range(n_lev):
                    n_k = nsteps[lev]
                    s32 = lv_s[lev]
                    c32 = lv_c[lev]
                    found = lv_found[lev]
                    m2 = lv_m2[lev]
                    for mem in range(lev_first[lev], lev_first[lev + 1]):
                        st = stacks[mem]
                        first_mem = mem == lev_first[lev]
                        # the first (longest) exposure goes straight into the chosen sums
                        ts = s32 if first_mem else ms32
                        tc = c32 if first_mem else mc32
                        tt = top if first_mem else mtop
                        ta = sa if first_mem else msa
                        t2s = s2 if first_mem else ms2
                        t2c = c2 if first_mem else mc2
                        if full:
                            _zero(t2s, t2c, ta, nj)
                        if exact32[mem]:
                            _zero(ts, tc, tt, nj)
                        else:
                            _zero(s64, c64, tt, nj)
                        for k in range(0, n_k, 4):
                            k1 = min(k + 1, n_k - 1)
                            k2 = min(k + 2, n_k - 1)
                            k3 = min(k + 3, n_k - 1)
                            if full and exact32[mem]:
                                _acc4_full32(st[k, r, j0:j1], st[k1, r, j0:j1],
                                           st[k2, r, j0:j1], st[k3, r, j0:j1], sw32, cw32,
                                           s2w, c2w, ew, mem, k, nj, ts, tc, tt, t2s, t2c, ta)
                            elif full:
                                _acc4_full64(st[k, r, j0:j1], st[k1, r, j0:j1],
                                           st[k2, r, j0:j1], st[k3, r, j0:j1], sw, cw, s2w,
                                           c2w, ew, mem, k, nj, s64, c64, tt, t2s, t2c, ta)
                            elif exact32[mem]:
                                _acc4_32(st[k, r, j0:j1], st[k1, r, j0:j1],
                                      st[k2, r, j0:j1], st[k3, r, j0:j1],
                                      sw32[mem, k], sw32[mem, k + 1], sw32[mem, k + 2],
                                      sw32[mem, k + 3], cw32[mem, k], cw32[mem, k + 1],
                                      cw32[mem, k + 2], cw32[mem, k + 3], nj, ts, tc, tt)
                            else:
                                _acc4_64(st[k, r, j0:j1], st[k1, r, j0:j1],
                                      st[k2, r, j0:j1], st[k3, r, j0:j1],
                                      sw[mem, k], sw[mem, k + 1], sw[mem, k + 2],
                                      sw[mem, k + 3], cw[mem, k], cw[mem, k + 1],
                                      cw[mem, k + 2], cw[mem, k + 3], nj, s64, c64, tt)
                        if not exact32[mem]:
                            _to32(s64, c64, ts, tc, nj)
                        e = exposure[mem]
                        if first_mem:
                            for j in range(nj):
                                found[j] = (top[j] < lim) | top_all
                            if full and hdr_last and lev == n_lev - 1:
                                for j in range(nj):
                                    expo[j] = e
                        else:  # a shorter exposure where the longer ones saturate
                            for j in range(nj):
                                sel[j] = (not found[j]) & ((mtop[j] < lim) | top_all)
                            for j in range(nj):
                                s32[j] = ms32[j] if sel[j] else s32[j]
                            for j in range(nj):
                                c32[j] = mc32[j] if sel[j] else c32[j]
                            for j in range(nj):
                                found[j] = found[j] | sel[j]
                            if full:
                                for j in range(nj):
                                    sa[j] = msa[j] if sel[j] else sa[j]
                                for j in range(nj):
                                    s2[j] = ms2[j] if sel[j] else s2[j]
                                for j in range(nj):
                                    c2[j] = mc2[j] if sel[j] else c2[j]
                                if hdr_last and lev == n_lev - 1:
                                    for j in range(nj):
                                        expo[j] = e if sel[j] else expo[j]
                    _phase32(s32, c32, lv_ph[lev], m2, nj)
                    inv_n = 1.0 / n_k
                    thr = min_mod2[lev]
                    xscale = length / (TWO_PI * periods[lev])
                    wl = lv_w[lev]
                    if full:
                        # weight 1 / sigma_x^2 (before the noise factor) from the
                        # quadrature level (sigma_I of the phase): cos 2phi = (C^2 - S^2) /
                        # R^2, sin 2phi = -2 S C / R^2 (float32: the weights and sigma
                        # need no more); 0 where sigma would be 0
                        wk = _F32(2.0 * inv_n / (xscale * xscale))
                        inv_n32 = _F32(inv_n)
                        nc32 = _F32(noise_c)
                        ng32 = _F32(noise_gain)
                        m_two = _F32(-2.0)
                        if small_sums:
                            # the same weight with one division instead of two, both sides
                            # of w = wk R^2 / d multiplied by R^2: R^2 d = nc R^2 + ng
                            # max(sa R^2 - (R^2 cos 2phi c2 - R^2 sin 2phi s2), 0) / N.
                            # (Only where the sums are bounded, |sums| < 2^25: the products
                            # of three of them stay far inside float32.)
                            for j in range(nj):
                                a = s32[j]
                                b = c32[j]
                                r2 = m2[j]
                                pq = (b * b - a * a) * c2[j] - (m_two * a * b) * s2[j]
                                q = (sa[j] * r2 - pq) * inv_n32
                                dd = nc32 * r2 + ng32 * (q if q > _ZERO32 else _ZERO32)
                                use = (r2 > _ZERO32) & (dd > _ZERO32)
                                w = wk * r2 * r2 / (dd if use else _ONE32)
                                wl[j] = w if use else _ZERO32
                        for j in range(nj if not small_sums else 0):
                            a = s32[j]
                            b = c32[j]
                            r2 = m2[j]
                            pos = r2 > _ZERO32
                            inv = _ONE32 / (r2 if pos else _ONE32)
                            cos2 = (b * b - a * a) * inv if pos else _ONE32
                            sin2 = (m_two * a * b) * inv if pos else _ZERO32
                            quad = (sa[j] - (cos2 * c2[j] - sin2 * s2[j])) * inv_n32
                            d = nc32 + ng32 * (quad if quad > _ZERO32 else _ZERO32)
                            w = wk * r2 / (d if d > _ZERO32 else _ONE32)
                            wl[j] = w if d > _ZERO32 else _ZERO32
                        if lev == n_lev - 1:
                            o_bg = out_bg[r, j0:j1]
                            for j in range(nj):
                                o_bg[j] = float(sa[j]) * inv_n
                            if hdr_last:
                                o_exp = out_exp[r, j0:j1]
                                for j in range(nj):
                                    o_exp[j] = expo[j]
                    else:
                        wscale = _F32((2.0 * periods[lev] * inv_n) ** 2)
                        for j in range(nj):
                            wl[j] = wscale * m2[j]
                    if lev == 0:
                        for j in range(nj):
                            pv[j] = found[j] & (m2[j] >= thr)
                    else:
                        for j in range(nj):
                            pv[j] = pv[j] & found[j] & (m2[j] >= thr)
                # ---- the series' terms this tile needs (see the docstring)
                for j in range(nj):
                    wden[j] = _ZERO32
                for lev in range(n_lev):
                    wl = lv_w[lev]
                    lo = wbound[lev, 1]
                    for j in range(nj):
                        wden[j] += wl[j] * lo
                for j in range(nj):  # (0 where the pixel cannot be valid)
                    d = wden[j]
                    use = pv[j] & (d > _ZERO32)
                    wden[j] = _ONE32 / (d if use else _ONE32) if use else _ZERO32
                for lev in range(n_lev):
                    n_g[lev] = 0
                    n_nf[lev] = 0
                    if has_series[lev] and not has_table[lev]:
                        n_max = (ser_n[lev] + SERIES_BLOCK - 1) // SERIES_BLOCK * SERIES_BLOCK
                        share = float(_share_max(lv_w[lev], wden, w32, nj)) * float(
                            wbound[lev, 0])
                        share = min(share, 1.0)
                        xs = length / (TWO_PI * periods[lev])
                        ng = _terms(ser_tg[lev], share * xs, tol_x, n_max)
                        if lev < n_lev - 1:
                            ng = max(ng, _terms(ser_tg[lev], periods[lev + 1] / periods[lev],
                                                tol_next, n_max))
                        n_g[lev] = ng
                        n_nf[lev] = _terms(ser_tn[lev], share, tol_nf, n_max)
                # ---- per level: correction, unwrapping, combination
                for lev in range(n_lev):
                    n_k = nsteps[lev]
                    last = lev == n_lev - 1
                    s32 = lv_s[lev]
                    c32 = lv_c[lev]
                    ph = lv_ph[lev]
                    m2 = lv_m2[lev]
                    found = lv_found[lev]
                    wl = lv_w[lev]
                    p = periods[lev]
                    inv_n = 1.0 / n_k
                    thr = min_mod2[lev]
                    xscale = length / (TWO_PI * p)
                    corrected = False
                    if has_table[lev]:
                        # (scalar look-ups); with the noise factor at the measured phase
                        _table_correct32(ph, tables[lev], nf_tables[lev], tscale, nj, full,
                                         nfac)
                        corrected = full
                    elif has_series[lev]:
                        _series_correct32(ph, s32, c32, m2, ser_a[lev], ser_b[lev],
                                          ser_c0[lev], ser_d[lev], n_g[lev], ser_sc, nj,
                                          full, ser_da[lev], ser_db[lev], n_nf[lev], nfac)
                        corrected = full
                    if corrected:
                        for j in range(nj):
                            fs = nfac[j]
                            w32[j] = wl[j] / (fs * fs)
                    else:
                        for j in range(nj):
                            w32[j] = wl[j]
                    if lev == 0:
                        for j in range(nj):
                            q = ph[j] + cut32
                            kq = -np.floor(q * inv2pi32)  # 1 where ph < -cut, else 0
                            phi_abs[j] = q + _TWO_PI32 * kq - cut32
                            kk[j] = kq  # (read where the one-period level is the last)
                        for j in range(nj):
                            ok[j] = found[j] & (m2[j] >= thr)
                        if full:
                            for j in range(nj):
                                good = m2[j] >= thr
                                sat[j] = not found[j]
                                low[j] = not good
                                shadow[j] = not good
                                rel[j] = True
                    else:
                        ratio = _F32(p / periods[lev - 1])
                        for j in range(nj):
                            phv = ph[j]
                            pred = phi_abs[j] * ratio
                            kq = np.floor((pred - phv) * inv2pi32 + half32)
                            fp = phv + _TWO_PI32 * kq
                            kk[j] = kq
                            phi_abs[j] = fp
                            res_ok[j] = abs(pred - fp) <= max_res32
                        for j in range(nj):
                            ok[j] = ok[j] & res_ok[j] & found[j] & (m2[j] >= thr)
                        if full:
                            for j in range(nj):
                                good = m2[j] >= thr
                                sat[j] = sat[j] | (not found[j])
                                low[j] = low[j] | (not good)
                                shadow[j] = shadow[j] & (not good)
                                rel[j] = rel[j] & res_ok[j]
                    if not last:  # coarse levels: x_l and the sums in float64 (in
                        # float32 their rounding, ~1e-7 x, reached 1.3e-4 px at L = 3840)
                        if lev == 0:
                            for j in range(nj):
                                w = w32[j]
                                num[j] = float(w) * (float(phi_abs[j]) * xscale)
                                den64[j] = float(w)
                                den[j] = w
                        else:
                            for j in range(nj):
                                w = w32[j]
                                xl = (float(ph[j]) + TWO_PI * float(kk[j])) * xscale
                                num[j] += float(w) * xl
                                den64[j] += float(w)
                                den[j] += w
                    else:
                        # x = sum_l w_l x_l / sum_l w_l in float64
                        hi = length - 0.5
                        for j in range(nj):
                            xf = (float(ph[j]) + TWO_PI * float(kk[j])) * xscale
                            w = w32[j]
                            if lev == 0:
                                dsum = w
                                x = xf
                            else:
                                dsum = den[j] + w
                                d64 = den64[j] + float(w)
                                x = (num[j] + float(w) * xf) / d64 if d64 > 0.0 else xf
                            den[j] = dsum
                            valid = ok[j] & (dsum > _ZERO32) & (x >= -0.5) & (x <= hi)
                            o_u[j] = x if valid else np.nan
                            o_mask[j] = valid
                        bscale = _F32(2.0 * inv_n)
                        for j in range(nj):  # (float32 square root: 8 lanes)
                            o_mod[j] = float(bscale * math.sqrt(m2[j]))
                if full:
                    o_sigma = out_sigma[r, j0:j1]
                    o_sat = out_sat[r, j0:j1]
                    o_low = out_low[r, j0:j1]
                    o_shadow = out_shadow[r, j0:j1]
                    o_rel = out_rel[r, j0:j1]
                    for j in range(nj):
                        sg = float(_ONE32 / math.sqrt(den[j]))
                        o_sigma[j] = sg if o_mask[j] else np.nan
                        o_sat[j] = sat[j]
                        o_low[j] = low[j]
                        o_shadow[j] = shadow[j]
                        o_rel[j] = rel[j]


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


