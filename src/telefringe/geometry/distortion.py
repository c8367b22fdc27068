"""Distortion models: radial + thin prism on the sensor plane (the telecentric devices'
model), and OpenCV's radial + tangential model on normalised coordinates (pinhole).

Radial + thin prism, forward (sensor mm, relative to the principal point)::

    r2 = xu**2 + yu**2
    xd = xu + k1 * xu * r2 + s1 * r2
    yd = yu + k1 * yu * r2 + s2 * r2

``k1`` in 1/mm^2, ``s1`` and ``s2`` in 1/mm. The compiled scalar form of the same
formula (used inside kernels) is :mod:`telefringe.geometry._distortion_kernels`; the
NumPy form here is the reference both are tested against.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "ConvergenceError",
    "distort_normalized",
    "distort_normalized_jacobian",
    "distort_sensor",
    "undistort_normalized",
    "undistort_sensor",
]


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


# --------------------------------------------------------------------------- OpenCV's model
def distort_normalized(x, y, k1: float, k2: float, p1: float, p2: float, k3: float):
    """OpenCV's radial + tangential distortion of normalised image coordinates.

    ``r2 = x^2 + y^2``, ``a = 1 + k1 r2 + k2 r2^2 + k3 r2^3``,
    ``xd = x a + 2 p1 x y + p2 (r2 + 2 x^2)``, ``yd = y a + p1 (r2 + 2 y^2) + 2 p2 x y``
    (as ``cv2.projectPoints`` with the coefficients (k1, k2, p1, p2, k3)).

    Parameters
    ----------
    x, y : ndarray of float, any (broadcastable) shape, ``X / Z`` and ``Y / Z`` (unitless).

    Returns
    -------
    xd, yd : ndarray of float, same shape.
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    r2 = x * x + y * y
    a = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return (x * a + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * a + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)


def distort_normalized_jacobian(x, y, k1, k2, p1, p2, k3):
    """d(xd, yd)/d(x, y) of :func:`distort_normalized`: (a, b, c, d) with
    ``[[a, b], [c, d]]`` the Jacobian, each shaped like x."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    r2 = x * x + y * y
    rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    D = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d rad / d r2
    a = rad + 2.0 * x * x * D + 2.0 * p1 * y + 6.0 * p2 * x
    b = 2.0 * x * y * D + 2.0 * p1 * x + 2.0 * p2 * y
    c = 2.0 * x * y * D + 2.0 * p1 * x + 2.0 * p2 * y
    d = rad + 2.0 * y * y * D + 6.0 * p1 * y + 2.0 * p2 * x
    return a, b, c, d


def undistort_normalized(xd, yd, k1: float, k2: float, p1: float, p2: float, k3: float, *,
                         tol: float = 1e-14, max_iter: int = 50):
    """Invert :func:`distort_normalized` by Newton's method.

    Parameters
    ----------
    xd, yd : ndarray of float, any (broadcastable) shape, distorted normalised coordinates.
    tol : float, convergence tolerance on the forward model's residual (unitless; 1e-14
        is 1e-11 px for a 1000 px focal length).

    Returns
    -------
    x, y : ndarray of float, the undistorted normalised coordinates.

    Raises
    ------
    ConvergenceError
        If a finite point does not converge, or only to a root beyond the fold of the
        distortion (where the forward map is not invertible: its Jacobian's determinant or
        trace is not positive). Non-finite inputs give non-finite outputs.
    """
    xd, yd = np.broadcast_arrays(np.asarray(xd, dtype=float), np.asarray(yd, dtype=float))
    x = xd.copy()
    y = yd.copy()
    if k1 == 0.0 and k2 == 0.0 and p1 == 0.0 and p2 == 0.0 and k3 == 0.0:
        return x, y
    finite = np.isfinite(xd) & np.isfinite(yd)
    thresh = np.maximum(tol, 64.0 * np.finfo(float).eps * (np.abs(xd) + np.abs(yd)))
    with np.errstate(all="ignore"):
        for _ in range(max_iter):
            fx, fy = distort_normalized(x, y, k1, k2, p1, p2, k3)
            fx = fx - xd
            fy = fy - yd
            a, b, c, d = distort_normalized_jacobian(x, y, k1, k2, p1, p2, k3)
            det = a * d - b * c
            x = x - (d * fx - b * fy) / det
            y = y - (-c * fx + a * fy) / det
            if not np.any((np.abs(fx) + np.abs(fy) > thresh)[finite]):
                break
        fx, fy = distort_normalized(x, y, k1, k2, p1, p2, k3)
        res = np.abs(fx - xd) + np.abs(fy - yd)
        a, b, c, d = distort_normalized_jacobian(x, y, k1, k2, p1, p2, k3)
        unfolded = (a * d - b * c > 0) & (a + d > 0)
    diverged = finite & ~(res <= 10.0 * thresh)
    folded = finite & ~diverged & ~unfolded
    if np.any(diverged) or np.any(folded):
        raise ConvergenceError(
            f"undistortion failed for {int(np.count_nonzero(diverged | folded))} of "
            f"{int(np.count_nonzero(finite))} point(s) ({int(np.count_nonzero(diverged))} did "
            f"not converge, {int(np.count_nonzero(folded))} only have a solution beyond the "
            f"fold of the distortion): the distortion (k1={k1:g}, k2={k2:g}, p1={p1:g}, "
            f"p2={p2:g}, k3={k3:g}) is not invertible there; check the coefficients or keep "
            "to the image area")
    return x, y
