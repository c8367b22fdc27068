"""Compiled, ball-parallel kernels of the point-spread cap fits (private;
:func:`telefringe.metrology.bga.psf._fit_caps_smoothed`). The caps are packed one after
the other (points ``pts`` (N, 3) and per-point arrays; ball k owns rows
``off[k]:off[k + 1]``); each ball is fitted by one thread (``numba.prange``), the same
steps as the NumPy forms in ``psf`` (:func:`~telefringe.metrology.bga.psf._smoothing_shape`,
:func:`~telefringe.metrology.bga.psf._cap_residuals`,
:func:`~telefringe.metrology.bga.psf._schur_normal_equations`) and
:func:`telefringe.metrology.spheres.fit_sphere` (robust, fixed radius), in float64
without fastmath; sums run in point order, so results agree with the NumPy forms to
rounding (tests/test_bga_caps_kernels.py).

Status codes per ball: 0 fitted, 1 too few points, 2 fit failed, 3 too few points
facing the camera.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from telefringe.metrology._fit_kernels import _inv, _solve, sphere_fixed_robust

OK, TOO_FEW, FAILED, TOO_FEW_FACING = 0, 1, 2, 3


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _det3(A):
    return (A[0, 0] * (A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1])
            - A[0, 1] * (A[1, 0] * A[2, 2] - A[1, 2] * A[2, 0])
            + A[0, 2] * (A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]))


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _gram(J):
    """J^T J (n, n) of J (m, n), the sums in row order."""
    n = J.shape[1]
    G = np.zeros((n, n))
    for i in range(J.shape[0]):
        for a in range(n):
            for b in range(n):
                G[a, b] += J[i, a] * J[i, b]
    return G


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _shape(p, c, r, view, rho2_max):
    """cos of the surface tilt (clipped to [1e-3, 1]) and g = lap(z) / 2 of one point
    (see ``psf._smoothing_shape``)."""
    v0 = p[0] - c[0]
    v1 = p[1] - c[1]
    v2 = p[2] - c[2]
    along = v0 * view[0] + v1 * view[1] + v2 * view[2]
    vv = v0 * v0 + v1 * v1 + v2 * v2
    rho2 = min(max(vv - along * along, 0.0), rho2_max)
    g = (2.0 * r * r - rho2) / (2.0 * (r * r - rho2) ** 1.5)
    dist = np.sqrt(vv)
    cos_t = (v0 / dist) * view[0] + (v1 / dist) * view[1] + (v2 / dist) * view[2]
    return min(max(cos_t, 1e-3), 1.0), g


@nb.njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def prepare_caps(pts, sig, bg, view, off, r, rho2_max, cos_min, npar, reject_k, mad,
                 out_pts, out_R, out_w, out_view, counts, c0, status):
    """Per ball: drop points with a non-finite coordinate, sigma or gradient term (or
    sigma <= 0); a robust sphere of radius ``r`` (unit weights) gives each point's
    surface tilt; the points facing the camera (cos tilt >= ``cos_min``) are kept, with
    their regressors R = (g + B0, B1, B2)[:npar] and weights 1 / (sigma cos tilt)^2.

    pts (N, 3), sig (N,), bg (N, 3), view (N, 3) each point's unit vector toward the
    camera (one for all with a telecentric camera, each pixel's own with a pinhole);
    off (n_balls + 1,) int64. Outputs, ball k in rows off[k]:off[k] + counts[k]:
    out_pts (N, 3), out_R (N, npar), out_w (N,), out_view (N, 3); c0 (n_balls, 3) the
    start centres; status (n_balls,) int64 (see the module).
    """
    for k in nb.prange(off.size - 1):
        a = off[k]
        n = off[k + 1] - a
        p = np.empty((n, 3))
        s = np.empty(n)
        b = np.empty((n, 3))
        vw = np.empty((n, 3))
        m = 0
        for i in range(a, a + n):
            good = np.isfinite(sig[i]) and sig[i] > 0.0
            for j in range(3):
                good = good and np.isfinite(pts[i, j]) and np.isfinite(bg[i, j])
            if good:
                for j in range(3):
                    p[m, j] = pts[i, j]
                    b[m, j] = bg[i, j]
                    vw[m, j] = view[i, j]
                s[m] = sig[i]
                m += 1
        counts[k] = 0
        if m < 10:
            status[k] = TOO_FEW
            continue
        # np.bool_ / np.int64, not literals: the one signature spheres.fit_sphere and
        # fit_caps also call (a literal argument compiles its own, ~2.5 s each)
        ok, c, f, J, keep = sphere_fixed_robust(p[:m], np.ones(m), np.zeros(3),
                                                np.bool_(False), r, reject_k,
                                                np.int64(5), mad)
        if not ok or not (np.isfinite(c[0]) and np.isfinite(c[1]) and np.isfinite(c[2])):
            status[k] = FAILED
            continue
        if _det3(_gram(J)) == 0.0:  # fit_sphere's covariance would not invert
            status[k] = FAILED
            continue
        q = 0
        for i in range(m):
            cos_t, g = _shape(p[i], c, r, vw[i], rho2_max)
            if cos_t >= cos_min:
                row = a + q
                for j in range(3):
                    out_pts[row, j] = p[i, j]
                    out_view[row, j] = vw[i, j]
                out_R[row, 0] = g + b[i, 0]
                for j in range(1, npar):
                    out_R[row, j] = b[i, j]
                out_w[row] = 1.0 / (s[i] * cos_t) ** 2
                q += 1
        if q < 10:
            status[k] = TOO_FEW_FACING
            continue
        counts[k] = q
        for j in range(3):
            c0[k, j] = c[j]
        status[k] = OK


@nb.njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def fit_caps(pts, R, w, off, counts, c0, balls, theta, view, r, reject_k, mad,
             status, centre, cov, rms, form, n_inl, inl, q_out, A_out, b_out, chi2_out,
             dof_out, dc_out, schur_ok):
    """Per ball ``balls[t]`` (rows off[k]:off[k] + counts[k] of the arrays of
    :func:`prepare_caps`, ``view`` (N, 3) its ``out_view``): the points moved up their
    view direction by R . theta, a robust sphere of
    radius ``r`` from ``c0[k]`` weighted by w / mean(w), its covariance (3, 3), rms and
    form error, its inliers (``inl`` over the ball's rows) and moved points (``q_out``);
    then the radial residuals, Jacobians J (centre) and K (theta) at the inliers and the
    ball's share of the reduced normal equations of theta (weights w): A_out[t] (p, p),
    b_out[t] (p,), chi2_out[t], dof_out[t], and the centre's sensitivity dc_out[t]
    (3, p) = -H^-1 J^T W K (``schur_ok[t]`` False where H is singular). ``status[t]``:
    0 fitted, 2 failed.
    """
    npar = theta.size
    for t in nb.prange(balls.size):
        k = balls[t]
        a = off[k]
        m = counts[k]
        q = np.empty((m, 3))
        wf = np.empty(m)
        sw = 0.0
        for i in range(m):
            sh = 0.0
            for j in range(npar):
                sh += R[a + i, j] * theta[j]
            for j in range(3):
                q[i, j] = pts[a + i, j] + sh * view[a + i, j]
                q_out[a + i, j] = q[i, j]
            sw += w[a + i]
        mean_w = sw / m
        for i in range(m):
            wf[i] = w[a + i] / mean_w
        schur_ok[t] = False
        ok, c, f, J, keep = sphere_fixed_robust(q, wf, c0[k], np.bool_(True), r, reject_k,
                                                np.int64(5), mad)
        good = ok and np.isfinite(c[0]) and np.isfinite(c[1]) and np.isfinite(c[2])
        JtJ = _gram(J)
        if not good or _det3(JtJ) == 0.0:
            status[t] = FAILED
            continue
        nk = 0
        s2 = 0.0
        for i in range(m):
            inl[a + i] = keep[i]
            if keep[i]:
                s2 += wf[i] * f[nk] * f[nk]
                nk += 1
        s2 /= max(nk - 3, 1)
        JtJ_inv = _inv(JtJ)
        for x in range(3):
            for y in range(3):
                cov[t, x, y] = s2 * JtJ_inv[x, y]
        ss = 0.0
        fmin = np.inf
        fmax = -np.inf
        for i in range(nk):
            ss += f[i] * f[i]
            fmin = min(fmin, f[i])
            fmax = max(fmax, f[i])
        rms[t] = np.sqrt(ss / nk)
        form[t] = fmax - fmin
        n_inl[t] = nk
        for j in range(3):
            centre[t, j] = c[j]
        status[t] = OK
        # residuals and Jacobians at the inliers (psf._cap_residuals), reduced system
        H = np.zeros((3, 3))
        JWK = np.zeros((3, npar))
        JWr = np.zeros(3)
        KWK = np.zeros((npar, npar))
        KWr = np.zeros(npar)
        chi2 = 0.0
        nn = np.empty(3)
        Kr = np.empty(npar)
        for i in range(m):
            if not keep[i]:
                continue
            v0 = q[i, 0] - c[0]
            v1 = q[i, 1] - c[1]
            v2 = q[i, 2] - c[2]
            dist = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
            nn[0] = v0 / dist
            nn[1] = v1 / dist
            nn[2] = v2 / dist
            res = dist - r
            along = nn[0] * view[a + i, 0] + nn[1] * view[a + i, 1] + nn[2] * view[a + i, 2]
            wi = w[a + i]
            for j in range(npar):
                Kr[j] = along * R[a + i, j]
            for x in range(3):
                jx = -nn[x]
                JWr[x] += jx * wi * res
                for y in range(3):
                    H[x, y] += jx * wi * (-nn[y])
                for y in range(npar):
                    JWK[x, y] += jx * wi * Kr[y]
            for x in range(npar):
                KWr[x] += Kr[x] * wi * res
                for y in range(npar):
                    KWK[x, y] += Kr[x] * wi * Kr[y]
            chi2 += res * wi * res
        if _det3(H) == 0.0:
            continue
        HiJK = _solve(H, JWK)
        HiJf = _solve(H, JWr.reshape((3, 1)))
        for x in range(npar):
            for y in range(npar):
                s = 0.0
                for z in range(3):
                    s += JWK[z, x] * HiJK[z, y]
                A_out[t, x, y] = KWK[x, y] - s
            s = 0.0
            for z in range(3):
                s += JWK[z, x] * HiJf[z, 0]
            b_out[t, x] = KWr[x] - s
        chi2_out[t] = chi2
        dof_out[t] = nk - 3
        for x in range(3):
            for y in range(npar):
                dc_out[t, x, y] = -HiJK[x, y]
        schur_ok[t] = True
