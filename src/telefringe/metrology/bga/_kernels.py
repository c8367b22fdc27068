"""Compiled kernels of the BGA measurement (private). float64, no fastmath: the same
arithmetic as the NumPy forms they replace, in one pass without temporaries."""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True, error_model="numpy")
def footprint_counts(xyz, mask, T, c, s, origin, pitch, rows, cols, radius):
    """Valid points within ``radius`` (mm, on the plane) of each grid position.

    xyz : (h, w, 3) float64, mm; mask : (h, w) bool. T : (2, 3) float64, the substrate
    plane's in-plane axes. c, s : cos and sin of the grid's angle; origin : (2,) mm, grid
    position (0, 0) in that frame; pitch : mm. Per valid point q = T p, f = (q R -
    origin) / pitch with R = [[c, -s], [s, c]] (x' along the columns, y' along the rows),
    k = round(f); counted at (k_y, k_x) when on the grid and |f - k| pitch < radius.
    Returns (rows, cols) int64."""
    counts = np.zeros((rows, cols), dtype=np.int64)
    h, w = mask.shape
    for r in range(h):
        for j in range(w):
            if not mask[r, j]:
                continue
            x = xyz[r, j, 0]
            y = xyz[r, j, 1]
            z = xyz[r, j, 2]
            p0 = x * T[0, 0] + y * T[0, 1] + z * T[0, 2]
            p1 = x * T[1, 0] + y * T[1, 1] + z * T[1, 2]
            f0 = (p0 * c + p1 * s - origin[0]) / pitch
            f1 = (p0 * -s + p1 * c - origin[1]) / pitch
            k0 = np.rint(f0)
            k1 = np.rint(f1)
            if not (0.0 <= k0 < cols and 0.0 <= k1 < rows):
                continue
            if np.hypot(f0 - k0, f1 - k1) * pitch < radius:
                counts[int(k1), int(k0)] += 1
    return counts


@nb.njit(inline="always")
def _grad(f, r, j, h, w):
    """np.gradient of f (h, w) at (r, j), unit spacing, first-order edges: (d/dr, d/dj)."""
    if r == 0:
        gv = f[1, j] - f[0, j]
    elif r == h - 1:
        gv = f[h - 1, j] - f[h - 2, j]
    else:
        gv = (f[r + 1, j] - f[r - 1, j]) / 2.0
    if j == 0:
        gu = f[r, 1] - f[r, 0]
    elif j == w - 1:
        gu = f[r, w - 1] - f[r, w - 2]
    else:
        gu = (f[r, j + 1] - f[r, j - 1]) / 2.0
    return gv, gu


@nb.njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def log_and_depth(image, xyz, mask, directions, ln_i, t):
    """ln_i = log(image) where image > 0, else NaN; t = x . d, each valid point's
    position along its pixel's viewing direction d (mm), NaN where invalid. image, mask
    : (h, w); xyz, directions : (h, w, 3) (directions may be a broadcast view); ln_i, t :
    (h, w) float64 outputs. Rows in parallel."""
    h, w = mask.shape
    for r in nb.prange(h):
        for j in range(w):
            v = image[r, j]
            ln_i[r, j] = np.log(v) if v > 0 else np.nan
            if mask[r, j]:
                t[r, j] = (xyz[r, j, 0] * directions[r, j, 0] + xyz[r, j, 1]
                           * directions[r, j, 1] + xyz[r, j, 2] * directions[r, j, 2])
            else:
                t[r, j] = np.nan


@nb.njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def gradient_terms(ln_i, t, px2, out):
    """out[..., 0] = (gi_u gt_u + gi_v gt_v) / px2, out[..., 1] = gi_u, out[..., 2] = gi_v
    with (gi_v, gi_u) = np.gradient(ln_i), (gt_v, gt_u) = np.gradient(t) (the same
    arithmetic). ln_i, t : (h, w) float64, h, w >= 2; out : (h, w, 3) float64. Rows in
    parallel."""
    h, w = ln_i.shape
    for r in nb.prange(h):
        for j in range(w):
            gi_v, gi_u = _grad(ln_i, r, j, h, w)
            gt_v, gt_u = _grad(t, r, j, h, w)
            out[r, j, 0] = (gi_u * gt_u + gi_v * gt_v) / px2
            out[r, j, 1] = gi_u
            out[r, j, 2] = gi_v


