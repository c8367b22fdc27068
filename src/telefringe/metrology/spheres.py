"""Spheres: algebraic start, geometric (optionally fixed-radius, robust) fits, and a
sphere standing on a plane in a scan, optionally through a model of the camera's point
spread (:func:`spread_shift`).

Why a point-spread model
------------------------
A camera pixel does not see the surface point on its line: it averages the projected
fringes over its point spread (the pixel's own area and the lens's defocus; variance s^2
per axis, camera pixels^2), weighted by the brightness. The decoded projector coordinate
is then, to first order, ``u + s^2 (lap(u) / 2 + grad(ln I) . grad(u))`` (derivatives
over the camera pixels) instead of ``u``. On a plane both terms vanish or only slide the
point within the plane; on a sphere they move every point along its camera line, inward
near the top (by about 2 s^2 / R in object units for a Lambertian sphere lit obliquely)
and outward toward the limb, which biases the fitted radius and pulls the centre: on the
virtual rigs (camera blur 0.5 px, 4 x 4 binned) 1-5 um, 5-20 times the fit's noise.
On the mixed rig with the true devices and no noise the plain fit's centre was off by
(+4.6, -1.4, -5.4) um; with the camera's blur off (the pixel's own 1/12 px^2 left),
(+1.1, -0.3, -1.4) um, in proportion to s^2; tracing every pixel exactly or one albedo
for sphere and plane changed it by < 0.15 um (the renderer is not the cause).
:func:`measure_sphere` given the rig and an image fits through the model (with s^2
estimated, or given); a two-camera rig is not modelled yet (its points are fitted as
they are).
"""

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

#: Step (camera px) of the finite differences of the point-spread model.
_SPREAD_STEP_PX = 0.25
#: Default largest angle (deg) between a fitted point's sphere normal and the direction
#: back to the camera: beyond it the first-order point-spread model no longer describes
#: the points (the shift grows as 1 / cos^3 toward the limb, and the spread there mixes
#: the background in).
SPREAD_MAX_VIEW_DEG = 60.0
#: Default margin (camera px) around a fitted pixel whose lines must all meet the visible
#: sphere (the reach of a point spread of about 0.5 px sigma beyond the pixel's own half).
SPREAD_MARGIN_PX = 2.0


