"""Compiled scalar form of the telecentric device model (numba): the one copy of
:class:`telefringe.devices.telecentric.TelecentricDevice`'s formulas that kernels call,
in the reconstruction and in the virtual rig.

The NumPy model in :mod:`telefringe.devices.telecentric` is the reference these are tested
against (to rounding: the kernels multiply by the inverse pixel pitch where the NumPy
model divides by the pitch). The distortion is
:mod:`telefringe.geometry._distortion_kernels`'.

A device is passed to the kernels as plain numbers (see :func:`kernel_args`)::

    intr = (m, du, dv, u0, v0, k1, s1, s2)     # magnification, pitch mm, principal point px,
                                               # distortion 1/mm^2, 1/mm
    R    = R_dev_world, a flat row-major 9-tuple (or a (3, 3) array for kernel_args' callers)
    t    = (t0, t1) mm, the in-plane translation

Forward: ``xu = m (R[0] . X + t0)``, ``yu = m (R[1] . X + t1)``, distort, then
``u = u0 + xd / du``, ``v = v0 + yd / dv``. Backward: a pixel's world line is
``X(s) = a R[0] + b R[1] + s R[2]`` with ``(a, b) = (xu / m - t0, yu / m - t1)`` of its
undistorted sensor point: every pixel's line has the direction ``R[2]``.
"""

from __future__ import annotations

import numba
import numpy as np

from telefringe.geometry._distortion_kernels import (
    distort_point,
    undistort_point,
    undistort_point_fixed,
)

__all__ = ["kernel_args", "flat_rotation", "sensor_of_point", "pixel_of_sensor",
           "project_point", "sensor_of_pixel", "line_of_sensor", "line_point",
           "backproject_point", "backproject_point_fixed", "backproject_lines",
           "project_many"]


def kernel_args(device):
    """``(intr, R, t)`` of a TelecentricDevice for the kernels: ``intr`` the 8-tuple of
    floats above, ``R`` (3, 3) contiguous float64, ``t`` (2,) contiguous float64 (writable
    copies)."""
    k = device.intrinsics
    intr = (float(k.m), float(k.du), float(k.dv), float(k.u0), float(k.v0), float(k.k1),
            float(k.s1), float(k.s2))
    # fresh writable copies whatever the device's arrays are (read-only, views): numba
    # compiles one signature per array flag, so a read-only R would cost a second compile
    return (intr, np.array(device.R_dev_world, dtype=np.float64, order="C"),
            np.array(device.t_dev, dtype=np.float64, order="C"))


@numba.njit(inline="always")
def flat_rotation(R):  # pragma: no cover - numba
    """A (3, 3) array as a row-major 9-tuple (kept in registers inside a loop)."""
    return (R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1], R[2, 2])


@numba.njit(inline="always")
def sensor_of_point(x, y, z, m, R9, t0, t1):  # pragma: no cover - numba
    """World point (x, y, z) mm -> undistorted sensor (xu, yu) mm; R9 row-major."""
    return (m * (x * R9[0] + y * R9[1] + z * R9[2] + t0),
            m * (x * R9[3] + y * R9[4] + z * R9[5] + t1))


@numba.njit(inline="always")
def pixel_of_sensor(xu, yu, u0, v0, idu, idv, k1, s1, s2):  # pragma: no cover - numba
    """Undistorted sensor (xu, yu) mm -> observed pixel (u, v); idu, idv = 1 / pitch."""
    xd, yd = distort_point(xu, yu, k1, s1, s2)
    return u0 + xd * idu, v0 + yd * idv


@numba.njit(inline="always")
def project_point(x, y, z, m, u0, v0, idu, idv, k1, s1, s2, R9, t0,
                  t1):  # pragma: no cover - numba
    """World point mm -> observed pixel (u, v) (TelecentricDevice.project)."""
    xu, yu = sensor_of_point(x, y, z, m, R9, t0, t1)
    return pixel_of_sensor(xu, yu, u0, v0, idu, idv, k1, s1, s2)


@numba.njit(inline="always")
def sensor_of_pixel(u, v, u0, v0, du, dv):  # pragma: no cover - numba
    """Observed pixel (u, v) -> distorted sensor (xd, yd) mm."""
    return (u - u0) * du, (v - v0) * dv


@numba.njit(inline="always")
def line_of_sensor(xu, yu, m, t0, t1):  # pragma: no cover - numba
    """Undistorted sensor (xu, yu) mm -> the line offsets (a, b) mm of its world line."""
    return xu / m - t0, yu / m - t1


@numba.njit(inline="always")
def line_point(a, b, s, R9):  # pragma: no cover - numba
    """The point ``a R[0] + b R[1] + s R[2]`` (mm) of the line (a, b) at depth s mm."""
    return (a * R9[0] + b * R9[3] + s * R9[6], a * R9[1] + b * R9[4] + s * R9[7],
            a * R9[2] + b * R9[5] + s * R9[8])


@numba.njit(inline="always")
def backproject_point(u, v, m, u0, v0, du, dv, k1, s1, s2, t0,
                      t1):  # pragma: no cover - numba
    """Observed pixel -> its line offsets (a, b) mm and ok (the undistortion converged
    short of the fold), iterating to the model's tolerance."""
    xd, yd = sensor_of_pixel(u, v, u0, v0, du, dv)
    xu, yu, ok = undistort_point(xd, yd, k1, s1, s2)
    a, b = line_of_sensor(xu, yu, m, t0, t1)
    return a, b, ok


@numba.njit(inline="always")
def backproject_point_fixed(u, v, m, u0, v0, du, dv, k1, s1, s2, t0, t1,
                            n_steps):  # pragma: no cover - numba
    """:func:`backproject_point` in ``n_steps`` fixed Newton steps (vectorises); where ok
    is False, redo the pixel with :func:`backproject_point`."""
    xd, yd = sensor_of_pixel(u, v, u0, v0, du, dv)
    xu, yu, ok = undistort_point_fixed(xd, yd, k1, s1, s2, n_steps)
    a, b = line_of_sensor(xu, yu, m, t0, t1)
    return a, b, ok


@numba.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def backproject_lines(u, v, intr, t, a_out, b_out):  # pragma: no cover - numba
    """Line offsets of the pixels u, v (n,) into a_out, b_out (n,); returns the number of
    finite pixels whose undistortion failed (NaN pixels give NaN lines)."""
    m, du, dv, u0, v0, k1, s1, s2 = intr
    t0 = t[0]
    t1 = t[1]
    n_bad = 0
    for i in numba.prange(u.shape[0]):
        a, b, ok = backproject_point(u[i], v[i], m, u0, v0, du, dv, k1, s1, s2, t0, t1)
        if np.isfinite(u[i]) and np.isfinite(v[i]) and not ok:
            n_bad += 1
        a_out[i] = a
        b_out[i] = b
    return n_bad


@numba.njit(cache=True, nogil=True)
def project_many(P, intr, R, t):  # pragma: no cover - numba
    """Project world points P (n, 3) mm -> observed pixels u, v (n,)."""
    n = P.shape[0]
    up = np.empty(n)
    vp = np.empty(n)
    m, du, dv, u0, v0, k1, s1, s2 = intr
    idu = 1.0 / du
    idv = 1.0 / dv
    R9 = flat_rotation(R)
    t0 = t[0]
    t1 = t[1]
    for i in range(n):
        up[i], vp[i] = project_point(P[i, 0], P[i, 1], P[i, 2], m, u0, v0, idu, idv, k1, s1,
                                     s2, R9, t0, t1)
    return up, vp