@nb.njit(cache=True, nogil=True, error_model="numpy")
def heights(xyz, mask, normal, offset, out):
    """out = x . normal - offset per valid pixel (NaN where ``mask`` is False): the signed
    height (mm) of each point above the plane. xyz : (h, w, 3) float64; mask : (h, w)
    bool; normal : (3,); out : (h, w) float64."""
    h, w = mask.shape
    for r in range(h):
        for j in range(w):
            if mask[r, j]:
                out[r, j] = (xyz[r, j, 0] * normal[0] + xyz[r, j, 1] * normal[1]
                             + xyz[r, j, 2] * normal[2]) - offset
            else:
                out[r, j] = np.nan


@nb.njit(cache=True, nogil=True, error_model="numpy")
def row_steps(xyz):
    """The finite distances (mm) in x and y between each point and its right-hand
    neighbour, sqrt(dx^2 + dy^2) (as ``np.linalg.norm(np.diff(xyz[..., :2], axis=1),
    axis=2)`` without its NaNs), in row order. xyz : (h, w, 3) float64."""
    h, w, _ = xyz.shape
    out = np.empty(h * max(w - 1, 0))
    k = 0
    for r in range(h):
        for j in range(w - 1):
            dx = xyz[r, j + 1, 0] - xyz[r, j, 0]
            dy = xyz[r, j + 1, 1] - xyz[r, j, 1]
            s = np.sqrt(dx * dx + dy * dy)
            if np.isfinite(s):
                out[k] = s
                k += 1
    return out[:k]


@nb.njit(cache=True, nogil=True)
def within_taxicab(mask, k):
    """Pixels within city-block distance ``k`` (>= 1) of a True pixel of ``mask`` (h, w):
    the same as ``scipy.ndimage.binary_dilation(mask, iterations=k)`` with its default
    cross structure (k dilations by the 4-neighbourhood reach exactly the pixels within
    city-block distance k, paths staying inside the image). Two raster passes of the
    exact 4-neighbour distance transform. Returns (h, w) bool."""
    h, w = mask.shape
    big = h + w + 1
    d = np.empty((h, w), dtype=np.int64)
    for r in range(h):
        for j in range(w):
            v = 0 if mask[r, j] else big
            if r > 0:
                v = min(v, d[r - 1, j] + 1)
            if j > 0:
                v = min(v, d[r, j - 1] + 1)
            d[r, j] = v
    out = np.empty((h, w), dtype=np.bool_)
    for r in range(h - 1, -1, -1):
        for j in range(w - 1, -1, -1):
            v = d[r, j]
            if r < h - 1:
                v = min(v, d[r + 1, j] + 1)
            if j < w - 1:
                v = min(v, d[r, j + 1] + 1)
            d[r, j] = v
            out[r, j] = v <= k
    return out


