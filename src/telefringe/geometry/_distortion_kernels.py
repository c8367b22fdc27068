"""Compiled scalar form of the radial + thin-prism sensor distortion (numba): the forward
map, its Jacobian, the fold test and its inversion, shared by every device model that uses
this distortion, in the reconstruction and the virtual rig.

:mod:`telefringe.geometry.distortion` is the NumPy reference these are tested against (the
same formula, the same Newton iteration, tolerance and fold checks).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["distort_point", "distortion_jacobian", "is_unfolded", "distortion_residual",
           "undistortion_threshold", "undistort_point", "undistort_point_fixed",
           "unfolded_radius2"]

_EPS = 2.220446049250313e-16


@numba.njit(inline="always")
def distort_point(xu, yu, k1, s1, s2):  # pragma: no cover - numba
    """Undistorted sensor point (xu, yu) mm -> distorted (xd, yd) mm."""
    r2 = xu * xu + yu * yu
    return xu + k1 * xu * r2 + s1 * r2, yu + k1 * yu * r2 + s2 * r2


@numba.njit(inline="always")
def distortion_jacobian(xu, yu, k1, s1, s2):  # pragma: no cover - numba
    """[[a, b], [c, d]] = d(xd, yd)/d(xu, yu) at the undistorted point (xu, yu), as (a, b,
    c, d)."""
    r2 = xu * xu + yu * yu
    a = 1.0 + k1 * (r2 + 2.0 * xu * xu) + 2.0 * s1 * xu
    b = 2.0 * k1 * xu * yu + 2.0 * s1 * yu
    c = 2.0 * k1 * xu * yu + 2.0 * s2 * xu
    d = 1.0 + k1 * (r2 + 2.0 * yu * yu) + 2.0 * s2 * yu
    return a, b, c, d


@numba.njit(inline="always")
def is_unfolded(a, b, c, d):  # pragma: no cover - numba
    """Whether the distortion is invertible at a point of Jacobian [[a, b], [c, d]]: a root
    where the forward map is folded (det <= 0) or flipped (trace <= 0) lies beyond the fold
    (e.g. the mirrored outer root of a strong barrel distortion) and is not the inverse."""
    return (a * d - b * c > 0.0) & (a + d > 0.0)


@numba.njit(inline="always")
def distortion_residual(xu, yu, xd, yd, k1, s1, s2):  # pragma: no cover - numba
    """The distortion of the undistorted sensor point (xu, yu) minus (xd, yd), mm, and its
    Jacobian: (fx, fy, a, b, c, d) with [[a, b], [c, d]] = d(distorted)/d(xu, yu)."""
    x, y = distort_point(xu, yu, k1, s1, s2)
    a, b, c, d = distortion_jacobian(xu, yu, k1, s1, s2)
    return x - xd, y - yd, a, b, c, d


@numba.njit(inline="always")
def undistortion_threshold(xd, yd):  # pragma: no cover - numba
    """The residual (mm) an inversion must reach at (xd, yd): 1e-12 mm, or the rounding of
    the forward model where that is larger."""
    return max(1e-12, 64.0 * _EPS * (abs(xd) + abs(yd)))


@numba.njit(cache=True, nogil=True)
def undistort_point(xd, yd, k1, s1, s2):  # pragma: no cover - numba
    """Newton inversion of the sensor distortion at one point (as
    :func:`telefringe.geometry.distortion.undistort_sensor`).

    Returns (xu, yu, ok): ok is False where it does not converge or converges beyond the
    fold of the distortion.
    """
    if k1 == 0.0 and s1 == 0.0 and s2 == 0.0:
        return xd, yd, True
    thresh = undistortion_threshold(xd, yd)
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
    ok = (res <= 10.0 * thresh) and is_unfolded(a, b, c, d)
    return xu, yu, ok


@numba.njit(inline="always")
def undistort_point_fixed(xd, yd, k1, s1, s2, n_steps):  # pragma: no cover - numba
    """The inversion in a fixed number of steps with no data-dependent branch (a loop of
    these vectorises): from the first-order inverse, ``n_steps`` Newton steps, then the
    acceptance test of :func:`undistort_point` tightened to its stopping tolerance.

    Returns (xu, yu, ok); where ok is False, use :func:`undistort_point`.
    """
    r2 = xd * xd + yd * yd
    xu = xd - (k1 * xd + s1) * r2
    yu = yd - (k1 * yd + s2) * r2
    for _ in range(n_steps):
        fx, fy, a, b, c, d = distortion_residual(xu, yu, xd, yd, k1, s1, s2)
        idet = 1.0 / (a * d - b * c)
        xu = xu - (d * fx - b * fy) * idet
        yu = yu - (a * fy - c * fx) * idet
    fx, fy, a, b, c, d = distortion_residual(xu, yu, xd, yd, k1, s1, s2)
    ok = (abs(fx) + abs(fy) <= undistortion_threshold(xd, yd)) & is_unfolded(a, b, c, d)
    return xu, yu, ok


def unfolded_radius2(k1, s1, s2) -> float:
    """Squared radius (undistorted sensor mm^2) within which the distortion cannot fold.

    With r^2 = xu^2 + yu^2 and s = max(|s1|, |s2|), the Jacobian of the distortion has
    diagonal terms >= 1 - 3|k1| r^2 - 2 s r and off-diagonal ones <= |k1| r^2 + 2 s r in
    magnitude, so its determinant and trace are positive (:func:`is_unfolded`, the fold
    check of :func:`telefringe.geometry.distortion.undistort_sensor`) while
    4 |k1| r^2 + 4 s r < 1. The radius returned is 0.99 of that bound's root (inf without
    distortion). Plain Python: computed once per device, outside the kernels.
    """
    k = abs(float(k1))
    s = max(abs(float(s1)), abs(float(s2)))
    if k == 0.0 and s == 0.0:
        return np.inf
    r = 1.0 / (4.0 * s) if k == 0.0 else (np.sqrt(s * s + k) - s) / (2.0 * k)
    return float((0.99 * r) ** 2)
