"""Radial + thin-prism distortion on the sensor plane (the telecentric devices' model).

Forward (sensor mm, relative to the principal point)::

    r2 = xu**2 + yu**2
    xd = xu + k1 * xu * r2 + s1 * r2
    yd = yu + k1 * yu * r2 + s2 * r2

``k1`` in 1/mm^2, ``s1`` and ``s2`` in 1/mm. The compiled scalar form of the same
formula (used inside kernels) is :mod:`telefringe.geometry._distortion_kernels`; the
NumPy form here is the reference both are tested against.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ConvergenceError", "distort_sensor", "undistort_sensor"]


class ConvergenceError(ValueError):
    """An iterative inversion (e.g. undistortion) did not converge."""


def distort_sensor(xu, yu, k1: float, s1: float, s2: float):
    """Apply radial + thin-prism distortion on the sensor plane.

    Parameters
    ----------
    xu, yu : ndarray of float, any (broadcastable) shape
        Undistorted sensor coordinates in mm, relative to the principal point.
    k1 : float   radial coefficient, 1/mm^2.
    s1, s2 : float   thin-prism coefficients, 1/mm.

    Returns
    -------
    xd, yd : ndarray of float, same shape, distorted sensor mm.
    """
    xu = np.asarray(xu, dtype=float)
    yu = np.asarray(yu, dtype=float)
    r2 = xu * xu + yu * yu
    return xu + k1 * xu * r2 + s1 * r2, yu + k1 * yu * r2 + s2 * r2


def undistort_sensor(xd, yd, k1: float, s1: float, s2: float, *, tol: float = 1e-12,
                     max_iter: int = 50):
    """Invert :func:`distort_sensor` by Newton's method.

    Parameters
    ----------
    xd, yd : ndarray of float, any (broadcastable) shape, distorted sensor mm.
    k1, s1, s2 : float, distortion coefficients (see :func:`distort_sensor`).
    tol : float
        Convergence tolerance in mm on the residual of the forward model (default
        1e-12 mm, i.e. 2e-10 px for a 5 um pixel).

    Returns
    -------
    xu, yu : ndarray of float, undistorted sensor mm.

    Raises
    ------
    ConvergenceError
        If any finite input point does not converge, or converges only to a root
        beyond the fold of the distortion (where the forward map is not invertible).
        Non-finite inputs give non-finite outputs (NaN stays NaN).
    """
    xd, yd = np.broadcast_arrays(np.asarray(xd, dtype=float), np.asarray(yd, dtype=float))
    xu = xd.copy()
    yu = yd.copy()
    if k1 == 0.0 and s1 == 0.0 and s2 == 0.0:
        return xu, yu
    finite = np.isfinite(xd) & np.isfinite(yd)
    # the residual cannot be smaller than the rounding of the forward model
    thresh = np.maximum(tol, 64.0 * np.finfo(float).eps * (np.abs(xd) + np.abs(yd)))

    def jacobian(xu, yu, r2):
        a = 1.0 + k1 * (r2 + 2.0 * xu * xu) + 2.0 * s1 * xu
        b = 2.0 * k1 * xu * yu + 2.0 * s1 * yu
        c = 2.0 * k1 * xu * yu + 2.0 * s2 * xu
        d = 1.0 + k1 * (r2 + 2.0 * yu * yu) + 2.0 * s2 * yu
        return a, b, c, d

    # diverging points (no inverse) may overflow; they are reported below, not warned
    with np.errstate(all="ignore"):
        for _ in range(max_iter):
            r2 = xu * xu + yu * yu
            fx = xu + k1 * xu * r2 + s1 * r2 - xd
            fy = yu + k1 * yu * r2 + s2 * r2 - yd
            a, b, c, d = jacobian(xu, yu, r2)
            det = a * d - b * c
            dx = (d * fx - b * fy) / det
            dy = (-c * fx + a * fy) / det
            xu = xu - dx
            yu = yu - dy
            err = np.abs(fx) + np.abs(fy)
            if not np.any((err > thresh)[finite]):
                break
        r2 = xu * xu + yu * yu
        res = (np.abs(xu + k1 * xu * r2 + s1 * r2 - xd)
               + np.abs(yu + k1 * yu * r2 + s2 * r2 - yd))
        a, b, c, d = jacobian(xu, yu, r2)
        # A root where the forward map is folded (det <= 0) or flipped (trace <= 0) is
        # not the inverse: it lies beyond the fold of the distortion, e.g. the mirrored
        # outer root of a strong barrel distortion.
        unfolded = (a * d - b * c > 0) & (a + d > 0)
    diverged = finite & ~(res <= 10.0 * thresh)
    folded = finite & ~diverged & ~unfolded
    if np.any(diverged) or np.any(folded):
        parts = []
        if np.any(diverged):
            worst = np.where(np.isnan(res), np.inf, res)[diverged].max()
            parts.append(f"{int(np.count_nonzero(diverged))} did not converge (worst residual "
                         f"{float(worst):.3g} mm)")
        if np.any(folded):
            parts.append(f"{int(np.count_nonzero(folded))} only have a solution beyond the "
                         "fold of the distortion")
        raise ConvergenceError(
            f"undistortion failed for {int(np.count_nonzero(diverged | folded))} of "
            f"{int(np.count_nonzero(finite))} point(s): {' and '.join(parts)}. The distortion "
            f"(k1={k1:g} 1/mm^2, s1={s1:g}, s2={s2:g} 1/mm) is not invertible there; check "
            "the coefficients or keep to the image area"
        )
    return xu, yu
