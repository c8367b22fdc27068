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
estimated, or given).

Two cameras (:func:`stereo_spread_shift`): each camera's decoded phase is biased by its
own spread, and the matcher interpolates the second camera's map bilinearly at the
matched sub-pixel, which on a curved map adds ``f (1 - f) H / 2`` per axis; the point
moves along the first camera's line to where the two biased phases agree. On the
``stereo`` preset binned 4 x 4 (true rig) the plain fit's radius was off by +9.5 um and
its centre's z by -12.3 um (18 sigma); the fit through the model by +0.4 and -0.4 um
(z 0.3), s^2 = 0.32 +- 0.05 px^2 for the renderer's 0.30. From the renderer's exact
phase maps (no spread) the predicted interpolation shift matched the measured one per
point to 0.018 um RMS for 0.61 um RMS (regression slope 1.001). Over 10 noise seeds
(true rig) the plain fit's radius was off by +7.8 to +10.2 um (z 14-20), the model's
by -4.1 to +4.3 um; its z-scores' RMS was 0.83 and 1.02 for the centre's x and y but
1.74 and 1.73 for its z and the radius (2 seeds of 10 at |z| 3.1-3.6), and s^2 scattered
by 0.075 px^2 for a predicted 0.05: the fit's covariance understates the parameters
that trade against s^2. Neighbouring matches interpolate the same pixels of the second
camera, so their noise is correlated; given the match's noise split
(``measure_sphere(..., noise=match_noise(...))``) the covariance is the exact sandwich
(:func:`_sandwich`), 6-9 % larger in every sigma (z RMS 1.63 and 1.63 over the same
seeds): not the main cause. White noise of the decoded sigmas on the exact phase maps
gives z RMS 1.13 / 1.08 (59 draws), on the seeds' mean decoded maps 0.73 / 0.74 (16
draws). It is not the decoder's per-scan correction of the projector's nonlinearity:
with each camera's model from a noise-free render instead, or no correction at all, the
same seeds give z RMS 1.64 / 1.64 and 1.61 / 1.60 (the learned model moves the radius
by 0.04 um RMS: a phase error both cameras share at one projector phase cancels in the
match), and the decoded errors are white at the decoder's sigma (variance 0.93-1.05
sigma^2 at every view angle, neighbour correlation < 0.05). Over 30 more seeds (30-59)
the z RMS is 1.25 / 1.29, white noise of the sigmas in place of the decoded errors 1.17
/ 1.21 (seeds 20-29 were a high draw: two s^2 estimates 3 sigma off). What stays is
the s^2 estimate's bias, mostly from the brightness image's noise: its log-gradient
enters the model's terms, and noise in a regressor shrinks its coefficient. The
noise-free render's maps with the scans' noisy images give s^2 = 0.252 px^2 for the
renderer's 0.298 and miss the centre's z by -1.12 um and the radius by +0.99 um; with
the noise-free images s^2 = 0.284 and -0.37 / +0.39 um (the limb: at a 40-degree view
limit 0.292 and +0.06 / +0.03 um); with s^2 given as 0.298, +0.02 / +0.08 um. Over the
seeds 30-59 the radius is off by +0.91 +- 0.28 um on average (0.67 of its sigma; s^2
0.280); the noise-free images instead give +0.41 um, s^2 0.304 and z RMS 1.07 / 1.09
(``benchmarks/stereo_sphere_seeds.py``).

