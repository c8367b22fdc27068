"""Compiled inner loops of the virtual rig (numba, no fastmath: plain IEEE arithmetic)."""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["accumulate_samples", "heightfield_eval", "heightfield_intersect"]


@numba.njit(cache=True, nogil=True)
def accumulate_samples(coord, weight, per_pixel, profile, x_first, inv_step, out):
    """Sum the samples of each pixel: ``out[p] = sum_s weight * profile(coord)``.

    Parameters
    ----------
    coord : (P * n,) float64, projector coordinate of each sample (pixel-major).
    weight : (P * n,) float32 or float64, weight of each sample (includes 1/n).
    per_pixel : int, n, the number of samples of each pixel.
    profile : (K,) float64, the emitted intensity sampled at ``x_first + k / inv_step``;
        linear interpolation between samples, 0 beyond both ends.
    out : (P,) float64, written.
    """
    npix = out.shape[0]
    last = profile.shape[0] - 1
    for p in range(npix):
        acc = 0.0
        base = p * per_pixel
        for s in range(per_pixel):
            w = weight[base + s]
            if w == 0.0:
                continue
            x = (coord[base + s] - x_first) * inv_step
            if x < 0.0 or x >= last:
                continue
            i = int(x)
            f = x - i
            acc += w * (profile[i] * (1.0 - f) + profile[i + 1] * f)
        out[p] = acc


@numba.njit(cache=True, nogil=True)
def _hf_at(z, px, x0, y0, x, y):
    """Bilinear height and gradient at (x, y); nan outside the grid."""
    rows, cols = z.shape
    fx = (x - x0) / px
    fy = (y - y0) / px
    if not (fx >= 0.0 and fy >= 0.0 and fx <= cols - 1 and fy <= rows - 1):
        return np.nan, 0.0, 0.0
    j = min(int(fx), cols - 2)
    i = min(int(fy), rows - 2)
    a = fx - j
    b = fy - i
    z00 = z[i, j]
    z01 = z[i, j + 1]
    z10 = z[i + 1, j]
    z11 = z[i + 1, j + 1]
    h = (z00 * (1 - a) * (1 - b) + z01 * a * (1 - b) + z10 * (1 - a) * b + z11 * a * b)
    dhdx = ((z01 - z00) * (1 - b) + (z11 - z10) * b) / px
    dhdy = ((z10 - z00) * (1 - a) + (z11 - z01) * a) / px
    return h, dhdx, dhdy


@numba.njit(cache=True, nogil=True)
def heightfield_eval(z, px, x0, y0, xs, ys):
    """Bilinear height (nan outside) and gradient at points (xs, ys) (N,)."""
    n = xs.shape[0]
    h = np.empty(n)
    gx = np.empty(n)
    gy = np.empty(n)
    for k in range(n):
        h[k], gx[k], gy[k] = _hf_at(z, px, x0, y0, xs[k], ys[k])
    return h, gx, gy


@numba.njit(cache=True, nogil=True)
def heightfield_intersect(z, px, x0, y0, o, d):
    """First crossing from above of rays ``o + t d`` with a bilinear height field.

    Marches in steps of px/4 in x-y (at most 1/8 of the height range in z), then bisects
    the first sign change of ``z_ray - h`` to 1e-9 mm. Returns t (N,) (inf: no hit) and
    the upward unit normal (N, 3).
    """
    n = o.shape[0]
    t_out = np.full(n, np.inf)
    nrm = np.zeros((n, 3))
    zmin = z.min()
    zmax = z.max()
    dxy = np.sqrt(d[0] * d[0] + d[1] * d[1])
    span = max(zmax - zmin, 1e-9)
    step = np.inf
    if dxy > 0:
        step = 0.25 * px / dxy
    if abs(d[2]) > 0:
        step = min(step, 0.125 * span / abs(d[2]))
        step = max(step, 1e-9)
    if not np.isfinite(step):
        return t_out, nrm
    for k in range(n):
        # parameter range where the ray is within [zmin, zmax]
        if d[2] != 0.0:
            ta = (zmax - o[k, 2]) / d[2]
            tb = (zmin - o[k, 2]) / d[2]
            if ta > tb:
                ta, tb = tb, ta
        else:
            if o[k, 2] < zmin or o[k, 2] > zmax:
                continue
            ta = 0.0
            tb = 1e6
        ta = max(ta, 0.0) - step
        tb = tb + step
        if tb <= 0:
            continue
        prev_f = np.nan
        prev_t = ta
        t = ta
        found = False
        while t <= tb + step:
            x = o[k, 0] + t * d[0]
            y = o[k, 1] + t * d[1]
            h, _, _ = _hf_at(z, px, x0, y0, x, y)
            f = o[k, 2] + t * d[2] - h
            if prev_f > 0.0 and f <= 0.0:
                lo = prev_t
                hi = t
                for _ in range(200):
                    if hi - lo <= 1e-9:
                        break
                    mid = 0.5 * (lo + hi)
                    hm, _, _ = _hf_at(z, px, x0, y0, o[k, 0] + mid * d[0], o[k, 1] + mid * d[1])
                    fm = o[k, 2] + mid * d[2] - hm
                    if fm > 0.0:
                        lo = mid
                    elif fm <= 0.0:
                        hi = mid
                    else:  # left the grid in between: keep the inside end
                        lo = mid
                th = 0.5 * (lo + hi)
                h, gx, gy = _hf_at(z, px, x0, y0, o[k, 0] + th * d[0], o[k, 1] + th * d[1])
                if h == h:
                    t_out[k] = th
                    s = np.sqrt(gx * gx + gy * gy + 1.0)
                    nrm[k, 0] = -gx / s
                    nrm[k, 1] = -gy / s
                    nrm[k, 2] = 1.0 / s
                    found = True
            if found:
                break
            prev_f = f  # nan outside the grid: no crossing from outside
            prev_t = t
            t += step
    return t_out, nrm
