"""Numba kernels of the decoder (private). No fastmath anywhere; ``cache=True``."""

from __future__ import annotations

import math

import numba as nb
import numpy as np

TWO_PI = 2.0 * math.pi


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
