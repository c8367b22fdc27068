"""Compiled kernels of the fits (private): the geometric sphere fit's Levenberg-Marquardt
iteration (:func:`telefringe.metrology.spheres._sphere_geometric`) and the robust
fixed-radius sphere fit. The same arithmetic as the NumPy forms they replace, in float64
without fastmath, so that a BGA's hundreds of small caps are not bound by NumPy's
per-call overhead. (The plane's kernels are in ``_plane_kernels``.)"""

from __future__ import annotations

import numba as nb
import numpy as np

# Small hand-written forms of the NumPy functions these kernels need. numba's own
# (np.percentile, np.median, np.linalg.solve / inv: LAPACK through scipy) each cost
# several CPU seconds of compilation in every kernel that uses them; these cost a
# fraction of one. The order statistics are exact (the same values as numba's);
# the 3 x 3 / 4 x 4 solves are LU with partial pivoting, LAPACK's algorithm, equal to
# it to rounding (tests/test_fit_kernels.py). Arrays are copied element by element, not
# by slice assignment, whose shape check compiles numba's string formatting (~5 s).


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _order_pair(a, k):
    """The (k+1)-th and (k+2)-th smallest values of ``a`` (n,) (0 <= k < n - 1), by
    partial selection (a quickselect that reorders ``a`` in place)."""
    lo = 0
    hi = a.size - 1
    while hi > lo:
        mid = (lo + hi) >> 1
        # median of three as the pivot: a[lo] <= a[mid] <= a[hi]
        if a[mid] < a[lo]:
            a[mid], a[lo] = a[lo], a[mid]
        if a[hi] < a[mid]:
            a[hi], a[mid] = a[mid], a[hi]
            if a[mid] < a[lo]:
                a[mid], a[lo] = a[lo], a[mid]
        pivot = a[mid]
        i = lo
        j = hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while pivot < a[j]:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        # a[lo:j + 1] <= pivot, a[j + 1:i] == pivot, a[i:hi + 1] >= pivot
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    nxt = a[k + 1]
    for i in range(k + 2, a.size):
        if a[i] < nxt:
            nxt = a[i]
    return a[k], nxt


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _percentile(h, q):
    """``np.percentile(h, q)`` of ``h`` (n,) for 0 < q < 100 (linear interpolation
    between the closest ranks, numba's formula; NaN where ``h`` holds a NaN or is
    empty)."""
    n = h.size
    for i in range(n):
        if np.isnan(h[i]):
            return np.nan
    if n == 0:
        return np.nan
    if n == 1:
        return h[0]
    rank = 1.0 + (n - 1) * (q / 100.0)
    f = np.floor(rank)
    m = rank - f
    lower, upper = _order_pair(h.copy(), int(f) - 1)
    return lower * (1 - m) + upper * m


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _median(a):
    """``np.median(a)`` of ``a`` (n,) (NaN where it holds a NaN or is empty)."""
    n = a.size
    for i in range(n):
        if np.isnan(a[i]):
            return np.nan
    if n == 0:
        return np.nan
    if n == 1:
        return a[0]
    half = n >> 1
    if n & 1 == 0:
        lo, hi = _order_pair(a.copy(), half - 1)
        return (lo + hi) / 2
    return _order_pair(a.copy(), half - 1)[1]


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _solve(A, B):
    """X (n, k) with A X = B for a small A (n, n) and B (n, k): LU with partial
    pivoting (the row of the largest magnitude; multipliers by the pivot's reciprocal,
    as LAPACK's getrf), forward then back substitution. Raises LinAlgError, as
    ``np.linalg.solve``, where A or B holds an inf or NaN or a pivot is exactly zero."""
    n = A.shape[0]
    for i in range(n):
        for j in range(n):
            if not np.isfinite(A[i, j]):
                raise np.linalg.LinAlgError("Array must not contain infs or NaNs.")
        for j in range(B.shape[1]):
            if not np.isfinite(B[i, j]):
                raise np.linalg.LinAlgError("Array must not contain infs or NaNs.")
    LU = A.copy()
    X = B.copy()
    for c in range(n):
        p = c
        big = abs(LU[c, c])
        for i in range(c + 1, n):
            if abs(LU[i, c]) > big:
                big = abs(LU[i, c])
                p = i
        if big == 0.0:
            raise np.linalg.LinAlgError("Matrix is singular to machine precision.")
        if p != c:
            for j in range(n):
                LU[c, j], LU[p, j] = LU[p, j], LU[c, j]
            for j in range(X.shape[1]):
                X[c, j], X[p, j] = X[p, j], X[c, j]
        rec = 1.0 / LU[c, c]
        for i in range(c + 1, n):
            LU[i, c] *= rec
        for i in range(c + 1, n):
            li = LU[i, c]
            for j in range(c + 1, n):
                LU[i, j] -= li * LU[c, j]
    for j in range(X.shape[1]):
        for c in range(n):
            for i in range(c + 1, n):
                X[i, j] -= LU[i, c] * X[c, j]
        for c in range(n - 1, -1, -1):
            X[c, j] /= LU[c, c]
            for i in range(c):
                X[i, j] -= LU[i, c] * X[c, j]
    return X


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _inv(A):
    """The inverse of a small A (n, n) (:func:`_solve` of the identity)."""
    return _solve(A, np.eye(A.shape[0]))


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
            sol = _solve(A, g.reshape((npar, 1)))
            for a in range(4):
                step[a] = -sol[a, 0] if a < npar else 0.0
                xn[a] = x[a] + step[a]
            cn = _cost(p, w, xn, fn, dn, distn)
            if cn <= cost:
                for a in range(4):
                    x[a] = xn[a]
                for i in range(m):
                    f[i] = fn[i]
                    dist[i] = distn[i]
                    for a in range(3):
                        d[i, a] = dn[i, a]
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


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _start_fixed(p, w, r):
    """The start of a fixed-radius fit of a cap seen from the camera side: the weighted total least
    squares plane of the points, the mean of their highest quarter along its normal, minus
    r times the normal."""
    m = p.shape[0]
    sw = 0.0
    for i in range(m):
        sw += w[i]
    c = np.zeros(3)
    for k in range(3):
        s = 0.0
        for i in range(m):
            s += p[i, k] * w[i]
        c[k] = s / sw
    S = np.zeros((3, 3))
    for a in range(3):
        for b in range(a, 3):
            s = 0.0
            for i in range(m):
                s += (p[i, a] - c[a]) * w[i] * (p[i, b] - c[b])
            S[a, b] = s
            S[b, a] = s
    _, evecs = np.linalg.eigh(S)
    n = evecs[:, 0].copy()
    if n[2] < 0:
        n = -n
    h = np.empty(m)
    for i in range(m):
        h[i] = (p[i, 0] - c[0]) * n[0] + (p[i, 1] - c[1]) * n[1] + (p[i, 2] - c[2]) * n[2]
    q = _percentile(h, 75.0)
    top = np.zeros(3)
    cnt = 0
    for i in range(m):
        if h[i] >= q:
            cnt += 1
            for k in range(3):
                top[k] += p[i, k]
    return top / cnt - r * n


