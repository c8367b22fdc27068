"""Measurements on point clouds: planes, circle-marker spacing, spheres, BGA, step heights.

Every fit returns a small frozen result with its uncertainty; degenerate input raises
:class:`MetrologyError` (a ``ValueError``) with a message that says what is missing.
Point arrays are (n, 3) in mm (world frame); organised clouds are
:class:`telefringe.reconstruction.cloud.PointCloud` (one point per camera pixel, NaN = invalid).

Conventions
-----------
- Plane normals point toward the camera (``normal[2] > 0``), so distances above a plane
  (heights) are positive toward the camera.
- ``rms`` and form errors are computed from the inliers of robust fits.
- Standard uncertainties come from the residuals of each fit (the noise level is
  estimated, not assumed), through the fit's linearised normal equations.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from telefringe.reconstruction.cloud import PointCloud

__all__ = [
    "MetrologyError",
    "Plane",
    "PlaneFit",
    "PlaneDistance",
    "fit_plane",
    "plane_distance",
    "MarkerCentres",
    "GridSpacing",
    "PlateMeasurement",
    "marker_centres_3d",
    "grid_spacing",
    "measure_plate",
    "SphereFit",
    "fit_sphere",
    "measure_sphere",
    "BGANominal",
    "Coplanarity",
    "BGAMeasurement",
    "seating_plane_coplanarity",
    "measure_bga",
    "StepMeasurement",
    "measure_steps",
]

_MAD = 1.482602218505602  # MAD -> standard deviation for Gaussian data
_TUKEY_C = 4.685  # Tukey biweight tuning constant (95 % efficiency at the Gaussian)


class MetrologyError(ValueError):
    """A measurement cannot be made from this input (too few points, degenerate shape)."""


def _readonly(*arrays):
    for a in arrays:
        if isinstance(a, np.ndarray):
            a.setflags(write=False)


def _tangent_basis(n: np.ndarray) -> np.ndarray:
    """(2, 3) orthonormal basis of the plane normal to ``n``: e1 along world x's
    projection (or y's when n is near x), e2 = n x e1."""
    ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = ref - (ref @ n) * n
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    return np.stack([e1, e2])


# --------------------------------------------------------------------------------------
# Planes
# --------------------------------------------------------------------------------------
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
        _readonly(n)
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
        normal at the centroid (uncorrelated with the tilts there).
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

    def __post_init__(self):
        super().__post_init__()
        _readonly(self.centroid, self.inliers, self.tangent, self.tilt_covariance)

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
        return float(np.sqrt(self.sigma_offset**2 + q @ self.tilt_covariance @ q))


def _tls_plane(P: np.ndarray, w: np.ndarray):
    """Weighted total least squares plane of points P (3, n) (coordinate rows, for
    contiguous BLAS products): (normal, centroid, eigenvalues)."""
    sw = w.sum()
    c = (P @ w) / sw
    Q = P - c[:, None]
    S = (Q * w) @ Q.T
    evals, evecs = np.linalg.eigh(S)
    n = evecs[:, 0]
    if n[2] < 0:
        n = -n
    return n, c, evals


def _plane_from_3(p3: np.ndarray):
    n = np.cross(p3[1] - p3[0], p3[2] - p3[0])
    nn = np.linalg.norm(n)
    if nn < 1e-12 * max(1.0, float(np.max(np.abs(p3)))) ** 2:
        return None
    n = n / nn
    return n, float(n @ p3[0])


def _lmeds_plane(p: np.ndarray, rng: np.random.Generator, *, trials: int = 300,
                 max_points: int = 20000):
    """Least-median-of-squares plane from random triples (breakdown 50 %)."""
    sub = p if p.shape[0] <= max_points else p[rng.choice(p.shape[0], max_points,
                                                          replace=False)]
    best = None
    best_med = np.inf
    for _ in range(trials):
        idx = rng.choice(sub.shape[0], 3, replace=False)
        pl = _plane_from_3(sub[idx])
        if pl is None:
            continue
        n, d = pl
        med = float(np.median((sub @ n - d) ** 2))
        if med < best_med:
            best_med, best = med, (n, d)
    if best is None:
        raise MetrologyError("the points are collinear: no plane")
    return best[0], best[1], np.sqrt(best_med)


def fit_plane(points, *, weights=None, robust: bool = False, seed: int = 0,
              max_iter: int = 50) -> PlaneFit:
    """Fit a plane to points (total least squares, optionally robust).

    Parameters
    ----------
    points : (n, 3) array_like of float, mm, or PointCloud (its valid points)
        Non-finite rows are ignored.
    weights : (n,) array_like of float, optional
        Relative weights (e.g. 1 / sigma_z^2); the uncertainty is scaled by the
        residuals, so only their ratios matter.
    robust : bool
        Least median of squares start (random triples from ``seed``, breakdown point
        50 %), then Tukey-biweight iteratively reweighted least squares; points with zero
        final weight are outliers. Otherwise plain least squares on all points.
    seed : int
        Seeds the robust start.

    Returns
    -------
    PlaneFit

    Raises
    ------
    MetrologyError
        Fewer than 3 points, collinear points, or fewer than 3 inliers.
    """
    if isinstance(points, PointCloud):
        p = points.points()
        if weights is None:
            s = points.sigma_z[points.mask]
            if np.all(np.isfinite(s) & (s > 0)):
                weights = 1.0 / s**2
        finite = np.ones(p.shape[0], dtype=bool)
    else:
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise MetrologyError(f"points must have shape (n, 3), got {p.shape}")
        finite = np.all(np.isfinite(p), axis=1)
    n_all = p.shape[0]
    if weights is None:
        w0 = np.ones(n_all)
    else:
        w0 = np.asarray(weights, dtype=np.float64).reshape(-1)
        if w0.shape[0] != n_all:
            raise MetrologyError(f"weights must have {n_all} values, got {w0.shape[0]}")
        finite &= np.isfinite(w0) & (w0 >= 0)
    pf = p[finite]
    wf = w0[finite]
    if pf.shape[0] < 3 or np.count_nonzero(wf) < 3:
        raise MetrologyError(f"a plane needs at least 3 points, got {pf.shape[0]}")
    wf = wf / wf.mean()
    P = np.ascontiguousarray(pf.T)  # (3, n)
    keep = np.ones(pf.shape[0], dtype=bool)
    if robust:
        rng = np.random.default_rng(seed)
        n, d, med = _lmeds_plane(pf, rng)
        r = n @ P - d
        scale = max(_MAD * np.median(np.abs(r)), 1e-12)
        extent = float(np.max(np.ptp(P, axis=1))) + 1e-12
        for _ in range(max_iter):
            u = r / (_TUKEY_C * scale)
            wt = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
            wr = wf * wt
            if np.count_nonzero(wr) < 3:
                raise MetrologyError("robust plane fit: fewer than 3 inliers")
            n_new, c, _ = _tls_plane(P, wr)
            d_new = float(n_new @ c)
            r = n_new @ P - d_new
            inl = wt > 0
            # robust scale from at most ~200k of the inliers (a regular subsample)
            ri = r[inl]
            ri = ri[::max(1, ri.size // 200_000)]
            new_scale = max(_MAD * np.median(np.abs(ri)), 1e-12)
            # converged when the plane moves by less than 1e-3 of its own standard
            # uncertainty (offset scale / sqrt(n); tilt that over the points' extent)
            n_in = max(int(np.count_nonzero(inl)), 1)
            tol = 1e-3 * new_scale / np.sqrt(n_in)
            done = (abs(d_new - d) < tol and np.linalg.norm(n_new - n) * extent < tol
                    and abs(new_scale - scale) < 1e-3 * scale)
            n, d, scale = n_new, d_new, new_scale
            if done:
                break
        keep = np.abs(r) < _TUKEY_C * scale
        if np.count_nonzero(keep) < 3:
            raise MetrologyError("robust plane fit: fewer than 3 inliers")
    Pk = P if robust is False else P[:, keep]
    wk = wf[keep]
    n, c, evals = _tls_plane(Pk, wk)
    if evals[1] <= 1e-12 * max(evals[2], 1e-300):
        raise MetrologyError("the points are collinear: no plane")
    d = float(n @ c)
    r = n @ Pk - d
    nk = Pk.shape[1]
    wk_n = wk / wk.mean()
    dof = max(nk - 3, 1)
    s2 = float(np.sum(wk_n * r * r) / dof)
    T = _tangent_basis(n)
    q = T @ (Pk - c[:, None])  # (2, nk)
    M = (q * wk_n) @ q.T
    try:
        tilt_cov = s2 * np.linalg.inv(M)
    except np.linalg.LinAlgError:
        raise MetrologyError("the points are collinear: no plane") from None
    inliers = np.zeros(n_all, dtype=bool)
    idx = np.flatnonzero(finite)
    inliers[idx[keep]] = True
    return PlaneFit(n, d, centroid=c, rms=float(np.sqrt(np.mean(r * r))),
                    flatness=float(r.max() - r.min()), n_points=int(n_all),
                    n_inliers=int(nk), inliers=inliers, tangent=T, tilt_covariance=tilt_cov,
                    sigma_offset=float(np.sqrt(s2 / wk_n.sum())))


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


# --------------------------------------------------------------------------------------
# Circle-marker plates
# --------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class MarkerCentres:
    """3D centres of markers seen in the camera image.

    Attributes
    ----------
    xyz : (n, 3) mm, NaN where not measured.
    sigma_xyz : (n, 3) mm, standard uncertainties of the local fits.
    n_points : (n,) int, cloud points used for each marker.
    valid : (n,) bool.
    """

    xyz: np.ndarray
    sigma_xyz: np.ndarray
    n_points: np.ndarray
    valid: np.ndarray

    def __post_init__(self):
        _readonly(self.xyz, self.sigma_xyz, self.n_points, self.valid)


def _poly_design(du: np.ndarray, dv: np.ndarray, degree: int) -> np.ndarray:
    cols = [np.ones_like(du)]
    for k in range(1, degree + 1):
        for j in range(k + 1):
            cols.append(du ** (k - j) * dv**j)
    return np.stack(cols, axis=1)


def marker_centres_3d(cloud: PointCloud, centres_px, *, inner_px: float | None = None,
                      outer_px: float | None = None, degree: int = 2, min_points: int = 30,
                      sigma_px=0.0) -> MarkerCentres:
    """3D position of marker centres from their camera-image centres.

    Around each marker, X, Y and Z of the cloud are smooth functions of the camera pixel
    (u, v) (affine on a plane for a telecentric camera; distortion adds a slowly varying
    term): a weighted polynomial of ``degree`` in (u - u_c, v - v_c) is fitted to each
    over the annulus ``inner_px <= r <= outer_px`` (the light surround: the dark marker
    itself decodes poorly) and evaluated at the centre. For a telecentric camera the
    image of a circle's centre is the centre of its image ellipse, so this is the 3D
    centre of the marker on the surface. No rig model is needed.

    Parameters
    ----------
    cloud : PointCloud (organised, camera pixel grid).
    centres_px : (n, 2) array_like of float, (u, v) px; NaN rows are skipped.
    inner_px, outer_px : float, optional
        Annulus radii (px). Defaults: 0.3 and 0.48 times the median distance between
        neighbouring centres (markers of half the pitch in diameter, as on the paper's
        plate, end at 0.25).
    degree : int, 1 or 2 (or 3).
    min_points : int, fewer valid points in the annulus leaves the marker unmeasured.
    sigma_px : float or (n,) array_like
        Standard uncertainty of the image centres (px, per axis). The uncertainty of the
        result includes it (through the local slopes of X, Y, Z with u and v) besides the
        noise of the cloud; with the default 0 only the cloud's noise counts.

    Returns
    -------
    MarkerCentres
    """
    c = np.asarray(centres_px, dtype=np.float64)
    if c.ndim != 2 or c.shape[1] != 2:
        raise MetrologyError(f"centres_px must have shape (n, 2), got {c.shape}")
    if degree not in (1, 2, 3):
        raise MetrologyError(f"degree must be 1, 2 or 3, got {degree!r}")
    ok = np.all(np.isfinite(c), axis=1)
    if inner_px is None or outer_px is None:
        cf = c[ok]
        if cf.shape[0] < 2:
            raise MetrologyError("give inner_px and outer_px: fewer than 2 marker centres "
                                 "to estimate the spacing from")
        dd = np.linalg.norm(cf[:, None, :] - cf[None, :, :], axis=2)
        np.fill_diagonal(dd, np.inf)
        spacing = float(np.median(dd.min(axis=1)))
        inner_px = 0.3 * spacing if inner_px is None else inner_px
        outer_px = 0.48 * spacing if outer_px is None else outer_px
    inner_px = float(inner_px)
    outer_px = float(outer_px)
    if not (0 <= inner_px < outer_px):
        raise MetrologyError(f"need 0 <= inner_px < outer_px, got {inner_px}, {outer_px}")
    rows, cols = cloud.shape
    xyz = cloud.xyz
    sig = cloud.sigma_line
    n = c.shape[0]
    s_px = np.broadcast_to(np.asarray(sigma_px, dtype=np.float64), (n,))
    out = np.full((n, 3), np.nan)
    out_s = np.full((n, 3), np.nan)
    npts = np.zeros(n, dtype=np.int64)
    for k in range(n):
        if not ok[k]:
            continue
        uc, vc = c[k]
        u_lo = max(int(np.floor(uc - outer_px)), 0)
        u_hi = min(int(np.ceil(uc + outer_px)), cols - 1)
        v_lo = max(int(np.floor(vc - outer_px)), 0)
        v_hi = min(int(np.ceil(vc + outer_px)), rows - 1)
        if u_hi < u_lo or v_hi < v_lo:
            continue
        vv, uu = np.mgrid[v_lo:v_hi + 1, u_lo:u_hi + 1]
        du = (uu - uc).ravel()
        dv = (vv - vc).ravel()
        r2 = du * du + dv * dv
        sel = (r2 >= inner_px**2) & (r2 <= outer_px**2)
        win = xyz[v_lo:v_hi + 1, u_lo:u_hi + 1].reshape(-1, 3)
        sel &= np.all(np.isfinite(win), axis=1)
        if np.count_nonzero(sel) < max(min_points, 3 * (degree + 1) * (degree + 2) // 2):
            continue
        s = sig[v_lo:v_hi + 1, u_lo:u_hi + 1].ravel()[sel]
        w = 1.0 / s**2 if np.all(np.isfinite(s) & (s > 0)) else np.ones(s.shape[0])
        w = w / w.mean()
        A = _poly_design(du[sel] / outer_px, dv[sel] / outer_px, degree)
        Y = win[sel]
        sw = np.sqrt(w)
        # one pass of rejection of gross outliers (e.g. a wrong fringe order) at 5 sigma
        keep = np.ones(A.shape[0], dtype=bool)
        for _ in range(2):
            coef, *_ = np.linalg.lstsq(A[keep] * sw[keep, None], Y[keep] * sw[keep, None],
                                       rcond=None)
            res = Y - A @ coef
            rz = res @ cloud.direction  # residuals along the camera line
            scale = _MAD * np.median(np.abs(rz[keep])) + 1e-15
            new_keep = np.abs(rz) <= 5.0 * scale
            if np.array_equal(new_keep, keep):
                break
            keep = new_keep
        Ak = A[keep] * sw[keep, None]
        if Ak.shape[0] <= Ak.shape[1]:
            continue
        coef, *_ = np.linalg.lstsq(Ak, Y[keep] * sw[keep, None], rcond=None)
        res = (Y[keep] - A[keep] @ coef) * sw[keep, None]
        dof = Ak.shape[0] - Ak.shape[1]
        s2 = np.sum(res * res, axis=0) / dof  # per coordinate
        cov00 = np.linalg.inv(Ak.T @ Ak)[0, 0]
        out[k] = coef[0]
        # the centre's own error moves the point along the surface: d xyz / d(u, v)
        slope2 = (coef[1] ** 2 + coef[2] ** 2) / outer_px**2
        out_s[k] = np.sqrt(s2 * cov00 + s_px[k] ** 2 * slope2)
        npts[k] = int(np.count_nonzero(keep))
    return MarkerCentres(out, out_s, npts, np.all(np.isfinite(out), axis=1))


@dataclass(frozen=True, eq=False)
class GridSpacing:
    """Distances between neighbouring marker centres (as in the paper's Table 3).

    Attributes
    ----------
    nominal_mm : float, the nominal pitch.
    dist_x : (rows, cols - 1) mm, 3D distance between markers (i, j) and (i, j + 1)
        (along the grid's columns = world x); NaN where one is missing.
    dist_y : (rows - 1, cols) mm, between (i, j) and (i + 1, j) (along y).
    mean_x, mean_y : float, mm.   std_x, std_y : float, mm (ddof = 1).
    abs_err_x, abs_err_y : float, mm, |mean - nominal|.
    rms_err_x, rms_err_y : float, mm, RMS of (distance - nominal).
    n_x, n_y : int, number of distances.
    """

    nominal_mm: float
    dist_x: np.ndarray
    dist_y: np.ndarray
    mean_x: float
    mean_y: float
    std_x: float
    std_y: float
    abs_err_x: float
    abs_err_y: float
    rms_err_x: float
    rms_err_y: float
    n_x: int
    n_y: int

    def __post_init__(self):
        _readonly(self.dist_x, self.dist_y)


def grid_spacing(centres_xyz, *, rows: int, cols: int, pitch_mm: float) -> GridSpacing:
    """Neighbour distances of a grid of 3D marker centres.

    Parameters
    ----------
    centres_xyz : (rows * cols, 3) or (rows, cols, 3) array_like, mm, row-major target
        order (row i along y, column j along x); NaN rows for missing markers.
    rows, cols : int.   pitch_mm : float, the nominal pitch.
    """
    c = np.asarray(centres_xyz, dtype=np.float64).reshape(int(rows), int(cols), 3)
    dx = np.linalg.norm(np.diff(c, axis=1), axis=2)
    dy = np.linalg.norm(np.diff(c, axis=0), axis=2)
    fx = dx[np.isfinite(dx)]
    fy = dy[np.isfinite(dy)]
    if fx.size < 2 or fy.size < 2:
        raise MetrologyError(
            f"too few neighbouring markers measured ({fx.size} along x, {fy.size} along y)")
    p = float(pitch_mm)
    return GridSpacing(p, dx, dy, float(fx.mean()), float(fy.mean()), float(fx.std(ddof=1)),
                       float(fy.std(ddof=1)), abs(float(fx.mean()) - p),
                       abs(float(fy.mean()) - p), float(np.sqrt(np.mean((fx - p) ** 2))),
                       float(np.sqrt(np.mean((fy - p) ** 2))), int(fx.size), int(fy.size))


@dataclass(frozen=True, eq=False)
class PlateMeasurement:
    """A circle-marker plate measured from a scan (one row of the paper's Table 3).

    Attributes
    ----------
    plane : PlaneFit, robust fit to the whole cloud.
    z : PlaneDistance, the plane's distance from the reference plane (Z measured).
    centres : MarkerCentres, (rows * cols) in target order.
    spacing : GridSpacing.
    """

    plane: PlaneFit
    z: PlaneDistance
    centres: MarkerCentres
    spacing: GridSpacing


def measure_plate(cloud: PointCloud, centres_px, *, rows: int, cols: int, pitch_mm: float,
                  reference: Plane | None = None, inner_px: float | None = None,
                  outer_px: float | None = None, seed: int = 0) -> PlateMeasurement:
    """Measure a circle-marker plate: its plane, its height and its marker spacing.

    Parameters
    ----------
    cloud : PointCloud.
    centres_px : (rows * cols, 2) camera-image marker centres in target order (row-major,
        NaN where not found), e.g. ``telefringe.targets.detect_circle_grid(...).centers``.
    rows, cols, pitch_mm : the plate's grid.
    reference : Plane, default Z = 0 (the calibration's reference pose).
    inner_px, outer_px : annulus of :func:`marker_centres_3d`.
    seed : seeds the robust plane fit.
    """
    c = np.asarray(centres_px, dtype=np.float64)
    if c.shape != (int(rows) * int(cols), 2):
        raise MetrologyError(f"centres_px must have shape ({rows * cols}, 2), got {c.shape}")
    plane = fit_plane(cloud, robust=True, seed=seed)
    ref = Plane.horizontal(0.0) if reference is None else reference
    centres = marker_centres_3d(cloud, c, inner_px=inner_px, outer_px=outer_px)
    spacing = grid_spacing(centres.xyz, rows=rows, cols=cols, pitch_mm=pitch_mm)
    return PlateMeasurement(plane, plane_distance(plane, ref), centres, spacing)


# --------------------------------------------------------------------------------------
# Spheres
# --------------------------------------------------------------------------------------
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
        _readonly(self.centre, self.inliers, self.covariance)

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


def _sphere_start_fixed(p: np.ndarray, w: np.ndarray, r: float) -> np.ndarray:
    """Start for a fixed-radius fit of a cap seen from the camera side: below the top
    of the points (the mean of their highest quarter along the normal of their plane)
    by r. (An algebraic start is unreliable on the few points of a small cap.)"""
    n, c, _ = _tls_plane(np.ascontiguousarray(p.T), w)
    h = (p - c) @ n
    top = p[h >= np.percentile(h, 75)]
    return top.mean(axis=0) - r * n


def _sphere_geometric(p: np.ndarray, w: np.ndarray, c: np.ndarray, r: float,
                      max_iter: int = 100, *, fixed_radius: bool = False):
    """Levenberg-Marquardt on the radial residuals |p - c| - r (r fixed if asked)."""
    sw = np.sqrt(w)
    x = np.concatenate([c, [r]])
    lam = 1e-3
    npar = 3 if fixed_radius else 4

    def resid(x):
        d = p - x[:3]
        dist = np.sqrt(np.sum(d * d, axis=1))
        return dist - x[3], d, dist

    def jac(d, dist):
        J = np.column_stack([-d / dist[:, None], -np.ones(p.shape[0])]) * sw[:, None]
        return J[:, :npar]

    f, d, dist = resid(x)
    cost = float(np.sum(w * f * f))
    for _ in range(max_iter):
        J = jac(d, dist)
        fw = f * sw
        H = J.T @ J
        g = J.T @ fw
        improved = False
        for _ in range(20):
            step = np.zeros(4)
            step[:npar] = -np.linalg.solve(H + lam * np.diag(np.diag(H)), g)
            xn = x + step
            fn, dn, distn = resid(xn)
            cn = float(np.sum(w * fn * fn))
            if cn <= cost:
                x, f, d, dist, cost_old, cost = xn, fn, dn, distn, cost, cn
                lam = max(lam / 10, 1e-12)
                improved = True
                break
            lam *= 10
        if not improved:
            break
        if np.linalg.norm(step) <= 1e-12 * (1.0 + np.linalg.norm(x)) or (
                cost_old - cost) <= 1e-15 * max(cost_old, 1e-300):
            break
    return x[:3], float(x[3]), f, jac(d, dist)


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
    if isinstance(points, PointCloud):
        p = points.points()
        finite = np.ones(p.shape[0], dtype=bool)
    else:
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise MetrologyError(f"points must have shape (n, 3), got {p.shape}")
        finite = np.all(np.isfinite(p), axis=1)
    n_all = p.shape[0]
    w0 = np.ones(n_all) if weights is None else np.asarray(weights, dtype=np.float64)
    if w0.shape != (n_all,):
        raise MetrologyError(f"weights must have {n_all} values")
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
    for _ in range(max_rounds if robust else 1):
        if np.count_nonzero(keep) < 5:
            raise MetrologyError("robust sphere fit: fewer than 5 inliers")
        if fixed:
            c0 = (np.asarray(start, dtype=np.float64) if start is not None
                  else _sphere_start_fixed(pf[keep], wf[keep], float(radius)))
            c, r, f, J = _sphere_geometric(pf[keep], wf[keep], c0, float(radius),
                                           fixed_radius=True)
        else:
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


def _components(mask: np.ndarray):
    from scipy import ndimage

    labels, n = ndimage.label(mask, structure=np.ones((3, 3), dtype=bool))
    return labels, n


def measure_sphere(cloud: PointCloud, *, min_height: float | None = None,
                   edge_px: int = 1, seed: int = 0) -> tuple[SphereFit, PlaneFit | None]:
    """Find and fit the sphere standing on a plane in a scan.

    The base plane is fitted robustly; the largest connected region standing more than
    ``min_height`` above it (default: 8 robust sigma of the plane, at least 20 um) is the
    sphere, shrunk by ``edge_px`` pixels (silhouette pixels mix surfaces), and fitted
    robustly. When no plane holds at least 20 % of the points, all points are fitted.

    Returns
    -------
    (SphereFit, PlaneFit or None)
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
        pts = cloud.xyz[region & mask]
    else:
        pts = cloud.points()
    return fit_sphere(pts, robust=True), base


# --------------------------------------------------------------------------------------
# BGA
# --------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class BGANominal:
    """The nominal ball grid.

    Attributes
    ----------
    rows, cols : int, or None: the grid spanned by the balls found (then a missing ball
        on the outer rows or columns cannot be told from a smaller grid).
    pitch_mm, ball_diameter_mm : float.
    present : (rows, cols) bool, optional: populated positions (default: all).
    centre_of_gravity : (2,) world (x, y) mm, optional: where the package's weight acts,
        for the seating plane (default: the centre of the ball grid).
    """

    rows: int | None
    cols: int | None
    pitch_mm: float
    ball_diameter_mm: float
    present: np.ndarray | None = None
    centre_of_gravity: tuple | None = None

    def __post_init__(self):
        if (self.rows is None) != (self.cols is None):
            raise MetrologyError("give both rows and cols, or neither")
        if self.rows is not None and (int(self.rows) < 1 or int(self.cols) < 1):
            raise MetrologyError("rows and cols must be >= 1")
        if self.rows is None and self.present is not None:
            raise MetrologyError("a populated map needs rows and cols")
        if not (np.isfinite(self.pitch_mm) and self.pitch_mm > 0):
            raise MetrologyError("pitch_mm must be > 0")
        if not (np.isfinite(self.ball_diameter_mm) and 0 < self.ball_diameter_mm):
            raise MetrologyError("ball_diameter_mm must be > 0")
        if self.present is not None:
            p = np.array(self.present, dtype=bool)
            if p.shape != (self.rows, self.cols):
                raise MetrologyError(f"present must have shape ({self.rows}, {self.cols})")
            _readonly(p)
            object.__setattr__(self, "present", p)

    def populated(self) -> np.ndarray:
        return (np.ones((self.rows, self.cols), dtype=bool) if self.present is None
                else self.present)


@dataclass(frozen=True, eq=False)
class Coplanarity:
    """Coplanarity of the ball apexes against the seating plane (JEDEC).

    Attributes
    ----------
    value : float, mm, the largest distance of an apex from the seating plane.
    distances : (n,) mm, each ball's apex distance from the seating plane (>= 0).
    contacts : (k,) int, indices of the balls the package rests on (k >= 3, usually 3).
    normal : (3,) world unit normal of the seating plane (toward the camera).
    offset : float, mm, ``normal . x = offset`` on the seating plane.
    """

    value: float
    distances: np.ndarray
    contacts: np.ndarray
    normal: np.ndarray
    offset: float

    def __post_init__(self):
        _readonly(self.distances, self.contacts, self.normal)


def seating_plane_coplanarity(apexes, centre_of_gravity, *, reference: Plane) -> Coplanarity:
    """Seating plane and coplanarity of ball apexes (JEDEC definition).

    Turned balls-down onto a flat surface, a package rests on three balls: the plane
    through three apexes that has all other apexes on the package side and whose
    triangle contains the package's centre of gravity. Coplanarity is the largest
    distance of any apex from that seating plane (JEDEC JESD22-B108 / the "seating
    plane" coplanarity of package outline standards).

    Here the balls point toward the camera: in coordinates (x', y') on the ``reference``
    (substrate) plane and height h above it, the seating plane ``h = a x' + b y' + c`` is
    the lowest plane lying on or above every apex at the centre of gravity, i.e. the
    linear program ``min a x_g + b y_g + c  s.t.  a x'_i + b y'_i + c >= h_i``, whose
    solution is the facet of the apexes' upper convex hull above the centre of gravity.

    Parameters
    ----------
    apexes : (n, 3) world mm, n >= 3.
    centre_of_gravity : (2,) or (3,) world mm; projected onto ``reference``.
    reference : Plane, the substrate plane.
    """
    from scipy.optimize import linprog

    A = np.asarray(apexes, dtype=np.float64)
    if A.ndim != 2 or A.shape[1] != 3 or A.shape[0] < 3 or not np.all(np.isfinite(A)):
        raise MetrologyError("coplanarity needs at least 3 finite apexes (n, 3)")
    T = _tangent_basis(reference.normal)
    q = A @ T.T  # (n, 2)
    h = A @ reference.normal - reference.offset
    g = np.asarray(centre_of_gravity, dtype=np.float64).reshape(-1)
    if g.size == 2:
        g = np.array([g[0], g[1], float(reference.z_at(g[0], g[1]))])
    qg = T @ g
    q0 = q.mean(axis=0)  # centred for conditioning
    qc = q - q0
    res = linprog(np.array([qg[0] - q0[0], qg[1] - q0[1], 1.0]),
                  A_ub=-np.column_stack([qc, np.ones(len(h))]), b_ub=-h,
                  bounds=[(None, None)] * 3, method="highs")
    if res.status != 0:
        raise MetrologyError(
            "no seating plane: the centre of gravity is outside the balls' footprint")
    a, b, c = res.x
    above = a * qc[:, 0] + b * qc[:, 1] + c - h  # >= 0, vertical gap
    norm = np.sqrt(1.0 + a * a + b * b)
    dist = np.maximum(above, 0.0) / norm
    tol = 1e-9 + 1e-9 * np.max(np.abs(h))
    contacts = np.flatnonzero(above <= tol)
    # the plane in world coordinates: h - a x' - b y' = c  (x' measured from q0)
    nw = (reference.normal - a * T[0] - b * T[1]) / norm
    off = (c + reference.offset - a * q0[0] - b * q0[1]) / norm
    return Coplanarity(float(dist.max()), dist, contacts, nw, float(off))


@dataclass(frozen=True, eq=False)
class BGAMeasurement:
    """A BGA inspection.

    Per ball (n found balls, in row-major grid order):

    index : (n, 2) int, (row i, column j) on the nominal grid.
    centre : (n, 3) world mm, fitted sphere centre.
    sigma_centre : (n, 3) mm, its standard uncertainty (from the cap fit's residuals, or
        from the highlight fit for refined balls).
    refined : (n,) bool, the centre's position on the substrate comes from the ball's
        specular highlight (see :func:`measure_bga`).
    apex : (n, 3) world mm, top of the ball (farthest from the substrate).
    height : (n,) mm, apex height above the substrate plane.
    sigma_height : (n,) mm, its standard uncertainty.
    diameter : (n,) mm, of the fitted sphere; NaN where the cap did not determine it
        (the fit then used the nominal diameter).
    position : (n, 2) mm, ball centre on the substrate plane, in the grid's frame
        (x' along the columns, y' along the rows, origin at the grid's first position).
    rms : (n,) mm, RMS radial residual of the cap fit.   n_points : (n,) int.

    Grid-wide:

    substrate : PlaneFit.
    found : (rows, cols) bool.   missing : ((i, j), ...) populated positions not found.
    unexpected : ((i, j), ...) balls found where the nominal grid has none.
    pitch_x : (rows, cols - 1) mm, in-plane distance between neighbouring ball centres
        along the columns (NaN where one is missing); pitch_y : (rows - 1, cols).
    pitch_error_max : float, mm, largest |pitch - nominal|.
    coplanarity : Coplanarity (JEDEC seating plane).
    grid_angle_deg : float, the grid's rotation on the substrate.
    psf_variance, sigma_psf_variance : float, mm^2, the camera's point-spread variance
        (per axis, on the object) estimated from the caps and its standard uncertainty,
        when the caps were fitted with it (``psf_model``); else NaN.
    """

    index: np.ndarray
    centre: np.ndarray
    sigma_centre: np.ndarray
    refined: np.ndarray
    apex: np.ndarray
    height: np.ndarray
    sigma_height: np.ndarray
    diameter: np.ndarray
    position: np.ndarray
    rms: np.ndarray
    n_points: np.ndarray
    substrate: PlaneFit
    found: np.ndarray
    missing: tuple
    unexpected: tuple
    pitch_x: np.ndarray
    pitch_y: np.ndarray
    pitch_error_max: float
    coplanarity: Coplanarity
    grid_angle_deg: float
    nominal: BGANominal
    psf_variance: float = np.nan
    sigma_psf_variance: float = np.nan

    def __post_init__(self):
        _readonly(self.index, self.centre, self.sigma_centre, self.refined, self.apex,
                  self.height, self.sigma_height, self.diameter, self.position, self.rms,
                  self.n_points, self.found, self.pitch_x, self.pitch_y)

    @property
    def n_balls(self) -> int:
        return int(self.index.shape[0])


def _apex_sigma(fit: SphereFit, n: np.ndarray) -> float:
    # apex = c + r n: var = n^T C_c n + 2 n^T C_cr + C_rr
    C = fit.covariance
    g = np.concatenate([n, [1.0]])
    return float(np.sqrt(max(g @ C @ g, 0.0)))


def _register_grid(pos: np.ndarray, pitch: float, rows: int, cols: int,
                   populated: np.ndarray):
    """Integer grid indices of ball positions pos (n, 2) on the substrate plane."""
    n = pos.shape[0]
    # orientation: nearest-neighbour directions modulo 90 deg
    if n >= 2:
        d = pos[:, None, :] - pos[None, :, :]
        dist = np.hypot(d[..., 0], d[..., 1])
        np.fill_diagonal(dist, np.inf)
        nn = np.argmin(dist, axis=1)
        ok = np.abs(dist[np.arange(n), nn] - pitch) < 0.25 * pitch
        vec = d[nn, np.arange(n)][ok]
    else:
        vec = np.zeros((0, 2))
    if vec.shape[0] == 0:
        theta = 0.0
    else:
        ang = np.arctan2(vec[:, 1], vec[:, 0])
        z = np.mean(np.exp(4j * ang))
        theta = float(np.angle(z) / 4.0)  # in (-45, 45] deg
    c, s = np.cos(theta), np.sin(theta)
    local = pos @ np.array([[c, -s], [s, c]])  # rotate by -theta
    f = local / pitch
    # lattice offset: circular mean of the fractional parts
    off = np.angle(np.mean(np.exp(2j * np.pi * f), axis=0)) / (2 * np.pi)
    k = np.round(f - off).astype(np.int64)
    frac = f - off - k
    on_grid = np.all(np.abs(frac) < 0.3, axis=1)
    if not np.any(on_grid):
        raise MetrologyError("no ball lies on a lattice of the nominal pitch")
    kmin = k[on_grid].min(axis=0)
    span = k[on_grid].max(axis=0) - kmin + 1  # (cols, rows)
    if rows is None:
        return None, theta, None, span
    if span[0] > cols or span[1] > rows:
        raise MetrologyError(
            f"the balls found span {span[1]} x {span[0]} positions, more than the nominal "
            f"{rows} x {cols} grid (wrong pitch or grid size?)")
    # place the found block inside the nominal grid: the shift that best matches the
    # populated positions (unique when the found balls span the whole grid)
    best = None
    for si in range(rows - span[1] + 1):
        for sj in range(cols - span[0] + 1):
            jj = k[on_grid, 0] - kmin[0] + sj
            ii = k[on_grid, 1] - kmin[1] + si
            score = int(np.count_nonzero(populated[ii, jj]))
            cand = (score, -(si + sj), si, sj)
            if best is None or cand > best[0]:
                best = (cand, [(si, sj)])
            elif cand[0] == best[0][0]:
                best[1].append((si, sj))
    if len(best[1]) > 1:
        raise MetrologyError(
            "cannot place the balls found on the nominal grid: a whole edge row or column "
            "is missing and the populated map does not decide; give BGANominal.present")
    si, sj = best[1][0]
    idx = np.full((n, 2), -1, dtype=np.int64)
    idx[on_grid, 0] = k[on_grid, 1] - kmin[1] + si
    idx[on_grid, 1] = k[on_grid, 0] - kmin[0] + sj
    origin_local = (np.array([kmin[0] - sj, kmin[1] - si]) + off) * pitch
    return idx, theta, origin_local, span


def _gauss_spots(wins: np.ndarray, u0: float, v0: float, *, max_iter: int = 60):
    """Least-squares fits of a pixel-integrated 2D Gaussian + background to many windows.

    ``wins`` (n, n0, n1): each is fitted with a * ex(u) * ey(v) + b, ex the integral over
    the pixel of a unit Gaussian of centre x and sigma sg (error functions), by
    Levenberg-Marquardt run on all windows at once (analytic Jacobian; bounds a >= 0,
    -1 <= x <= n1, -1 <= y <= n0, 0.2 <= sg <= 0.4 min(n0, n1) by projection). Returns
    a list of (x, y, cov_xy (2, 2), sg) in window pixel coordinates, or None where the
    fit failed or the spot is not clear (peak below 10 residual sigma, or within a pixel
    of the window's edge).
    """
    from scipy.special import erf

    W = np.asarray(wins, dtype=np.float64)
    n, n0, n1 = W.shape
    uu = np.arange(n1, dtype=np.float64)
    vv = np.arange(n0, dtype=np.float64)
    r2 = np.sqrt(2.0)
    c_pdf = 1.0 / np.sqrt(2.0 * np.pi)
    lo = np.array([0.0, -1.0, -1.0, 0.2, -np.inf])
    hi = np.array([np.inf, n1, n0, 0.4 * min(n0, n1), np.inf])

    def axis_terms(c, sg, grid):
        # (n, m): pixel integral of the unit Gaussian and its derivatives in c and sg
        zp = (grid[None, :] + 0.5 - c[:, None]) / (r2 * sg[:, None])
        zm = (grid[None, :] - 0.5 - c[:, None]) / (r2 * sg[:, None])
        ep, em = np.exp(-zp * zp), np.exp(-zm * zm)
        e = 0.5 * (erf(zp) - erf(zm))
        de_dc = -c_pdf / sg[:, None] * (ep - em)
        de_ds = -(r2 * c_pdf) / sg[:, None] * (zp * ep - zm * em)
        return e, de_dc, de_ds

    def model_jac(P):
        a, x, y, sg, b = P.T
        ex, dex, dsx = axis_terms(x, sg, uu)
        ey, dey, dsy = axis_terms(y, sg, vv)
        g = ey[:, :, None] * ex[:, None, :]  # (n, n0, n1)
        m = a[:, None, None] * g + b[:, None, None]
        J = np.stack([g, a[:, None, None] * ey[:, :, None] * dex[:, None, :],
                      a[:, None, None] * dey[:, :, None] * ex[:, None, :],
                      a[:, None, None] * (ey[:, :, None] * dsx[:, None, :]
                                          + dsy[:, :, None] * ex[:, None, :]),
                      np.ones_like(g)], axis=-1)
        return m.reshape(n, -1), J.reshape(n, -1, 5)

    b0 = W.reshape(n, -1).min(axis=1)
    P = np.column_stack([(W.reshape(n, -1).max(axis=1) - b0) * 2 * np.pi * 0.7**2,
                         np.full(n, float(u0)), np.full(n, float(v0)), np.full(n, 0.7), b0])
    Y = W.reshape(n, -1)
    m, J = model_jac(P)
    r = m - Y
    cost = np.sum(r * r, axis=1)
    lam = np.full(n, 1e-3)
    done = np.zeros(n, dtype=bool)
    eye = np.eye(5)
    for _ in range(max_iter):
        H = np.einsum("nki,nkj->nij", J, J)
        g = np.einsum("nki,nk->ni", J, r)
        A = H + lam[:, None, None] * (np.einsum("nii->ni", H)[:, :, None] * eye)
        try:
            step = -np.linalg.solve(A, g[..., None])[..., 0]
        except np.linalg.LinAlgError:
            break
        Pn = np.clip(P + step, lo, hi)
        mn, Jn = model_jac(Pn)
        rn = mn - Y
        cn = np.sum(rn * rn, axis=1)
        better = (cn < cost) & ~done
        small = np.max(np.abs(Pn - P) / (np.abs(P) + 1e-3), axis=1) < 1e-10
        P[better], r[better], J[better] = Pn[better], rn[better], Jn[better]
        done |= better & ((cost - cn) <= 1e-12 * cost) | small
        cost = np.where(better, cn, cost)
        lam = np.where(better, np.maximum(lam / 10, 1e-12), np.minimum(lam * 10, 1e12))
        done |= lam >= 1e12
        if done.all():
            break
    out = []
    dof = max(n0 * n1 - 5, 1)
    for k in range(n):
        a, x, y, sg, b = P[k]
        s2r = float(cost[k]) / dof
        try:
            cov = s2r * np.linalg.inv(J[k].T @ J[k])
        except np.linalg.LinAlgError:
            out.append(None)
            continue
        peak = a / (2 * np.pi * sg * sg)
        if not (np.all(np.isfinite(P[k])) and peak > 10.0 * np.sqrt(s2r)
                and 1.0 <= x <= n1 - 2 and 1.0 <= y <= n0 - 2):
            out.append(None)
            continue
        out.append((x, y, cov[1:3, 1:3], sg))
    return out


def _refine_by_highlights(cloud: PointCloud, image: np.ndarray, regions, centre, sig_c,
                          nrm, radius, sig_surface):
    """Ball centres on the substrate plane from their specular highlights.

    Under telecentric camera and projector every ball is seen and lit the same way, so
    its highlight sits at the same offset from its centre on every ball: the highlight
    (a small bright spot, located to ~0.01 px by a Gaussian fit) gives each ball's
    position relative to the others far better than the noisy cap fit; the common offset
    is the median of (highlight - cap centre) over the balls.

    The highlight's 3-D point is where its camera line meets the ball's fitted sphere.
    The line is exact (the points of neighbouring pixels lie on their own lines whatever
    their depth error: only their components across the viewing direction are used);
    the depth along it comes from the sphere fit of the whole cap, not from the few
    points at the highlight (whose depth noise, ~ sigma_line / 5, would move the centre
    on the substrate by the viewing direction's tilt times that).

    ``radius`` (n,) are the fitted radii, ``sig_surface`` (n,) the standard uncertainty
    of the fitted surface along the viewing direction near the top (mm).

    Returns (centre, sigma_centre, refined, lines (n, 3): a point of each highlight's
    camera line or NaN, median offset (3,) of highlight from centre or None).
    """
    if image.shape != cloud.shape:
        raise MetrologyError(f"image has shape {image.shape}, the cloud {cloud.shape}")
    rows, cols = cloud.shape
    d = np.asarray(cloud.direction, dtype=np.float64)
    h = 3
    hl = np.full(centre.shape, np.nan)
    hl_cov = np.full((centre.shape[0], 3, 3), np.nan)
    lines = np.full(centre.shape, np.nan)  # a point of each highlight's camera line
    found = []
    for k, (sl, reg) in enumerate(regions):
        sub = np.where(reg, image[sl], -np.inf)
        if not np.any(np.isfinite(sub)):
            continue
        pi, pj = np.unravel_index(int(np.nanargmax(np.nan_to_num(sub, nan=-np.inf))),
                                  sub.shape)
        pv, pu = sl[0].start + pi, sl[1].start + pj
        if not (h <= pv < rows - h and h <= pu < cols - h):
            continue
        win = image[pv - h:pv + h + 1, pu - h:pu + h + 1]
        if not np.all(np.isfinite(win)):
            continue
        found.append((k, pv, pu, win))
    spots = (_gauss_spots(np.stack([f[3] for f in found]), float(h), float(h))
             if found else [])
    for (k, pv, pu, _), g in zip(found, spots, strict=True):
        if g is None:
            continue
        x, y, cov_uv, _ = g
        du = np.arange(-h, h + 1, dtype=np.float64) - (x - h)
        dv = np.arange(-h, h + 1, dtype=np.float64) - (y - h)
        DV, DU = np.meshgrid(dv, du, indexing="ij")
        P = cloud.xyz[pv - h:pv + h + 1, pu - h:pu + h + 1].reshape(-1, 3)
        ok = np.all(np.isfinite(P), axis=1)
        if np.count_nonzero(ok) < 12:
            continue
        # the camera lines of the window's pixels: their points' components across the
        # viewing direction, a smooth (affine up to distortion) function of the pixel
        Q = P[ok] - np.outer(P[ok] @ d, d)
        A = _poly_design(DU.ravel()[ok], DV.ravel()[ok], 2)
        coef, *_ = np.linalg.lstsq(A, Q, rcond=None)
        J = coef[1:3].T  # (3, 2): d q / d (u, v)
        q = coef[0]
        # front intersection of the line q + t d with the sphere
        w = q - centre[k]
        b = float(w @ d)
        disc = b * b - (float(w @ w) - radius[k] ** 2)
        if not disc >= 0:
            continue
        t = -b - np.sqrt(disc)
        lines[k] = q
        hl[k] = q + t * d
        hl_cov[k] = J @ cov_uv @ J.T + sig_surface[k] ** 2 * np.outer(d, d)
    good = np.all(np.isfinite(hl), axis=1)
    if np.count_nonzero(good) < 3:
        return centre, sig_c, np.zeros(centre.shape[0], dtype=bool), lines, None
    off = hl[good] - centre[good]
    med = np.median(off, axis=0)
    # the median's uncertainty (common to all balls): 1.25 std / sqrt(n)
    s_med = 1.2533 * off.std(axis=0, ddof=1) / np.sqrt(off.shape[0])
    new_c = centre.copy()
    new_s = sig_c.copy()
    delta = hl[good] - med - centre[good]
    delta -= (delta @ nrm)[:, None] * nrm  # move on the substrate plane only
    new_c[good] = centre[good] + delta
    T = _tangent_basis(nrm)
    # in-plane uncertainty from the highlight fit and the median offset; along the
    # normal the cap fit's
    var_t = np.einsum("ij,kjl,il->ki", T, hl_cov[good], T)  # (m, 2), tangent basis
    var_t = var_t + (T**2) @ (s_med**2)
    var_n = (sig_c[good] ** 2) @ (nrm**2)  # (m,)
    new_s[good] = np.sqrt(var_t @ (T**2) + var_n[:, None] * nrm**2)
    return new_c, new_s, good, lines, med


def _fit_cap(pts: np.ndarray, sig: np.ndarray, view: np.ndarray, D: float, *,
             weighted: bool, max_view_angle_deg: float | None, fixed_radius: bool):
    """Fit one ball's cap; returns (SphereFit, radius_was_free) or None.

    A first robust fit with the nominal radius gives each point's surface normal; points
    whose surface is tilted more than ``max_view_angle_deg`` from facing the camera
    (``view``: unit vector toward the camera) are dropped (the pixel footprint and the
    camera's point spread average a range of depths there, and the average of a convex
    surface lies below it, increasingly so as 1 / cos^3 of the tilt). The final fit
    weights each point by 1 / sigma_r^2, sigma_r = sigma_line * cos(tilt) its
    uncertainty along the radius (points move along the viewing direction only). The
    radius is free when the cap determines it (0.7 D < diameter < 1.4 D and
    sigma_radius < 5 % D), else the nominal D / 2.
    """
    ok = np.all(np.isfinite(pts), axis=1)
    if weighted:
        ok &= np.isfinite(sig) & (sig > 0)
    pts, sig = pts[ok], sig[ok]
    if pts.shape[0] < 10:
        return None
    w = None
    if weighted or max_view_angle_deg is not None:
        f0 = fit_sphere(pts, robust=True, radius=D / 2)
        nn = pts - f0.centre
        nn /= np.linalg.norm(nn, axis=1)[:, None]
        cos_t = np.clip(nn @ view, 1e-3, 1.0)
        keep = np.ones(pts.shape[0], dtype=bool)
        if max_view_angle_deg is not None:
            keep = cos_t >= np.cos(np.radians(max_view_angle_deg))
        if np.count_nonzero(keep) < 10:
            return None
        pts, cos_t, sig = pts[keep], cos_t[keep], sig[keep]
        if weighted:
            w = 1.0 / (sig * cos_t) ** 2
    f = None
    if not fixed_radius:
        try:
            f = fit_sphere(pts, weights=w, robust=True)
            if not (0.7 * D < f.diameter < 1.4 * D and f.sigma_radius < 0.05 * D):
                f = None
        except MetrologyError:
            f = None
    free = f is not None
    if f is None:
        f = fit_sphere(pts, weights=w, robust=True, radius=D / 2)
        if not f.rms < 0.1 * D:  # not a cap of the nominal ball
            return None
    return f, free


def _smoothing_shape(pts: np.ndarray, centre: np.ndarray, r: float, view: np.ndarray):
    """Per point: cos of the surface tilt from facing the camera, and g = -lap(z) / 2.

    For a sphere seen along ``view``, the depth below the top is z(rho) =
    r - sqrt(r^2 - rho^2) (rho across the viewing direction); a camera whose point spread
    has variance s^2 (mm^2, per axis, on the object) measures the spread-averaged depth,
    deeper by s^2 g to first order, g = lap(z) / 2 = (2 r^2 - rho^2) / (2 (r^2 -
    rho^2)^(3/2)) (1 / mm). ``g`` is clipped at 80 deg of tilt.
    """
    v = pts - centre
    along = v @ view
    rho2 = np.maximum(np.sum(v * v, axis=1) - along**2, 0.0)
    rho2 = np.minimum(rho2, (r * np.sin(np.radians(80.0))) ** 2)
    g = (2.0 * r * r - rho2) / (2.0 * (r * r - rho2) ** 1.5)
    nn = v / np.linalg.norm(v, axis=1)[:, None]
    return np.clip(nn @ view, 1e-3, 1.0), g


def _brightness_gradient_terms(cloud: PointCloud, image: np.ndarray, projector,
                               px_mm: float) -> tuple[np.ndarray, bool]:
    """Per-pixel regressors of the depth shift that brightness gradients cause.

    A camera pixel averages the projector coordinate u_P over its point spread weighted
    by the brightness I, so where I varies the average is taken around a point moved by
    delta = s^2 grad(ln I) pixels (s^2 the spread's variance): u_P is off by delta .
    grad(u_P), which moves the point along its camera line by that over du_P/dt, i.e. by
    delta . (k + grad(t)), t the depth along the line and k (2,) the depth change per
    pixel at constant u_P (one vector for a telecentric rig). Returns ``(B, known)``, B of
    shape (rows, cols, 3): with the ``projector``, B[..., 0] is the whole shift per mm^2
    of s^2 on the object and B[..., 1:] = 0 (``known`` True); without it, B[..., 0] is
    the grad(t) part per mm^2 and B[..., 1:] = grad(ln I) (1 / px), whose coefficient
    s^2 k is then estimated from the data (``known`` False). Only the u fringes are
    modelled (the v axis adds little depth information). NaN where unknown.
    """
    d = np.asarray(cloud.direction, dtype=np.float64)
    xyz = np.where(cloud.mask[..., None], cloud.xyz, np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        ln_i = np.log(np.where(image > 0, image, np.nan))
    gi_v, gi_u = np.gradient(ln_i)
    B = np.zeros(cloud.shape + (3,))
    if projector is not None:
        up = np.asarray(projector.project(xyz)[0], dtype=np.float64)
        x0 = np.nanmedian(xyz.reshape(-1, 3), axis=0)
        du_dt = float((np.asarray(projector.project(x0 + 0.01 * d)[0])
                       - np.asarray(projector.project(x0)[0])) / 0.01)  # px / mm
        gu_v, gu_u = np.gradient(up)
        B[..., 0] = (gi_u * gu_u + gi_v * gu_v) / du_dt / px_mm**2
        return B, True
    t = xyz @ d
    gt_v, gt_u = np.gradient(t)
    B[..., 0] = (gi_u * gt_u + gi_v * gt_v) / px_mm**2
    B[..., 1] = gi_u
    B[..., 2] = gi_v
    return B, False


def _fit_along_line(q: np.ndarray, w: np.ndarray, a: np.ndarray, d: np.ndarray, r: float,
                    c0: np.ndarray):
    """Sphere of radius r with its centre on the line a + t d, fitted to points q (m, 3)
    with weights w: Gauss-Newton on t. Returns (centre (3,), sigma_t (mm)) or None."""
    t = float((c0 - a) @ d)
    for _ in range(20):
        v = q - (a + t * d)
        dist = np.linalg.norm(v, axis=1)
        f = dist - r
        j = -(v @ d) / dist  # d f / d t
        den = float(j @ (w * j))
        if not den > 0:
            return None
        step = -float(j @ (w * f)) / den
        t += step
        if abs(step) < 1e-9:
            break
    v = q - (a + t * d)
    f = np.linalg.norm(v, axis=1) - r
    dof = max(q.shape[0] - 1, 1)
    s_t = float(np.sqrt(float(f @ (w * f)) / dof / den))
    if not np.isfinite(t):
        return None
    return a + t * d, s_t


def _fit_caps_smoothed(caps, view: np.ndarray, r: float, *, max_view_angle_deg: float,
                       free_gradient: bool, sub_every: int = 4, rounds: int = 6):
    """Fixed-radius cap fits that model the camera's point spread, and its variance.

    ``caps``: list of (pts (m, 3), sig (m,), B (m, 3)) per ball (B: see
    :func:`_brightness_gradient_terms`, zeros when no image). The points of each ball are
    moved up the viewing direction by s^2 (g + B0) + a . (B1, B2) (g: see
    :func:`_smoothing_shape`; a = 0 unless ``free_gradient``) and fitted with a sphere of
    radius ``r`` weighted by 1 / (sigma_line cos(tilt))^2. The global parameters
    theta = (s^2[, a1, a2]), common to every ball (one camera, one rig), are estimated by
    Gauss-Newton on all balls' residuals at once (Schur complement of the per-ball
    centres), on every ``sub_every``-th ball.

    Returns (fits (list of SphereFit or None), data (per ball: corrected points of the
    fit, their weights, and d(centre)/d(theta) (3, p)), theta (p,), cov_theta (p, p)).
    """
    cos_min = np.cos(np.radians(max_view_angle_deg))
    npar = 3 if free_gradient else 1
    sel = []
    for pts, sig, bg in caps:
        ok = (np.all(np.isfinite(pts), axis=1) & np.isfinite(sig) & (sig > 0)
              & np.all(np.isfinite(bg), axis=1))
        pts, sig, bg = pts[ok], sig[ok], bg[ok]
        if pts.shape[0] < 10:
            sel.append(None)
            continue
        try:
            f0 = fit_sphere(pts, robust=True, radius=r)
        except MetrologyError:
            sel.append(None)
            continue
        cos_t, _ = _smoothing_shape(pts, f0.centre, r, view)
        keep = cos_t >= cos_min
        if np.count_nonzero(keep) < 10:
            sel.append(None)
            continue
        sel.append((pts[keep], sig[keep], bg[keep], f0.centre))

    def fit_one(item, theta):
        pts, sig, bg, c = item
        cos_t, g = _smoothing_shape(pts, c, r, view)
        R = np.column_stack([g + bg[:, 0], bg[:, 1], bg[:, 2]])[:, :npar]
        q = pts + np.outer(R @ theta, view)  # moved up, toward the camera
        w = 1.0 / (sig * cos_t) ** 2
        f = fit_sphere(q, weights=w, robust=True, radius=r, start=c)
        m = f.inliers
        v = q[m] - f.centre
        dist = np.linalg.norm(v, axis=1)
        nn = v / dist[:, None]
        J = -nn  # d res / d centre
        K = (nn @ view)[:, None] * R[m]  # d res / d theta
        H = J.T @ (w[m][:, None] * J)
        return f, q, w, J, K, dist - r, H

    theta = np.zeros(npar)
    cov = np.full((npar, npar), np.inf)
    sub = [k for k, it in enumerate(sel) if it is not None][::max(int(sub_every), 1)]
    for _ in range(rounds):
        A = np.zeros((npar, npar))
        bvec = np.zeros(npar)
        chi2 = 0.0
        dof = 0
        for k in sub:
            try:
                f, q, w, J, K, res, H = fit_one(sel[k], theta)
            except MetrologyError:
                continue
            wk = w[f.inliers]
            try:
                HiJK = np.linalg.solve(H, J.T @ (wk[:, None] * K))
                HiJf = np.linalg.solve(H, J.T @ (wk * res))
            except np.linalg.LinAlgError:
                continue
            KW = K.T * wk
            A += KW @ K - (KW @ J) @ HiJK
            bvec += KW @ res - (KW @ J) @ HiJf
            chi2 += float(res @ (wk * res))
            dof += res.size - 3
        try:
            step = -np.linalg.solve(A, bvec)
            cov = chi2 / max(dof - npar, 1) * np.linalg.inv(A)
        except np.linalg.LinAlgError:
            break
        theta = theta + step
        # stop well inside the estimate's own uncertainty
        if abs(step[0]) < 0.05 * np.sqrt(cov[0, 0]):
            break
    fits = []
    data = []
    for it in sel:
        f = None
        if it is not None:
            try:
                f, q, w, J, K, _, H = fit_one(it, theta)
                # the centre's sensitivity to theta (at its optimum: H dc = -J^T W K dth)
                dc = -np.linalg.solve(H, J.T @ (w[f.inliers][:, None] * K))
            except (MetrologyError, np.linalg.LinAlgError):
                f = None
        fits.append(f)
        data.append(None if f is None else (q[f.inliers], w[f.inliers], dc))
    return fits, data, theta, cov


def _sigma_weights(cloud: PointCloud, sel: np.ndarray):
    """1 / sigma_z^2 of the selected points, or None when some are unknown."""
    s = cloud.sigma_z[sel]
    return 1.0 / s**2 if np.all(np.isfinite(s) & (s > 0)) else None


def measure_bga(cloud: PointCloud, nominal: BGANominal, *, image=None,
                min_height: float | None = None, min_fraction: float = 0.2,
                edge_px: int | None = None, cap_min_height: float | None = None,
                weighted: bool = False, max_view_angle_deg: float | None = None,
                highlight_px: float | None = None, fixed_radius: bool = False,
                psf_model: bool = True, projector=None, substrate_margin: float | None = None,
                seed: int = 0) -> BGAMeasurement:
    """Inspect a ball grid array from its point cloud.

    Steps: the substrate plane is fitted robustly (the balls are outliers); pixels more
    than ``min_height`` (default 0.2 ball diameters) above it form connected regions,
    one per ball (regions smaller than ``min_fraction`` of a ball's footprint are
    ignored, and so are regions too large or too wide for one ball); the substrate is
    refitted away from them (``substrate_margin``). Each region, shrunk
    by ``edge_px`` pixels (silhouette pixels mix ball and
    substrate; default 1 when a ball is at least 10 pixels wide, else 0: on small balls
    the points are too few to spare), keeping points higher than ``cap_min_height``
    (default 0.3 ball diameters, above the shadowed flank) and away from the highlight
    (``highlight_px``), is fitted with a sphere: by default (``psf_model``) of the
    nominal radius, through a model of the camera's point spread, weighted by each
    point's uncertainty (else robust, free radius when the cap determines it); with an
    ``image``, the centre is then held on its highlight's camera line and only its depth
    along it refitted. The apex is
    the sphere's point farthest from the substrate. Balls are then registered on the
    nominal grid (its rotation and offset found from the balls themselves), which gives
    the missing balls, the pitch between neighbours and the JEDEC seating-plane
    coplanarity (see :func:`seating_plane_coplanarity`).

    Parameters
    ----------
    cloud : PointCloud.   nominal : BGANominal.
    image : (rows, cols) array_like, optional
        An unsaturated image of the scene in the camera's pixels (e.g. the HDR radiance
        of the decoder's background,
        :attr:`telefringe.reconstruction.pipeline.Reconstruction.radiance`).
        When given, each ball's position on the substrate comes from its specular
        highlight (Gaussian fit, ~0.01 px), offset by the median (highlight - cap centre)
        of all balls: with a telecentric camera and projector every ball shows its
        highlight at the same place, so the pitch is measured about 5x better than from
        the cap fits alone. The highlight's 3-D point is where its camera line meets the
        ball's fitted sphere (so the depth noise of the few points at the highlight does
        not leak onto the substrate through the tilt of the viewing direction). Balls
        without a clear highlight keep their cap centres.
    weighted : bool
        Weight each cap point by 1 / sigma_r^2 (its ``sigma_line`` projected on the
        sphere's radius).
    max_view_angle_deg : float, optional
        Drop cap points whose surface is tilted more than this from facing the camera.
    highlight_px : float, optional
        Drop cap points within this many pixels of the brightest pixel of ``image`` (the
        camera's point spread carries the highlight's phase into them, beyond the first
        order of ``psf_model``); 0 keeps them. Default 2.5 when a ball is at least 10
        pixels wide (the highlight of the paper rig's balls, ~1 px sigma, has fallen to
        the diffuse level there), else 0.
    fixed_radius : bool
        Fit every cap with the nominal radius (an assumption: the balls are spheres of
        the nominal diameter); the diameter is then not reported.
    psf_model : bool
        Fit the caps with the nominal radius and a model of the camera's point spread:
        a pixel measures the spread-averaged surface, which on a convex cap lies deeper
        than the surface (by s^2 lap(z) / 2, growing as the cap tilts away), and where
        the brightness varies the average is taken off-centre (by s^2 grad(ln I), with
        ``image``). The spread's variance s^2 (one camera, so one value for every ball)
        is estimated from the caps themselves (reported as ``psf_variance``), and so is
        the depth change per pixel of that shift at constant projector coordinate unless
        ``projector`` gives it; points tilted more than ``max_view_angle_deg`` (default
        60) from facing the camera are dropped, every point is weighted by
        1 / sigma_r^2. Needs the nominal diameter to hold (the radius is not fitted).
    projector : TelecentricDevice, optional
        The (calibrated) projector: gives the projector coordinate of each point and its
        rate along the camera line, for the brightness-gradient term of ``psf_model``
        (u fringes only; without it the term's geometric factor is estimated, which also
        absorbs the v fringes' share).
    substrate_margin : float, optional
        The substrate plane is refitted on points farther than this (mm, default D / 2)
        from every ball region (next to a ball the substrate's points are biased by its
        shadow edge and the light of its flank spread by the camera); 0 keeps the first
        fit on all points.
    seed : seeds the robust substrate fit.

    Returns
    -------
    BGAMeasurement
    """
    from scipy import ndimage

    if cloud.count < 10:
        raise MetrologyError(f"the cloud has {cloud.count} valid points: no BGA")
    if image is not None and np.shape(image) != cloud.shape:
        raise MetrologyError(f"image has shape {np.shape(image)}, the cloud {cloud.shape}")
    D = float(nominal.ball_diameter_mm)
    pitch = float(nominal.pitch_mm)
    # a first substrate plane, to find the balls (0.2 D above it): on every third row and
    # column of a large cloud (it is refitted on all the points away from the balls)
    k = 3 if cloud.count > 200_000 else 1
    sub_sel = np.zeros(cloud.shape, dtype=bool)
    sub_sel[::k, ::k] = True
    sub_sel &= cloud.mask
    substrate = fit_plane(cloud.xyz[sub_sel], weights=_sigma_weights(cloud, sub_sel),
                          robust=True, seed=seed)
    nrm = substrate.normal
    h = np.where(cloud.mask, cloud.xyz @ nrm - substrate.offset, np.nan)
    thr = 0.2 * D if min_height is None else float(min_height)
    cap_thr = 0.3 * D if cap_min_height is None else float(cap_min_height)
    above = np.nan_to_num(h, nan=-np.inf) > thr
    labels, n_lab = _components(above)
    if n_lab == 0:
        raise MetrologyError(f"no ball: nothing stands {thr:.3g} mm above the substrate")
    # expected footprint of a ball in pixels (from the cloud's point spacing)
    pts_all = cloud.xyz
    step = np.linalg.norm(np.diff(pts_all[:, :, :2], axis=1), axis=2)
    px_mm = float(np.nanmedian(step)) if np.any(np.isfinite(step)) else np.nan
    foot = np.pi * (D / 2) ** 2 / px_mm**2 if np.isfinite(px_mm) else 0.0
    if edge_px is None:
        edge_px = 1 if (np.isfinite(px_mm) and D / px_mm >= 10.0) else 0
    if highlight_px is None:
        highlight_px = 2.5 if (np.isfinite(px_mm) and D / px_mm >= 10.0) else 0.0
    margin = 0.5 * D if substrate_margin is None else float(substrate_margin)
    if margin > 0 and np.isfinite(px_mm):
        # refit the substrate away from the balls: next to a ball the substrate's points
        # are biased (its shadow edge and its flank's light, spread by the camera)
        near = ndimage.binary_dilation(above, iterations=max(int(np.ceil(margin / px_mm)), 1))
        far = cloud.mask & ~near
        if cloud.count > 200_000:  # every second row and column is plenty
            far[1::2, :] = False
            far[:, 1::2] = False
        if np.count_nonzero(far) >= max(100, 0.01 * cloud.count):
            substrate = fit_plane(cloud.xyz[far], weights=_sigma_weights(cloud, far),
                                  robust=True, seed=seed)
            nrm = substrate.normal
            h = np.where(cloud.mask, cloud.xyz @ nrm - substrate.offset, np.nan)
    sizes = np.bincount(labels.ravel(), minlength=n_lab + 1)
    slices = ndimage.find_objects(labels)
    bgrad, grad_known = None, True
    if psf_model and image is not None and np.isfinite(px_mm):
        bgrad, grad_known = _brightness_gradient_terms(cloud, np.asarray(image, np.float64),
                                                       projector, px_mm)
    fits = []
    regions = []
    free_r = []
    caps = []
    view = -np.asarray(cloud.direction, dtype=np.float64)
    image_arr = None if image is None else np.asarray(image, dtype=np.float64)
    for lab in range(1, n_lab + 1):
        if sizes[lab] < max(min_fraction * foot, 8):
            continue
        sl = slices[lab - 1]
        # a ball is compact: no wider than twice its diameter, no larger than 3 footprints
        if np.isfinite(px_mm) and (max(sl[0].stop - sl[0].start, sl[1].stop - sl[1].start)
                                   > 2.0 * D / px_mm + 2 or sizes[lab] > 3.0 * foot + 10):
            continue
        reg = labels[sl] == lab
        if edge_px > 0:
            reg = ndimage.binary_erosion(reg, iterations=int(edge_px))
        hh = h[sl]
        sel = reg & (np.nan_to_num(hh, nan=-np.inf) > cap_thr)
        if image_arr is not None and highlight_px > 0:
            # pixels near the specular highlight: the camera's point spread mixes the
            # highlight's (far brighter) light, and so its phase, into them
            sub_img = np.where(labels[sl] == lab, image_arr[sl], -np.inf)
            pi, pj = np.unravel_index(int(np.argmax(sub_img)), sub_img.shape)
            vv, uu = np.mgrid[0:sub_img.shape[0], 0:sub_img.shape[1]]
            sel &= np.hypot(vv - pi, uu - pj) > highlight_px
        pts = cloud.xyz[sl][sel]
        sig = cloud.sigma_line[sl][sel]
        if pts.shape[0] < 10:
            continue
        if psf_model:
            caps.append((pts, sig, np.zeros((pts.shape[0], 3)) if bgrad is None
                         else bgrad[sl][sel]))
            regions.append((sl, labels[sl] == lab))
            continue
        try:
            f = _fit_cap(pts, sig, view, D, weighted=weighted,
                         max_view_angle_deg=max_view_angle_deg, fixed_radius=fixed_radius)
        except MetrologyError:
            continue
        if f is None:
            continue
        f, free = f
        fits.append(f)
        free_r.append(free)
        regions.append((sl, labels[sl] == lab))
    smoothing = (np.nan, np.nan)
    if psf_model:
        all_fits, all_data, theta, cov_theta = _fit_caps_smoothed(
            caps, view, D / 2, max_view_angle_deg=(60.0 if max_view_angle_deg is None
                                                   else float(max_view_angle_deg)),
            free_gradient=not grad_known)
        smoothing = (float(theta[0]), float(np.sqrt(cov_theta[0, 0])))
        keep = [k for k, f in enumerate(all_fits) if f is not None and f.rms < 0.1 * D]
        fits = [all_fits[k] for k in keep]
        cap_data = [all_data[k] for k in keep]
        regions = [regions[k] for k in keep]
        free_r = [False] * len(fits)
    if not fits:
        raise MetrologyError("no ball could be fitted")
    centre = np.array([f.centre for f in fits])
    sig_c = np.array([f.sigma_centre for f in fits]).reshape(-1, 3)
    radius = np.array([f.radius for f in fits])
    refined = np.zeros(len(fits), dtype=bool)
    med = None
    if image is not None:
        sig_top = np.array([_apex_sigma(f, nrm) for f in fits])
        centre, sig_c, refined, lines, med = _refine_by_highlights(
            cloud, np.asarray(image, np.float64), regions, centre, sig_c, nrm, radius,
            sig_top)
    sig_top = np.array([_apex_sigma(f, nrm) for f in fits])
    if psf_model and image is not None and med is not None:
        # every ball's centre lies on its highlight's camera line shifted by the common
        # offset: fit the one remaining unknown, the depth along that line
        d = np.asarray(cloud.direction, dtype=np.float64)
        for k in np.flatnonzero(refined):
            res = _fit_along_line(cap_data[k][0], cap_data[k][1], lines[k] - med, d,
                                  radius[k], centre[k])
            if res is not None:
                centre[k], s_t = res
                sig_top[k] = s_t * abs(float(d @ nrm))
    if psf_model and np.all(np.isfinite(cov_theta)):
        # the estimated spread parameters are common to every ball: their uncertainty
        # moves every apex together
        for k in range(len(fits)):
            gk = nrm @ cap_data[k][2]  # d height / d theta
            sig_top[k] = np.hypot(sig_top[k], np.sqrt(max(float(gk @ cov_theta @ gk), 0.0)))
    apex = centre + radius[:, None] * nrm
    height = apex @ nrm - substrate.offset
    sig_h = np.array([np.hypot(st, substrate.sigma_at(a))
                      for st, a in zip(sig_top, apex, strict=True)])
    T = _tangent_basis(nrm)
    pos = centre @ T.T
    if nominal.rows is None:
        # the grid is the span of the balls found
        _, _, _, span = _register_grid(pos, pitch, None, None, None)
        nominal = replace(nominal, rows=int(span[1]), cols=int(span[0]))
    populated = nominal.populated()
    rows, cols = int(nominal.rows), int(nominal.cols)
    idx, theta, origin_local, _ = _register_grid(pos, pitch, rows, cols, populated)
    # keep one ball per grid position (the one with the most points), drop off-grid blobs
    order = sorted(range(len(fits)), key=lambda k: -fits[k].n_inliers)
    taken = np.full((rows, cols), -1, dtype=np.int64)
    for k in order:
        i, j = idx[k]
        if i >= 0 and taken[i, j] < 0:
            taken[i, j] = k
    sel = taken[taken >= 0]  # row-major grid order
    found = taken >= 0
    missing = tuple((int(i), int(j)) for i, j in np.argwhere(populated & ~found))
    unexpected = tuple((int(i), int(j)) for i, j in np.argwhere(~populated & found))
    c_, s_ = np.cos(theta), np.sin(theta)
    local = pos[sel] @ np.array([[c_, -s_], [s_, c_]]) - origin_local
    grid_xyz = np.full((rows, cols, 2), np.nan)
    grid_xyz[found] = local
    px = np.linalg.norm(np.diff(grid_xyz, axis=1), axis=2)
    py = np.linalg.norm(np.diff(grid_xyz, axis=0), axis=2)
    errs = np.concatenate([px[np.isfinite(px)], py[np.isfinite(py)]]) - pitch
    # centre of gravity: given, or the centre of the nominal grid
    if nominal.centre_of_gravity is not None:
        cog = np.asarray(nominal.centre_of_gravity, dtype=np.float64)
    else:
        mid_local = np.array([(cols - 1) / 2.0, (rows - 1) / 2.0]) * pitch + origin_local
        mid_plane = np.array([[c_, -s_], [s_, c_]]) @ mid_local  # rotate back by theta
        cog = (mid_plane[0] * T[0] + mid_plane[1] * T[1]
               + substrate.offset * nrm)
    cop = seating_plane_coplanarity(apex[sel], cog, reference=substrate.plane)
    return BGAMeasurement(
        index=np.argwhere(found), centre=centre[sel],
        sigma_centre=sig_c[sel], refined=refined[sel],
        apex=apex[sel], height=height[sel],
        sigma_height=sig_h[sel],
        diameter=np.where(np.asarray(free_r)[sel], 2.0 * radius[sel], np.nan),
        position=local,
        rms=np.array([fits[k].rms for k in sel]),
        n_points=np.array([fits[k].n_inliers for k in sel], dtype=np.int64),
        substrate=substrate, found=found, missing=missing, unexpected=unexpected,
        pitch_x=px, pitch_y=py,
        pitch_error_max=float(np.max(np.abs(errs))) if errs.size else np.nan,
        coplanarity=cop, grid_angle_deg=float(np.degrees(theta)), nominal=nominal,
        psf_variance=float(smoothing[0]), sigma_psf_variance=float(smoothing[1]))


# --------------------------------------------------------------------------------------
# Step heights
# --------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class StepMeasurement:
    """Parallel flat levels of a step gauge.

    Attributes
    ----------
    normal : (3,) common unit normal of the levels (toward the camera).
    offsets : (k,) mm, ``normal . x = offset`` of each level, ascending.
    heights : (k,) mm, each level's height above the lowest (``offsets - offsets[0]``).
    sigma_heights : (k,) mm, standard uncertainty of ``heights`` (0 for the lowest).
    step_heights : (k - 1,) mm, height of each level above the one below.
    sigma_steps : (k - 1,) mm.
    rms : (k,) mm, RMS residual of each level.   n_points : (k,) int.
    centroids : (k, 3) mm.
    labels : (rows, cols) int, level of each pixel (-1: unused).
    """

    normal: np.ndarray
    offsets: np.ndarray
    heights: np.ndarray
    sigma_heights: np.ndarray
    step_heights: np.ndarray
    sigma_steps: np.ndarray
    rms: np.ndarray
    n_points: np.ndarray
    centroids: np.ndarray
    labels: np.ndarray

    def __post_init__(self):
        _readonly(self.normal, self.offsets, self.heights, self.sigma_heights,
                  self.step_heights, self.sigma_steps, self.rms, self.n_points,
                  self.centroids, self.labels)


def _level_peaks(h: np.ndarray, *, min_step: float, min_points: int, bin_mm: float):
    lo, hi = float(h.min()), float(h.max())
    nb = max(int(np.ceil((hi - lo) / bin_mm)) + 1, 1)
    if nb > 2_000_000:
        raise MetrologyError("height range too large for the bin size")
    hist, edges = np.histogram(h, bins=nb, range=(lo, lo + nb * bin_mm))
    centres = 0.5 * (edges[:-1] + edges[1:])
    # counts within +- min_step / 3 of each bin (the band a level's points are taken from)
    half = max(int(round(min_step / 3.0 / bin_mm)), 0)
    counts = np.convolve(hist, np.ones(2 * half + 1, dtype=np.int64), mode="same")
    # tallest first; a peak must be min_step away from every taller one
    order = np.argsort(-counts, kind="stable")
    peaks = []
    for b in order:
        if counts[b] < min_points:
            break
        if all(abs(centres[b] - p) >= min_step for p in peaks):
            peaks.append(float(centres[b]))
    return sorted(peaks)


def _joint_parallel_planes(pts_list, n0: np.ndarray):
    """Common normal and offsets of parallel planes, Gauss-Newton on (tilts, offsets)."""
    n = n0.copy()
    K = len(pts_list)
    for _ in range(5):
        T = _tangent_basis(n)
        Ms = np.zeros((2 + K, 2 + K))
        bs = np.zeros(2 + K)
        for k, p in enumerate(pts_list):
            q = p @ T.T  # (m, 2)
            r = p @ n  # residual model: n.p + t.q - d_k = 0
            # normal equations, accumulated
            Mqq = q.T @ q
            Ms[:2, :2] += Mqq
            sq = q.sum(axis=0)
            Ms[:2, 2 + k] -= sq
            Ms[2 + k, :2] -= sq
            Ms[2 + k, 2 + k] += p.shape[0]
            bs[:2] -= q.T @ r
            bs[2 + k] += r.sum()
        try:
            x = np.linalg.solve(Ms, bs)
        except np.linalg.LinAlgError:
            raise MetrologyError("the levels do not determine a plane orientation") from None
        n_new = n + x[0] * T[0] + x[1] * T[1]
        n_new /= np.linalg.norm(n_new)
        if n_new[2] < 0:
            n_new = -n_new
        moved = np.linalg.norm(n_new - n)
        n = n_new
        if moved < 1e-13:
            break
    # final offsets, residuals and covariance at the solution
    T = _tangent_basis(n)
    offsets = np.array([float(np.mean(p @ n)) for p in pts_list])
    res = [p @ n - d for p, d in zip(pts_list, offsets, strict=True)]
    N = sum(p.shape[0] for p in pts_list)
    s2 = sum(float(np.sum(r * r)) for r in res) / max(N - 2 - K, 1)
    M = np.zeros((2 + K, 2 + K))
    for k, p in enumerate(pts_list):
        q = p @ T.T
        M[:2, :2] += q.T @ q
        sq = q.sum(axis=0)
        M[:2, 2 + k] -= sq
        M[2 + k, :2] -= sq
        M[2 + k, 2 + k] += p.shape[0]
    cov = s2 * np.linalg.inv(M)
    return n, offsets, res, cov


def _dominant_normal(cloud: PointCloud) -> np.ndarray:
    """Median of the normals of the cloud's pixel quads: the orientation shared by most
    of the surface (the levels of a step gauge; a plane fit would tilt along the
    staircase)."""
    xyz = cloud.xyz
    a = xyz[:-1, 1:] - xyz[:-1, :-1]
    b = xyz[1:, :-1] - xyz[:-1, :-1]
    nq = np.cross(a, b).reshape(-1, 3)
    nq = nq[np.all(np.isfinite(nq), axis=1)]
    if nq.shape[0] < 3:
        raise MetrologyError("too few neighbouring valid points to find the orientation")
    nq /= np.linalg.norm(nq, axis=1, keepdims=True)
    nq[nq[:, 2] < 0] *= -1
    n = np.median(nq, axis=0)
    return n / np.linalg.norm(n)


def measure_steps(cloud: PointCloud, *, min_step: float = 0.05, min_points: int = 200,
                  edge_px: int = 2) -> StepMeasurement:
    """Heights of the flat levels of a step gauge (parallel planes fitted jointly).

    The median normal of the surface gives a first orientation; heights along it are
    histogrammed and
    every peak holding at least ``min_points`` points, ``min_step`` (mm) or more from a
    taller one, is a level. Pixels within ``min_step / 3`` of a level, with their region
    shrunk by ``edge_px`` pixels (edges mix levels), are fitted as parallel planes with
    one common normal (Gauss-Newton, twice with re-assignment, 4-sigma rejection).

    Returns
    -------
    StepMeasurement
    """
    from scipy import ndimage

    if not (np.isfinite(min_step) and min_step > 0):
        raise MetrologyError("min_step must be > 0")
    pts = cloud.points()
    if pts.shape[0] < 2 * min_points:
        raise MetrologyError(f"the cloud has {pts.shape[0]} valid points: too few for steps")
    n = _dominant_normal(cloud)
    labels = np.full(cloud.shape, -1, dtype=np.int64)
    xyz = cloud.xyz
    mask = cloud.mask
    for _ in range(2):
        h_img = np.where(mask, xyz @ n, np.nan)
        hv = h_img[mask]
        bin_mm = min_step / 10.0
        peaks = _level_peaks(hv, min_step=min_step, min_points=min_points, bin_mm=bin_mm)
        if len(peaks) < 2:
            raise MetrologyError(
                f"found {len(peaks)} level(s) of at least {min_points} points: no step")
        labels[:] = -1
        pts_list = []
        keep_peaks = []
        for pk in peaks:
            sel = mask & (np.abs(np.nan_to_num(h_img, nan=np.inf) - pk) < min_step / 3)
            if edge_px > 0:
                sel = ndimage.binary_erosion(sel, iterations=int(edge_px))
            if np.count_nonzero(sel) < min_points:
                continue
            p = xyz[sel]
            # refine the level robustly: 4-sigma rejection around its median height
            r = p @ n
            med = np.median(r)
            scale = _MAD * np.median(np.abs(r - med)) + 1e-12
            good = np.abs(r - med) <= 4.0 * scale
            sel_idx = np.argwhere(sel)[good]
            labels[sel_idx[:, 0], sel_idx[:, 1]] = len(pts_list)
            pts_list.append(p[good])
            keep_peaks.append(pk)
        if len(pts_list) < 2:
            raise MetrologyError("fewer than 2 levels left after edge removal: no step")
        n, offsets, res, cov = _joint_parallel_planes(pts_list, n)
    order = np.argsort(offsets)
    offsets = offsets[order]
    K = len(offsets)
    cov_d = cov[2:, 2:][np.ix_(order, order)]
    relabel = np.full(K + 1, -1, dtype=np.int64)
    relabel[order] = np.arange(K)
    labels = np.where(labels >= 0, relabel[labels], -1)
    heights = offsets - offsets[0]
    sig_h = np.array([np.sqrt(max(cov_d[k, k] + cov_d[0, 0] - 2 * cov_d[k, 0], 0.0))
                      for k in range(K)])
    steps = np.diff(offsets)
    sig_s = np.array([np.sqrt(max(cov_d[k + 1, k + 1] + cov_d[k, k] - 2 * cov_d[k + 1, k],
                                  0.0)) for k in range(K - 1)])
    rms = np.array([float(np.sqrt(np.mean(res[k] ** 2))) for k in order])
    npts = np.array([pts_list[k].shape[0] for k in order], dtype=np.int64)
    cents = np.array([pts_list[k].mean(axis=0) for k in order])
    return StepMeasurement(n, offsets, heights, sig_h, steps, sig_s, rms, npts, cents, labels)
