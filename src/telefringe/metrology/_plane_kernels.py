"""Compiled kernels of the robust plane fit (private): one Tukey-biweight iteratively
reweighted least squares round of :func:`telefringe.metrology.planes.fit_plane` in two
passes over the points, without NumPy's temporaries (a BGA's substrate has ~150 000
points and the fit ~10 rounds). float64, no fastmath; the sums run in point order (not
NumPy's pairwise order), so the results agree with the NumPy form to rounding
(tests/test_plane_kernels.py)."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _moments(p, w):
    """Weighted centroid c (3,) and scatter S (3, 3) about it of points p (n, 3) with
    weights w (n,) (points of weight 0 are skipped); NaN when the weights sum to 0."""
    sw = 0.0
    s = np.zeros(3)
    for i in range(p.shape[0]):
        wi = w[i]
        sw += wi
        for k in range(3):
            s[k] += wi * p[i, k]
    c = s / sw
    S = np.zeros((3, 3))
    for i in range(p.shape[0]):
        wi = w[i]
        if wi == 0.0:
            continue
        q0 = p[i, 0] - c[0]
        q1 = p[i, 1] - c[1]
        q2 = p[i, 2] - c[2]
        S[0, 0] += wi * q0 * q0
        S[0, 1] += wi * q0 * q1
        S[0, 2] += wi * q0 * q2
        S[1, 1] += wi * q1 * q1
        S[1, 2] += wi * q1 * q2
        S[2, 2] += wi * q2 * q2
    S[1, 0] = S[0, 1]
    S[2, 0] = S[0, 2]
    S[2, 1] = S[1, 2]
    return c, S


@nb.njit(cache=True, nogil=True, error_model="numpy")
def tukey_moments(p, wf, r, cs):
    """Weighted centroid and scatter of points ``p`` (n, 3) with the weights
    ``wf * (1 - u^2)^2`` where ``|u| < 1``, else 0, ``u = r / cs`` (``r`` (n,) residuals,
    ``cs`` > 0 the Tukey cut in their unit).

    Returns (n_pos: points of positive weight, c (3,) weighted centroid, S (3, 3)
    weighted scatter about c); c and S are NaN when no weight is positive.
    """
    n = p.shape[0]
    w = np.empty(n)
    n_pos = 0
    for i in range(n):
        u = r[i] / cs
        wi = 0.0
        if abs(u) < 1.0:
            t = 1.0 - u * u
            wi = wf[i] * (t * t)
        w[i] = wi
        if wi > 0.0:
            n_pos += 1
    c, S = _moments(p, w)
    return n_pos, c, S


@nb.njit(cache=True, nogil=True, error_model="numpy")
def kept_moments(p, w, keep):
    """Weighted centroid c (3,) and scatter S (3, 3) of the points ``p`` (n, 3) where
    ``keep`` (n,) bool, weights ``w`` (n,)."""
    wk = np.empty(p.shape[0])
    for i in range(p.shape[0]):
        wk[i] = w[i] if keep[i] else 0.0
    return _moments(p, wk)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def plane_statistics(p, w, keep, normal, offset, c, T):
    """The statistics of a plane fit over the kept points (``keep`` (n,) bool) of ``p``
    (n, 3) with weights ``w`` (n,): residuals r = p . normal - offset, in-plane
    coordinates q = T (p - c) (``T`` (2, 3)).

    Returns (n_kept, sum w, sum w r^2, sum r^2, min r, max r, M (2, 2) = sum w q q^T).
    """
    nk = 0
    sw = 0.0
    swr2 = 0.0
    sr2 = 0.0
    rmin = np.inf
    rmax = -np.inf
    M = np.zeros((2, 2))
    for i in range(p.shape[0]):
        if not keep[i]:
            continue
        x0 = p[i, 0]
        x1 = p[i, 1]
        x2 = p[i, 2]
        r = x0 * normal[0] + x1 * normal[1] + x2 * normal[2] - offset
        wi = w[i]
        nk += 1
        sw += wi
        swr2 += wi * r * r
        sr2 += r * r
        rmin = min(rmin, r)
        rmax = max(rmax, r)
        y0 = x0 - c[0]
        y1 = x1 - c[1]
        y2 = x2 - c[2]
        a = T[0, 0] * y0 + T[0, 1] * y1 + T[0, 2] * y2
        b = T[1, 0] * y0 + T[1, 1] * y1 + T[1, 2] * y2
        M[0, 0] += wi * a * a
        M[0, 1] += wi * a * b
        M[1, 1] += wi * b * b
    M[1, 0] = M[0, 1]
    return nk, sw, swr2, sr2, rmin, rmax, M


@nb.njit(cache=True, nogil=True, error_model="numpy")
def plane_residuals(p, normal, offset):
    """p . normal - offset (n,) of points p (n, 3)."""
    out = np.empty(p.shape[0])
    for i in range(p.shape[0]):
        out[i] = p[i, 0] * normal[0] + p[i, 1] * normal[1] + p[i, 2] * normal[2] - offset
    return out


@nb.njit(cache=True, nogil=True, error_model="numpy")
def residuals_of_inliers(p, normal, offset, r, cs, out):
    """Replace the residuals ``r`` (n,) by those of the plane ``normal . x = offset``,
    ``p @ normal - offset``, and write into ``out`` the new absolute residuals of the
    points that were inliers (``|r_old / cs| < 1``, i.e. of positive Tukey weight), in
    point order. Returns how many were written."""
    k = 0
    for i in range(p.shape[0]):
        inl = abs(r[i] / cs) < 1.0
        v = p[i, 0] * normal[0] + p[i, 1] * normal[1] + p[i, 2] * normal[2] - offset
        r[i] = v
        if inl:
            out[k] = abs(v)
            k += 1
    return k


@nb.njit(cache=True, nogil=True, error_model="numpy")
def lmeds_best(sub, triples):
    """The least-median-of-squares trial: per trial t the plane through the points
    ``sub[triples[t]]`` (unit normal, offset n . p0; skipped when the three are collinear:
    the cross product's norm below 1e-12 max(1, max |coordinate|)^2) and the median of
    the squared distances of every point of ``sub`` (m, 3) to it; the first trial of the
    smallest median is returned as (t, normal (3,), offset, median), t = -1 when every
    trial is collinear.

    The trials run in order; a trial's median is computed only when it can beat the best
    so far: fewer than (m + 1) // 2 squared distances at or below the best median b mean
    the lower middle order statistic, and so the median, exceeds b (strictly), so the
    trial is skipped without changing which trial wins (the same first best as computing
    every median).
    """
    m = sub.shape[0]
    need = (m + 1) // 2
    r2 = np.empty(m)
    best_t = -1
    best = np.inf
    best_n = np.zeros(3)
    best_d = 0.0
    for t in range(triples.shape[0]):
        a = sub[triples[t, 0]]
        b = sub[triples[t, 1]]
        c = sub[triples[t, 2]]
        u0, u1, u2 = b[0] - a[0], b[1] - a[1], b[2] - a[2]
        v0, v1, v2 = c[0] - a[0], c[1] - a[1], c[2] - a[2]
        n0 = u1 * v2 - u2 * v1
        n1 = u2 * v0 - u0 * v2
        n2 = u0 * v1 - u1 * v0
        nn = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        big = 1.0
        for k in range(3):
            big = max(big, abs(a[k]), abs(b[k]), abs(c[k]))
        if nn < 1e-12 * big * big:
            continue
        n0 /= nn
        n1 /= nn
        n2 /= nn
        d = n0 * a[0] + n1 * a[1] + n2 * a[2]
        below = 0
        for i in range(m):
            r = sub[i, 0] * n0 + sub[i, 1] * n1 + sub[i, 2] * n2 - d
            r2[i] = r * r
            if r2[i] <= best:
                below += 1
        if below < need:
            continue  # its median exceeds the best
        med = np.median(r2)
        if med < best:
            best = med
            best_t = t
            best_n[0] = n0
            best_n[1] = n1
            best_n[2] = n2
            best_d = d
    return best_t, best_n, best_d, best
