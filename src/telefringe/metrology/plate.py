"""Circle-marker plates: 3D marker centres, their spacing, the plate's plane and height
(the paper's Table 3)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from telefringe.metrology._common import _MAD, MetrologyError, _freeze, _poly_design
from telefringe.metrology.planes import Plane, PlaneDistance, PlaneFit, fit_plane, plane_distance
from telefringe.reconstruction.cloud import PointCloud


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
        _freeze(self, "xyz", "sigma_xyz", "n_points", "valid")


def marker_centres_3d(cloud: PointCloud, centres_px, *, inner_px: float | None = None,
                      outer_px: float | None = None, degree: int = 2, min_points: int = 30,
                      sigma_px=0.0, offsets_px=None) -> MarkerCentres:
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
    sigma_px : float, (n,) or (n, 2) array_like
        Standard uncertainty of the image centres (px; one for both axes, or (u, v) per
        centre, e.g. ``GridDetection.center_sigma``). The uncertainty of the result
        includes it (through the local slopes of X, Y, Z with u and v) besides the noise
        of the cloud; with the default 0 only the cloud's noise counts.
    offsets_px : (n, 2) array_like, px, optional
        Read each marker at ``centres_px - offsets_px`` (the annulus stays about
        ``centres_px``): the bias of a detected centre, the image of the circle's centre
        being ``centres_px - offsets_px`` (see :func:`measure_plate`).

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
    off = (np.zeros(c.shape) if offsets_px is None
           else np.array(np.broadcast_to(np.asarray(offsets_px, dtype=np.float64), c.shape)))
    if not np.all(np.isfinite(off[ok])):
        raise MetrologyError("offsets_px must be finite where a centre is given")
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
    dirs = np.asarray(cloud.directions, dtype=np.float64)
    n = c.shape[0]
    s_in = np.asarray(sigma_px, dtype=np.float64)
    s_px = np.array(np.broadcast_to(s_in[:, None] if s_in.ndim == 1 else s_in, (n, 2)))
    if not np.all(np.isfinite(s_px[ok]) & (s_px[ok] >= 0)):
        raise MetrologyError("sigma_px must be finite and >= 0 where a centre is given")
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
        # each point's camera line (one direction for a telecentric camera)
        dwin = (dirs if dirs.ndim == 1
                else dirs[v_lo:v_hi + 1, u_lo:u_hi + 1].reshape(-1, 3)[sel])
        sw = np.sqrt(w)
        # one pass of rejection of gross outliers (e.g. a wrong fringe order) at 5 sigma
        keep = np.ones(A.shape[0], dtype=bool)
        for _ in range(2):
            coef, *_ = np.linalg.lstsq(A[keep] * sw[keep, None], Y[keep] * sw[keep, None],
                                       rcond=None)
            res = Y - A @ coef
            rz = np.sum(res * dwin, axis=1)  # residuals along the camera lines
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
        # evaluated at the circle centre's image (the detected centre minus its offset)
        a0 = _poly_design(np.array([-off[k, 0] / outer_px]), np.array([-off[k, 1] / outer_px]),
                          degree)[0]
        cov00 = float(a0 @ np.linalg.solve(Ak.T @ Ak, a0))
        out[k] = a0 @ coef
        # the centre's own error moves the point along the surface: d xyz / d(u, v)
        slope2 = (s_px[k, 0] ** 2 * coef[1] ** 2 + s_px[k, 1] ** 2 * coef[2] ** 2) / outer_px**2
        out_s[k] = np.sqrt(s2 * cov00 + slope2)
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
        _freeze(self, "dist_x", "dist_y")


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
    uncertainty : dict of str -> Uncertainty, or None: ``"z"``, ``"tilt_deg"``,
        ``"spacing_x"``, ``"spacing_y"`` with the noise and calibration parts (set by
        :func:`telefringe.metrology.uncertainty.plate_uncertainty`; None until then).
    centre_offsets_px : (rows * cols, 2) ndarray, px, or None: the predicted bias of each
        detected centre (its circle's image centre minus the image of the circle's
        centre), subtracted before the cloud was read; None when not corrected (no
        camera given to :func:`measure_plate`).
    """

    plane: PlaneFit
    z: PlaneDistance
    centres: MarkerCentres
    spacing: GridSpacing
    uncertainty: dict | None = None
    centre_offsets_px: np.ndarray | None = None

    def __post_init__(self):
        _freeze(self, "centre_offsets_px")


