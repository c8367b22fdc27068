"""Compiled scalar inversion of the sensor distortion, shared by the reconstruction
and the virtual rig (the same Newton iteration, tolerance and fold checks as
:func:`telefringe.geometry.distortion.undistort_sensor`)."""

from __future__ import annotations

import numba

__all__ = ["undistort_point", "distortion_residual"]


@numba.njit(inline="always")
def distortion_residual(xu, yu, xd, yd, k1, s1, s2):
    """The distortion of the undistorted sensor point (xu, yu) minus (xd, yd), mm, and its
    Jacobian: (fx, fy, a, b, c, d) with [[a, b], [c, d]] = d(distorted)/d(xu, yu)."""
    r2 = xu * xu + yu * yu
    fx = xu + k1 * xu * r2 + s1 * r2 - xd
    fy = yu + k1 * yu * r2 + s2 * r2 - yd
    a = 1.0 + k1 * (r2 + 2.0 * xu * xu) + 2.0 * s1 * xu
    b = 2.0 * k1 * xu * yu + 2.0 * s1 * yu
    c = 2.0 * k1 * xu * yu + 2.0 * s2 * xu
    d = 1.0 + k1 * (r2 + 2.0 * yu * yu) + 2.0 * s2 * yu
    return fx, fy, a, b, c, d


@numba.njit(cache=True, nogil=True)
def undistort_point(xd, yd, k1, s1, s2):
    """Newton inversion of the sensor distortion at one point (as
    :func:`telefringe.geometry.distortion.undistort_sensor`).

    Returns (xu, yu, ok): ok is False where it does not converge or converges beyond the
    fold of the distortion.
    """
    if k1 == 0.0 and s1 == 0.0 and s2 == 0.0:
        return xd, yd, True
    thresh = max(1e-12, 64.0 * 2.220446049250313e-16 * (abs(xd) + abs(yd)))
    xu = xd
    yu = yd
    for _ in range(50):
        fx, fy, a, b, c, d = distortion_residual(xu, yu, xd, yd, k1, s1, s2)
        det = a * d - b * c
        xu = xu - (d * fx - b * fy) / det
        yu = yu - (-c * fx + a * fy) / det
        if abs(fx) + abs(fy) <= thresh:
            break
    fx, fy, a, b, c, d = distortion_residual(xu, yu, xd, yd, k1, s1, s2)
    res = abs(fx) + abs(fy)
    ok = (res <= 10.0 * thresh) and (a * d - b * c > 0.0) and (a + d > 0.0)
    return xu, yu, ok
