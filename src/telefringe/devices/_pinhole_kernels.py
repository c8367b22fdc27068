"""Compiled scalar form of the pinhole device model (numba): the one copy of
:class:`telefringe.devices.pinhole.PinholeDevice`'s formulas that kernels call (the
reconstruction's compiled solver).

The NumPy model in :mod:`telefringe.devices.pinhole` (with
:mod:`telefringe.geometry.distortion`) is the reference these are tested against.

A device is passed to the kernels as plain numbers (see :func:`kernel_args`)::

    intr = (fx, fy, cx, cy, k1, k2, p1, p2, k3)   # px, px, OpenCV's distortion
    R    = R_dev_world (3, 3), flattened row-major to a 9-tuple inside the kernels
    t    = (tx, ty, tz) mm

Forward: ``Y = R X + t``, ``x, y = Y0 / Y2, Y1 / Y2`` (NaN where Y2 <= 0), OpenCV's
distortion, ``u = fx xd + cx``, ``v = fy yd + cy``.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["kernel_args", "distort_point", "distortion_jacobian", "is_unfolded",
           "project_point", "project_many", "undistort_point", "backproject_many"]

_EPS = 2.220446049250313e-16


def kernel_args(device):
    """``(intr, R, t)`` of a PinholeDevice for the kernels: ``intr`` the 9-tuple of floats
    above, ``R`` (3, 3) and ``t`` (3,) contiguous float64 (writable copies)."""
    k = device.intrinsics
    intr = (float(k.fx), float(k.fy), float(k.cx), float(k.cy), float(k.k1), float(k.k2),
            float(k.p1), float(k.p2), float(k.k3))
    # fresh writable copies whatever the device's arrays are (read-only, views): numba
    # compiles one signature per array flag, so a read-only R would cost a second compile
    return (intr, np.array(device.R_dev_world, dtype=np.float64, order="C"),
            np.array(device.t_dev, dtype=np.float64, order="C"))


@numba.njit(inline="always")
def distort_point(x, y, k1, k2, p1, p2, k3):  # pragma: no cover - numba
    """Normalised (x, y) -> distorted (xd, yd), OpenCV's model."""
    r2 = x * x + y * y
    a = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return (x * a + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * a + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)


@numba.njit(inline="always")
def distortion_jacobian(x, y, k1, k2, p1, p2, k3):  # pragma: no cover - numba
    """d(xd, yd)/d(x, y) as (a, b, c, d) = [[a, b], [c, d]]."""
    r2 = x * x + y * y
    rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    D = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    a = rad + 2.0 * x * x * D + 2.0 * p1 * y + 6.0 * p2 * x
    b = 2.0 * x * y * D + 2.0 * p1 * x + 2.0 * p2 * y
    d = rad + 2.0 * y * y * D + 6.0 * p1 * y + 2.0 * p2 * x
    return a, b, b, d


@numba.njit(inline="always")
def is_unfolded(a, b, c, d):  # pragma: no cover - numba
    """Whether the distortion is invertible at a point of Jacobian [[a, b], [c, d]] (the
    fold test of :func:`telefringe.geometry.distortion.undistort_normalized`)."""
    return (a * d - b * c > 0.0) & (a + d > 0.0)


@numba.njit(inline="always")
def project_point(X0, X1, X2, intr, R9, t0, t1, t2):  # pragma: no cover - numba
    """World point (mm) -> observed pixel (u, v); NaN at or behind the device."""
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = intr
    Y0 = R9[0] * X0 + R9[1] * X1 + R9[2] * X2 + t0
    Y1 = R9[3] * X0 + R9[4] * X1 + R9[5] * X2 + t1
    Y2 = R9[6] * X0 + R9[7] * X1 + R9[8] * X2 + t2
    if not Y2 > 0.0:
        return np.nan, np.nan
    iz = 1.0 / Y2
    xd, yd = distort_point(Y0 * iz, Y1 * iz, k1, k2, p1, p2, k3)
    return fx * xd + cx, fy * yd + cy


@numba.njit(cache=True, nogil=True)
def project_many(P, intr, R, t):  # pragma: no cover - numba
    """Project world points P (n, 3) mm -> observed pixels u, v (n,)."""
    n = P.shape[0]
    up = np.empty(n)
    vp = np.empty(n)
    R9 = (R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1], R[2, 2])
    for i in range(n):
        up[i], vp[i] = project_point(P[i, 0], P[i, 1], P[i, 2], intr, R9, t[0], t[1], t[2])
    return up, vp


@numba.njit(inline="always")
def undistort_point(xd, yd, k1, k2, p1, p2, k3):  # pragma: no cover - numba
    """Newton inversion of the distortion at one point, as
    :func:`telefringe.geometry.distortion.undistort_normalized` (start at the distorted
    point, tolerance max(1e-14, 64 eps (|xd| + |yd|)) on the forward residual, 50 steps).

    Returns (x, y, ok): ok is False where it does not converge or converges beyond the
    fold of the distortion.
    """
    if k1 == 0.0 and k2 == 0.0 and p1 == 0.0 and p2 == 0.0 and k3 == 0.0:
        return xd, yd, True
    thresh = max(1e-14, 64.0 * _EPS * (abs(xd) + abs(yd)))
    x = xd
    y = yd
    for _ in range(50):
        fx, fy = distort_point(x, y, k1, k2, p1, p2, k3)
        fx -= xd
        fy -= yd
        a, b, c, d = distortion_jacobian(x, y, k1, k2, p1, p2, k3)
        det = a * d - b * c
        x = x - (d * fx - b * fy) / det
        y = y - (-c * fx + a * fy) / det
        if abs(fx) + abs(fy) <= thresh:
            break
    fx, fy = distort_point(x, y, k1, k2, p1, p2, k3)
    a, b, c, d = distortion_jacobian(x, y, k1, k2, p1, p2, k3)
    ok = (abs(fx - xd) + abs(fy - yd) <= 10.0 * thresh) and is_unfolded(a, b, c, d)
    return x, y, ok


@numba.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def backproject_many(u, v, intr, R, d_out):  # pragma: no cover - numba
    """Unit world directions d_out (3, n) of the rays through the pixels u, v (n,)
    (PinholeDevice.backproject; the rays all start at the centre ``-R^T t``); NaN where
    the inversion fails. Returns the number of finite pixels whose inversion failed."""
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = intr
    n_bad = 0
    for i in numba.prange(u.shape[0]):
        x, y, ok = undistort_point((u[i] - cx) / fx, (v[i] - cy) / fy, k1, k2, p1, p2, k3)
        # d = R^T (x, y, 1), normalised
        d0 = R[0, 0] * x + R[1, 0] * y + R[2, 0]
        d1 = R[0, 1] * x + R[1, 1] * y + R[2, 1]
        d2 = R[0, 2] * x + R[1, 2] * y + R[2, 2]
        inv = 1.0 / np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        good = ok and np.isfinite(u[i]) and np.isfinite(v[i])
        n_bad += np.isfinite(u[i]) and np.isfinite(v[i]) and not ok
        d_out[0, i] = d0 * inv if good else np.nan
        d_out[1, i] = d1 * inv if good else np.nan
        d_out[2, i] = d2 * inv if good else np.nan
    return n_bad