@nb.njit(cache=True, nogil=True)
def eroded_taxicab(mask, k):
    """Pixels of ``mask`` (h, w) bool whose city-block distance to every False pixel,
    and to every pixel outside the array, exceeds ``k`` (>= 1): the same as
    ``scipy.ndimage.binary_erosion(mask, iterations=k)`` with its default cross
    structure and border value 0. Two raster passes of the exact 4-neighbour distance
    transform to the nearest False pixel (the outside counting as False)."""
    h, w = mask.shape
    big = h + w + 1
    d = np.empty((h, w), dtype=np.int64)
    for r in range(h):
        for j in range(w):
            v = big if mask[r, j] else 0
            v = min(v, d[r - 1, j] + 1 if r > 0 else 1)
            v = min(v, d[r, j - 1] + 1 if j > 0 else 1)
            d[r, j] = v
    out = np.empty((h, w), dtype=np.bool_)
    for r in range(h - 1, -1, -1):
        for j in range(w - 1, -1, -1):
            v = d[r, j]
            v = min(v, d[r + 1, j] + 1 if r < h - 1 else 1)
            v = min(v, d[r, j + 1] + 1 if j < w - 1 else 1)
            d[r, j] = v
            out[r, j] = v > k
    return out


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _spot_model(P, n0, n1, m, J):
    """A pixel-integrated 2D Gaussian + background, P = (a, x, y, sg, b), on an n0 x n1
    window (row-major): model m (n0 n1,) and Jacobian J (n0 n1, 5)."""
    a, x, y, sg, b = P[0], P[1], P[2], P[3], P[4]
    r2 = np.sqrt(2.0)
    c_pdf = 1.0 / np.sqrt(2.0 * np.pi)
    ex = np.empty(n1)
    dex = np.empty(n1)
    dsx = np.empty(n1)
    ey = np.empty(n0)
    dey = np.empty(n0)
    dsy = np.empty(n0)
    for grid_n, c, e, de_dc, de_ds in ((n1, x, ex, dex, dsx), (n0, y, ey, dey, dsy)):
        for i in range(grid_n):
            zp = (i + 0.5 - c) / (r2 * sg)
            zm = (i - 0.5 - c) / (r2 * sg)
            ep = np.exp(-zp * zp)
            em = np.exp(-zm * zm)
            e[i] = 0.5 * (math.erf(zp) - math.erf(zm))
            de_dc[i] = -c_pdf / sg * (ep - em)
            de_ds[i] = -(r2 * c_pdf) / sg * (zp * ep - zm * em)
    k = 0
    for v in range(n0):
        for u in range(n1):
            g = ey[v] * ex[u]
            m[k] = a * g + b
            J[k, 0] = g
            J[k, 1] = a * ey[v] * dex[u]
            J[k, 2] = a * dey[v] * ex[u]
            J[k, 3] = a * (ey[v] * dsx[u] + dsy[v] * ex[u])
            J[k, 4] = 1.0
            k += 1


@nb.njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def gauss_spots(W, P0, lo, hi, max_iter, P_out, cost_out, JtJ_out, ok_out):
    """Levenberg-Marquardt fits of :func:`_spot_model` to each window ``W`` (n, n0, n1)
    from ``P0`` (n, 5), bounds ``lo``, ``hi`` (5,) applied by projection: damping
    ``H + lam diag(H)``, lam from 1e-3, /10 on a better step (>= 1e-12), x10 otherwise;
    a window is done when its cost falls by at most 1e-12 of itself, its parameters move
    by less than 1e-10 relative (+1e-3), or lam reaches 1e12. Outputs per window: the
    parameters, the cost (sum of squared residuals), J^T J (5, 5) at the solution, and
    ok False where a damped system was singular (the fit stopped there). Windows in
    parallel."""
    n, n0, n1 = W.shape
    npx = n0 * n1
    for k in nb.prange(n):
        Y = W[k].reshape(npx)
        P = P0[k].copy()
        m = np.empty(npx)
        J = np.empty((npx, 5))
        mn = np.empty(npx)
        Jn = np.empty((npx, 5))
        _spot_model(P, n0, n1, m, J)
        r = m - Y
        cost = np.sum(r * r)
        lam = 1e-3
        ok = True
        for _ in range(max_iter):
            H = J.T @ J
            g = J.T @ r
            A = H.copy()
            for i in range(5):
                A[i, i] += lam * H[i, i]
            if np.linalg.det(A) == 0.0:
                ok = False
                break
            step = -np.linalg.solve(A, g)
            Pn = np.minimum(np.maximum(P + step, lo), hi)
            _spot_model(Pn, n0, n1, mn, Jn)
            rn = mn - Y
            cn = np.sum(rn * rn)
            small = np.max(np.abs(Pn - P) / (np.abs(P) + 1e-3)) < 1e-10
            better = cn < cost
            done = small
            if better:
                done = done or (cost - cn) <= 1e-12 * cost
                P = Pn
                r = rn
                J[:, :] = Jn
                cost = cn
                lam = max(lam / 10, 1e-12)
            else:
                lam = min(lam * 10, 1e12)
            if done or lam >= 1e12:
                break
        P_out[k] = P
        cost_out[k] = cost
        JtJ_out[k] = J.T @ J
        ok_out[k] = ok


