"""Planes: fits (total least squares, robust), distances between planes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from telefringe.metrology._common import (
    _MAD,
    _TUKEY_C,
    MetrologyError,
    _freeze,
    _points_and_weights,
    _tangent_basis,
)


@dataclass(frozen=True, eq=False)
class Plane:
    """The plane ``normal . x = offset`` (normal (3,) unit, mm)."""

    normal: np.ndarray
    offset: float

    def __post_init__(self):
        n = np.array(self.normal, dtype=np.float64).reshape(3)
        nn = float(np.linalg.norm(n))
        if not np.isfinite(nn) or nn == 0 or not np.isfinite(self.offset):
            raise MetrologyError("a plane needs a finite non-zero normal and a finite offset")
        off = float(self.offset) / nn
        n = n / nn
        if n[2] < 0:
            n, off = -n, -off
        n.setflags(write=False)
        object.__setattr__(self, "normal", n)
        object.__setattr__(self, "offset", off)

    @classmethod
    def horizontal(cls, z: float = 0.0) -> Plane:
        """The plane Z = z (the reference plane of a calibration's world frame is Z = 0)."""
        return cls(np.array([0.0, 0.0, 1.0]), float(z))

    def distance(self, points) -> np.ndarray:
        """Signed distances (...,) mm of points (..., 3) from the plane (+ toward camera)."""
        return np.asarray(points, dtype=np.float64) @ self.normal - self.offset

    def z_at(self, x, y) -> np.ndarray:
        """Z (mm) of the plane above (x, y) (broadcast)."""
        n = self.normal
        return (self.offset - n[0] * np.asarray(x) - n[1] * np.asarray(y)) / n[2]


@dataclass(frozen=True, eq=False)
class PlaneFit(Plane):
    """A plane fitted to points.

    Attributes
    ----------
    normal, offset : as :class:`Plane`.
    centroid : (3,) mm, weighted centroid of the inliers (a point of the plane).
    rms : float, mm, RMS distance of the inliers from the plane.
    flatness : float, mm, peak-to-valley of the inliers' distances from the fitted
        (least-squares) plane.
    n_points : int, points given.   n_inliers : int.
    inliers : (n_points,) bool.
    tangent : (2, 3) orthonormal basis of the plane (its tilts are along these).
    tilt_covariance : (2, 2) rad^2, covariance of the normal's tilt toward ``tangent``.
    sigma_offset : float, mm, standard uncertainty of the plane's position along its
        normal at the centroid (uncorrelated with the tilts there for independent points).
    tilt_offset_covariance : (2,) mm rad or None, the covariance of the tilts with that
        position: set by a fit with correlated noise (``fit_plane(..., noise=)``), None
        (zero) otherwise.
    correlated : bool, the covariance holds the correlation of the points' noise (a
        stereo match's, ``fit_plane(..., noise=)``).
    """

    centroid: np.ndarray = None
    rms: float = np.nan
    flatness: float = np.nan
    n_points: int = 0
    n_inliers: int = 0
    inliers: np.ndarray = None
    tangent: np.ndarray = None
    tilt_covariance: np.ndarray = None
    sigma_offset: float = np.nan
    tilt_offset_covariance: np.ndarray | None = None
    correlated: bool = False

    def __post_init__(self):
        super().__post_init__()
        _freeze(self, "centroid", "inliers", "tangent", "tilt_covariance",
                "tilt_offset_covariance")

    @property
    def plane(self) -> Plane:
        return Plane(self.normal, self.offset)

    @property
    def tilt_deg(self) -> float:
        """Angle (deg) between the normal and world +z."""
        return float(np.degrees(np.arccos(np.clip(self.normal[2], -1.0, 1.0))))

    def sigma_at(self, point) -> float:
        """Standard uncertainty (mm) of the plane's position along its normal at ``point``."""
        q = self.tangent @ (np.asarray(point, dtype=np.float64) - self.centroid)
        var = self.sigma_offset**2 + q @ self.tilt_covariance @ q
        if self.tilt_offset_covariance is not None:
            var += 2.0 * float(q @ self.tilt_offset_covariance)
        return float(np.sqrt(max(var, 0.0)))


def _lmeds_plane(p: np.ndarray, rng: np.random.Generator, *, trials: int = 300,
                 max_points: int = 20000):
    """Least-median-of-squares plane from random triples (breakdown 50 %): the first
    trial of the smallest median (:func:`telefringe.metrology._plane_kernels.lmeds_best`,
    which skips the medians of trials that cannot win). Returns (normal (3,), offset,
    sqrt(median squared distance))."""
    from telefringe.metrology._plane_kernels import lmeds_best

    sub = p if p.shape[0] <= max_points else p[rng.choice(p.shape[0], max_points,
                                                          replace=False)]
    triples = np.array([rng.choice(sub.shape[0], 3, replace=False) for _ in range(trials)],
                       dtype=np.int64).reshape(trials, 3)
    t, normal, offset, median = lmeds_best(np.ascontiguousarray(sub, dtype=np.float64),
                                           triples)
    if t < 0:
        raise MetrologyError("the points are collinear: no plane")
    return normal, float(offset), np.sqrt(median)


def fit_plane(points, *, weights=None, robust: bool = False, seed: int = 0,
              max_iter: int = 50, noise=None) -> PlaneFit:
    """Fit a plane to points (total least squares, optionally robust).

    Parameters
    ----------
    points : (n, 3) array_like of float, mm, or PointCloud (its valid points)
        Non-finite rows are ignored.
    weights : (n,) array_like of float, optional
        Relative weights (e.g. 1 / sigma_z^2); the uncertainty is scaled by the
        residuals, so only their ratios matter. For a PointCloud the default is
        1 / sigma_z^2 per point (a point without a finite, positive sigma_z is left out;
        only a cloud with no sigma at all is fitted unweighted).
    robust : bool
        Least median of squares start (random triples from ``seed``, breakdown point
        50 %), then Tukey-biweight iteratively reweighted least squares; points with zero
        final weight are outliers. Otherwise plain least squares on all points.
    seed : int
        Seeds the robust start.
    noise : StereoNoise, optional, with a PointCloud matched by two cameras: the points'
        noise split into its independent parts
        (:func:`telefringe.reconstruction.stereo.match_noise` of the match that made the
        cloud, on its grid). Neighbouring matches share the second camera's pixels, so
        their errors are correlated and the usual covariance (independent points)
        understates the plane's; with it the covariance is the sandwich of the points'
        exact covariance (:func:`_plane_sandwich`), scaled by the residuals. The fit is
        the same.

    Returns
    -------
    PlaneFit

    Raises
    ------
    MetrologyError
        Fewer than 3 points, collinear points, or fewer than 3 inliers; ``noise`` without
        a cloud, of another shape, or not covering a fitted point.
    """
    from telefringe.metrology._plane_kernels import (
        kept_moments,
        plane_residuals,
        plane_statistics,
        residuals_of_inliers,
        tukey_moments,
    )

    p, w0, finite = _points_and_weights(points, weights, sigma_weights=True)
    n_all = p.shape[0]
    finite &= np.isfinite(w0) & (w0 >= 0)
    pf = np.ascontiguousarray(p[finite], dtype=np.float64)  # (n, 3)
    wf = w0[finite]
    if pf.shape[0] < 3 or np.count_nonzero(wf) < 3:
        raise MetrologyError(f"a plane needs at least 3 points, got {pf.shape[0]}")
    wf = np.ascontiguousarray(wf / wf.mean(), dtype=np.float64)
    keep = np.ones(pf.shape[0], dtype=bool)
    # every pass over the points is compiled (telefringe.metrology._plane_kernels): a
    # BGA's substrate has ~150 000 points and its robust fit ~10 rounds
    if robust:
        rng = np.random.default_rng(seed)
        n, d, med = _lmeds_plane(pf, rng)
        r = plane_residuals(pf, n, d)
        scale = max(_MAD * np.median(np.abs(r)), 1e-12)
        extent = float(np.max(pf.max(axis=0) - pf.min(axis=0))) + 1e-12
        buf = np.empty(pf.shape[0])
        for _ in range(max_iter):
            # one round: the Tukey-weighted plane, then its residuals (r) and the
            # absolute residuals of the round's inliers (buf[:n_in]) for the new scale
            cs = _TUKEY_C * scale
            n_pos, c, S = tukey_moments(pf, wf, r, cs)
            if n_pos < 3:
                raise MetrologyError("robust plane fit: fewer than 3 inliers")
            n_new = np.linalg.eigh(S)[1][:, 0]
            if n_new[2] < 0:
                n_new = -n_new
            d_new = float(n_new @ c)
            n_in = residuals_of_inliers(pf, n_new, d_new, r, cs, buf)
            # robust scale from at most ~200k of the inliers (a regular subsample)
            ri = buf[:n_in]
            ri = ri[::max(1, ri.size // 200_000)]
            new_scale = max(_MAD * np.median(ri), 1e-12)
            # converged when the plane moves by less than 1e-3 of its own standard
            # uncertainty (offset scale / sqrt(n); tilt that over the points' extent)
            tol = 1e-3 * new_scale / np.sqrt(max(n_in, 1))
            done = (abs(d_new - d) < tol and np.linalg.norm(n_new - n) * extent < tol
                    and abs(new_scale - scale) < 1e-3 * scale)
            n, d, scale = n_new, d_new, new_scale
            if done:
                break
        keep = np.abs(r) < _TUKEY_C * scale
        if np.count_nonzero(keep) < 3:
            raise MetrologyError("robust plane fit: fewer than 3 inliers")
    # weighted total least squares on the kept points
    c, S = kept_moments(pf, wf, keep)
    evals, evecs = np.linalg.eigh(S)
    n = evecs[:, 0]
    if n[2] < 0:
        n = -n
    if evals[1] <= 1e-12 * max(evals[2], 1e-300):
        raise MetrologyError("the points are collinear: no plane")
    d = float(n @ c)
    T = _tangent_basis(n)
    nk, sw, swr2, sr2, rmin, rmax, M = plane_statistics(pf, wf, keep, n, d, c, T)
    # weights normalised to mean 1 over the kept points
    mean_w = sw / nk
    dof = max(nk - 3, 1)
    s2 = float(swr2 / mean_w / dof)
    try:
        tilt_cov = s2 * np.linalg.inv(M / mean_w)
    except np.linalg.LinAlgError:
        raise MetrologyError("the points are collinear: no plane") from None
    inliers = np.zeros(n_all, dtype=bool)
    idx = np.flatnonzero(finite)
    inliers[idx[keep]] = True
    sigma_offset = float(np.sqrt(s2 / (sw / mean_w)))
    cross = None
    if noise is not None:
        cov = _plane_sandwich(points, noise, idx, pf, wf, keep, n, c, T)
        tilt_cov = cov[:2, :2]
        sigma_offset = float(np.sqrt(cov[2, 2]))
        cross = cov[:2, 2]
    return PlaneFit(n, d, centroid=c, rms=float(np.sqrt(sr2 / nk)),
                    flatness=float(rmax - rmin), n_points=int(n_all),
                    n_inliers=int(nk), inliers=inliers, tangent=T, tilt_covariance=tilt_cov,
                    sigma_offset=sigma_offset, tilt_offset_covariance=cross,
                    correlated=noise is not None)


def _noise_at(cloud, noise, what: str):
    """The StereoNoise ``noise``'s (var_own (n,), weights (n, K), sources (n, K)) at the
    cloud's valid points (row-major, as ``cloud.points()``)."""
    from telefringe.reconstruction.cloud import PointCloud

    if not isinstance(cloud, PointCloud):
        raise MetrologyError(f"noise needs the {what} as a PointCloud (its pixels)")
    if np.shape(noise.var_own) != cloud.shape:
        raise MetrologyError(f"noise has shape {np.shape(noise.var_own)}, the cloud "
                             f"{cloud.shape}")
    m = cloud.mask
    return (np.asarray(noise.var_own, dtype=np.float64)[m],
            np.asarray(noise.weights, dtype=np.float64)[m],
            np.asarray(noise.sources)[m])


def _plane_sandwich(cloud, noise, idx, pf, wf, keep, n, c, T):
    """Covariance (3, 3) of (tilt toward T[0], tilt toward T[1] (rad), offset along
    ``n`` at the centroid ``c`` (mm)) of the weighted total-least-squares plane of the
    kept points, with their correlated noise.

    The residual ``n . (p - c)`` of a point moves by ``(n . d) delta_s`` when the point
    moves by ``delta_s`` along its line ``d``; the linearised weighted fit is an ordinary
    one in ``sqrt(w)``-scaled rows, design ``[T (p - c), -1]``, whose covariance is the
    sandwich (:func:`telefringe.metrology.spheres._sandwich`) of the points' covariance
    from the noise split (``idx`` the points' indices among the cloud's valid points,
    ``pf``/``wf``/``keep`` the fit's points, weights and kept rows)."""
    from telefringe.metrology.spheres import _sandwich

    var_own, weights, sources = _noise_at(cloud, noise, "points")
    use = keep & (wf > 0)
    sel = idx[use]
    var_own, weights, sources = var_own[sel], weights[sel], sources[sel]
    if not np.all(np.isfinite(var_own)):
        raise MetrologyError("noise does not cover every fitted point (NaN var_own)")
    dirs = np.asarray(cloud.directions, dtype=np.float64)
    dv = (np.broadcast_to(dirs, (sel.size, 3)) if dirs.ndim == 1
          else dirs[cloud.mask][sel])
    p = pf[use] - c
    sw = np.sqrt(wf[use])
    J = np.column_stack([p @ T.T, -np.ones(sel.size)]) * sw[:, None]
    f = (p @ n) * sw
    a = (dv @ n) * sw
    try:
        Ninv = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        raise MetrologyError("the points are collinear: no plane") from None
    return _sandwich(J, a, Ninv, f, var_own, weights, sources)


@dataclass(frozen=True)
class PlaneDistance:
    """Distance between two (nearly parallel) planes.

    Attributes
    ----------
    distance : float, mm, signed distance of ``a``'s point ``at`` from plane ``b``,
        along ``b``'s normal (positive: ``a`` is on the camera side of ``b``).
    angle_deg : float, angle between the normals.
    sigma : float, mm, standard uncertainty of ``distance`` from the fits' uncertainties
        (planes without uncertainty count as exact).
    at : (3,) mm, the point of ``a`` where the distance is taken.
    """

    distance: float
    angle_deg: float
    sigma: float
    at: tuple


def plane_distance(a: Plane, b: Plane, *, at=None) -> PlaneDistance:
    """Distance of plane ``a`` from plane ``b`` (e.g. a scan's plane from the reference).

    Parameters
    ----------
    a, b : Plane or PlaneFit
    at : (3,) array_like, optional
        Where to take the distance: the point of ``a`` nearest to it. Default ``a``'s
        centroid when ``a`` is a fit, else the foot of the world origin on ``a``.
    """
    if at is None:
        at = getattr(a, "centroid", None)
        if at is None:
            at = a.normal * a.offset
    at = np.asarray(at, dtype=np.float64).reshape(3)
    # the point of a nearest to `at`
    pa = at - (at @ a.normal - a.offset) * a.normal
    dist = float(pa @ b.normal - b.offset)
    ang = float(np.degrees(np.arccos(np.clip(abs(a.normal @ b.normal), -1.0, 1.0))))
    var = 0.0
    for pl in (a, b):
        if isinstance(pl, PlaneFit) and np.isfinite(pl.sigma_offset):
            var += pl.sigma_at(pa) ** 2
    return PlaneDistance(dist, ang, float(np.sqrt(var)), tuple(float(x) for x in pa))
