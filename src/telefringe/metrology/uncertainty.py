"""Measurement uncertainty: the decoding noise and the calibration, for every measured
quantity.

Each ``*_uncertainty`` function takes a measurement, the cloud it was made from and the
:class:`~telefringe.calibration.rig.RigCalibration` that triangulated the cloud, and
returns the measurement with its ``uncertainty`` field set: a dict of
:class:`Uncertainty` (value, ``u_noise``, ``u_calibration``, combined ``u``, expanded
``U = k u`` with k = 2) per quantity. The calibration part is the correlated term shared
by every point of the calibration (:mod:`telefringe.calibration.uncertainty`):

- fits over many points (planes, the levels of a step gauge, a sphere) are linearised at
  their solution: the change of the fit's parameters is a fixed linear function of the
  points' displacements (the fit's normal equations; the points' residuals enter at
  second order only), summed over every point the fit used
  (:func:`~telefringe.calibration.uncertainty.sum_point_jacobian`);
- quantities of a few points (marker centres, ball apexes) are recomputed from the points
  moved along each principal direction of the calibration covariance (central
  differences, :func:`~telefringe.calibration.uncertainty.propagate_fd`: exact to second
  order). A marker's centre is a polynomial fit over its surround evaluated at the
  centre, so its displacement is the deformation's at the centre (exact for a
  deformation that is quadratic over the surround); a ball's fitted sphere moves as its
  cap does, taken at the apex (the cap's middle; the deformation's change over a ball is
  about 1e-4 of its size).

``u_noise`` is each measurement's own uncertainty from its residuals (the repeatability).
The two parts are independent and add in quadrature. A quantity near a non-smooth point
(a tilt angle near zero, a coplanarity whose seating plane changes) has a non-Gaussian
spread that a linear propagation does not describe; the value is still given.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from telefringe.calibration.uncertainty import (
    covariance_factor,
    point_jacobian,
    propagate_fd,
    stereo_calibration,
    sum_point_jacobian,
)
from telefringe.metrology._common import MetrologyError, _tangent_basis

__all__ = [
    "K_EXPANDED",
    "Uncertainty",
    "plate_uncertainty",
    "steps_uncertainty",
    "sphere_uncertainty",
    "bga_uncertainty",
    "weight_v_of",
    "for_stereo",
    "for_stereo_scan",
]

#: Coverage factor of the expanded uncertainty U = k u (about 95 % for a Gaussian).
K_EXPANDED = 2.0


@dataclass(frozen=True, eq=False)
class Uncertainty:
    """A measured quantity and its standard uncertainty, in parts.

    Attributes
    ----------
    value : float or ndarray (any shape), the measured value (mm, or deg for angles).
    u_noise : same shape, the standard uncertainty from the decoding noise (from the
        fit's residuals; NaN where not known).
    u_calibration : same shape, from the calibration's parameter covariance (the error
        shared by every point of the calibration).
    u : same shape, the combined standard uncertainty ``sqrt(u_noise^2 +
        u_calibration^2)`` (a NaN part counts as 0 when the other is known).
    U : same shape, the expanded uncertainty ``k u``.
    k : float, the coverage factor (2).
    """

    value: object
    u_noise: object
    u_calibration: object
    u: object = None
    U: object = None
    k: float = K_EXPANDED

    def __post_init__(self):
        def arr(x):
            a = np.array(x, dtype=np.float64)
            return float(a) if a.ndim == 0 else a

        v, un, uc = (arr(x) for x in (self.value, self.u_noise, self.u_calibration))
        both_nan = np.isnan(un) & np.isnan(uc)
        u = np.where(both_nan, np.nan, np.hypot(np.nan_to_num(un), np.nan_to_num(uc)))
        u = arr(u)
        put = object.__setattr__
        for name, val in (("value", v), ("u_noise", un), ("u_calibration", uc), ("u", u),
                          ("U", arr(self.k * np.asarray(u)))):
            if isinstance(val, np.ndarray):
                val.setflags(write=False)
            put(self, name, val)


def weight_v_of(cloud) -> float:
    """The weight of v_p against u_p that the triangulation of ``cloud`` used: 1 when it
    combined both axes (it kept a u/v ``residual``; equal weights per projector pixel,
    the triangulator's choice without the decoder's sigmas), else 0 (u_p alone)."""
    return 0.0 if getattr(cloud, "residual", None) is None else 1.0


def for_stereo(calibration, coords_2, *, use_v_p: bool = True):
    """The calibration of a two-camera rig as the ``calibration`` argument of the
    functions here for a cloud matched between its cameras (``reconstruct --second``,
    :func:`~telefringe.reconstruction.pipeline.reconstruct_stereo_scans`): its points'
    calibration part then comes from both cameras' parameters through the two-ray
    triangulation (:func:`~telefringe.calibration.uncertainty.stereo_calibration`).

    Parameters
    ----------
    calibration : RigCalibration of a rig with two cameras.
    coords_2 : the second camera's decoded coordinates (``Reconstruction.coords_2``:
        ``u_p``, ``v_p``, ``sigma_u_p``, ``sigma_v_p``, (rows, cols) projector px).
    use_v_p : whether the matching combined both axes (its default), as passed to it.

    Returns
    -------
    StereoCalibration
    """
    axes = ["u"] + (["v"] if use_v_p and getattr(coords_2, "v_p", None) is not None else [])
    maps = [getattr(coords_2, f"{a}_p") for a in axes]
    sig = [getattr(coords_2, f"sigma_{a}_p", None) for a in axes]
    return stereo_calibration(calibration, maps,
                              sigmas_2=None if any(x is None for x in sig) else sig)


def for_stereo_scan(calibration, scan_2):
    """:func:`for_stereo` with the second camera's scan decoded as ``telefringe
    reconstruct --second`` decodes it by default (the camera noise ``"auto"``, the
    calibration's projector nonlinearity where it has one): what ``telefringe measure
    sphere --rig`` and ``telefringe batch --second`` propagate the calibration of a
    two-camera cloud with.

    Raises
    ------
    telefringe.fringes.decode.DecodeError, ValueError
        The scan cannot be decoded, or does not suit the calibration.
    """
    from telefringe.fringes.decode import decode

    opts = {"noise": "auto"}
    if getattr(calibration, "phase_errors", None):
        opts["phase_errors"] = calibration.phase_errors
    return for_stereo(calibration, decode(scan_2, **opts))


def _factor(calibration):
    cov = getattr(calibration, "covariance", None)
    if cov is None:
        raise MetrologyError("the calibration has no parameter covariance")
    L = covariance_factor(cov)
    n = len(getattr(calibration, "parameter_names", ())) or L.shape[0]
    if L.shape[0] != n:
        raise MetrologyError("the calibration's covariance does not match its parameters")
    return L


def _plane_jacobian(calibration, pts, w, normal, centroid, tangent, weight_v):
    """d(t1, t2, d, centroid x, y, z)/dtheta (6, n_params) of a weighted total least
    squares plane through ``pts`` (n, 3) with weights ``w`` (n,), linearised at its
    solution: the perturbed plane is ``(n + T^T t) . X = d0 + d + t . T c``."""
    w = w / w.sum()
    q = (pts - centroid) @ tangent.T  # (n, 2)
    a = np.column_stack([q, -np.ones(pts.shape[0])])  # d residual / d (t, d)
    N = (a * w[:, None]).T @ a
    Ninv = np.linalg.inv(N)
    G = np.empty((pts.shape[0], 6, 3))
    G[:, :3, :] = -(w[:, None] * (a @ Ninv.T))[:, :, None] * normal[None, None, :]
    G[:, 3:, :] = w[:, None, None] * np.eye(3)[None]
    return sum_point_jacobian(calibration, pts, G, weight_v=weight_v)


def _perturbed_plane(normal, offset, centroid, tangent, dp):
    n = normal + tangent.T @ dp[:2]
    nn = np.linalg.norm(n)
    d = offset + dp[2] + dp[:2] @ (tangent @ centroid)
    return n / nn, d / nn, centroid + dp[3:6]


def _fd_params(fun, J, L):
    """G (m, r): central differences of ``fun(dp)`` along dp = +-J L_k (fun(0) is the
    value); exact for fun linear in dp, second order otherwise."""
    cols = []
    for k in range(L.shape[1]):
        dp = J @ L[:, k]
        cols.append((np.asarray(fun(dp)) - np.asarray(fun(-dp))).ravel() / 2.0)
    return np.stack(cols, axis=1) if cols else np.zeros((np.asarray(fun(0 * J[:, 0])).size,
                                                         0))


def _u_of(G):
    return np.sqrt(np.sum(G * G, axis=1))


def _angle_deg(n, ref):
    return float(np.degrees(np.arccos(np.clip(abs(float(n @ ref)), -1.0, 1.0))))


def _cloud_weights(cloud, sel):
    s = cloud.sigma_z[sel]
    good = np.isfinite(s) & (s > 0)
    if not good.any():
        return np.ones(s.shape)
    return np.where(good, 1.0 / np.where(good, s, 1.0) ** 2, 0.0)


# --------------------------------------------------------------------------- plate
def _spacing_means(C, rows, cols):
    c = C.reshape(rows, cols, 3)
    dx = np.linalg.norm(np.diff(c, axis=1), axis=2)
    dy = np.linalg.norm(np.diff(c, axis=0), axis=2)
    return np.array([np.nanmean(dx), np.nanmean(dy)])


def _spacing_noise(C, S, rows, cols):
    """Noise of the mean neighbour distances from each centre's sigma (n, 3), linear."""
    c = C.reshape(rows, cols, 3)
    s2 = (S.reshape(rows, cols, 3)) ** 2
    out = []
    for axis in (1, 0):
        d = np.diff(c, axis=axis)
        dist = np.linalg.norm(d, axis=2)
        ok = np.isfinite(dist)
        e = np.where(ok[..., None], d / np.where(ok, dist, 1.0)[..., None], 0.0) / ok.sum()
        g = np.zeros_like(c)
        if axis == 1:
            g[:, 1:] += e
            g[:, :-1] -= e
        else:
            g[1:] += e
            g[:-1] -= e
        out.append(float(np.sqrt(np.nansum(g * g * s2))))
    return np.array(out)


def plate_uncertainty(measurement, cloud, calibration, *, reference=None, weight_v=None):
    """The plate's measurement with ``uncertainty`` set.

    Parameters
    ----------
    measurement : PlateMeasurement (:func:`~telefringe.metrology.plate.measure_plate`).
    cloud : PointCloud it was measured from.
    calibration : RigCalibration that triangulated the cloud (``covariance``).
    reference : Plane, the reference of ``measurement.z`` (default Z = 0).
    weight_v : see :func:`~telefringe.calibration.uncertainty.point_jacobian`; default
        :func:`weight_v_of` the cloud.

    Returns
    -------
    PlateMeasurement whose ``uncertainty`` holds ``"z"`` (the plane's height above the
    reference, mm), ``"tilt_deg"`` (its angle to the reference, deg), ``"spacing_x"`` and
    ``"spacing_y"`` (mean neighbour distances, mm).
    """
    from telefringe.metrology.planes import Plane, plane_distance

    wv = weight_v_of(cloud) if weight_v is None else weight_v
    L = _factor(calibration)
    m = measurement
    pl = m.plane
    ref = Plane.horizontal(0.0) if reference is None else reference
    pts_all = cloud.points()
    sel = np.asarray(pl.inliers, dtype=bool)
    if sel.shape[0] != pts_all.shape[0]:
        raise MetrologyError("the plate's plane was not fitted to this cloud")
    w = _cloud_weights(cloud, cloud.mask)[sel]
    Jp = _plane_jacobian(calibration, pts_all[sel], w, pl.normal, pl.centroid, pl.tangent, wv)

    def plane_q(dp):
        n, d, c = _perturbed_plane(pl.normal, pl.offset, pl.centroid, pl.tangent, dp)
        p2 = Plane(n, d)
        dist = plane_distance(p2, ref, at=c)
        return np.array([dist.distance, _angle_deg(n, ref.normal)])

    Gp = _fd_params(plane_q, Jp, L)
    # noise of the tilt angle from the fit's tilt covariance (angle along the tilt)
    eps = 1e-7
    gt = np.array([(plane_q(np.r_[eps * e, 0, 0, 0, 0])[1]
                    - plane_q(np.r_[-eps * e, 0, 0, 0, 0])[1]) / (2 * eps)
                   for e in np.eye(2)])
    u_tilt_noise = float(np.sqrt(gt @ pl.tilt_covariance @ gt))
    C = np.asarray(m.centres.xyz)
    valid = np.asarray(m.centres.valid, dtype=bool)
    rows, cols = m.spacing.dist_x.shape[0], m.spacing.dist_y.shape[1]
    Jc = point_jacobian(calibration, C[valid], weight_v=wv)

    def spacing(Cv):
        full = np.full(C.shape, np.nan)
        full[valid] = Cv
        return _spacing_means(full, rows, cols)

    Gs = propagate_fd(spacing, C[valid], Jc, L)
    u_sp_noise = _spacing_noise(C, np.asarray(m.centres.sigma_xyz), rows, cols)
    u_p = _u_of(Gp)
    u_s = _u_of(Gs)
    unc = {
        "z": Uncertainty(m.z.distance, m.z.sigma, u_p[0]),
        "tilt_deg": Uncertainty(m.z.angle_deg, u_tilt_noise, u_p[1]),
        "spacing_x": Uncertainty(m.spacing.mean_x, u_sp_noise[0], u_s[0]),
        "spacing_y": Uncertainty(m.spacing.mean_y, u_sp_noise[1], u_s[1]),
    }
    return replace(m, uncertainty=unc)


# --------------------------------------------------------------------------- steps
def steps_uncertainty(measurement, cloud, calibration, *, weight_v=None):
    """The step gauge's measurement with ``uncertainty`` set: ``"heights"`` (each level
    above the lowest, (k,) mm) and ``"step_heights"`` ((k - 1,) mm).

    The levels' joint fit (one common normal, an offset per level) is linearised at its
    solution over the points it used (``measurement.labels``).
    """
    wv = weight_v_of(cloud) if weight_v is None else weight_v
    L = _factor(calibration)
    m = measurement
    labels = np.asarray(m.labels)
    sel = (labels >= 0) & cloud.mask
    pts = cloud.xyz[sel]
    lab = labels[sel]
    n = np.asarray(m.normal)
    K = int(np.asarray(m.offsets).size)
    T = _tangent_basis(n)
    q = pts @ T.T
    a = np.zeros((pts.shape[0], 2 + K))
    a[:, :2] = q
    a[np.arange(pts.shape[0]), 2 + lab] = -1.0
    M = a.T @ a
    Minv = np.linalg.inv(M)
    G = -(a @ Minv.T)[:, :, None] * n[None, None, :]  # (n, 2 + K, 3)
    J = sum_point_jacobian(calibration, pts, G, weight_v=wv)  # (2 + K, P)
    Jd = J[2:]
    Jh = Jd - Jd[0]
    Js = np.diff(Jd, axis=0)
    uh = np.sqrt(np.sum((Jh @ L) ** 2, axis=1))
    us = np.sqrt(np.sum((Js @ L) ** 2, axis=1))
    unc = {"heights": Uncertainty(m.heights, m.sigma_heights, uh),
           "step_heights": Uncertainty(m.step_heights, m.sigma_steps, us)}
    return replace(m, uncertainty=unc)


# --------------------------------------------------------------------------- sphere
def sphere_uncertainty(measurement, cloud, calibration, *, weight_v=None):
    """The sphere's measurement with ``uncertainty`` set: ``"radius"`` (mm) and
    ``"centre"`` ((3,) mm, world frame).

    The geometric fit is linearised at its solution over the points it used
    (``measurement.fitted``); a fit through the camera's point-spread model
    (``measurement.spread``) with its own design, the spread's variance a parameter when
    it was estimated with the sphere.
    """
    wv = weight_v_of(cloud) if weight_v is None else weight_v
    L = _factor(calibration)
    m = measurement
    fitted = getattr(m, "fitted", None)
    if fitted is None:
        raise MetrologyError("the sphere measurement does not record its points (measure "
                             "it again with this version)")
    sel = np.asarray(fitted, dtype=bool) & cloud.mask
    pts = cloud.xyz[sel]
    f = m.sphere
    spread = getattr(m, "spread", None)
    if spread is None:
        d = pts - f.centre
        r = np.linalg.norm(d, axis=1)
        uvec = d / r[:, None]
        a = np.column_stack([-uvec, -np.ones(pts.shape[0])])  # d residual / d (c, R)
        k_noise = 0.0
    else:
        # the fit through the point-spread model: its residuals' design, with the spread's
        # variance a parameter when it was estimated (the points move the estimate too)
        from telefringe.metrology.spheres import spread_design

        dirs = cloud.directions
        dv = np.broadcast_to(dirs, pts.shape) if dirs.ndim == 1 else dirs[sel]
        # k_noise: the corrected normal equations' noise part (spheres._eiv_correction)
        a, uvec, k_noise = spread_design(m, pts, dv)
    Ninv = np.linalg.inv(a.T @ a - k_noise)
    G = (-(a @ Ninv.T)[:, :, None] * uvec[:, None, :])[:, :4]  # (n, 4, 3): (c, R)
    J = sum_point_jacobian(calibration, pts, G, weight_v=wv)
    u = np.sqrt(np.sum((J @ L) ** 2, axis=1))
    sc = np.sqrt(np.diag(f.covariance))
    unc = {"radius": Uncertainty(f.radius, sc[3], u[3]),
           "centre": Uncertainty(np.asarray(f.centre), sc[:3], u[:3])}
    return replace(m, uncertainty=unc)


# --------------------------------------------------------------------------- BGA
def bga_uncertainty(measurement, cloud, calibration, *, weight_v=None,
                    substrate_k: float = 3.0):
    """The BGA measurement with ``uncertainty`` set: ``"height"`` ((n,) apex heights above
    the substrate, mm), ``"position"`` ((n, 2) mm, grid frame), ``"pitch_x"`` ((rows,
    cols - 1) mm), ``"pitch_y"`` ((rows - 1, cols) mm), ``"pitch_error_max"`` (the pair
    with the largest pitch error) and ``"coplanarity"`` (mm).

    Cost: one point Jacobian per ball and one plane linearisation over the substrate (its
    points: valid points within ``substrate_k`` RMS of it), then the grid stage (grid
    registration, pitch, the coplanarity on its seating plane) repeated twice per
    principal direction of the covariance (about 22 for a telecentric rig): no per-pixel
    work beyond the substrate's sum.
    """
    from telefringe.metrology.bga.coplanarity import seating_plane_coplanarity
    from telefringe.metrology.bga.grid import _grid_local, _register_grid
    from telefringe.metrology.bga.measure import COG_K
    from telefringe.metrology.planes import Plane

    wv = weight_v_of(cloud) if weight_v is None else weight_v
    L = _factor(calibration)
    m = measurement
    sub = m.substrate
    h_img = np.where(cloud.mask, cloud.xyz @ sub.normal - sub.offset, np.nan)
    sel = np.abs(np.nan_to_num(h_img, nan=np.inf)) < substrate_k * max(sub.rms, 1e-12)
    pts = cloud.xyz[sel]
    w = _cloud_weights(cloud, sel)
    c_sub = np.average(pts, axis=0, weights=w)
    Jp = _plane_jacobian(calibration, pts, w, sub.normal, c_sub, sub.tangent, wv)
    A = np.asarray(m.apex)
    JA = point_jacobian(calibration, A, weight_v=wv)  # (n, 3, P)
    radius = np.einsum("ij,j->i", A - np.asarray(m.centre), sub.normal)
    nominal = m.nominal
    rows, cols = int(nominal.rows), int(nominal.cols)
    pitch = float(nominal.pitch_mm)
    populated = nominal.populated()
    idx = np.asarray(m.index, dtype=int)
    T0 = _tangent_basis(sub.normal)
    sig_c = np.asarray(m.sigma_centre)
    sig_plane = np.sqrt(np.mean(np.sum((sig_c[:, None, :] * T0[None]) ** 2, axis=2)))
    cop_tol = COG_K * float(sig_plane)
    sig_h = np.asarray(m.sigma_height)

    def grid_q(dA, dp):
        n, d, c = _perturbed_plane(sub.normal, sub.offset, c_sub, sub.tangent, dp)
        Ap = A + dA
        centre = Ap - radius[:, None] * n
        T = _tangent_basis(n)
        pos = centre @ T.T
        _, theta, origin_local, _ = _register_grid(pos, pitch, rows, cols, populated)
        local = _grid_local(pos, theta, origin_local)
        grid_xy = np.full((rows, cols, 2), np.nan)
        grid_xy[idx[:, 0], idx[:, 1]] = local
        px = np.linalg.norm(np.diff(grid_xy, axis=1), axis=2)
        py = np.linalg.norm(np.diff(grid_xy, axis=0), axis=2)
        if nominal.centre_of_gravity is not None:
            cog = np.asarray(nominal.centre_of_gravity, dtype=np.float64)
        else:
            c_, s_ = np.cos(theta), np.sin(theta)
            mid_local = np.array([(cols - 1) / 2.0, (rows - 1) / 2.0]) * pitch + origin_local
            mid_plane = np.array([[c_, -s_], [s_, c_]]) @ mid_local
            cog = mid_plane[0] * T[0] + mid_plane[1] * T[1] + d * n
        if fixed_seat:
            cop_value = _seated(Ap, n)
        else:
            cop_value = float(seating_plane_coplanarity(
                Ap, cog, reference=Plane(n, d), cog_tolerance=cop_tol,
                sigma_heights=sig_h).value)
        height = Ap @ n - d
        return height, local, px, py, cop_value

    # the coplanarity on its seating plane held on its three contacts, the farthest ball
    # held too (a linear uncertainty cannot describe a change of seat); the whole
    # seating-plane search again only when the package rocks between seats
    cop = m.coplanarity
    contacts = np.asarray(cop.contacts, dtype=int)
    far = int(np.argmax(np.asarray(cop.distances)))

    def _seated(Ap, n):
        p0, p1, p2 = Ap[contacts[:3]]
        nn = np.cross(p1 - p0, p2 - p0)
        nn = nn / np.linalg.norm(nn)
        if nn @ n < 0:
            nn = -nn
        return float(nn @ p0 - nn @ Ap[far])

    fixed_seat = bool(not cop.rocks and contacts.size == 3
                      and abs(_seated(A, sub.normal) - float(cop.value))
                      <= 1e-9 + 1e-6 * abs(float(cop.value)))

    def flat(dA, dp):
        h, loc, px, py, cop = grid_q(dA, dp)
        return np.concatenate([h, loc.ravel(), px.ravel(), py.ravel(), [cop]])

    cols_G = []
    for k in range(L.shape[1]):
        dA = JA @ L[:, k]
        dp = Jp @ L[:, k]
        cols_G.append((flat(dA, dp) - flat(-dA, -dp)) / 2.0)
    G = np.stack(cols_G, axis=1)
    u = np.where(np.isfinite(G).all(axis=1), _u_of(np.nan_to_num(G)), np.nan)
    nb = A.shape[0]
    o = 0
    u_h = u[o:o + nb]
    o += nb
    u_pos = u[o:o + 2 * nb].reshape(nb, 2)
    o += 2 * nb
    npx = rows * (cols - 1)
    u_px = u[o:o + npx].reshape(rows, cols - 1)
    o += npx
    npy = (rows - 1) * cols
    u_py = u[o:o + npy].reshape(rows - 1, cols)
    o += npy
    u_cop = float(u[o])
    # noise parts: the centres' in-plane sigmas; a pitch is the difference of two centres
    s_pos = np.sqrt(np.sum((sig_c[:, None, :] * T0[None]) ** 2, axis=2))  # (n, 2)
    s_grid = np.full((rows, cols), np.nan)
    s_grid[idx[:, 0], idx[:, 1]] = np.sqrt(np.mean(s_pos ** 2, axis=1))
    s_px = np.hypot(s_grid[:, 1:], s_grid[:, :-1])
    s_py = np.hypot(s_grid[1:], s_grid[:-1])
    px, py = np.asarray(m.pitch_x), np.asarray(m.pitch_y)
    err = np.concatenate([np.abs(px - pitch).ravel(), np.abs(py - pitch).ravel()])
    worst = int(np.nanargmax(np.where(np.isfinite(err), err, -np.inf))) if np.any(
        np.isfinite(err)) else None
    if worst is None:
        pe = Uncertainty(np.nan, np.nan, np.nan)
    else:
        sn = np.concatenate([s_px.ravel(), s_py.ravel()])[worst]
        sc = np.concatenate([u_px.ravel(), u_py.ravel()])[worst]
        pe = Uncertainty(m.pitch_error_max, sn, sc)
    unc = {
        "height": Uncertainty(m.height, sig_h, u_h),
        "position": Uncertainty(m.position, s_pos, u_pos),
        "pitch_x": Uncertainty(px, s_px, u_px),
        "pitch_y": Uncertainty(py, s_py, u_py),
        "pitch_error_max": pe,
        "coplanarity": Uncertainty(m.coplanarity.value, m.coplanarity.sigma, u_cop),
    }
    return replace(m, uncertainty=unc)
