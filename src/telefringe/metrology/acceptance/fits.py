"""Least-squares (Gaussian) sphere and plane fits of the acceptance test, with the 0.3 %
exclusion of VDI/VDE 2634 Part 2.

These fits minimise the sum of squared *orthogonal* distances (geometric least squares,
as ISO 10360-6 / PTB's TraCIM test data define the reference solutions), with equal
weights: the guideline's characteristics are properties of the point set, not of a
noise model. They are exact: on data whose least-squares solution is known they return
it to rounding (tests/test_acceptance_fits.py builds such data sets).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from telefringe.metrology._common import MetrologyError

__all__ = ["LSSphere", "LSPlane", "ls_sphere", "ls_plane", "n_excluded", "trimmed"]


@dataclass(frozen=True, eq=False)
class LSSphere:
    """A least-squares sphere with free radius.

    Attributes
    ----------
    centre : (3,) mm.   radius : float, mm.
    residuals : (n,) mm, ``|p - centre| - radius`` of the points fitted.
    covariance : (4, 4) mm^2, of (cx, cy, cz, r), from the residuals' scatter (the
        statistical uncertainty of the fit, assuming independent points).
    iterations : int, Gauss-Newton iterations taken.
    """

    centre: np.ndarray
    radius: float
    residuals: np.ndarray
    covariance: np.ndarray
    iterations: int

    @property
    def diameter(self) -> float:
        return 2.0 * self.radius


@dataclass(frozen=True, eq=False)
class LSPlane:
    """A least-squares (total least squares) plane ``normal . x = normal . centroid``.

    Attributes
    ----------
    normal : (3,) unit, with a non-negative z component.   centroid : (3,) mm.
    residuals : (n,) mm, signed distances of the points fitted.
    """

    normal: np.ndarray
    centroid: np.ndarray
    residuals: np.ndarray


def _points(points) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise MetrologyError(f"points must have shape (n, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise MetrologyError("points must be finite")
    return p


def ls_sphere(points, *, tol: float = 1e-13, max_iter: int = 200) -> LSSphere:
    """Least-squares sphere with free radius: minimises ``sum (|p_i - c| - r)^2``.

    Start: the algebraic (Kasa) sphere; then Gauss-Newton on the orthogonal distances
    (with step halving when a step does not lower the sum), until the step is below
    ``tol`` relative to the size of the point set. Points are centred first, for
    conditioning.

    Parameters
    ----------
    points : (n, 3) array_like of float, mm, n >= 4, not coplanar.

    Returns
    -------
    LSSphere

    Raises
    ------
    MetrologyError
        Fewer than 4 points, coplanar points, or no convergence.
    """
    p = _points(points)
    n = p.shape[0]
    if n < 4:
        raise MetrologyError(f"a sphere needs at least 4 points, got {n}")
    m = p.mean(axis=0)
    q = p - m
    scale = float(np.sqrt(np.mean(np.sum(q * q, axis=1)))) or 1.0
    A = np.column_stack([2.0 * q, np.ones(n)])
    b = np.sum(q * q, axis=1)
    sol, _, rank, sv = np.linalg.lstsq(A, b, rcond=None)
    if rank < 4 or sv[-1] <= 1e-12 * sv[0]:
        raise MetrologyError("the points are coplanar (or fewer than 4 distinct): no sphere")
    c = sol[:3]
    r2 = sol[3] + c @ c
    if not r2 > 0:
        raise MetrologyError("no sphere fits these points (negative radius squared)")
    x = np.concatenate([c, [np.sqrt(r2)]])

    def resid(x):
        d = q - x[:3]
        dist = np.sqrt(np.sum(d * d, axis=1))
        return dist - x[3], d, dist

    f, d, dist = resid(x)
    cost = float(f @ f)
    floor = n * (1e-14 * scale) ** 2  # sums of squares below this are rounding
    prev = np.inf
    iterations = 0
    for _ in range(max_iter):
        iterations += 1
        J = np.column_stack([-d / dist[:, None], -np.ones(n)])
        step = np.linalg.lstsq(J, -f, rcond=None)[0]
        # step halving only where the sum of squares clearly rises (near the solution
        # its changes are at the rounding level and the full step is taken)
        t = 1.0
        while True:
            xn = x + t * step
            fn, dn, distn = resid(xn)
            cn = float(fn @ fn)
            # rounding moves each residual by ~1e-16 scale, the sum by ~2 |f| that much
            noise = 1e-14 * scale * np.sqrt(n * max(cost, cn)) + floor
            if cn <= cost * (1.0 + 1e-9) + noise or t < 1e-6:
                break
            t *= 0.5
        x, f, d, dist, cost = xn, fn, dn, distn, cn
        size = float(np.linalg.norm(step))
        # converged: a full step below tol, or steps at the rounding floor that no longer
        # shrink (Gauss-Newton's steps shrink geometrically until rounding stops them)
        if t == 1.0 and (size <= tol * scale or (size <= 1e-10 * scale and size > 0.5 * prev)):
            break
        prev = size
    else:
        raise MetrologyError("the sphere fit did not converge")
    J = np.column_stack([-d / dist[:, None], -np.ones(n)])
    dof = max(n - 4, 1)
    try:
        cov = float(f @ f) / dof * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        raise MetrologyError("the sphere is not determined by these points") from None
    return LSSphere(centre=x[:3] + m, radius=float(x[3]), residuals=f, covariance=cov,
                    iterations=iterations)


def ls_plane(points) -> LSPlane:
    """Least-squares (orthogonal distance) plane: the centroid and the eigenvector of the
    smallest eigenvalue of the points' scatter matrix (exact, no iteration).

    Parameters
    ----------
    points : (n, 3) array_like of float, mm, n >= 3, not collinear.

    Returns
    -------
    LSPlane

    Raises
    ------
    MetrologyError
        Fewer than 3 points, or collinear points.
    """
    p = _points(points)
    if p.shape[0] < 3:
        raise MetrologyError(f"a plane needs at least 3 points, got {p.shape[0]}")
    c = p.mean(axis=0)
    q = p - c
    # the SVD of the centred points (better conditioned than the scatter matrix)
    _, s, vt = np.linalg.svd(q, full_matrices=False)
    if s[1] <= 1e-12 * s[0]:
        raise MetrologyError("the points are collinear: no plane")
    nrm = vt[2]
    if nrm[2] < 0:
        nrm = -nrm
    return LSPlane(normal=nrm, centroid=c, residuals=q @ nrm)


def n_excluded(n: int, fraction: float) -> int:
    """How many of ``n`` points the exclusion of ``fraction`` (0.003) removes: the
    largest whole number not above ``fraction * n`` ("up to 0.3 %")."""
    if not 0 <= fraction < 0.5:
        raise MetrologyError(f"the excluded fraction must be in [0, 0.5), got {fraction}")
    return int(np.floor(fraction * n + 1e-9))


def trimmed(points, fit, fraction: float):
    """Fit, drop the ``n_excluded`` points of largest |residual|, fit the rest again.

    Parameters
    ----------
    points : (n, 3) mm.   fit : :func:`ls_sphere` or :func:`ls_plane`.
    fraction : float, 0.003 for the guideline's 0.3 %.

    Returns
    -------
    (fit result of the kept points, kept : (n,) bool)
    """
    p = _points(points)
    first = fit(p)
    k = n_excluded(p.shape[0], fraction)
    keep = np.ones(p.shape[0], dtype=bool)
    if k == 0:
        return first, keep
    order = np.argsort(np.abs(first.residuals), kind="stable")
    keep[order[-k:]] = False
    return fit(p[keep]), keep