def measure_plate(cloud: PointCloud, centres_px, *, rows: int, cols: int, pitch_mm: float,
                  reference: Plane | None = None, inner_px: float | None = None,
                  outer_px: float | None = None, seed: int = 0, camera=None,
                  marker_diameter_mm: float | None = None, noise=None,
                  centres_sigma_px=None) -> PlateMeasurement:
    """Measure a circle-marker plate: its plane, its height and its marker spacing.

    A detected marker centre is the centre of the circle's image, not the image of the
    circle's centre (lens distortion and perspective bend the circle's image; under
    radial distortion like a magnification change of 3 k1 rho^2, rho the marker's radius
    on the sensor). Given the ``camera`` that made the cloud and the markers' diameter,
    each detected centre is corrected by its predicted bias: the image centre of a circle
    of that diameter on the fitted plane, about the marker's 3D centre, through the
    camera's full model, minus the image of that centre
    (:func:`telefringe.calibration.centres.circle_image_centres`, as the calibration
    corrects its own detected centres), and the cloud is read at the corrected pixel.
    The bias is evaluated at the centre read at the detected pixel, which is off the
    corrected one by the bias itself (about 0.01 px): the bias changes over it by a part
    in 1e4 of its size (tests/test_plate_centre_bias.py bounds it).

    Parameters
    ----------
    cloud : PointCloud.
    centres_px : (rows * cols, 2) camera-image marker centres in target order (row-major,
        NaN where not found), e.g. ``telefringe.targets.detect_circle_grid(...).centers``.
    rows, cols, pitch_mm : the plate's grid.
    reference : Plane, default Z = 0 (the calibration's reference pose).
    inner_px, outer_px : annulus of :func:`marker_centres_3d`.
    seed : seeds the robust plane fit.
    camera : Device, optional, the camera that made the cloud (e.g. ``rig.camera``; its
        pixels are the cloud's). Without it the detected centres are used as they are
        (``centre_offsets_px`` is None): a bias of up to a few 1e-5 of the spacing on a
        distorting lens.
    marker_diameter_mm : float, the markers' diameter (needed with ``camera``).
    noise : StereoNoise, optional, a cloud matched by two cameras: the plane's covariance
        (Z and tilt) then holds the correlation of neighbouring matches
        (``fit_plane(..., noise=)``).
    centres_sigma_px : (rows * cols, 2) array_like, px, optional: the standard
        uncertainties (u, v) of the detected centres (``GridDetection.center_sigma``).
        They enter the centres' ``sigma_xyz`` and so the spacing's noise: the mean
        spacing along a row telescopes to its two end markers' difference, so the
        detection error of the first and last columns (rows) reaches it undamped by the
        number of markers (on the fast virtual rig 0.005 px per centre, 0.03 um on a
        3 mm spacing, twice the cloud's part; tests/test_spacing_centre_sigma.py). Without
        it (None) the detected centres count as exact.

    Returns
    -------
    PlateMeasurement
    """
    c = np.asarray(centres_px, dtype=np.float64)
    if c.shape != (int(rows) * int(cols), 2):
        raise MetrologyError(f"centres_px must have shape ({rows * cols}, 2), got {c.shape}")
    if camera is not None:
        if marker_diameter_mm is None or not (np.isfinite(marker_diameter_mm)
                                              and marker_diameter_mm > 0):
            raise MetrologyError("give the markers' diameter (marker_diameter_mm > 0) to "
                                 f"correct their detected centres, got {marker_diameter_mm!r}")
        size = getattr(camera, "image_size", None)
        if size is not None and tuple(size) != (cloud.shape[1], cloud.shape[0]):
            raise MetrologyError(f"the camera is {size[0]} x {size[1]} px but the cloud is "
                                 f"{cloud.shape[1]} x {cloud.shape[0]}: give the camera that "
                                 "made it")
    plane = fit_plane(cloud, robust=True, seed=seed, noise=noise)
    ref = Plane.horizontal(0.0) if reference is None else reference
    if centres_sigma_px is None:
        s_px = 0.0
    else:
        s_px = np.asarray(centres_sigma_px, dtype=np.float64)
        if s_px.shape != c.shape:
            raise MetrologyError(f"centres_sigma_px must have shape {c.shape}, "
                                 f"got {s_px.shape}")
    centres = marker_centres_3d(cloud, c, inner_px=inner_px, outer_px=outer_px,
                                sigma_px=s_px)
    offsets = None
    if camera is not None:
        offsets = centre_offsets(camera, centres.xyz, plane.normal, 0.5 * marker_diameter_mm)
        centres = marker_centres_3d(cloud, c, inner_px=inner_px, outer_px=outer_px,
                                    offsets_px=np.nan_to_num(offsets), sigma_px=s_px)
    spacing = grid_spacing(centres.xyz, rows=rows, cols=cols, pitch_mm=pitch_mm)
    return PlateMeasurement(plane, plane_distance(plane, ref), centres, spacing,
                            centre_offsets_px=offsets)


def centre_offsets(camera, centres_xyz, normal, radius_mm: float) -> np.ndarray:
    """Predicted bias of detected circle centres: the image centre of each circle minus
    the image of its centre, through the camera's full model.

    Parameters
    ----------
    camera : Device.
    centres_xyz : (n, 3) array_like, mm, the circles' centres (world; NaN rows give NaN).
    normal : (3,) or (n, 3) array_like, the plane normal(s).
    radius_mm : float, the circles' radius.

    Returns
    -------
    (n, 2) ndarray, px.
    """
    from telefringe.calibration.centres import circle_image_centres

    X = np.asarray(centres_xyz, dtype=np.float64).reshape(-1, 3)
    out = np.full((X.shape[0], 2), np.nan)
    ok = np.all(np.isfinite(X), axis=1)
    if ok.any():
        Xo = X[ok]
        nrm = np.asarray(normal, dtype=np.float64)
        if nrm.ndim == 2:
            nrm = nrm[ok]
        out[ok] = (circle_image_centres(camera, Xo, nrm, float(radius_mm))
                   - np.stack(camera.project(Xo), axis=1))
    return out
