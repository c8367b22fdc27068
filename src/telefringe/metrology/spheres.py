"""Spheres: algebraic start, geometric (optionally fixed-radius, robust) fits, and a
sphere standing on a plane in a scan."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from telefringe.metrology._common import (
    _MAD,
    MetrologyError,
    _components,
    _freeze,
    _points_and_weights,
)
from telefringe.metrology.planes import PlaneFit, fit_plane
from telefringe.reconstruction.cloud import PointCloud


@dataclass(frozen=True, eq=False)
class SphereFit:
    """A sphere fitted to points.

    Attributes
    ----------
    centre : (3,) mm.   radius : float, mm.
    rms : float, mm, RMS radial residual of the inliers.
    form_error : float, mm, peak-to-valley of the inliers' radial residuals.
    n_points, n_inliers : int.   inliers : (n_points,) bool.
    covariance : (4, 4), of (cx, cy, cz, radius), mm^2.
    """

    centre: np.ndarray
    radius: float
    rms: float
    form_error: float
    n_points: int
    n_inliers: int
    inliers: np.ndarray
    covariance: np.ndarray

    def __post_init__(self):
        _freeze(self, "centre", "inliers", "covariance")

    @property
    def sigma_centre(self) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance)[:3])

    @property
    def sigma_radius(self) -> float:
        return float(np.sqrt(self.covariance[3, 3]))

    @property
    def diameter(self) -> float:
        return 2.0 * self.radius

    def apex(self, direction=(0.0, 0.0, 1.0)) -> np.ndarray:
        """The sphere's point farthest along ``direction`` (3,) (default +z, the top)."""
        d = np.asarray(direction, dtype=np.float64)
        return self.centre + self.radius * d / np.linalg.norm(d)


def _sphere_algebraic(p: np.ndarray, w: np.ndarray):
    """Kasa fit: |x|^2 = 2 c.x + (r^2 - |c|^2), linear least squares (the start)."""
    m = p.mean(axis=0)
    q = p - m  # centred for conditioning
    A = np.column_stack([2.0 * q, np.ones(q.shape[0])])
    b = np.sum(q * q, axis=1)
    sw = np.sqrt(w)
    sol, _, rank, sv = np.linalg.lstsq(A * sw[:, None], b * sw, rcond=None)
    if rank < 4 or sv[-1] <= 1e-10 * sv[0]:
        raise MetrologyError("the points are coplanar (or fewer than 4 distinct): no sphere")
    c = sol[:3]
    r2 = sol[3] + c @ c
    if not r2 > 0:
        raise MetrologyError("algebraic sphere fit failed (negative radius squared)")
    return c + m, float(np.sqrt(r2))


def _sphere_geometric(p: np.ndarray, w: np.ndarray, c: np.ndarray, r: float,
                      max_iter: int = 100, *, fixed_radius: bool = False):
    """Levenberg-Marquardt on the radial residuals |p - c| - r (r fixed if asked); the
    compiled loop :func:`telefringe.metrology._fit_kernels.sphere_lm`. Returns
    (centre (3,), radius, residuals (m,), weighted Jacobian (m, 3 or 4))."""
    from telefringe.metrology._fit_kernels import sphere_lm

    x0 = np.array([c[0], c[1], c[2], r], dtype=np.float64)
    x, f, J = sphere_lm(np.ascontiguousarray(p, dtype=np.float64),
                        np.ascontiguousarray(w, dtype=np.float64), x0,
                        3 if fixed_radius else 4, int(max_iter))
    return x[:3], float(x[3]), f, J