@dataclass(frozen=True)
class SpreadModel:
    """The camera point-spread model of a sphere fit (:func:`measure_sphere` with a rig).

    Attributes
    ----------
    variance_px2 : float, s^2, the point spread's variance per axis (camera pixels^2:
        the pixel's own 1/12 plus the lens's defocus), estimated from the sphere or given.
    sigma_variance_px2 : float, its standard uncertainty (0 when given).
    estimated : bool, s^2 was estimated from the sphere's points.
    brightness : bool, the brightness-gradient term was modelled (an image was given);
        without it only the curvature term is.
    max_view_deg : float, the points fitted face the camera within this angle.
    """

    variance_px2: float
    sigma_variance_px2: float
    estimated: bool
    brightness: bool
    max_view_deg: float


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
    spread : SpreadModel or None, the camera point-spread model the sphere was fitted
        through (None: a plain fit of the points, see :func:`measure_sphere`).
    spread_terms : (rows, cols, 2) or None, per fitted pixel the model's shift
        coefficients (a1 mm/px^2, a2 mm/px^4 of :func:`spread_shift`), NaN elsewhere.
    """

    sphere: SphereFit
    base: PlaneFit | None
    region: str
    fitted: np.ndarray | None = None
    uncertainty: dict | None = None
    spread: SpreadModel | None = None
    spread_terms: np.ndarray | None = None


def measure_sphere(cloud: PointCloud, *, min_height: float | None = None,
                   edge_px: int = 1, seed: int = 0, rig=None, image=None,
                   fringe_periods=None, psf_variance: float | None = None,
                   max_view_deg: float = SPREAD_MAX_VIEW_DEG) -> SphereMeasurement:
    """Find and fit the sphere standing on a plane in a scan.

    The base plane is fitted robustly; the largest connected region standing more than
    ``min_height`` above it (default: 8 robust sigma of the plane, at least 20 um) is the
    sphere, shrunk by ``edge_px`` pixels (silhouette pixels mix surfaces), and fitted
    robustly. When no plane holds at least 20 % of the points, all points are fitted,
    and the result's ``region`` says so.

    With the ``rig`` that measured the cloud (a camera + projector) and an ``image`` of
    the scene's brightness, the sphere is fitted through the camera's point-spread model
    (:func:`spread_shift`): each point is moved back along its line by the shift the
    spread-averaged fringes predict for the fitted sphere, on the points that face the
    camera within ``max_view_deg``, and the spread's variance is estimated with the
    sphere (or given as ``psf_variance``); its uncertainty is in the fit's covariance.
    Without them the points are fitted as they are: on a rig whose camera blurs, the
    radius and centre then carry a bias of the order of s^2 / R (see the module notes).

    Parameters
    ----------
    cloud : PointCloud (mm).
    min_height, edge_px, seed : see above (mm, px, the plane fit's seed).
    rig : Rig or RigCalibration, optional, one camera and a projector.
    image : (rows, cols) array_like, optional, the brightness of the scene in the
        camera's pixels (e.g. points.npz ``radiance``, the fringes' mean level).
    fringe_periods : (2,) projector px, optional, the finest u and v fringe periods
        (the second-order term of :func:`spread_shift`; without it the radius stays
        biased by about half of s^2 / R, s in mm on the object: 0.8 um on the mixed rig
        binned 4 x 4).
    psf_variance : float, optional, s^2 in camera px^2 when known (else estimated).
    max_view_deg : float, deg, with the spread model: the largest angle between a
        fitted point's sphere normal and the direction back to the camera.

    Returns
    -------
    SphereMeasurement
    """
    from scipy import ndimage

    if (rig is None) != (image is None) or (rig is None and (
            psf_variance is not None or fringe_periods is not None)):
        raise MetrologyError("the point-spread model needs both the rig and the image")
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
    if rig is None:
        return SphereMeasurement(fit, base, where, fitted)
    fit, fitted, spread, terms = _measure_with_spread(
        cloud, sel, fit, rig, image, fringe_periods=fringe_periods,
        psf_variance=psf_variance, max_view_deg=max_view_deg,
        plane=None if base is None else (base.normal, base.offset))
    return SphereMeasurement(fit, base, where, fitted, spread=spread, spread_terms=terms)


def _measure_with_spread(cloud: PointCloud, sel, fit0: SphereFit, rig, image, *,
                         fringe_periods, psf_variance, max_view_deg: float,
                         max_incidence_deg: float | None = None, plane=None,
                         margin_px: float = SPREAD_MARGIN_PX, reject_k: float = 4.0,
                         rounds: int = 6):
    """The robust sphere fit through the point-spread model (:func:`measure_sphere`):
    returns (SphereFit, fitted (rows, cols) bool, SpreadModel, terms (rows, cols, 2))."""
    from telefringe.reconstruction._rig import as_rig
    from telefringe.reconstruction.cloud import TriangulationError

    try:
        r_ = as_rig(rig)
    except TriangulationError as exc:
        raise MetrologyError(str(exc)) from None
    if r_.projector is None or len(r_.cameras) != 1:
        raise MetrologyError("the point-spread model of a sphere needs a rig of one camera "
                             "and a projector")
    img = np.asarray(image, dtype=np.float64)
    if img.shape != cloud.shape:
        raise MetrologyError(f"image has shape {img.shape}, the cloud {cloud.shape}")
    if not (np.isfinite(max_view_deg) and 0 < max_view_deg <= 90):
        raise MetrologyError(f"max_view_deg must be in (0, 90], got {max_view_deg!r}")
    free = psf_variance is None
    if not free and not (np.isfinite(psf_variance) and psf_variance >= 0):
        raise MetrologyError(f"psf_variance must be >= 0 (px^2), got {psf_variance!r}")
    with np.errstate(divide="ignore", invalid="ignore"):
        gv, gu = np.gradient(np.log(np.where(img > 0, img, np.nan)))
    rows, cols = np.nonzero(sel)
    pix = np.stack([cols, rows], axis=1).astype(np.float64)
    p = cloud.xyz[sel]
    dirs = cloud.directions
    d = (np.broadcast_to(dirs, p.shape) if dirs.ndim == 1 else dirs[sel]).astype(np.float64)
    g = np.stack([gu[sel], gv[sel]], axis=1)
    good = np.all(np.isfinite(g), axis=1) & np.all(np.isfinite(d), axis=1)
    both = cloud.residual is not None
    cos_min = np.cos(np.radians(max_view_deg))
    lit_min = None if max_incidence_deg is None else np.cos(np.radians(max_incidence_deg))
    x = np.array([*fit0.centre, fit0.radius, 0.0 if free else float(psf_variance)])
    keep = fit0.inliers.copy()
    prev = None
    for _ in range(rounds):
        a1, a2, ok = spread_shift(r_.camera, r_.projector, x[:3], x[3], pix, d,
                                  grad_ln_i=np.nan_to_num(g), both_axes=both,
                                  fringe_periods=fringe_periods, plane=plane,
                                  margin_px=margin_px)
        f_all, _, nn = _spread_design(p, d, a1, a2, x, False)
        facing = -np.sum(nn * d, axis=1) >= cos_min
        if lit_min is not None:
            facing &= _incidence_cos(r_.projector, p, nn) >= lit_min
        usable = ok & good & facing
        cand = usable & keep
        if np.count_nonzero(cand) < 10:
            raise MetrologyError(f"only {np.count_nonzero(cand)} points of the sphere face "
                                 f"the camera within {max_view_deg:g} deg")
        x, f, J = _fit_sphere_spread(p[cand], d[cand], a1[cand], a2[cand], x[:3], x[3],
                                     x[4], free)
        f_all, _, _ = _spread_design(p, d, a1, a2, x, False)
        scale = _MAD * np.median(np.abs(f)) + 1e-15
        new_keep = np.abs(f_all) <= reject_k * scale
        state = (new_keep & usable).tobytes()
        if prev is not None and state == prev:
            break
        prev = state
        keep = new_keep
    used = cand
    if not (np.isfinite(x[3]) and x[3] > 0 and np.all(np.isfinite(x[:3]))):
        raise MetrologyError("the sphere fit through the point-spread model did not converge")
    dof = max(f.size - J.shape[1], 1)
    s2r = float(f @ f / dof)
    try:
        cov5 = s2r * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        raise MetrologyError("the sphere is not determined by these points") from None
    cov = cov5[:4, :4]
    sphere = SphereFit(x[:3].copy(), float(x[3]), float(np.sqrt(np.mean(f * f))),
                       float(f.max() - f.min()), int(p.shape[0]), int(f.size), used, cov)
    spread = SpreadModel(float(x[4]), float(np.sqrt(cov5[4, 4])) if free else 0.0, free,
                         True, float(max_view_deg))
    fitted = np.zeros(cloud.shape, dtype=bool)
    fitted[sel] = used
    terms = np.full(cloud.shape + (2,), np.nan)
    terms[rows[used], cols[used], 0] = a1[used]
    terms[rows[used], cols[used], 1] = a2[used]
    return sphere, fitted, spread, terms


# --------------------------------------------------------------------------- point spread
def _incidence_cos(projector, points, normals):
    """cos of the angle between each point's surface normal (n, 3) and the direction
    back to the projector (its line through the point, Device protocol)."""
    u, v = projector.project(points)
    rays = projector.backproject(u, v)
    dp = np.broadcast_to(np.asarray(rays.direction, dtype=np.float64), points.shape)
    c = np.sum(normals * dp, axis=1)
    # the lines' direction is one way for every point: the points measured are lit, so
    # they face the projector (most of them, whatever the outliers)
    return c if np.median(c) >= 0 else -c


def _line_sphere(o, d, c, r):
    """Depth t (...) of the first meeting of the lines o + t d (unit d, toward the scene)
    with the sphere (c, r); NaN where a line misses it."""
    oc = o - c
    b = np.sum(d * oc, axis=-1)
    disc = b * b - (np.sum(oc * oc, axis=-1) - r * r)
    with np.errstate(invalid="ignore"):
        return np.where(disc >= 0, -b - np.sqrt(np.where(disc >= 0, disc, 0.0)), np.nan)


def spread_shift(camera, projector, centre, radius: float, pixels, view, *,
                 grad_ln_i=None, both_axes: bool = True, fringe_periods=None,
                 plane=None, margin_px: float = 0.0):
    """Shift of each pixel's triangulated point along its camera line predicted by the
    camera's point spread, for a sphere seen by a camera + projector rig.

    The projector coordinates the pixel's neighbourhood sees on the sphere are traced
    through the rig's own models (``camera.backproject``, ``projector.project``, their
    distortion included) on a 3 x 3 stencil of +- 0.25 px; their gradient ``g`` and
    Hessian ``H`` (projector px per camera px) give the decoded coordinate's shift for a
    point spread of variance ``s^2`` per axis (camera px^2), the expansion of the phase
    of the spread-averaged fringe to second order in s^2:

        du = s^2 (tr(H) / 2 + b . g) + s^4 (b' H b - k^2 g' H g) / 2,

    ``b`` = grad(ln I) (1/px) the brightness gradient, ``k`` = 2 pi / (finest fringe
    period, projector px): the fringe's own phase gradient weights the curvature term
    (exact for a Gaussian spread over a log-linear brightness and a quadratic phase).
    The point moves along its line by du over du/dt (with both axes: the least-squares
    combination of the u and v shifts, equal weights in projector pixels).

    Parameters
    ----------
    camera, projector : devices of the Device protocol (the rig that measured the cloud).
    centre : (3,) mm; radius : mm, the sphere (e.g. a first fit).
    pixels : (n, 2) camera pixels (column, row).
    view : (n, 3) or (3,), each pixel's viewing direction (from the camera into the
        scene: ``PointCloud.directions``), which picks the side of the sphere seen.
    grad_ln_i : (n, 2) 1/px, optional, d ln(I) / d(column, row) of the image's
        brightness at each pixel; None: the curvature terms only.
    both_axes : bool, the points were triangulated from u and v (else from u only).
    fringe_periods : (2,) projector px, optional, the finest fringe period of the u and
        the v fringes; None: the k^2 term is left out.
    plane : (normal (3,), offset mm), optional, the plane the sphere stands on: the
        sphere below it (``x . normal < offset``) is hidden.
    margin_px : float, px, also require the lines at this distance around the pixel (8
        directions) to meet the visible sphere: the point spread of a pixel nearer the
        limb or the foot of the sphere sees another surface, which the model does not
        describe.

    Returns
    -------
    a1, a2 : (n,) mm / px^2 and mm / px^4: the point moves away from the camera by
        ``s^2 a1 + s^4 a2``.
    ok : (n,) bool, every traced line of the pixel (and of its margin) met the
        visible sphere.
    """
    pix = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    n = pix.shape[0]
    h = _SPREAD_STEP_PX
    offs = np.array([[0, 0], [h, 0], [-h, 0], [0, h], [0, -h], [h, h], [-h, -h], [h, -h],
                     [-h, h]], dtype=np.float64)
    m = offs.shape[0]
    if margin_px > 0:
        ang = np.arange(8) * (np.pi / 4)
        offs = np.concatenate([offs, margin_px * np.stack([np.cos(ang), np.sin(ang)], 1)])
    uu = pix[:, :1] + offs[:, 0]
    vv = pix[:, 1:] + offs[:, 1]
    mt = offs.shape[0]
    rays = camera.backproject(uu, vv)
    o = np.broadcast_to(np.asarray(rays.origin, dtype=np.float64), (n, mt, 3))
    d = np.broadcast_to(np.asarray(rays.direction, dtype=np.float64), (n, mt, 3))
    vw = np.broadcast_to(np.asarray(view, dtype=np.float64), (n, 3))
    sgn = np.where(np.sum(d[:, 0] * vw, axis=1) < 0, -1.0, 1.0)
    d = d * sgn[:, None, None]
    t = _line_sphere(o, d, np.asarray(centre, dtype=np.float64), float(radius))
    X = o + d * np.nan_to_num(t)[..., None]
    if plane is not None:
        nrm, off = np.asarray(plane[0], dtype=np.float64), float(plane[1])
        t = np.where(X @ nrm - off > 0, t, np.nan)
    ok = np.all(np.isfinite(t), axis=1)
    o, d, X = o[:, :m], d[:, :m], X[:, :m]
    eps = 1e-3  # mm along the centre line
    X0 = X[:, 0]
    Xs = np.concatenate([X.reshape(-1, 3), X0 + eps * d[:, 0], X0 - eps * d[:, 0]])
    UV = projector.project(Xs)
    b = (np.zeros((n, 2)) if grad_ln_i is None
         else np.asarray(grad_ln_i, dtype=np.float64).reshape(n, 2))
    num1 = np.zeros(n)
    num2 = np.zeros(n)
    den = np.zeros(n)
    for k in range(2 if both_axes else 1):
        P = np.asarray(UV[k], dtype=np.float64)
        S = P[:m * n].reshape(n, m)
        p_t = (P[m * n:(m + 1) * n] - P[(m + 1) * n:]) / (2 * eps)
        gx = (S[:, 1] - S[:, 2]) / (2 * h)
        gy = (S[:, 3] - S[:, 4]) / (2 * h)
        hxx = (S[:, 1] + S[:, 2] - 2 * S[:, 0]) / (h * h)
        hyy = (S[:, 3] + S[:, 4] - 2 * S[:, 0]) / (h * h)
        hxy = (S[:, 5] + S[:, 6] - S[:, 7] - S[:, 8]) / (4 * h * h)
        first = 0.5 * (hxx + hyy) + b[:, 0] * gx + b[:, 1] * gy
        second = 0.5 * (b[:, 0] ** 2 * hxx + 2 * b[:, 0] * b[:, 1] * hxy + b[:, 1] ** 2 * hyy)
        if fringe_periods is not None:
            kf = 2 * np.pi / float(fringe_periods[k])
            second = second - 0.5 * kf * kf * (gx * gx * hxx + 2 * gx * gy * hxy
                                               + gy * gy * hyy)
        num1 += p_t * first
        num2 += p_t * second
        den += p_t * p_t
    with np.errstate(invalid="ignore", divide="ignore"):
        a1 = num1 / den
        a2 = num2 / den
    ok &= np.isfinite(a1) & np.isfinite(a2)
    return np.where(ok, a1, 0.0), np.where(ok, a2, 0.0), ok


def _spread_design(p, d, a1, a2, x, free: bool):
    """Residuals |p_i - shift_i d_i - c| - r (shift_i = s2 a1_i + s2^2 a2_i), their
    Jacobian (n, 4 or 5) in (cx, cy, cz, r[, s2]) and the unit normals (n, 3)."""
    s2 = x[4]
    q = p - (s2 * a1 + s2 * s2 * a2)[:, None] * d
    v = q - x[:3]
    dist = np.linalg.norm(v, axis=1)
    nn = v / dist[:, None]
    J = np.empty((p.shape[0], 5 if free else 4))
    J[:, :3] = -nn
    J[:, 3] = -1.0
    if free:
        J[:, 4] = -np.sum(nn * d, axis=1) * (a1 + 2.0 * s2 * a2)
    return dist - x[3], J, nn


def _fit_sphere_spread(p, d, a1, a2, c0, r0, s2_0: float, free: bool, max_iter: int = 50):
    """Gauss-Newton for the sphere on which the points, moved back along their lines
    ``d`` by the point-spread shift ``s2 a1 + s2^2 a2``, lie: s2 free (from ``s2_0``) or
    fixed at ``s2_0``. Returns (x = (cx, cy, cz, r, s2), residuals (n,), Jacobian)."""
    x = np.array([c0[0], c0[1], c0[2], r0, float(s2_0)])
    npar = 5 if free else 4
    for _ in range(max_iter):
        f, J, _ = _spread_design(p, d, a1, a2, x, free)
        step = np.linalg.lstsq(J, -f, rcond=None)[0]
        x[:npar] += step
        if np.all(np.abs(step[:4]) < 1e-12 * max(1.0, abs(x[3]))):
            break
    f, J, _ = _spread_design(p, d, a1, a2, x, free)
    return x, f, J


def finest_fringe_periods(manifest) -> tuple[float, float] | None:
    """The finest fringe period of each axis of a scan (projector px): ``(p_u, p_v)``
    for :func:`measure_sphere`'s ``fringe_periods``, from a
    :class:`~telefringe.fringes.scan.ScanManifest` (an axis without fringes gets the
    other's period, which then takes no part); None without phase groups."""
    out = {}
    for g in manifest.phase_groups:
        p = manifest.axis_length(g.axis) / float(g.periods)
        out[g.axis] = min(out.get(g.axis, np.inf), p)
    if not out:
        return None
    pu = out.get("u", out.get("v"))
    pv = out.get("v", pu)
    return float(pu), float(pv)
