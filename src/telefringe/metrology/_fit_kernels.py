"""Compiled kernels of the fits (private): the geometric sphere fit's Levenberg-Marquardt
iteration (:func:`telefringe.metrology.spheres._sphere_geometric`) and the least median
of squares plane's trials (:func:`telefringe.metrology.planes._lmeds_plane`). The same
arithmetic as the NumPy forms they replace, in float64 without fastmath, so that a BGA's
hundreds of small caps and a plane's hundreds of trials are not bound by NumPy's per-call
overhead (the trials also run in parallel)."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _cost(p, w, x, f, d, dist):
    """Radial residuals |p - c| - r of x = (c, r) into f (with d = p - c and dist), and
    the weighted cost sum w f^2."""
    cost = 0.0
    for i in range(p.shape[0]):
        a = p[i, 0] - x[0]
        b = p[i, 1] - x[1]
        c = p[i, 2] - x[2]
        d[i, 0] = a
        d[i, 1] = b
        d[i, 2] = c
        r = np.sqrt(a * a + b * b + c * c)
        dist[i] = r
        f[i] = r - x[3]
        cost += w[i] * f[i] * f[i]
    return cost


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _jac(d, dist, sw, npar, J):
    """Weighted Jacobian rows sqrt(w) d f / d(c, r) (the first npar columns)."""
    for i in range(d.shape[0]):
        s = sw[i] / dist[i]
        J[i, 0] = -d[i, 0] * s
        J[i, 1] = -d[i, 1] * s
        J[i, 2] = -d[i, 2] * s
        if npar == 4:
            J[i, 3] = -sw[i]


@nb.njit(cache=True, nogil=True, error_model="numpy")
def sphere_lm(p, w, x0, npar, max_iter):
    """Levenberg-Marquardt on the radial residuals of points ``p`` (m, 3) with weights
    ``w`` (m,) from ``x0`` = (centre, radius); npar 3 keeps the radius fixed.

    Returns (x (4,), f (m,) residuals, J (m, npar) weighted Jacobian at x). Damping
    ``H + lam diag(H)``, lam from 1e-3, divided by 10 on success (>= 1e-12) and
    multiplied by 10 on failure (20 tries per iteration); stops when a step is below
    1e-12 (1 + |x|) or the cost decreases by less than 1e-15 of itself.
    """
    m = p.shape[0]
    sw = np.sqrt(w)
    x = x0.copy()
    f = np.empty(m)
    d = np.empty((m, 3))
    dist = np.empty(m)
    fn = np.empty(m)
    dn = np.empty((m, 3))
    distn = np.empty(m)
    J = np.empty((m, npar))
    H = np.empty((npar, npar))
    g = np.empty(npar)
    xn = np.empty(4)
    step = np.zeros(4)
    lam = 1e-3
    cost = _cost(p, w, x, f, d, dist)
    cost_old = cost
    for _ in range(max_iter):
        _jac(d, dist, sw, npar, J)
        for a in range(npar):
            ga = 0.0
            for i in range(m):
                ga += J[i, a] * f[i] * sw[i]
            g[a] = ga
            for b in range(a, npar):
                s = 0.0
                for i in range(m):
                    s += J[i, a] * J[i, b]
                H[a, b] = s
                H[b, a] = s
        improved = False
        for _ in range(20):
            A = H.copy()
            for a in range(npar):
                A[a, a] += lam * H[a, a]
            sol = np.linalg.solve(A, g)
            for a in range(4):
                step[a] = -sol[a] if a < npar else 0.0
                xn[a] = x[a] + step[a]
            cn = _cost(p, w, xn, fn, dn, distn)
            if cn <= cost:
                x[:] = xn
                f[:] = fn
                d[:, :] = dn
                dist[:] = distn
                cost_old = cost
                cost = cn
                lam = max(lam / 10, 1e-12)
                improved = True
                break
            lam *= 10
        if not improved:
            break
        if np.sqrt(np.sum(step * step)) <= 1e-12 * (1.0 + np.sqrt(np.sum(x * x))) or (
                cost_old - cost) <= 1e-15 * max(cost_old, 1e-300):
            break
    _jac(d, dist, sw, npar, J)
    return x, f, J


@nb.njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def lmeds_trials(sub, triples, normals, offsets, medians):
    """Per trial t: the plane through the points ``sub[triples[t]]`` (unit normal, offset
    n . p0) and the median of the squared distances of every point of ``sub`` (m, 3) to
    it; ``medians[t]`` is inf where the three points are collinear (the cross product's
    norm below 1e-12 max(1, max |coordinate|)^2)."""
    m = sub.shape[0]
    for t in nb.prange(triples.shape[0]):
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
            medians[t] = np.inf
            continue
        n0 /= nn
        n1 /= nn
        n2 /= nn
        d = n0 * a[0] + n1 * a[1] + n2 * a[2]
        r2 = np.empty(m)
        for i in range(m):
            r = sub[i, 0] * n0 + sub[i, 1] * n1 + sub[i, 2] * n2 - d
            r2[i] = r * r
        normals[t, 0] = n0
        normals[t, 1] = n1
        normals[t, 2] = n2
        offsets[t] = d
        medians[t] = np.median(r2)
