"""The calibration's uncertainty carried into triangulated points and into anything
computed from them.

A rig calibration estimates the parameter vector ``theta`` of its devices (camera then
projector, each device's ``param_names``; :attr:`RigCalibration.parameter_names`) with a
covariance ``Sigma`` (:attr:`RigCalibration.covariance`). Every point triangulated with
that rig is a function ``X(theta)`` of the parameters, so all points of every scan made
with one calibration share its error: a calibration error is a smooth deformation of
space that does not average away over many points. For a quantity ``q`` computed from
points, its calibration part is ``u_cal(q)^2 = J Sigma J^T`` with ``J = dq/dtheta``
through the triangulation (the correlated term), beside the decoding noise (independent
per pixel, already in ``sigma_line`` / ``sigma_z``); the two add in quadrature.

The derivative of a point (:func:`point_jacobian`) is exact to first order for every
camera + projector rig of the :class:`~telefringe.devices.base.Device` protocol (any
models): a point ``X`` seen by camera pixel ``c`` with projector coordinates ``p``
satisfies ``camera.project(X) = c`` (the pixel is known exactly) and, along that camera
line, minimises the weighted projector misfit ``sum_a w_a (projector.project(X)_a -
p_a)^2`` (u only: ``w_v = 0``; both axes: the triangulator's weights ``1 / sigma_a^2``).
The implicit function theorem gives ``dX/dtheta`` from the devices'
``project_jacobian`` alone, at ``X`` (the observed ``c`` and ``p`` are implied by ``X``
to first order; the misfit's own residual enters at second order only). Points matched
between two cameras (stereo) take the same form with the second camera in the
projector's place and the image metric of the matching (:func:`stereo_calibration`):
the two-ray triangulation through both cameras' parameters. Other rigs can use
:func:`point_jacobian_fd`: central differences through a re-triangulation the caller
passes in.

World-frame gauge: the world frame is the calibration target at its reference pose (its
pose is held fixed in the adjustment, six parameters that are not estimated); every
device parameter, poses included, is estimated relative to it. The covariance of the
device poses therefore holds how well that frame is realised: quantities in world
coordinates (a plane's height above Z = 0, its tilt, a sphere's centre) carry that part;
quantities invariant under a rigid motion of the world (distances, radii, step heights,
pitch, coplanarity) do not see it (their ``J`` is orthogonal to it). Parameters held
fixed by the calibration (NaN rows of the covariance, e.g. a fixed principal point) are
exact here. A telecentric device has no translation along its axis (its images do not see
it), so the rig's parameter vector holds none.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from telefringe.geometry.interpolation import bilinear

__all__ = [
    "StereoCalibration",
    "stereo_calibration",
    "covariance_factor",
    "point_jacobian",
    "point_jacobian_fd",
    "sum_point_jacobian",
    "propagate_fd",
    "point_sigma",
    "PointUncertainty",
]

_CHUNK = 65536


def _devices(rig):
    """(camera, projector) of a Rig or of an object holding one as ``.rig``."""
    inner = getattr(rig, "rig", rig)
    cam = getattr(inner, "camera", None)
    proj = getattr(inner, "projector", None)
    if cam is None or proj is None:
        raise ValueError("the rig needs a camera and a projector for point_jacobian (two "
                         "cameras: stereo_calibration; other rigs: point_jacobian_fd with "
                         "their own triangulation)")
    return cam, proj


def covariance_factor(covariance, *, rtol: float = 1e-14) -> np.ndarray:
    """A factor ``L`` (n, r) of a parameter covariance: ``L @ L.T == covariance``.

    Rows and columns that are NaN (parameters the calibration held fixed) count as
    exact (zero). Columns are the principal directions scaled by their standard
    deviations, largest first; eigenvalues below ``rtol`` times the largest (rounding)
    are dropped.

    Parameters
    ----------
    covariance : (n, n) array_like, symmetric positive semi-definite.

    Returns
    -------
    (n, r) ndarray, r <= n.
    """
    C = np.array(covariance, dtype=np.float64)
    if C.ndim != 2 or C.shape[0] != C.shape[1]:
        raise ValueError(f"covariance must be square, got shape {C.shape}")
    C = np.where(np.isfinite(C), C, 0.0)
    C = 0.5 * (C + C.T)
    evals, evecs = np.linalg.eigh(C)
    top = float(evals[-1]) if evals.size else 0.0
    keep = evals > rtol * max(top, 0.0)
    if top <= 0 or not keep.any():
        return np.zeros((C.shape[0], 0))
    order = np.argsort(-evals[keep])
    return (evecs[:, keep] * np.sqrt(evals[keep]))[:, order]


def _weights(weight_v, n):
    w = np.broadcast_to(np.asarray(0.0 if weight_v is None else weight_v, dtype=np.float64),
                        (n,))
    if np.any(~np.isfinite(w)) or np.any(w < 0):
        raise ValueError("weight_v must be finite and >= 0")
    return w


def point_jacobian(rig, xyz, *, weight_v=None) -> np.ndarray:
    """Derivative of triangulated points with respect to the rig's parameters.

    Parameters
    ----------
    rig : Rig, or RigCalibration (any Device models for camera and projector), or a
        :class:`StereoCalibration` (:func:`stereo_calibration`: points matched between
        two cameras).
    xyz : (n, 3) array_like, mm, triangulated points (world frame); finite.
    weight_v : float or (n,) array_like, optional
        Weight of the projector's v coordinate relative to its u coordinate in the
        triangulation, ``(sigma_u_p / sigma_v_p)^2``: None or 0 when the points were
        triangulated from u_p alone, 1 for both axes with equal uncertainties (what the
        triangulator does without the decoder's sigmas). Not used for stereo points
        (their weights are in the :class:`StereoCalibration`).

    Returns
    -------
    (n, 3, n_params) ndarray, mm per parameter unit, parameters in the order of
    ``camera.param_names`` then ``projector.param_names`` (``RigCalibration.parameter_names``;
    a rig with two cameras: ``camera``, ``camera_2``, then ``projector`` where it has one,
    the devices a point does not depend on with zero columns).

    Raises
    ------
    ValueError
        A point where the camera line does not cross the projector's coordinates (its
        projector coordinates do not change along the camera's line); a two-camera rig
        not given as a :class:`StereoCalibration` (how its points were triangulated is
        then unknown).
    """
    if isinstance(rig, StereoCalibration):
        return _stereo_point_jacobian(rig, xyz)
    inner = getattr(rig, "rig", rig)
    if len(getattr(inner, "cameras", ())) > 1:
        raise ValueError("a rig with two cameras: its points were matched between the "
                         "cameras, and their calibration part needs the second camera's "
                         "decoded coordinates (stereo_calibration / "
                         "metrology.uncertainty.for_stereo), which a points file does not "
                         "hold")
    cam, proj = _devices(rig)
    X = np.asarray(xyz, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"xyz must have shape (n, 3), got {X.shape}")
    n = X.shape[0]
    wv = _weights(weight_v, n)
    metric = np.zeros((n, 2, 2))
    metric[:, 0, 0] = 1.0
    metric[:, 1, 1] = wv
    dX_c, dX_p = _line_jacobian(cam, proj, X, metric)
    return np.concatenate([dX_c, dX_p], axis=2)


def _line_jacobian(cam, other, X, metric):
    """dX/dtheta of points ``X`` (n, 3) fixed on ``cam``'s line through their (exact)
    pixel, placed along it by minimising ``r^T M r`` with ``r`` the change of their
    image in ``other`` (a projector, or the second camera of a stereo pair) and ``M`` the
    (n, 2, 2) ``metric``. Returns (dX/dtheta_cam (n, 3, Pc), dX/dtheta_other (n, 3, Po))."""
    _, Jc_p, Jc_X = cam.project_jacobian(X)  # (n, 2, Pc), (n, 2, 3)
    _, Jp_p, Jp_X = other.project_jacobian(X)
    # the camera line's direction: the null vector of the camera's point Jacobian
    d = np.cross(Jc_X[:, 0], Jc_X[:, 1])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # minimum-norm solution of Jc_X dX = -Jc_p dtheta_c: dX0 = -Jc_X^+ Jc_p, with
    # Jc_X^+ = Jc_X^T (Jc_X Jc_X^T)^-1 (the 2 x 2 inverse written out)
    r0, r1 = Jc_X[:, 0], Jc_X[:, 1]
    a, b, c = np.sum(r0 * r0, 1), np.sum(r0 * r1, 1), np.sum(r1 * r1, 1)
    det = a * c - b * b
    # rows of (Jc_X Jc_X^T)^-1 Jc_p, then back through Jc_X^T
    y0 = (c[:, None] * Jc_p[:, 0] - b[:, None] * Jc_p[:, 1]) / det[:, None]
    y1 = (a[:, None] * Jc_p[:, 1] - b[:, None] * Jc_p[:, 0]) / det[:, None]
    dX0_c = -(r0[:, :, None] * y0[:, None, :] + r1[:, :, None] * y1[:, None, :])
    g = np.einsum("nij,nj->ni", Jp_X, d)  # (n, 2) image px per mm along the line
    Mg = np.einsum("nij,nj->ni", metric, g)
    gwg = np.sum(g * Mg, axis=1)
    scale = np.max(np.abs(Jp_X), axis=(1, 2)) * np.sqrt(
        np.max(np.abs(metric), axis=(1, 2)))
    if np.any(~(gwg > (1e-6 * scale) ** 2)):
        raise ValueError("the projector's coordinates do not change along the camera's line "
                         "at some points: they cannot be triangulated")
    h = Mg / gwg[:, None]  # (n, 2): ds = -h . (d image px)
    # camera parameters: dX = dX0 + d ds, ds = -h . (Jp_X dX0)
    hJ = np.einsum("ni,nij->nj", h, Jp_X)  # (n, 3)
    dX_c = dX0_c - d[:, :, None] * np.einsum("nj,njk->nk", hJ, dX0_c)[:, None, :]
    # the other device's parameters: ds = -h . Jp_p
    dX_p = -d[:, :, None] * np.einsum("ni,nik->nk", h, Jp_p)[:, None, :]
    return dX_c, dX_p


# --------------------------------------------------------------------------- stereo
@dataclass(frozen=True, eq=False)
class StereoCalibration:
    """A two-camera rig's calibration together with what its stereo points were matched
    on: the second camera's decoded projector coordinates (see
    :func:`stereo_calibration`). Has the calibration's ``covariance``,
    ``parameter_names`` and ``rig``, so it goes wherever a RigCalibration goes in
    :mod:`telefringe.metrology.uncertainty`.

    Attributes
    ----------
    calibration : RigCalibration (or anything with ``rig``, ``covariance`` and
        ``parameter_names``) whose rig has two cameras.
    maps : tuple of (rows, cols) ndarray, the second camera's decoded projector
        coordinates of every axis the matching used (u_p, and v_p), projector px, NaN
        where invalid.
    weights : tuple of (rows, cols) ndarray or None, per axis the weight of that axis
        (``1 / sigma^2``), or None for equal weights.
    """

    calibration: object
    maps: tuple
    weights: tuple | None = None

    @property
    def rig(self):
        return getattr(self.calibration, "rig", self.calibration)

    @property
    def covariance(self):
        return getattr(self.calibration, "covariance", None)

    @property
    def parameter_names(self):
        return getattr(self.calibration, "parameter_names", ())

    @property
    def parameters(self):
        return getattr(self.calibration, "parameters", None)


def stereo_calibration(calibration, maps_2, *, sigmas_2=None) -> StereoCalibration:
    """The calibration of a two-camera rig for the uncertainty of points matched between
    its cameras (``telefringe reconstruct --second``,
    :func:`~telefringe.reconstruction.stereo.match_stereo`).

    A stereo point ``X`` lies on the first camera's line through its pixel (known
    exactly), at the place where the second camera sees the same projector coordinates
    ``p_a`` as the first (least squares over the axes ``a`` used, weights ``w_a``). A
    change of the parameters moves that line and the second camera's image ``c2`` of
    the point; the data (the second camera's map ``P_a``) stay, so to first order the
    point slides along the moved line until ``sum_a w_a (g_a . dc2)^2`` is least, with
    ``g_a`` the gradient of ``P_a`` in the second camera's image at the match: the
    two-ray triangulation with the second ray's image metric ``M = sum_a w_a g_a
    g_a^T``. With one axis only the component of ``dc2`` across that axis's fringes
    counts (the match slides along a fringe). ``g_a`` is the bilinear gradient of the
    decoded map at ``c2`` (what the matching interpolates).

    Parameters
    ----------
    calibration : RigCalibration of a rig with two cameras (``covariance`` over
        ``camera``, ``camera_2`` and, where calibrated, ``projector`` parameters).
    maps_2 : (rows, cols) array_like or a sequence of them: the second camera's decoded
        projector coordinates of each axis the matching used (u_p; and v_p when it
        combined both axes), projector px, NaN where invalid.
    sigmas_2 : None or a sequence like ``maps_2`` of their standard uncertainties
        (projector px): each axis weighted by ``1 / sigma^2`` at the match; None: equal.

    Returns
    -------
    StereoCalibration
    """
    inner = getattr(calibration, "rig", calibration)
    if len(getattr(inner, "cameras", ())) < 2:
        raise ValueError("stereo_calibration needs a rig with two cameras")
    maps = np.asarray(maps_2, dtype=np.float64)
    maps = (maps,) if maps.ndim == 2 else tuple(maps)
    if not 1 <= len(maps) <= 2 or any(m.ndim != 2 or m.shape != maps[0].shape
                                      for m in maps):
        raise ValueError("maps_2: one or two (rows, cols) maps of the same shape")
    w = None
    if sigmas_2 is not None:
        sig = np.asarray(sigmas_2, dtype=np.float64)
        sig = (sig,) if sig.ndim == 2 else tuple(sig)
        if len(sig) != len(maps) or any(x.shape != maps[0].shape for x in sig):
            raise ValueError("sigmas_2 must match maps_2")
        with np.errstate(divide="ignore", invalid="ignore"):
            w = tuple(np.where(np.isfinite(x) & (x > 0), 1.0 / (x * x), np.nan) for x in sig)
    return StereoCalibration(calibration, tuple(m.copy() for m in maps), w)


def _stereo_point_jacobian(stereo: StereoCalibration, xyz) -> np.ndarray:
    X = np.asarray(xyz, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"xyz must have shape (n, 3), got {X.shape}")
    inner = stereo.rig
    names = tuple(inner.cameras)
    cam1, cam2 = inner.cameras[names[0]], inner.cameras[names[1]]
    u2, v2 = cam2.project(X)
    metric = np.zeros((X.shape[0], 2, 2))
    for k, A in enumerate(stereo.maps):
        _, gu, gv, _ = bilinear(A, u2, v2)
        g = np.stack([gu, gv], axis=1)
        w = 1.0 if stereo.weights is None else bilinear(stereo.weights[k], u2, v2)[0]
        metric += np.asarray(w)[..., None, None] * g[:, :, None] * g[:, None, :]
    bad = ~np.all(np.isfinite(metric), axis=(1, 2))
    if bad.any():
        raise ValueError(f"{int(bad.sum())} of {X.shape[0]} points are not inside a valid "
                         "cell of the second camera's decoded map (they cannot have been "
                         "matched there)")
    dX_1, dX_2 = _line_jacobian(cam1, cam2, X, metric)
    blocks = [dX_1, dX_2] + [np.zeros((X.shape[0], 3, len(c.param_names)))
                             for c in list(inner.cameras.values())[2:]]
    if getattr(inner, "projector", None) is not None:
        blocks.append(np.zeros((X.shape[0], 3, len(inner.projector.param_names))))
    return np.concatenate(blocks, axis=2)


def point_jacobian_fd(retriangulate: Callable, parameters, *, steps) -> np.ndarray:
    """Derivative of points by central differences through a re-triangulation (any rig).

    Parameters
    ----------
    retriangulate : callable ``theta (n_params,) -> (n, 3)`` points, mm: the same
        observations triangulated with the rig of parameters ``theta`` (e.g. built with
        each device's ``from_params``).
    parameters : (n_params,) array_like, the calibrated parameters.
    steps : (n_params,) array_like, the step per parameter (e.g. its standard deviation:
        the error of a central difference is then of the order of the curvature times
        the square of the parameter's own uncertainty); 0 skips a parameter.

    Returns
    -------
    (n, 3, n_params) ndarray.
    """
    th = np.asarray(parameters, dtype=np.float64).ravel()
    hs = np.broadcast_to(np.asarray(steps, dtype=np.float64), th.shape)
    cols = []
    for k in range(th.size):
        if not (np.isfinite(hs[k]) and hs[k] > 0):
            cols.append(None)
            continue
        e = np.zeros_like(th)
        e[k] = hs[k]
        cols.append((np.asarray(retriangulate(th + e)) - np.asarray(retriangulate(th - e)))
                    / (2.0 * hs[k]))
    n = next(c.shape[0] for c in cols if c is not None)
    return np.stack([np.zeros((n, 3)) if c is None else c for c in cols], axis=2)


def sum_point_jacobian(rig, xyz, coefficients, *, weight_v=None,
                       chunk: int = _CHUNK) -> np.ndarray:
    """``sum_i coefficients[i] @ point_jacobian(xyz[i])``: the derivative of a quantity
    that is linear in the points' displacements (e.g. a least-squares fit linearised at
    its solution), in chunks of points (bounded memory for millions of points).

    Parameters
    ----------
    rig : Rig or RigCalibration.
    xyz : (n, 3) array_like, mm.
    coefficients : (n, m, 3) array_like, d q / d X_i for the m quantities.
    weight_v : see :func:`point_jacobian` (scalar or (n,)).

    Returns
    -------
    (m, n_params) ndarray.
    """
    X = np.asarray(xyz, dtype=np.float64)
    G = np.asarray(coefficients, dtype=np.float64)
    if G.ndim != 3 or G.shape[0] != X.shape[0] or G.shape[2] != 3:
        raise ValueError(f"coefficients must have shape (n, m, 3) with n = {X.shape[0]}, "
                         f"got {G.shape}")
    wv = _weights(weight_v, X.shape[0])
    out = None
    for lo in range(0, X.shape[0], chunk):
        J = point_jacobian(rig, X[lo:lo + chunk], weight_v=wv[lo:lo + chunk])
        part = np.einsum("nmj,njk->mk", G[lo:lo + chunk], J)
        out = part if out is None else out + part
    if out is None:
        raise ValueError("no points")
    return out


def propagate_fd(f: Callable, points, jacobian, factor, *, step: float = 1.0) -> np.ndarray:
    """Calibration covariance of quantities ``f(points)`` by central differences along the
    principal directions of the parameter covariance.

    Each column ``L_k`` of ``factor`` (:func:`covariance_factor`) moves the points by
    ``D_k = jacobian @ L_k``; ``G[:, k] = (f(X + step D_k) - f(X - step D_k)) / (2 step)``
    and the covariance of ``f`` is ``G G^T``. With the default ``step`` of one standard
    deviation the error is of third order in the (small) calibration errors: exact to
    second order.

    Parameters
    ----------
    f : callable ``(n, 3) -> (m,)`` (the quantities of the points; must not change which
        points it uses between calls).
    points : (n, 3) array_like, mm.
    jacobian : (n, 3, n_params) array_like (:func:`point_jacobian`).
    factor : (n_params, r) array_like.

    Returns
    -------
    G : (m, r) ndarray, so that ``cov = G @ G.T`` and ``u_cal = sqrt(sum(G**2, axis=1))``.
    """
    X = np.asarray(points, dtype=np.float64)
    J = np.asarray(jacobian, dtype=np.float64)
    L = np.asarray(factor, dtype=np.float64)
    m = np.asarray(f(X), dtype=np.float64).ravel().size
    G = np.zeros((m, L.shape[1]))
    for k in range(L.shape[1]):
        D = J @ L[:, k]
        hi = np.asarray(f(X + step * D), dtype=np.float64).ravel()
        lo = np.asarray(f(X - step * D), dtype=np.float64).ravel()
        G[:, k] = (hi - lo) / (2.0 * step)
    return G


@dataclass(frozen=True, eq=False)
class PointUncertainty:
    """Standard uncertainties of points: the decoding noise, the calibration and both.

    Attributes
    ----------
    noise : (..., 3) ndarray, mm, per coordinate from the decoder's noise (independent
        from point to point).
    calibration : (..., 3) ndarray, mm, per coordinate from the calibration's covariance
        (shared by all points of the calibration: strongly correlated between points).
    combined : (..., 3) ndarray, mm, ``sqrt(noise^2 + calibration^2)``.
    """

    noise: np.ndarray
    calibration: np.ndarray
    combined: np.ndarray


def point_sigma(rig, xyz, covariance, *, sigma_noise=None, weight_v=None,
                chunk: int = _CHUNK) -> PointUncertainty:
    """Per-point standard uncertainties (X, Y, Z) from the calibration and the noise.

    Parameters
    ----------
    rig : Rig or RigCalibration.
    xyz : (..., 3) array_like, mm; non-finite points give NaN.
    covariance : (n_params, n_params) array_like (:attr:`RigCalibration.covariance`).
    sigma_noise : (..., 3) array_like, optional, mm (e.g. ``PointCloud.sigma_xyz``); NaN
        when not given.
    weight_v : see :func:`point_jacobian` (scalar).

    Returns
    -------
    PointUncertainty
    """
    X = np.asarray(xyz, dtype=np.float64)
    shape = X.shape
    flat = X.reshape(-1, 3)
    ok = np.all(np.isfinite(flat), axis=1)
    L = covariance_factor(covariance)
    cal = np.full(flat.shape, np.nan)
    idx = np.flatnonzero(ok)
    for lo in range(0, idx.size, chunk):
        sel = idx[lo:lo + chunk]
        J = point_jacobian(rig, flat[sel], weight_v=weight_v)
        cal[sel] = np.sqrt(np.sum((J @ L) ** 2, axis=2))
    cal = cal.reshape(shape)
    noise = (np.full(shape, np.nan) if sigma_noise is None
             else np.asarray(sigma_noise, dtype=np.float64) * np.ones(shape))
    return PointUncertainty(noise, cal, np.hypot(noise, cal))
