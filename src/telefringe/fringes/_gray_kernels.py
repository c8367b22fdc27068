"""Numba kernel of the complementary Gray-code unwrapping (private; see
:func:`telefringe.fringes.unwrap.unwrap_gray`, whose NumPy path is the reference).

One parallel pass over rows: each pixel's bits, contrasts, Gray index, typical (median)
contrast, fringe order, absolute phase and the bit-consistency check, with no image-sized
temporaries. The arithmetic is the NumPy path's, operation for operation in float64 (no
fastmath), so the result is bit-identical (tested in tests/test_gray_kernels.py).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

TWO_PI = 2.0 * math.pi


@nb.njit(inline="always")
def _rint(v):
    """Round half to even (``numpy.round``) of a finite float64."""
    r = math.floor(v)
    d = v - r
    if d > 0.5:
        return r + 1.0
    if d == 0.5 and (r * 0.5) != math.floor(r * 0.5):
        return r + 1.0
    return r


@nb.njit(cache=True, parallel=True)
def unwrap_gray_complementary(phase, images, threshold, min_contrast, bits, length,
                              absolute, bad):
    """Fill ``absolute`` (rows, cols) float64 (rad) and ``bad`` (rows, cols) bool.

    phase : (rows, cols) float64, wrapped, finite.  images : (bits + 1, rows, cols) DN.
    threshold, min_contrast : (rows, cols) float64, DN.  bits, length : int.
    """
    n = images.shape[0]
    rows, cols = phase.shape
    periods = 2 ** bits
    tol = min(2.0, length / periods / 4.0)
    scale = float(2 ** bits)
    scale_half = float(2 ** (bits + 1))
    half_pi = 0.5 * math.pi
    for r in nb.prange(rows):
        con = np.empty(n)
        srt = np.empty(n)
        bit = np.empty(n, dtype=np.bool_)
        for c in range(cols):
            thr = threshold[r, c]
            h = 0
            prev = False
            for j in range(n):
                d = float(images[j, r, c]) - thr
                b = d > 0
                bit[j] = b
                con[j] = abs(d)
                srt[j] = con[j]
                prev = prev ^ b
                if prev:
                    h |= 1 << (n - 1 - j)
            # median of the contrasts (numpy.median: mean of the two middle ones if even)
            for j in range(1, n):
                v = srt[j]
                k = j - 1
                while k >= 0 and srt[k] > v:
                    srt[k + 1] = srt[k]
                    k -= 1
                srt[k + 1] = v
            if n % 2:
                typical = srt[n // 2]
            else:
                typical = (srt[n // 2 - 1] + srt[n // 2]) / 2.0
            lim = max(min_contrast[r, c], 0.25 * typical)
            ph = phase[r, c]
            if abs(ph) <= half_pi:
                order = (h + 1) // 2
            else:
                blk = min(max(h // 2, 0), periods - 1)
                start = -((-blk * length) // periods)
                end = -((-(blk + 1) * length) // periods)
                s_b = TWO_PI * periods * (start - 0.5) / length
                e_b = TWO_PI * periods * (end - 0.5) / length
                order = int(_rint((0.5 * (s_b + e_b) - ph) / TWO_PI))
            ab = ph + TWO_PI * order
            absolute[r, c] = ab
            x = ab * length / (TWO_PI * periods)
            out = (x < -0.5) or (x >= length - 0.5)
            # a clear bit must match the code at the decoded coordinate (+- tol pixels)
            mism = np.uint64(0)
            for j in range(n):
                if con[j] >= lim:
                    mism |= np.uint64(1) << np.uint64(j)
            for s in range(5):
                if mism == 0:
                    break
                dx = (-tol, -0.5 * tol, 0.0, 0.5 * tol, tol)[s]
                xr = min(max(_rint(x + dx), 0.0), length - 1.0)
                blk = np.int64(math.floor(xr * scale / length))
                g = blk ^ (blk >> 1)
                hb = np.int64(math.floor(xr * scale_half / length))
                gh = (hb ^ (hb >> 1)) & 1
                for j in range(n):
                    e = ((g >> (bits - 1 - j)) & 1) if j < bits else gh
                    if (e == 1) == bit[j]:
                        mism &= ~(np.uint64(1) << np.uint64(j))
            bad[r, c] = out or mism != 0


# ------------------------------------------------------------- phase-shifting sums
_CHUNK = 4096


@nb.njit(cache=True, parallel=True)
def phase_sums(images, sin_w, cos_w, sin2_w, cos2_w, s, c, s2, c2, a):
    """The sums of :func:`telefringe.fringes.phase.wrapped_phase`, accumulated in place.

    images : (steps, npx) DN; the weights (steps,) float64; s, c, s2, c2, a : (npx,)
    float64, zero on entry. Each sum adds ``w_k * I_k`` for k = 0, 1, ... in that order,
    skipping zero weights, one product and one addition per term (no FMA): the NumPy
    loop's float64 operations, so the sums are bit-identical to it.
    """
    steps, npx = images.shape
    for blk in nb.prange((npx + _CHUNK - 1) // _CHUNK):
        lo = blk * _CHUNK
        hi = min(lo + _CHUNK, npx)
        for k in range(steps):
            ws, wc, ws2, wc2 = sin_w[k], cos_w[k], sin2_w[k], cos2_w[k]
            for i in range(lo, hi):
                v = float(images[k, i])
                if ws != 0.0:
                    s[i] += ws * v
                if wc != 0.0:
                    c[i] += wc * v
                if ws2 != 0.0:
                    s2[i] += ws2 * v
                if wc2 != 0.0:
                    c2[i] += wc2 * v
                a[i] += v
