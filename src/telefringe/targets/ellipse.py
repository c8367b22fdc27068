"""Ellipse fits of a marker's image: the algebraic fit of edge points, and the blurred-
ellipse intensity model (its Jacobian, a compiled kernel of its normal equations and the
Gauss-Newton fit of a marker window).

Under telecentric projection a circle images as an ellipse whose centre is the image of
the circle's centre (affine maps keep centres), so a marker's centre is the centre of the
fitted ellipse.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["fit_ellipse"]


# --------------------------------------------------------------------------- ellipse fit
def _axes_of(Q: np.ndarray):
    """Semi-axes and angle (a, b, theta) of the ellipse ``p^T Q p = 1`` (Q (2, 2)
    symmetric): a >= b, theta of the major axis in (-pi/2, pi/2]; None unless Q is
    positive definite."""
    ev, evec = np.linalg.eigh(Q)
    if not np.all(np.isfinite(ev)) or np.any(ev <= 0):
        return None
    # ev ascending: the smaller eigenvalue belongs to the major axis
    d = evec[:, 0]
    theta = float(np.arctan2(d[1], d[0]))
    if theta > np.pi / 2:
        theta -= np.pi
    elif theta <= -np.pi / 2:
        theta += np.pi
    return 1 / np.sqrt(ev[0]), 1 / np.sqrt(ev[1]), theta


def fit_ellipse(x, y):
    """Direct least-squares ellipse fit (Fitzgibbon, Pilu and Fisher; in the numerically
    stable form of Halir and Flusser) to points (x, y).

    Parameters
    ----------
    x, y : (n,) array_like of float, n >= 6.

    Returns
    -------
    params : (5,) ndarray, (x_c, y_c, a, b, theta), semi-axes a >= b, theta the angle
        of the major axis from +x (rad, in (-pi/2, pi/2]).
    rms : float, RMS of the (first-order) geometric distance of the points from it.

    Raises
    ------
    ValueError
        Fewer than 6 points, or no ellipse fits (collinear or degenerate points).
    """
    x = np.asarray(x, dtype=float).ravel()
    y = np.asarray(y, dtype=float).ravel()
    if x.size < 6 or x.size != y.size:
        raise ValueError("fit_ellipse needs at least 6 points (x and y of equal length)")
    mx, my = x.mean(), y.mean()
    s = max(np.sqrt(np.mean((x - mx) ** 2 + (y - my) ** 2)), 1e-12)
    xs, ys = (x - mx) / s, (y - my) / s
    D1 = np.column_stack([xs * xs, xs * ys, ys * ys])
    D2 = np.column_stack([xs, ys, np.ones_like(xs)])
    S1, S2, S3 = D1.T @ D1, D1.T @ D2, D2.T @ D2
    try:
        T = -np.linalg.solve(S3, S2.T)
    except np.linalg.LinAlgError:
        raise ValueError("fit_ellipse: degenerate points") from None
    M = S1 + S2 @ T
    M = np.array([M[2] / 2.0, -M[1], M[0] / 2.0])
    w, V = np.linalg.eig(M)
    V = np.real(V)
    cond = 4.0 * V[0] * V[2] - V[1] ** 2
    ok = np.flatnonzero(cond > 0)
    if ok.size == 0:
        raise ValueError("fit_ellipse: no ellipse fits these points")
    a1 = V[:, ok[np.argmin(np.abs(np.real(w[ok])))]]
    A, B, C = a1
    Dd, E, F = T @ a1
    # undo the normalisation: conic in original coordinates
    A0, B0, C0 = A / s**2, B / s**2, C / s**2
    D0 = Dd / s - 2 * A0 * mx - B0 * my
    E0 = E / s - 2 * C0 * my - B0 * mx
    F0 = F + A0 * mx**2 + B0 * mx * my + C0 * my**2 - Dd / s * mx - E / s * my
    det = 4 * A0 * C0 - B0**2
    if det <= 0:
        raise ValueError("fit_ellipse: no ellipse fits these points")
    xc = (B0 * E0 - 2 * C0 * D0) / det
    yc = (B0 * D0 - 2 * A0 * E0) / det
    Fc = A0 * xc**2 + B0 * xc * yc + C0 * yc**2 + D0 * xc + E0 * yc + F0
    Q = np.array([[A0, B0 / 2], [B0 / 2, C0]]) / (-Fc)
    axes = _axes_of(Q)
    if axes is None:
        raise ValueError("fit_ellipse: no ellipse fits these points")
    params = np.array([xc, yc, *axes])
    # first-order geometric distance: (q - 1) / |grad q| with q = p^T Q p
    px, py = x - xc, y - yc
    q = Q[0, 0] * px**2 + 2 * Q[0, 1] * px * py + Q[1, 1] * py**2
    gx = 2 * (Q[0, 0] * px + Q[0, 1] * py)
    gy = 2 * (Q[0, 1] * px + Q[1, 1] * py)
    dist = (q - 1) / np.maximum(np.hypot(gx, gy), 1e-300)
    return params, float(np.sqrt(np.mean(dist**2)))


def _ellipse_quadratic(params):
    """(2, 2) matrix Q with p^T Q p = 1 on the ellipse (p relative to the centre)."""
    _, _, a, b, th = params
    c, s = np.cos(th), np.sin(th)
    Rm = np.array([[c, -s], [s, c]])
    return Rm @ np.diag([1 / a**2, 1 / b**2]) @ Rm.T


def _blurred_ellipse(theta, x, y, *, jacobian: bool = False):
    """Image model of a dark ellipse on a planar background, blurred (Gaussian edge).

    ``theta`` (10,): (x_c, y_c, q11, q12, q22, sigma, depth, b0, b1, b2); ``x``, ``y``
    (n,) pixel coordinates relative to a fixed origin. Returns the model (n,) and, with
    ``jacobian``, its derivatives (n, 10). The edge distance is the first-order distance
    ``d = F / |grad F|`` of ``F = p^T Q p - 1``; its error grows with the distance from the
    edge but is the same at opposite points of the ellipse, so it changes the fitted
    size, not the centre.

    The lens blurs the irradiance, the product of the illumination ``b`` (the plane
    ``b0 + b1 x + b2 y``) and the reflectance ``M = 1 - depth * shade``: for a PSF of
    variance ``sigma^2`` and a linear ``b``, ``(b M) * PSF = b (M * PSF) + sigma^2
    grad b . grad (M * PSF)`` (exact for a Gaussian PSF). The second term is
    ``depth * sigma * phi(d / sigma) * (grad b . n)``, n the edge normal ``grad F / |grad
    F|``; without it the fitted edge moves by ``-sigma^2 grad b / b`` and the centre with
    it (measured on rendered markers: the detected centre's error regresses on
    ``grad ln b`` with slope -0.28 and -0.53 (u, v) at sigma^2 = 0.33 px^2, -1.03 and -1.19
    at 1.08 px^2; tests/test_targets.py renders a steep gradient).
    """
    from scipy.special import ndtr

    xc, yc, q11, q12, q22, sig, depth, b0, b1, b2 = theta
    px = x - xc
    py = y - yc
    qx = q11 * px + q12 * py
    qy = q12 * px + q22 * py
    F = px * qx + py * qy - 1.0
    G = np.sqrt(qx * qx + qy * qy) + 1e-300
    d = F / (2.0 * G)
    z = d / sig
    shade = ndtr(-z)  # 1 inside, 0 outside
    back = b0 + b1 * x + b2 * y
    one = 1.0 - depth * shade
    phi = np.exp(-0.5 * z * z) / np.sqrt(2.0 * np.pi)
    h = b1 * qx + b2 * qy  # grad b . n = h / G
    gn = h / G
    model = back * one + depth * sig * phi * gn
    if not jacobian:
        return model
    # d model / d d (n held): back depth phi / sig - depth z phi gn
    dM_dd = depth * phi * (back / sig - z * gn)
    # d = F / (2 G): dd = dF / (2 G) - F dG / (2 G^2), dG = (qx dqx + qy dqy) / G;
    # d gn = (b1 dqx + b2 dqy) / G - h dG / G^2
    a1 = dM_dd / (2.0 * G)
    c1 = depth * sig * phi / G
    a2 = dM_dd * F / (2.0 * G * G * G) + c1 * h / (G * G)  # times (qx dqx + qy dqy)
    J = np.empty((x.size, 10))
    J[:, 0] = a1 * (-2 * qx) - a2 * (qx * -q11 + qy * -q12) + c1 * (b1 * -q11 + b2 * -q12)
    J[:, 1] = a1 * (-2 * qy) - a2 * (qx * -q12 + qy * -q22) + c1 * (b1 * -q12 + b2 * -q22)
    J[:, 2] = a1 * (px * px) - a2 * (qx * px) + c1 * (b1 * px)
    J[:, 3] = a1 * (2 * px * py) - a2 * (qx * py + qy * px) + c1 * (b1 * py + b2 * px)
    J[:, 4] = a1 * (py * py) - a2 * (qy * py) + c1 * (b2 * py)
    J[:, 5] = -dM_dd * z + depth * phi * gn
    J[:, 6] = -back * shade + sig * phi * gn
    J[:, 7] = one
    J[:, 8] = x * one + c1 * qx
    J[:, 9] = y * one + c1 * qy
    return model, J


def _normal_equations_py(theta, x, y, z):
    """(J^T J, J^T r, r^T r) of :func:`_blurred_ellipse` at ``theta`` (reference code
    for the compiled kernel)."""
    model, J = _blurred_ellipse(theta, x, y, jacobian=True)
    r = z - model
    return J.T @ J, J.T @ r, float(r @ r)


def _make_kernel():
    try:
        import numba
    except ImportError:  # pragma: no cover - numba is a dependency
        return _normal_equations_py

    @numba.njit(cache=True, fastmath=False)
    def kernel(theta, x, y, z):
        xc, yc, q11, q12, q22, sig, depth, b0, b1, b2 = theta
        A = np.zeros((10, 10))
        g = np.zeros(10)
        cost = 0.0
        j = np.empty(10)
        k = 1.0 / np.sqrt(2.0 * np.pi)
        for i in range(x.size):
            px = x[i] - xc
            py = y[i] - yc
            qx = q11 * px + q12 * py
            qy = q12 * px + q22 * py
            F = px * qx + py * qy - 1.0
            G = np.sqrt(qx * qx + qy * qy) + 1e-300
            d = F / (2.0 * G)
            zz = d / sig
            shade = 0.5 * math.erfc(zz / np.sqrt(2.0))
            back = b0 + b1 * x[i] + b2 * y[i]
            one = 1.0 - depth * shade
            phi = np.exp(-0.5 * zz * zz) * k
            h = b1 * qx + b2 * qy
            gn = h / G
            r = z[i] - (back * one + depth * sig * phi * gn)
            dmd = depth * phi * (back / sig - zz * gn)
            a1 = dmd / (2.0 * G)
            c1 = depth * sig * phi / G
            a2 = dmd * F / (2.0 * G * G * G) + c1 * h / (G * G)
            j[0] = a1 * (-2.0 * qx) - a2 * (qx * -q11 + qy * -q12) + c1 * (b1 * -q11 + b2 * -q12)
            j[1] = a1 * (-2.0 * qy) - a2 * (qx * -q12 + qy * -q22) + c1 * (b1 * -q12 + b2 * -q22)
            j[2] = a1 * (px * px) - a2 * (qx * px) + c1 * (b1 * px)
            j[3] = a1 * (2.0 * px * py) - a2 * (qx * py + qy * px) + c1 * (b1 * py + b2 * px)
            j[4] = a1 * (py * py) - a2 * (qy * py) + c1 * (b2 * py)
            j[5] = -dmd * zz + depth * phi * gn
            j[6] = -back * shade + sig * phi * gn
            j[7] = one
            j[8] = x[i] * one + c1 * qx
            j[9] = y[i] * one + c1 * qy
            for p in range(10):
                g[p] += j[p] * r
                for q in range(p, 10):
                    A[p, q] += j[p] * j[q]
            cost += r * r
        for p in range(10):
            for q in range(p):
                A[p, q] = A[q, p]
        return A, g, cost

    return kernel


_KERNEL = None


def _normal_equations(theta, x, y, z):
    global _KERNEL
    if _KERNEL is None:
        _KERNEL = _make_kernel()
    return _KERNEL(np.ascontiguousarray(theta, dtype=np.float64), x, y, z)


def _fit_blurred_ellipse(win, xx, yy, params, bg, origin, depth, *, max_iter=15):
    """Gauss-Newton fit of :func:`_blurred_ellipse` to the pixels near a marker's edge.

    The model is evaluated at the pixel centres, so its error does not depend on where
    the edge falls within a pixel (the interpolation of edge crossings does, and leaves a
    bias of about 0.01 px on 20-40 px markers). ``params`` (x_c, y_c, a, b, theta) is the
    start. Returns (params (5,), residual rms relative to the background, centre
    covariance (2, 2) px^2) or None.

    The centre's covariance is the fit's, ``s^2 (J^T J)^-1`` with ``s^2`` the residuals'
    variance (cost over the n - 10 degrees of freedom) at the solution: the image noise
    and whatever of the image the model does not fit, taken as independent per pixel.
    On markers rendered by the fast virtual rig with its noise, the centres' RMS error
    over sigma is 0.84 (u) and 0.91 (v) with 21 x 21 edge sub-samples, 1.01 and 1.21 with
    the renderer's default 7 x 7, whose midpoint integration adds an error of its own
    (benchmarks/detector_bias.py; tests/test_spacing_centre_sigma.py).
    """
    xc, yc, a, b, th = params
    c, s_ = np.cos(th), np.sin(th)
    Rm = np.array([[c, -s_], [s_, c]])
    Q = Rm @ np.diag([1 / a**2, 1 / b**2]) @ Rm.T
    ox, oy = origin
    # pixels within ~4 px of the edge
    px, py = xx - xc, yy - yc
    Fq = Q[0, 0] * px**2 + 2 * Q[0, 1] * px * py + Q[1, 1] * py**2 - 1
    g = 2 * np.hypot(Q[0, 0] * px + Q[0, 1] * py, Q[0, 1] * px + Q[1, 1] * py)
    sel = np.abs(Fq / np.maximum(g, 1e-12)) < 4.0
    x, y, z = (xx - ox)[sel].astype(float), (yy - oy)[sel].astype(float), win[sel]
    if z.size < 30:
        return None
    theta = np.array([xc - ox, yc - oy, Q[0, 0], Q[0, 1], Q[1, 1], 0.8, depth,
                      bg[0], bg[1], bg[2]], dtype=float)
    x = np.ascontiguousarray(x, dtype=np.float64)
    y = np.ascontiguousarray(y, dtype=np.float64)
    z = np.ascontiguousarray(z, dtype=np.float64)
    A, g_, cost = _normal_equations(theta, x, y, z)
    lam = 1e-6  # the start (blob moments) is close: begin near Gauss-Newton
    for _ in range(max_iter):
        dA = np.maximum(np.diag(A), 1e-300)
        try:
            delta = np.linalg.solve(A + lam * np.diag(dA), g_)
        except np.linalg.LinAlgError:
            return None
        trial = theta + delta
        A2, g2, c2 = _normal_equations(trial, x, y, z)
        if np.isfinite(c2) and c2 <= cost:
            theta, A, g_, cost = trial, A2, g2, c2
            lam = max(lam / 10, 1e-9)
            if np.max(np.abs(delta[:2])) < 1e-4:  # px; the noise is ~50x larger
                break
        else:
            lam *= 10
            if lam > 1e6:
                break
    q11, q12, q22 = theta[2:5]
    if not np.all(np.isfinite(theta)) or not 0.05 < abs(theta[5]) < 10:
        return None
    axes = _axes_of(np.array([[q11, q12], [q12, q22]]))
    if axes is None or np.hypot(theta[0] + ox - xc, theta[1] + oy - yc) > 2.0:
        return None
    out = np.array([theta[0] + ox, theta[1] + oy, *axes])
    rms = float(np.sqrt(cost / z.size)) / max(abs(theta[7]), 1e-12)
    try:  # A is the normal matrix at theta (updated with every accepted step)
        cov = cost / (z.size - theta.size) * np.linalg.inv(A)[:2, :2]
    except np.linalg.LinAlgError:
        return None
    if not (np.all(np.isfinite(cov)) and cov[0, 0] >= 0 and cov[1, 1] >= 0):
        return None
    return out, rms, cov