The brightness image's noise (errors in the variables)
-------------------------------------------------------
A noise e of the log-gradient b moves both the shift the model predicts and its slope by
s^2, so the residuals and the s^2 column of the Jacobian share it and the plain least
squares shrink s^2 (by 11 % above: only the part of the shift the sphere's own
parameters cannot absorb tells s^2, and e is large against that part). The fit solves
the corrected normal equations instead (:func:`_eiv_correction`: the expected product
subtracted, first order in e's variance), with e's variance from the image itself
(:func:`_log_noise`: on the stereo scans within 1-2 % of the decoder's noise model over
their 24 phase images), and its covariance is the corrected equations' sandwich. The
noise-free render's maps with seed 30's noisy images now give s^2 = 0.281 px^2 (shared)
for 0.2835 with the noise-free images (before 0.252), the centre's z -0.45 um and the
radius +0.46 um (noise-free images -0.37 / +0.39; before -1.12 / +0.99). On a synthetic
sphere with 0.6 % image noise (tests/test_metrology_spheres.py) the old fit's s^2 was
22 % low, now +1.2 % (the correction's second order); at 1 % noise +3 %, and the
scatter of s^2 then exceeds its predicted sigma by 1.6 times: the first-order
correction is for images whose noise shrinks s^2 by at most about a fifth.
Over 40 draws of the ``stereo`` preset's noise (the noise-free render's maps and images
plus the decoder's sigmas and the camera's noise model as white noise:
``stereo_sphere_seeds.py --synthetic``) the z-scores' RMS (centre x, y, z, radius) is
1.00 0.88 1.07 1.09 (before 0.96 0.89 1.20 1.24), the mean error of the centre's z and
the radius -0.13 / +0.17 um (before -0.75 / +0.69); over the rendered seeds 30-69 0.78
1.02 1.12 1.11 (before 1.12 1.01 1.20 1.22), the mean errors +0.06 / +0.04 um (before
-0.58 / +0.58), the scatter 1.12 times the predicted sigma (one sampling sd of 40).

One variance per camera by default (``psf_shared``)
---------------------------------------------------
Each camera's point spread is its own lens's defocus at its own focus and distance, and
its own pixel: two cameras blur alike only by assumption. One shared variance is biased
when they do not, and choosing by a pre-test on the data (the former default: shared
when the two estimates agreed within 3 sigma) mixes two estimators whose mixture
neither covariance describes. The default is one variance each, whatever the data:
unbiased for any two cameras. It costs precision only along the baseline: the
difference s_1^2 - s_2^2 moves the matched points along it, and on the ``stereo``
preset (cameras 30 degrees apart in x) the centre's x sigma is 2.1-2.3 um for 0.33 um
with one shared variance, the radius' and the centre's y and z the same (over the 40
draws above z RMS 1.00 0.88 1.07 1.09 per camera, 0.96 0.89 1.08 1.10 shared).
``psf_shared=True`` is for cameras known to blur alike.
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
        the pixel's own 1/12 plus the lens's defocus), estimated from the sphere or given;
        of the first camera on a two-camera rig.
    sigma_variance_px2 : float, its standard uncertainty (0 when given).
    estimated : bool, s^2 was estimated from the sphere's points.
    brightness : bool, the brightness-gradient term was modelled (an image was given);
        without it only the curvature term is.
    max_view_deg : float, the points fitted face the camera (both cameras) within this
        angle.
    cameras : int, 1 (camera + projector) or 2 (two cameras matched on the projector's
        phase, :func:`stereo_spread_shift`).
    variance_2_px2, sigma_variance_2_px2 : float or None, the second camera's s^2 and its
        uncertainty (two cameras; equal to the first's when ``shared``).
    shared : bool, two cameras: one s^2 for both (asked for: ``psf_shared``).
    """

    variance_px2: float
    sigma_variance_px2: float
    estimated: bool
    brightness: bool
    max_view_deg: float
    cameras: int = 1
    variance_2_px2: float | None = None
    sigma_variance_2_px2: float | None = None
    shared: bool = False

    @property
    def variances(self) -> tuple[float, ...]:
        """The model's variance parameters (px^2): (s^2,) for one camera or a shared one,
        (s_1^2, s_2^2) for two cameras fitted apart."""
        if self.cameras == 1 or self.shared:
            return (self.variance_px2,)
        return (self.variance_px2, float(self.variance_2_px2))


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
    spread_terms : (rows, cols, 2) or (rows, cols, 5) or None, per fitted pixel the
        model's shift coefficients: one camera (a1 mm/px^2, a2 mm/px^4 of
        :func:`spread_shift`), two cameras (a_1, b_1, a_2, b_2, c of
        :func:`stereo_spread_shift`); NaN elsewhere.
    spread_noise : (k, k) or None, mm^2 / px^4, the part of the fit's normal matrix the
        brightness image's noise adds, for its k estimated variances
        (:func:`_eiv_correction`; the fit solves with ``J' J`` less it): zero when the
        variances were given; None without the spread model.
    """

    sphere: SphereFit
    base: PlaneFit | None
    region: str
    fitted: np.ndarray | None = None
    uncertainty: dict | None = None
    spread: SpreadModel | None = None
    spread_terms: np.ndarray | None = None
    spread_noise: np.ndarray | None = None


def measure_sphere(cloud: PointCloud, *, min_height: float | None = None,
                   edge_px: int = 1, seed: int = 0, rig=None, image=None,
                   image_2=None, fringe_periods=None, psf_variance=None,
                   psf_shared: bool = False,
                   max_view_deg: float = SPREAD_MAX_VIEW_DEG,
                   noise=None) -> SphereMeasurement:
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

    With a two-camera ``rig`` (the cloud matched by
    :func:`telefringe.reconstruction.stereo.match_stereo`, on the first camera's grid),
    ``image`` the first camera's brightness and ``image_2`` the second's (in its own
    pixels), the points move by the shift :func:`stereo_spread_shift` predicts: each
    camera's phase biased by its own spread, and the second camera's sub-pixel
    interpolation; the points must face both cameras within ``max_view_deg``. Each
    camera's variance is estimated (``psf_shared=True``: one for both; see the module
    notes for why the default is one each, whatever the data).

    The brightness image's noise enters the model through its log-gradient, a regressor
    of s^2: the fit corrects its normal equations for it (:func:`_eiv_correction`), with
    the noise's variance estimated from the image itself (:func:`_log_noise`; white
    noise assumed, as a camera's read and shot noise).

    Parameters
    ----------
    cloud : PointCloud (mm).
    min_height, edge_px, seed : see above (mm, px, the plane fit's seed).
    rig : Rig or RigCalibration, optional, one camera and a projector, or two cameras
        and the projector (its model traces the projector coordinates the cameras see:
        a two-camera rig needs the projector calibrated too).
    image : (rows, cols) array_like, optional, the brightness of the scene in the
        camera's pixels (e.g. points.npz ``radiance``, the fringes' mean level).
    image_2 : (rows_2, cols_2) array_like, the second camera's brightness (two cameras).
    fringe_periods : (2,) projector px, optional, the finest u and v fringe periods
        (the second-order term of :func:`spread_shift`; without it the radius stays
        biased by about half of s^2 / R, s in mm on the object: 0.8 um on the mixed rig
        binned 4 x 4).
    psf_variance : float or (2,), optional, s^2 in camera px^2 when known (else
        estimated): one for every camera, or one per camera of a two-camera rig.
    psf_shared : bool, two cameras: one variance for both (True: for cameras known to
        blur alike, same lens, focus and distance; it pins the centre along the
        baseline), or one each (False, the default).
    max_view_deg : float, deg, with the spread model: the largest angle between a
        fitted point's sphere normal and the direction back to the camera.
    noise : StereoNoise, optional, two cameras: the matched points' noise split into
        its independent parts (:func:`telefringe.reconstruction.stereo.match_noise` of
        the match that made the cloud); the fit's covariance then holds the correlation
        of neighbouring points (:func:`_sandwich`) instead of treating them as
        independent, which understates it.

    Returns
    -------
    SphereMeasurement
    """
    from scipy import ndimage

    if (rig is None) != (image is None) or (rig is None and (
            psf_variance is not None or fringe_periods is not None
            or image_2 is not None or noise is not None)):
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
    fit, fitted, spread, terms, k_noise = _measure_with_spread(
        cloud, sel, fit, rig, image, image_2=image_2, fringe_periods=fringe_periods,
        psf_variance=psf_variance, psf_shared=psf_shared, max_view_deg=max_view_deg,
        plane=None if base is None else (base.normal, base.offset), noise=noise)
    return SphereMeasurement(fit, base, where, fitted, spread=spread, spread_terms=terms,
                             spread_noise=k_noise)


def _log_gradients(img):
    """d ln(I) / d(column, row) (each (rows, cols), NaN where I <= 0): central
    differences, whose noise per axis has the variance ``(var_ln(I)[+1] +
    var_ln(I)[-1]) / 4`` (:func:`_log_noise`)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        gv, gu = np.gradient(np.log(np.where(img > 0, img, np.nan)))
    return gu, gv


#: The high-pass of :func:`_log_noise`: second differences along both axes (it removes
#: every polynomial without an x^2 y^2 term); the sum of its squared weights is 36.
_HIGH_PASS = np.outer([1.0, -2.0, 1.0], [1.0, -2.0, 1.0])
#: :func:`_log_noise` keeps the pixels whose squared high-pass is within this many times
#: the noise model's (a chi-square of one degree of freedom passes 9 with 0.27 %) ...
_NOISE_TRIM = 9.0
#: ... and the mean of that chi-square below 9 is this share of its mean
#: (P(chi2_3 < 9) / P(chi2_1 < 9)).
_NOISE_TRIM_MEAN = 0.97343


def _log_noise(img):
    """The variance (rows, cols) of the noise of ln(I) per pixel, from the image itself:
    ``c + a / I + b / I^2`` (a camera's fixed-pattern, shot and read noise over I^2,
    each >= 0) fitted to the square of the high-pass :data:`_HIGH_PASS` of ln(I) over 36
    (its expectation for white noise: independent between pixels, as a camera's read and
    shot noise, also binned). Pixels where the high-pass holds more than the model's
    noise (edges, highlights: :data:`_NOISE_TRIM`) are left out, iteratively, and the
    fit corrected for that trimming. A smooth brightness passes the high-pass as its
    fourth derivative d^4 ln(I) / dx^2 dy^2. NaN where I <= 0; zeros where the image
    holds no noise (fewer than 16 usable pixels, or a noise-free image)."""
    from scipy import ndimage
    from scipy.optimize import nnls

    with np.errstate(divide="ignore", invalid="ignore"):
        L = np.log(np.where(img > 0, img, np.nan))
    h = ndimage.correlate(L, _HIGH_PASS, mode="constant", cval=np.nan)
    v = h * h / float(np.sum(_HIGH_PASS ** 2))
    use = np.isfinite(v)
    I = np.where(use, img, 1.0)
    X = np.stack([np.ones(I.shape), 1.0 / I, 1.0 / (I * I)], axis=-1)
    if np.count_nonzero(use) < 16:
        return np.where(np.isfinite(L), 0.0, np.nan)
    # start from one level, the median's (a chi-square of one degree of freedom has its
    # median at 0.455 of its mean): the edges' and highlights' large values out at once
    model = np.full(I.shape, np.median(v[use]) / 0.45494)
    keep = use & (v <= _NOISE_TRIM * model)
    w = 1.0 / np.where(model > 0, model, np.inf)
    for _ in range(8):
        if np.count_nonzero(keep) < 16:
            return np.where(np.isfinite(L), 0.0, np.nan)
        A = X[keep] * w[keep, None]
        sc = np.linalg.norm(A, axis=0)
        sc[sc == 0] = 1.0
        # the same non-negative least squares on the 3 x 3 factor of the system
        Q, R = np.linalg.qr(A / sc)
        theta = nnls(R, Q.T @ (v[keep] * w[keep]))[0] / sc
        model = X @ theta
        if not np.any(model[use] > 0):
            return np.where(np.isfinite(L), 0.0, np.nan)
        new_keep = use & (v <= _NOISE_TRIM * model)
        w = 1.0 / np.where(model > 0, model, np.inf)  # chi-square: sd proportional to mean
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    fin = np.isfinite(L)
    Ii = np.where(fin, img, 1.0)
    out = (theta[0] + theta[1] / Ii + theta[2] / (Ii * Ii)) / _NOISE_TRIM_MEAN
    return np.where(fin, out, np.nan)


def _measure_with_spread(cloud: PointCloud, sel, fit0: SphereFit, rig, image, *,
                         fringe_periods, psf_variance, max_view_deg: float, image_2=None,
                         psf_shared: bool = False,
                         max_incidence_deg: float | None = None, plane=None,
                         margin_px: float = SPREAD_MARGIN_PX, reject_k: float = 4.0,
                         rounds: int = 6, noise=None):
    """The robust sphere fit through the point-spread model (:func:`measure_sphere`):
    returns (SphereFit, fitted (rows, cols) bool, SpreadModel, terms (rows, cols, 2 or
    5), the normal matrix's noise part (k, k) for the k variances (zero when given))."""
    from telefringe.geometry.interpolation import bilinear
    from telefringe.reconstruction._rig import as_rig
    from telefringe.reconstruction.cloud import TriangulationError

    try:
        r_ = as_rig(rig)
    except TriangulationError as exc:
        raise MetrologyError(str(exc)) from None
    stereo = len(r_.cameras) == 2
    if r_.projector is None or len(r_.cameras) not in (1, 2):
        raise MetrologyError("the point-spread model of a sphere needs a rig of one camera "
                             "and a projector, or of two cameras and the projector")
    if stereo and image_2 is None:
        raise MetrologyError("a two-camera rig's point-spread model needs the second "
                             "camera's image (image_2)")
    if not stereo and image_2 is not None:
        raise MetrologyError("image_2 is the second camera's: the rig has one camera")
    img = np.asarray(image, dtype=np.float64)
    if img.shape != cloud.shape:
        raise MetrologyError(f"image has shape {img.shape}, the cloud {cloud.shape}")
    if not (np.isfinite(max_view_deg) and 0 < max_view_deg <= 90):
        raise MetrologyError(f"max_view_deg must be in (0, 90], got {max_view_deg!r}")
    if psf_shared not in (True, False):
        raise MetrologyError(f"psf_shared must be True or False, got {psf_shared!r}")
    free = psf_variance is None
    if free:
        v0 = (0.0,) if not stereo or psf_shared else (0.0, 0.0)
    else:
        v0 = tuple(float(v) for v in np.atleast_1d(np.asarray(psf_variance, dtype=float)))
        if len(v0) not in ((1, 2) if stereo else (1,)) or not all(
                np.isfinite(v) and v >= 0 for v in v0):
            raise MetrologyError(f"psf_variance must be >= 0 (px^2), one value"
                                 f"{' or one per camera' if stereo else ''}, got "
                                 f"{psf_variance!r}")
        if stereo and psf_shared and len(v0) == 2 and v0[0] != v0[1]:
            raise MetrologyError("psf_shared with two different given variances")
    gu, gv = _log_gradients(img)
    nv = _log_noise(img)
    rows, cols = np.nonzero(sel)
    if noise is not None:
        if not stereo:
            raise MetrologyError("noise is a two-camera match's (StereoNoise): the rig has "
                                 "one camera")
        if np.shape(noise.var_own) != cloud.shape:
            raise MetrologyError(f"noise has shape {np.shape(noise.var_own)}, the cloud "
                                 f"{cloud.shape}")
        noise_sel = (np.asarray(noise.var_own)[sel], np.asarray(noise.weights)[sel],
                     np.asarray(noise.sources)[sel])
    pix = np.stack([cols, rows], axis=1).astype(np.float64)
    p = cloud.xyz[sel]
    dirs = cloud.directions
    d = (np.broadcast_to(dirs, p.shape) if dirs.ndim == 1 else dirs[sel]).astype(np.float64)
    g = np.stack([gu[sel], gv[sel]], axis=1)
    # the variance of each axis of g's noise (from the image's noise, white)
    q = np.zeros((p.shape[0], 2))
    q[:, 0] = 0.5 * nv[sel]
    good = (np.all(np.isfinite(g), axis=1) & np.all(np.isfinite(d), axis=1)
            & np.isfinite(q[:, 0]))
    if noise is not None:
        good &= np.isfinite(noise_sel[0])
    both = cloud.residual is not None
    if stereo:
        cam1, cam2 = (r_.cameras[nm] for nm in r_.camera_names[:2])
        img2 = np.asarray(image_2, dtype=np.float64)
        size2 = cam2.image_size
        if img2.ndim != 2 or (size2 is not None and img2.shape != (size2[1], size2[0])):
            raise MetrologyError(f"image_2 has shape {img2.shape}, the second camera "
                                 f"{None if size2 is None else (size2[1], size2[0])}")
        gu2, gv2 = _log_gradients(img2)
        with np.errstate(invalid="ignore"):
            u2, v2 = cam2.project(p)
        g2 = np.stack([bilinear(gu2, u2, v2)[0], bilinear(gv2, u2, v2)[0]], axis=1)
        # interpolated: the noise's variance times the sum of the squared weights (the
        # gradients of a cell's four pixels share no pixel of the image)
        nv2, _, _, (_, _, fx, fy) = bilinear(_log_noise(img2), u2, v2)
        q[:, 1] = 0.5 * nv2 * ((1 - fx) ** 2 + fx ** 2) * ((1 - fy) ** 2 + fy ** 2)
        good &= np.all(np.isfinite(g2), axis=1) & np.isfinite(q[:, 1])
    cos_min = np.cos(np.radians(max_view_deg))
    lit_min = None if max_incidence_deg is None else np.cos(np.radians(max_incidence_deg))

    def terms_at(x):
        """(T, the terms' derivatives by the brightness gradients, usable) of the model
        at the sphere x."""
        if stereo:
            T, ok, view2, S = _stereo_spread_shift(
                cam1, cam2, r_.projector, x[:3], x[3], pix, d, p,
                grad_ln_i=np.nan_to_num(g), grad_ln_i_2=np.nan_to_num(g2), both_axes=both,
                fringe_periods=fringe_periods, plane=plane, margin_px=margin_px)
        else:
            a1, a2, ok, S = _spread_shift(r_.camera, r_.projector, x[:3], x[3], pix, d,
                                          grad_ln_i=np.nan_to_num(g), both_axes=both,
                                          fringe_periods=fringe_periods, plane=plane,
                                          margin_px=margin_px)
            T = np.column_stack([a1, a2])
        _, _, nn = _design(p, d, T, x, False)
        facing = -np.sum(nn * d, axis=1) >= cos_min
        if stereo:
            facing &= -np.sum(nn * view2, axis=1) >= cos_min
        if lit_min is not None:
            facing &= _incidence_cos(r_.projector, p, nn) >= lit_min
        return T, S, ok & good & facing

    def robust(x, keep):
        prev = None
        for _ in range(rounds):
            T, S, usable = terms_at(x)
            cand = usable & keep
            if np.count_nonzero(cand) < 10:
                raise MetrologyError(f"only {np.count_nonzero(cand)} points of the sphere "
                                     f"face the camera{'s' if stereo else ''} within "
                                     f"{max_view_deg:g} deg")
            x, f, J, K = _fit_sphere_spread(p[cand], d[cand], T[cand], x, free,
                                            sens=S[cand], noise_var=q[cand])
            f_all, _, _ = _design(p, d, T, x, False)
            scale = _MAD * np.median(np.abs(f)) + 1e-15
            new_keep = np.abs(f_all) <= reject_k * scale
            state = (new_keep & usable).tobytes()
            if prev is not None and state == prev:
                break
            prev = state
            keep = new_keep
        if not (np.isfinite(x[3]) and x[3] > 0 and np.all(np.isfinite(x[:3]))):
            raise MetrologyError("the sphere fit through the point-spread model did not "
                                 "converge")
        dof = max(f.size - J.shape[1], 1)
        try:
            # the normal matrix less the brightness noise's part (_eiv_correction)
            Ninv = np.linalg.inv(J.T @ J - K)
        except np.linalg.LinAlgError:
            raise MetrologyError("the sphere is not determined by these points") from None
        if noise is None:
            # the sandwich of the corrected normal equations: the noise of the gradients
            # is in J' J (the spread of the estimating equations), not in their slope
            cov = float(f @ f / dof) * (Ninv @ (J.T @ J) @ Ninv)
        else:
            # the matched points' correlated noise (shared pixels of the second camera):
            # the sandwich of its exact covariance, scaled by the residuals
            _, _, nn = _design(p[cand], d[cand], T[cand], x, False)
            cov = _sandwich(J, np.sum(nn * d[cand], axis=1), Ninv, f,
                            *(a[cand] for a in noise_sel))
        return x, f, cov, T, cand, keep, K

    x = np.array([*fit0.centre, fit0.radius, *v0])
    x, f, cov, T, used, keep, K = robust(x, fit0.inliers.copy())
    if not np.all(np.diag(cov) >= 0.0):
        # a variance below zero (rounding about zero): some parameter, usually a spread
        # variance that the brightness noise's correction leaves without information, is
        # not determined by these points; no figure is given for it
        raise MetrologyError("the sphere's point-spread model is not determined by these "
                             "points (a parameter's variance came out below zero)")
    shared = not stereo or len(x) == 5
    sphere = SphereFit(x[:3].copy(), float(x[3]), float(np.sqrt(np.mean(f * f))),
                       float(f.max() - f.min()), int(p.shape[0]), int(f.size), used,
                       cov[:4, :4])
    sig = np.sqrt(np.diag(cov))[4:] if free else np.zeros(len(x) - 4)
    k2 = 4 if shared else 5
    spread = SpreadModel(float(x[4]), float(sig[0]), free, True, float(max_view_deg),
                         cameras=2 if stereo else 1,
                         variance_2_px2=float(x[k2]) if stereo else None,
                         sigma_variance_2_px2=float(sig[k2 - 4]) if stereo else None,
                         shared=bool(stereo and shared))
    fitted = np.zeros(cloud.shape, dtype=bool)
    fitted[sel] = used
    terms = np.full(cloud.shape + (T.shape[1],), np.nan)
    terms[rows[used], cols[used]] = T[used]
    k_noise = K[4:, 4:].copy() if free else np.zeros((len(x) - 4, len(x) - 4))
    return sphere, fitted, spread, terms, k_noise


def _sandwich(J, a, Ninv, f, var_own, weights, sources):
    """Covariance of a least-squares fit's parameters whose residuals' noise is
    correlated: ``k Ninv J' C J Ninv``.

    The residual i moves by ``a_i delta_s_i`` (``a`` (n,): d residual / d the point's
    position along its line), ``delta_s_i = e_i + sum_q weights[i, q] z[sources[i, q]]``
    (``e_i`` of variance ``var_own[i]``, ``z`` independent unit sources shared between
    points; sources < 0 unused), so ``C = diag(a^2 var_own) + B B'`` with ``B`` (n,
    sources) sparse; ``J' C J`` is formed through ``J' B`` without the (n, n) matrix.
    ``k = f' f / tr((I - H) C)`` (H the hat matrix ``J Ninv J'``; ``E[f' f] = tr((I - H)
    C)``) scales the covariance by what the residuals hold (1 when the points' sigmas are
    right; with ``C`` a multiple of the identity the usual ``f' f / dof Ninv``).

    J : (n, p) d residual / d parameters; Ninv : (p, p) = inv(J' J); f : (n,) residuals;
    var_own (n,), weights (n, K), sources (n, K) int (distinct within a row).
    """
    Ja = J * a[:, None]
    JCJ = (Ja * var_own[:, None]).T @ Ja
    use = sources >= 0
    src, inv = np.unique(sources[use], return_inverse=True)
    rows = np.broadcast_to(np.arange(J.shape[0])[:, None], sources.shape)[use]
    w = weights[use]
    JB = np.stack([np.bincount(inv, weights=Ja[rows, c] * w, minlength=src.size)
                   for c in range(J.shape[1])])
    JCJ += JB @ JB.T
    tr_c = float(np.sum(a * a * (var_own + np.sum(np.where(use, weights, 0.0) ** 2,
                                                    axis=1))))
    tr_hc = float(np.trace(Ninv @ JCJ))
    k = float(f @ f) / max(tr_c - tr_hc, 1e-300)
    return k * (Ninv @ JCJ @ Ninv)


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


def _phase_stencil(camera, projector, centre, radius: float, pixels, view, *,
                   grad_ln_i=None, n_axes: int = 2, fringe_periods=None, plane=None,
                   margin_px: float = 0.0):
    """The projector coordinates a camera's pixels see on a sphere, traced on a 3 x 3
    stencil of +- ``_SPREAD_STEP_PX`` around each pixel (the shared part of
    :func:`spread_shift` and :func:`stereo_spread_shift`).

    Returns a dict: ``X`` (n, 3) mm, the point each pixel's line meets first; ``d``
    (n, 3) its unit line direction, into the scene (along ``view``); ``ok`` (n,) bool;
    and per axis k (0: u, 1: v, the first ``n_axes``) ``first[k]`` = tr(H) / 2 + b . g
    (projector px per px^2) and ``second[k]`` = (b' H b - k_f^2 g' H g) / 2 (projector
    px per px^4), ``grad[k]`` (n, 2) = g (projector px per camera px) and ``hess[k]``
    (n, 3) = (H_uu, H_vv, H_uv), so that the decoded coordinate of a point spread of
    variance s^2 is u + s^2 first + s^4 second; d first[k] / d b = ``grad[k]`` and
    d second[k] / d b = ``dsecond[k]`` (n, 2) = H b (the brightness gradient's noise,
    :func:`_eiv_correction`).
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
    d, X = d[:, :m], X[:, :m]
    UV = projector.project(X.reshape(-1, 3))
    b = (np.zeros((n, 2)) if grad_ln_i is None
         else np.asarray(grad_ln_i, dtype=np.float64).reshape(n, 2))
    out = {"X": X[:, 0], "d": d[:, 0], "ok": ok, "first": [], "second": [], "grad": [],
           "hess": [], "dsecond": []}
    for k in range(n_axes):
        S = np.asarray(UV[k], dtype=np.float64).reshape(n, m)
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
        out["first"].append(first)
        out["second"].append(second)
        out["grad"].append(np.stack([gx, gy], axis=1))
        out["hess"].append(np.stack([hxx, hyy, hxy], axis=1))
        out["dsecond"].append(np.stack([b[:, 0] * hxx + b[:, 1] * hxy,
                                        b[:, 0] * hxy + b[:, 1] * hyy], axis=1))
    return out


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
    a1, a2, ok, _ = _spread_shift(camera, projector, centre, radius, pixels, view,
                                  grad_ln_i=grad_ln_i, both_axes=both_axes,
                                  fringe_periods=fringe_periods, plane=plane,
                                  margin_px=margin_px)
    return a1, a2, ok


def _spread_shift(camera, projector, centre, radius: float, pixels, view, *,
                  grad_ln_i=None, both_axes: bool = True, fringe_periods=None,
                  plane=None, margin_px: float = 0.0):
    """:func:`spread_shift`'s (a1, a2, ok) and their derivatives (n, 2, 2) by the
    brightness gradient b: ``[:, 0]`` d a1 / d b, ``[:, 1]`` d a2 / d b (mm px^-2 per
    px^-1, mm px^-4 per px^-1)."""
    st = _phase_stencil(camera, projector, centre, radius, pixels, view,
                        grad_ln_i=grad_ln_i, n_axes=2 if both_axes else 1,
                        fringe_periods=fringe_periods, plane=plane, margin_px=margin_px)
    X0, d0, ok = st["X"], st["d"], st["ok"]
    n = X0.shape[0]
    eps = 1e-3  # mm along the centre line
    UV = projector.project(np.concatenate([X0 + eps * d0, X0 - eps * d0]))
    num1 = np.zeros(n)
    num2 = np.zeros(n)
    den = np.zeros(n)
    sens = np.zeros((n, 2, 2))
    for k in range(len(st["first"])):
        P = np.asarray(UV[k], dtype=np.float64)
        p_t = (P[:n] - P[n:]) / (2 * eps)
        num1 += p_t * st["first"][k]
        num2 += p_t * st["second"][k]
        den += p_t * p_t
        sens[:, 0] += p_t[:, None] * st["grad"][k]
        sens[:, 1] += p_t[:, None] * st["dsecond"][k]
    with np.errstate(invalid="ignore", divide="ignore"):
        a1 = num1 / den
        a2 = num2 / den
        sens /= den[:, None, None]
    ok &= np.isfinite(a1) & np.isfinite(a2) & np.all(np.isfinite(sens), axis=(1, 2))
    return (np.where(ok, a1, 0.0), np.where(ok, a2, 0.0), ok,
            np.where(ok[:, None, None], sens, 0.0))


def stereo_spread_shift(camera, camera_2, projector, centre, radius: float, pixels,
                        view, points, *, grad_ln_i=None, grad_ln_i_2=None,
                        both_axes: bool = True, fringe_periods=None, plane=None,
                        margin_px: float = 0.0, max_gap_mm: float | None = None):
    """Shift of each matched point along the first camera's line predicted by the two
    cameras' point spreads (and the sub-pixel interpolation of the second camera's
    phase), for a sphere seen by a two-camera rig whose projector gives the phase.

    Each camera decodes the projector coordinate its pixel sees, biased by its own point
    spread (``s_1^2``, ``s_2^2``, camera px^2, each over its own image and brightness)
    as in :func:`spread_shift`: ``delta_c = s_c^2 first_c + s_c^4 second_c`` (projector
    px, traced on each camera's stencil). The stereo match (``reconstruction.stereo``)
    moves along the first camera's line to where the second camera's map, interpolated
    bilinearly at the matched sub-pixel ``p_2``, equals the first camera's value. The
    bilinear interpolation of a curved map adds ``e = (f_u (1 - f_u) H_uu + f_v (1 - f_v)
    H_vv) / 2`` (``f`` the fractions of ``p_2`` within its cell, ``H`` the map's Hessian
    per camera px^2; exact for a quadratic map). With ``g`` the second camera's map's
    derivative along the first camera's line (projector px per mm), the point moves by

        dt = sum_axes g (delta_1 - delta_2 - e) / sum_axes g^2

    (equal weights of the axes in projector pixels, as :func:`spread_shift`).

    Parameters
    ----------
    camera, camera_2, projector : the rig's devices (Device protocol); the projector's
        model traces the projector coordinates (its calibration, or the nominal one).
    centre : (3,) mm; radius : mm, the sphere.
    pixels : (n, 2) the first camera's pixels (column, row).
    view : (n, 3) or (3,), the first camera's viewing directions (into the scene).
    points : (n, 3) mm, the matched points (the cloud's): the second camera's pixel
        ``p_2`` is their projection (where the matcher interpolated).
    grad_ln_i, grad_ln_i_2 : (n, 2) 1/px, optional, the brightness gradients of each
        camera's image at ``pixels`` and at ``p_2``.
    both_axes, fringe_periods, plane, margin_px : as :func:`spread_shift` (the margin
        around both cameras' pixels).
    max_gap_mm : float, optional, the second camera's line through ``p_2`` must meet the
        sphere within this of the first camera's point (default: radius / 100); a point
        the second camera sees on another part of the sphere is not described.

    Returns
    -------
    terms : (n, 5): (a_1, b_1, a_2, b_2, c) with the shift away from the first camera
        ``s_1^2 a_1 + s_1^4 b_1 + s_2^2 a_2 + s_2^4 b_2 + c`` (mm / px^2, mm / px^4 and
        mm), zeros where not ok.
    ok : (n,) bool, every traced line of both cameras met the visible sphere there.
    view_2 : (n, 3) the second camera's unit viewing directions at ``p_2`` (into the
        scene), for the caller's facing test.
    """
    terms, ok, view_2, _ = _stereo_spread_shift(
        camera, camera_2, projector, centre, radius, pixels, view, points,
        grad_ln_i=grad_ln_i, grad_ln_i_2=grad_ln_i_2, both_axes=both_axes,
        fringe_periods=fringe_periods, plane=plane, margin_px=margin_px,
        max_gap_mm=max_gap_mm)
    return terms, ok, view_2


def _stereo_spread_shift(camera, camera_2, projector, centre, radius: float, pixels,
                         view, points, *, grad_ln_i=None, grad_ln_i_2=None,
                         both_axes: bool = True, fringe_periods=None, plane=None,
                         margin_px: float = 0.0, max_gap_mm: float | None = None):
    """:func:`stereo_spread_shift`'s (terms, ok, view_2) and the derivatives (n, 4, 2)
    of its terms (a_1, b_1) by the first camera's brightness gradient (``[:, :2]``) and
    of (a_2, b_2) by the second's (``[:, 2:]``)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = pts.shape[0]
    n_axes = 2 if both_axes else 1
    st1 = _phase_stencil(camera, projector, centre, radius, pixels, view,
                         grad_ln_i=grad_ln_i, n_axes=n_axes, fringe_periods=fringe_periods,
                         plane=plane, margin_px=margin_px)
    with np.errstate(invalid="ignore"):
        u2, v2 = camera_2.project(pts)
    p2 = np.stack([np.asarray(u2, dtype=np.float64).reshape(n),
                   np.asarray(v2, dtype=np.float64).reshape(n)], axis=1)
    fin = np.all(np.isfinite(p2), axis=1)
    p2s = np.where(fin[:, None], p2, 0.0)
    view2 = np.asarray(camera_2.R_dev_world, dtype=np.float64)[2]  # device z: the view
    st2 = _phase_stencil(camera_2, projector, centre, radius, p2s, view2,
                         grad_ln_i=grad_ln_i_2, n_axes=n_axes, fringe_periods=fringe_periods,
                         plane=plane, margin_px=margin_px)
    gap = np.linalg.norm(st2["X"] - st1["X"], axis=1)
    tol = float(radius) / 100.0 if max_gap_mm is None else float(max_gap_mm)
    ok = st1["ok"] & st2["ok"] & fin & (gap <= tol)
    # the second camera's pixel moves along its epipolar line: dp_2 / dt = J_2 d_1
    _, _, J2 = camera_2.project_jacobian(np.where(ok[:, None], st1["X"], pts))
    dp = np.einsum("mij,mj->mi", np.asarray(J2, dtype=np.float64), st1["d"])
    fu = p2s[:, 0] - np.floor(p2s[:, 0])
    fv = p2s[:, 1] - np.floor(p2s[:, 1])
    num = np.zeros((n, 5))
    den = np.zeros(n)
    sens = np.zeros((n, 4, 2))
    for k in range(n_axes):
        g = np.sum(st2["grad"][k] * dp, axis=1)
        hs = st2["hess"][k]
        e = 0.5 * (fu * (1 - fu) * hs[:, 0] + fv * (1 - fv) * hs[:, 1])
        num += g[:, None] * np.stack([st1["first"][k], st1["second"][k], -st2["first"][k],
                                      -st2["second"][k], -e], axis=1)
        den += g * g
        sens += g[:, None, None] * np.stack([st1["grad"][k], st1["dsecond"][k],
                                             -st2["grad"][k], -st2["dsecond"][k]], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        terms = num / den[:, None]
        sens /= den[:, None, None]
    ok &= np.all(np.isfinite(terms), axis=1) & np.all(np.isfinite(sens), axis=(1, 2))
    return (np.where(ok[:, None], terms, 0.0), ok, st2["d"],
            np.where(ok[:, None, None], sens, 0.0))


def _shift_and_slopes(T, v, free: bool):
    """The point-spread shift (n,) of the terms ``T`` (n, 2): (a1, a2) of one camera, or
    (n, 5): (a_1, b_1, a_2, b_2, c) of two (:func:`stereo_spread_shift`), for the
    variances ``v`` (one, or one per camera of a two-camera rig), and its derivatives
    (n, len(v)) by them (None when not ``free``)."""
    if T.shape[1] == 2:
        v1 = v[0]
        sh = v1 * T[:, 0] + v1 * v1 * T[:, 1]
        return sh, (T[:, :1] + 2.0 * v1 * T[:, 1:2]) if free else None
    v1, v2 = (v[0], v[0]) if len(v) == 1 else (v[0], v[1])
    sh = v1 * T[:, 0] + v1 * v1 * T[:, 1] + v2 * T[:, 2] + v2 * v2 * T[:, 3] + T[:, 4]
    if not free:
        return sh, None
    d1 = T[:, 0] + 2.0 * v1 * T[:, 1]
    d2 = T[:, 2] + 2.0 * v2 * T[:, 3]
    return sh, (d1 + d2)[:, None] if len(v) == 1 else np.stack([d1, d2], axis=1)


def _design(p, d, T, x, free: bool):
    """Residuals |p_i - shift_i d_i - c| - r of the points moved back along their lines
    by the point-spread shift of the terms ``T`` (:func:`_shift_and_slopes`), their
    Jacobian (n, 4, or 4 + the variances when ``free``) in (cx, cy, cz, r[, v...]) and the
    unit normals (n, 3); ``x`` = (cx, cy, cz, r, v...)."""
    sh, dv = _shift_and_slopes(T, x[4:], free)
    q = p - sh[:, None] * d
    v = q - x[:3]
    dist = np.linalg.norm(v, axis=1)
    nn = v / dist[:, None]
    J = np.empty((p.shape[0], x.size if free else 4))
    J[:, :3] = -nn
    J[:, 3] = -1.0
    if free:
        J[:, 4:] = -np.sum(nn * d, axis=1)[:, None] * dv
    return dist - x[3], J, nn


def spread_design(measurement, points, directions):
    """The design of a sphere fitted through a point-spread model, for linearising it
    (:func:`telefringe.metrology.uncertainty.sphere_uncertainty`).

    The fit solves the corrected normal equations (:func:`_eiv_correction`): points
    moved by dp move its parameters by ``-inv(J' J - K) J' (normals . dp)``, ``K`` the
    normal matrix's part from the brightness image's noise (``measurement.spread_noise``).
    Without ``K`` the linearisation is the plain least squares', another estimator: on
    the image with 0.6 % noise of tests/test_metrology_spheres.py its radius response
    is off by 39 % (its s^2 response 22 %; see the test of this function there), and on
    the rendered stereo sphere (tests/test_sphere_spread_stereo.py, seed 7) the plain
    influence rows of (cx, cy, cz, r) differ from the corrected by 15, 0.2, 8 and 8 %.

    Parameters
    ----------
    measurement : SphereMeasurement with ``spread`` set.
    points : (n, 3) mm, the cloud's points at ``measurement.fitted``; directions : (n, 3)
        their first camera's viewing directions.

    Returns
    -------
    J : (n, p) d residual / d (cx, cy, cz, r[, v...]), p = 4 + the estimated variances.
    normals : (n, 3) unit.
    K : (p, p), the noise part ``K`` (mm^2 / px^4 in the variances' block, else 0).
    """
    sp = measurement.spread
    f = measurement.sphere
    T = np.asarray(measurement.spread_terms)[np.asarray(measurement.fitted, dtype=bool)]
    x = np.array([*f.centre, f.radius, *sp.variances])
    _, J, nn = _design(np.asarray(points, dtype=np.float64),
                       np.asarray(directions, dtype=np.float64), T, x, sp.estimated)
    K = np.zeros((J.shape[1], J.shape[1]))
    kn = getattr(measurement, "spread_noise", None)
    if sp.estimated:
        if kn is None:
            raise MetrologyError("the sphere measurement does not record its spread fit's "
                                 "noise part (measure it again with this version)")
        K[4:, 4:] = np.asarray(kn, dtype=np.float64)
    return J, nn, K


def _eiv_correction(T, S, q, x, cosines):
    """The bias of a spread fit's normal equations from the noise of the brightness
    gradients b its terms take (errors in the variables), for the variances x[4:].

    A noise e of b (per point and camera, covariance ``q`` I) moves both the shift the
    model predicts (by ``ds/db . e``) and its slope by a variance v (by ``d(ds/dv)/db .
    e``): the residual and the variance's column of the Jacobian then share the term,
    and ``E[J_v' f] = sum c^2 q (d(ds/dv)/db . ds/db)`` (c the residual's derivative by
    the shift, ``cosines``) instead of 0 at the true parameters: a noisy regressor
    shrinks v. The fit solves ``J' f = that`` (to first order in q, the corrected score)
    with the normal matrix ``J' J - K``, ``K = sum c^2 q |d(ds/dv)/db|^2`` (the part of
    ``J' J`` the noise adds).

    T : (n, 2) or (n, 5) the terms (:func:`_shift_and_slopes`); S : (n, 2, 2) or (n, 4,
    2) their derivatives by b (:func:`_spread_shift`, :func:`_stereo_spread_shift`);
    q : (n, 2) the variance (px^-2) of each axis of the first and second camera's b;
    x : (cx, cy, cz, r, v...); cosines : (n,).

    Returns (bias (k,), K (k, k)) for the k = len(x) - 4 variances.
    """
    v = x[4:]
    c2 = cosines * cosines
    if T.shape[1] == 2:
        col = S[:, 0] + 2.0 * v[0] * S[:, 1]
        sh = v[0] * S[:, 0] + v[0] ** 2 * S[:, 1]
        w = c2 * q[:, 0]
        return (np.array([np.sum(w * np.sum(col * sh, axis=1))]),
                np.array([[np.sum(w * np.sum(col * col, axis=1))]]))
    v1, v2 = (v[0], v[0]) if v.size == 1 else (v[0], v[1])
    col1 = S[:, 0] + 2.0 * v1 * S[:, 1]
    col2 = S[:, 2] + 2.0 * v2 * S[:, 3]
    sh1 = v1 * S[:, 0] + v1 ** 2 * S[:, 1]
    sh2 = v2 * S[:, 2] + v2 ** 2 * S[:, 3]
    w1, w2 = c2 * q[:, 0], c2 * q[:, 1]
    b1 = np.sum(w1 * np.sum(col1 * sh1, axis=1))
    b2 = np.sum(w2 * np.sum(col2 * sh2, axis=1))
    k1 = np.sum(w1 * np.sum(col1 * col1, axis=1))
    k2 = np.sum(w2 * np.sum(col2 * col2, axis=1))
    if v.size == 1:  # one variance: its column moves with both cameras' noise
        return np.array([b1 + b2]), np.array([[k1 + k2]])
    return np.array([b1, b2]), np.diag([k1, k2])


def _fit_sphere_spread(p, d, T, x0, free: bool, max_iter: int = 50, *, sens=None,
                       noise_var=None):
    """Gauss-Newton for the sphere on which the points, moved back along their lines
    ``d`` by the point-spread shift of the terms ``T`` (:func:`_shift_and_slopes`), lie;
    the variances x0[4:] free or fixed. With ``sens`` and ``noise_var`` (the terms'
    derivatives by the brightness gradients and those gradients' noise variances,
    :func:`_eiv_correction`) free variances are fitted through the corrected normal
    equations. Returns (x = (cx, cy, cz, r, v...), residuals (n,), Jacobian, K (the
    normal matrix's noise part, (p, p), zero but in the variances' block))."""
    x = np.array(x0, dtype=np.float64)
    npar = x.size if free else 4
    eiv = free and sens is not None and noise_var is not None
    K = np.zeros((npar, npar))
    # the corrected equations' slope leaves out the correction's own small slope by the
    # sphere: their steps shrink linearly, not quadratically; a few more steps once
    # below the tolerance put the result at the fixed point to rounding
    polish = 0
    for _ in range(max_iter):
        f, J, nn = _design(p, d, T, x, free)
        if eiv:
            bias, K[4:, 4:] = _eiv_correction(T, sens, noise_var, x,
                                              np.sum(nn * d, axis=1))
            grad = J.T @ f
            grad[4:] -= bias
            N = J.T @ J - K
            sc = np.sqrt(np.abs(np.diag(N)))  # scaled for the conditioning (mm, px^2)
            sc[sc == 0] = 1.0
            step = -np.linalg.solve(N / np.outer(sc, sc), grad / sc) / sc
        else:
            step = np.linalg.lstsq(J, -f, rcond=None)[0]
        x[:npar] += step
        if np.all(np.abs(step[:4]) < 1e-12 * max(1.0, abs(x[3]))):
            polish += 1
            if not eiv or polish > 3:
                break
    f, J, nn = _design(p, d, T, x, free)
    if eiv:
        _, K[4:, 4:] = _eiv_correction(T, sens, noise_var, x, np.sum(nn * d, axis=1))
    return x, f, J, K


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


def measure_sphere_region(cloud: PointCloud, region, rig, image, *, image_2=None,
                          fringe_periods=None, psf_variance=None, psf_shared: bool = False,
                          max_view_deg: float = SPREAD_MAX_VIEW_DEG,
                          noise=None) -> SphereMeasurement:
    """The sphere of the points ``region`` selects, fitted through the cameras'
    point-spread model as :func:`measure_sphere` fits the sphere it finds (a free sphere,
    e.g. an acceptance test's, has no base plane to find it by).

    Parameters
    ----------
    cloud : PointCloud (mm).
    region : (rows, cols) bool, the sphere's pixels (already shrunk off its silhouette).
    rig, image, image_2, fringe_periods, psf_variance, psf_shared, max_view_deg, noise :
        as for :func:`measure_sphere`.

    Returns
    -------
    SphereMeasurement (``base`` None, ``region`` "the given region").

    Raises
    ------
    MetrologyError
        A region of another shape than the cloud or of fewer than 4 valid points, or
        what :func:`measure_sphere`'s model refuses.
    """
    sel = np.asarray(region, dtype=bool)
    if sel.shape != cloud.shape:
        raise MetrologyError(f"region has shape {sel.shape}, the cloud {cloud.shape}")
    sel = sel & cloud.mask
    if sel.sum() < 4:
        raise MetrologyError(f"the region holds {int(sel.sum())} valid points: no sphere")
    fit0 = fit_sphere(cloud.xyz[sel], robust=True)
    fit, fitted, spread, terms, k_noise = _measure_with_spread(
        cloud, sel, fit0, rig, image, image_2=image_2, fringe_periods=fringe_periods,
        psf_variance=psf_variance, psf_shared=psf_shared, max_view_deg=max_view_deg,
        noise=noise)
    return SphereMeasurement(fit, None, "the given region", fitted, spread=spread,
                             spread_terms=terms, spread_noise=k_noise)


def sphere_spread_options(rig, image, shape, manifest=None, scan_2=None) -> dict:
    """:func:`measure_sphere`'s point-spread options for a reconstruction made with
    ``rig`` (what ``telefringe measure sphere --rig`` and ``telefringe batch --measure
    sphere`` with a calibrated rig fit through); {} where the model cannot be used.

    Parameters
    ----------
    rig : Rig (one camera + projector, or two cameras + projector).
    image : (rows, cols) array or None, the first camera's radiance (None: {}).
    shape : (rows, cols), the cloud's grid (a rig whose camera has another size: {}).
    manifest : ScanManifest or None, the first camera's scan's (its finest fringe periods
        refine the model's second order; None: the second camera's, else none).
    scan_2 : Scan or None, the second camera's scan (two cameras; None: {}).

    Raises
    ------
    ValueError
        The second camera's scan does not have the rig's second camera's size.
    """
    if image is None:
        return {}
    size = rig.camera.image_size
    n_cams = len(rig.cameras)
    if (rig.projector is None or n_cams not in (1, 2) or (n_cams == 2 and scan_2 is None)
            or (size is not None and tuple(size) != (shape[1], shape[0]))):
        return {}
    periods = None if manifest is None else finest_fringe_periods(manifest)
    opts = {"rig": rig, "image": image, "fringe_periods": periods}
    if n_cams == 2:
        from telefringe.fringes.images import scan_radiance

        size_2 = rig.cameras[rig.camera_names[1]].image_size
        try:
            image_2 = scan_radiance(scan_2)
        except ValueError:  # no phase images
            return {}
        if size_2 is not None and image_2.shape != (size_2[1], size_2[0]):
            raise ValueError(f"the second camera's scan is {image_2.shape[1]} x "
                             f"{image_2.shape[0]} px, the rig's second camera {size_2[0]} x "
                             f"{size_2[1]}")
        opts["image_2"] = image_2
        if periods is None:
            opts["fringe_periods"] = finest_fringe_periods(scan_2.manifest)
    return opts