@nb.njit(cache=True, nogil=True, error_model="numpy")
def sphere_fixed_robust(p, w, start, has_start, r, reject_k, rounds, mad):
    """The fixed-radius branch of :func:`telefringe.metrology.spheres.fit_sphere`: up to
    ``rounds`` fits (:func:`sphere_lm`, from ``start`` or :func:`_start_fixed`), each
    keeping the points whose radial residual times sqrt(w) is within ``reject_k`` robust
    (MAD) standard deviations of the last fit's, until the kept points repeat.

    Returns (ok, centre (3,), residuals f of the kept points, weighted Jacobian J, keep
    (m,) bool of the last fit); ok False when fewer than 5 points are kept.
    """
    m = p.shape[0]
    keep = np.ones(m, dtype=np.bool_)
    x = np.zeros(4)
    f = np.empty(0)
    J = np.empty((0, 3))
    fitted = keep.copy()
    sq = np.sqrt(w)
    for _ in range(rounds):
        n_keep = 0
        for i in range(m):
            n_keep += keep[i]
        if n_keep < 5:
            return False, x[:3].copy(), f, J, keep
        pk = np.empty((n_keep, 3))
        wk = np.empty(n_keep)
        j = 0
        for i in range(m):
            if keep[i]:
                for ax in range(3):
                    pk[j, ax] = p[i, ax]
                wk[j] = w[i]
                j += 1
        c0 = start if has_start else _start_fixed(pk, wk, r)
        x0 = np.array([c0[0], c0[1], c0[2], r])
        # np.int64, not the literals: one compiled signature for this call and
        # spheres._sphere_geometric's (a literal argument compiles its own)
        x, f, J = sphere_lm(pk, wk, x0, np.int64(3), np.int64(100))
        fitted = keep.copy()
        if rounds == 1:
            break
        a = np.empty(n_keep)
        for i in range(n_keep):
            a[i] = abs(f[i] * np.sqrt(wk[i]))
        scale = mad * _median(a) + 1e-15
        same = True
        new_keep = np.empty(m, dtype=np.bool_)
        for i in range(m):
            dx = p[i, 0] - x[0]
            dy = p[i, 1] - x[1]
            dz = p[i, 2] - x[2]
            res = (np.sqrt(dx * dx + dy * dy + dz * dz) - x[3]) * sq[i]
            new_keep[i] = abs(res) <= reject_k * scale
            same = same and new_keep[i] == keep[i]
        if same:
            break
        keep = new_keep
    return True, x[:3].copy(), f, J, fitted