@nb.njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def highlight_lines(P, xs, ys, d, centres, radii, cov_uv, sig_surface, lines, hl, hl_cov):
    """Each highlight's camera line and its front intersection with the ball's sphere
    (:func:`telefringe.metrology.bga.highlights._refine_by_highlights`), one ball per
    thread.

    P (n, s, s, 3): the points of each highlight's s x s window (NaN where invalid),
    s = 2 h + 1; xs, ys (n,): the spot's centre in window pixels; d (3,): the viewing
    direction; centres (n, 3), radii (n,): the balls' spheres; cov_uv (n, 2, 2): the
    spot centre's covariance; sig_surface (n,): the surface's uncertainty along d.
    Per ball with at least 12 valid points: the points' components across d,
    q(u, v) = p - (p . d) d, fitted with a quadratic in the pixel offsets from the spot
    (least squares, ``np.linalg.lstsq`` with NumPy's default cut-off); lines[k] = q at
    the spot, hl[k] = its front intersection with the sphere, hl_cov[k] = J cov_uv J^T
    + sig_surface^2 d d^T (J = dq / d(u, v)); they stay NaN where the line misses the
    sphere or there are too few points.
    """
    n, s = P.shape[0], P.shape[1]
    h = (s - 1) // 2
    for k in nb.prange(n):
        m = 0
        for v in range(s):
            for u in range(s):
                if (np.isfinite(P[k, v, u, 0]) and np.isfinite(P[k, v, u, 1])
                        and np.isfinite(P[k, v, u, 2])):
                    m += 1
        if m < 12:
            continue
        A = np.empty((m, 6))
        Q = np.empty((m, 3))
        i = 0
        for v in range(s):
            for u in range(s):
                p0, p1, p2 = P[k, v, u, 0], P[k, v, u, 1], P[k, v, u, 2]
                if not (np.isfinite(p0) and np.isfinite(p1) and np.isfinite(p2)):
                    continue
                along = p0 * d[0] + p1 * d[1] + p2 * d[2]
                Q[i, 0] = p0 - along * d[0]
                Q[i, 1] = p1 - along * d[1]
                Q[i, 2] = p2 - along * d[2]
                du = (u - h) - (xs[k] - h)
                dv = (v - h) - (ys[k] - h)
                A[i, 0] = 1.0
                A[i, 1] = du
                A[i, 2] = dv
                A[i, 3] = du * du
                A[i, 4] = du * dv
                A[i, 5] = dv * dv
                i += 1
        coef = np.linalg.lstsq(A, Q, rcond=np.finfo(np.float64).eps * max(m, 6))[0]
        q = coef[0]
        w0 = q[0] - centres[k, 0]
        w1 = q[1] - centres[k, 1]
        w2 = q[2] - centres[k, 2]
        b = w0 * d[0] + w1 * d[1] + w2 * d[2]
        disc = b * b - ((w0 * w0 + w1 * w1 + w2 * w2) - radii[k] ** 2)
        if not disc >= 0:
            continue
        t = -b - np.sqrt(disc)
        J = np.ascontiguousarray(coef[1:3].T)  # (3, 2)
        C = J @ cov_uv[k] @ J.T
        for a in range(3):
            lines[k, a] = q[a]
            hl[k, a] = q[a] + t * d[a]
            for c in range(3):
                hl_cov[k, a, c] = C[a, c] + sig_surface[k] ** 2 * d[a] * d[c]