def fit_sphere(points, *, weights=None, robust: bool = False, reject_k: float = 4.0,
               max_rounds: int = 5, radius: float | None = None,
               start=None) -> SphereFit:
    """Fit a sphere: algebraic (Kasa) start, then geometric least squares.

    Parameters
    ----------
    points : (n, 3) array_like of float, mm, or PointCloud; non-finite rows ignored.
    weights : (n,) array_like, optional, relative weights (e.g. 1 / sigma_r^2, sigma_r
        the standard uncertainty of each point along the sphere's radius).
    robust : bool
        Repeat the fit without points whose radial residual times sqrt(weight) is beyond
        ``reject_k`` robust standard deviations (MAD) of these normalised residuals, up
        to ``max_rounds`` times.
    radius : float, optional
        Fit the centre only, with this radius (mm): for small caps whose curvature the
        points do not determine (then ``covariance``'s radius row and column are 0).
    start : (3,) array_like, optional
        With ``radius``: the centre to start from (e.g. a previous fit of the same cap)
        instead of the start estimated from the points.

    Returns
    -------
    SphereFit

    Raises
    ------
    MetrologyError
        Fewer than 4 points, coplanar points, or a fit that does not converge.
    """
    p, w0, finite = _points_and_weights(points, weights)
    n_all = p.shape[0]
    finite &= np.isfinite(w0) & (w0 > 0)
    idx = np.flatnonzero(finite)
    if idx.size < 4:
        raise MetrologyError(f"a sphere needs at least 4 points, got {idx.size}")
    pf = p[idx]
    wf = w0[idx] / w0[idx].mean()
    fixed = radius is not None
    if fixed and not (np.isfinite(radius) and radius > 0):
        raise MetrologyError(f"radius must be > 0, got {radius!r}")
    keep = np.ones(idx.size, dtype=bool)
    if fixed:  # the same rounds in one compiled call (a BGA fits hundreds of caps)
        from telefringe.metrology._fit_kernels import sphere_fixed_robust

        has_start = start is not None
        c0 = np.asarray(start, dtype=np.float64) if has_start else np.zeros(3)
        ok, c, f, J, keep = sphere_fixed_robust(
            np.ascontiguousarray(pf, dtype=np.float64), np.ascontiguousarray(wf), c0,
            has_start, float(radius), float(reject_k), int(max_rounds if robust else 1),
            _MAD)
        if not ok:
            raise MetrologyError("robust sphere fit: fewer than 5 inliers")
        r = float(radius)
        fitted = keep
    for _ in range(0 if fixed else max_rounds if robust else 1):  # a free radius
        if np.count_nonzero(keep) < 5:
            raise MetrologyError("robust sphere fit: fewer than 5 inliers")
        c0, r0 = _sphere_algebraic(pf[keep], wf[keep])
        c, r, f, J = _sphere_geometric(pf[keep], wf[keep], c0, r0)
        fitted = keep
        if not robust:
            break
        # residuals normalised by their weights (each point's own standard deviation
        # when the weights are 1 / sigma^2)
        res_all = (np.linalg.norm(pf - c, axis=1) - r) * np.sqrt(wf)
        scale = _MAD * np.median(np.abs(f * np.sqrt(wf[keep]))) + 1e-15
        new_keep = np.abs(res_all) <= reject_k * scale
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    keep = fitted  # the points of the last fit (the rounds may end before agreement)
    if not (np.isfinite(r) and r > 0 and np.all(np.isfinite(c))):
        raise MetrologyError("the sphere fit did not converge")
    wk = wf[keep]
    nk = int(np.count_nonzero(keep))
    dof = max(nk - J.shape[1], 1)
    s2 = float(np.sum(wk * f * f) / dof)
    cov = np.zeros((4, 4))
    try:
        cov[:J.shape[1], :J.shape[1]] = s2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        raise MetrologyError("the sphere is not determined by these points") from None
    inliers = np.zeros(n_all, dtype=bool)
    inliers[idx[keep]] = True
    return SphereFit(c, r, float(np.sqrt(np.mean(f * f))), float(f.max() - f.min()),
                     int(n_all), nk, inliers, cov)


@dataclass(frozen=True, eq=False)
class SphereMeasurement:
    """A sphere found in a scan (:func:`measure_sphere`).

    Attributes
    ----------
    sphere : SphereFit.
    base : PlaneFit or None, the plane it stands on; None when no plane holds 20 % of
        the points, and then every point was fitted as sphere (``region`` says so).
    region : str, which points were fitted: ``"above the base plane"`` or
        ``"all points (no base plane found)"``.
    fitted : (rows, cols) bool or None, the cloud's pixels whose points the sphere fit
        kept (its inliers).
    uncertainty : dict of str -> Uncertainty, or None: ``"radius"``, ``"centre"`` with
        the noise and calibration parts (set by
        :func:`telefringe.metrology.uncertainty.sphere_uncertainty`; None until then).
    """

    sphere: SphereFit
    base: PlaneFit | None
    region: str
    fitted: np.ndarray | None = None
    uncertainty: dict | None = None


def measure_sphere(cloud: PointCloud, *, min_height: float | None = None,
                   edge_px: int = 1, seed: int = 0) -> SphereMeasurement:
    """Find and fit the sphere standing on a plane in a scan.

    The base plane is fitted robustly; the largest connected region standing more than
    ``min_height`` above it (default: 8 robust sigma of the plane, at least 20 um) is the
    sphere, shrunk by ``edge_px`` pixels (silhouette pixels mix surfaces), and fitted
    robustly. When no plane holds at least 20 % of the points, all points are fitted,
    and the result's ``region`` says so.

    Returns
    -------
    SphereMeasurement
    """
    from scipy import ndimage

    if cloud.count < 4:
        raise MetrologyError(f"the cloud has {cloud.count} valid points: no sphere")
    base = None
    mask = cloud.mask
    try:
        plane = fit_plane(cloud, robust=True, seed=seed)
        if plane.n_inliers >= 0.2 * plane.n_points:
            base = plane
    except MetrologyError:
        base = None
    if base is not None:
        h = np.where(mask, cloud.xyz @ base.normal - base.offset, np.nan)
        thr = max(8.0 * base.rms, 0.02) if min_height is None else float(min_height)
        above = np.nan_to_num(h, nan=-np.inf) > thr
        labels, n = _components(above)
        if n == 0:
            raise MetrologyError(f"nothing stands more than {thr:.3g} mm above the plane")
        sizes = np.bincount(labels.ravel())[1:]
        region = labels == (1 + int(np.argmax(sizes)))
        if edge_px > 0:
            region = ndimage.binary_erosion(region, iterations=int(edge_px))
        sel = region & mask
        where = "above the base plane"
    else:
        sel = mask
        where = "all points (no base plane found)"
    fit = fit_sphere(cloud.xyz[sel], robust=True)
    fitted = np.zeros(mask.shape, dtype=bool)
    fitted[sel] = fit.inliers
    return SphereMeasurement(fit, base, where, fitted)
