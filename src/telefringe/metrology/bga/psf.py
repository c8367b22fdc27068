"""Cap fits through a model of the camera's point spread (its variance common to every
ball), and the brightness-gradient terms of that model."""

from __future__ import annotations

import warnings
from typing import NamedTuple

import numpy as np

from telefringe.metrology._common import _MAD, MetrologyError
from telefringe.metrology.bga.caps import CapFit
from telefringe.reconstruction.cloud import PointCloud


class PSFSolveWarning(RuntimeWarning):
    """The common point-spread parameters could not be estimated from the caps: the
    caps were fitted without the point-spread correction and ``psf_variance`` is NaN."""


class PSFConvergenceWarning(RuntimeWarning):
    """The point-spread parameters were still moving by more than 5 % of their sigma
    after the last Gauss-Newton round: the estimate (``psf_variance``) is the last
    iterate (``BGAMeasurement.psf_converged`` is False)."""


class PSFCapFits(NamedTuple):
    """Result of :func:`_fit_caps_smoothed`.

    caps : list of CapFit, one per input cap.   theta : (p,) the common parameters
    (s^2 in mm^2 first), NaN when the solve failed.   cov_theta : (p, p), NaN likewise.
    rounds : Gauss-Newton rounds run.   converged : bool.   n_balls : balls in the solve.
    sub : (n_balls,) int, those balls (indices into ``caps``).
    """

    caps: list
    theta: np.ndarray
    cov_theta: np.ndarray
    rounds: int
    converged: bool
    n_balls: int
    sub: np.ndarray | None = None


def shared_direction(cloud: PointCloud) -> np.ndarray | None:
    """The cloud's viewing direction (3,) when every pixel shares it (a telecentric
    camera), else None (a pinhole camera: :attr:`PointCloud.directions` per pixel)."""
    from telefringe.reconstruction.cloud import TriangulationError

    try:
        return np.asarray(cloud.direction, dtype=np.float64)
    except TriangulationError:
        return None


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
    d = shared_direction(cloud)
    B = np.zeros(cloud.shape + (3,))
    if projector is not None:
        if d is None:
            raise MetrologyError(
                "the projector's brightness-gradient term needs one viewing direction for "
                "every pixel (a telecentric camera); with this camera leave out the "
                "projector (the term's factor is then estimated from the caps)")
        xyz = np.where(cloud.mask[..., None], cloud.xyz, np.nan)
        with np.errstate(divide="ignore", invalid="ignore"):
            ln_i = np.log(np.where(image > 0, image, np.nan))
        gi_v, gi_u = np.gradient(ln_i)
        up = np.asarray(projector.project(xyz)[0], dtype=np.float64)
        x0 = np.nanmedian(xyz.reshape(-1, 3), axis=0)
        du_dt = float((np.asarray(projector.project(x0 + 0.01 * d)[0])
                       - np.asarray(projector.project(x0)[0])) / 0.01)  # px / mm
        gu_v, gu_u = np.gradient(up)
        B[..., 0] = (gi_u * gu_u + gi_v * gu_v) / du_dt / px_mm**2
        return B, True
    # (compiled passes: the same arithmetic as the NumPy form at the end)
    from telefringe.metrology.bga._kernels import gradient_terms, log_and_depth

    ln_i = np.empty(cloud.shape)
    t = np.empty(cloud.shape)
    log_and_depth(np.ascontiguousarray(image, dtype=np.float64),
                  np.ascontiguousarray(cloud.xyz, dtype=np.float64),
                  np.ascontiguousarray(cloud.mask),
                  np.broadcast_to(cloud.directions, cloud.shape + (3,)), ln_i, t)
    if min(t.shape) >= 2:
        gradient_terms(ln_i, t, float(px_mm**2), B)
        return B, False
    gi_v, gi_u = np.gradient(ln_i)
    gt_v, gt_u = np.gradient(t)
    B[..., 0] = (gi_u * gt_u + gi_v * gt_v) / px_mm**2
    B[..., 1] = gi_u
    B[..., 2] = gi_v
    return B, False


def _cap_residuals(pts: np.ndarray, R: np.ndarray, centre: np.ndarray, theta: np.ndarray,
                   r: float, view: np.ndarray):
    """Radial residuals of a cap's points moved by the point-spread model, and their
    Jacobians.

    The point p_i moves up the viewing direction by R_i . theta: q_i = p_i + (R_i . theta)
    view; its residual is |q_i - centre| - r. Returns (res (m,), J (m, 3) = d res /
    d centre, K (m, p) = d res / d theta).
    """
    q = pts + np.outer(R @ theta, view)
    v = q - centre
    dist = np.linalg.norm(v, axis=1)
    nn = v / dist[:, None]
    return dist - r, -nn, (nn @ view)[:, None] * R


def _schur_normal_equations(terms, npar: int):
    """Gauss-Newton normal equations of the common parameters theta with every ball's
    centre eliminated (Schur complement).

    ``terms``: per ball (res (m,), J (m, 3), K (m, p), w (m,)). With H = J^T W J the
    ball's centre block, the reduced system is A = sum K^T W K - K^T W J H^-1 J^T W K,
    b = sum K^T W res - K^T W J H^-1 J^T W res; the step is -A^-1 b. Returns (A, b, chi2,
    dof); balls whose H is singular are left out.
    """
    A = np.zeros((npar, npar))
    bvec = np.zeros(npar)
    chi2 = 0.0
    dof = 0
    for res, J, K, wk in terms:
        H = J.T @ (wk[:, None] * J)
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
    return A, bvec, chi2, dof


def _reduced_system(fits: dict, npar: int):
    """The reduced normal equations of theta summed over the balls of one
    :func:`_fit_packed` call (balls whose centre block is singular left out, as in
    :func:`_schur_normal_equations`): (A (p, p), b (p,), chi2, dof)."""
    ok = fits["schur_ok"]
    return (fits["A"][ok].sum(axis=0).reshape(npar, npar), fits["b"][ok].sum(axis=0),
            float(fits["chi2"][ok].sum()), int(fits["dof"][ok].sum()))


def _fit_packed(packed: dict, balls: np.ndarray, theta: np.ndarray, r: float) -> dict:
    """The caps ``balls`` of ``packed`` (from :func:`_pack_caps`) fitted with the common
    parameters ``theta``, one ball per thread
    (:func:`telefringe.metrology.bga._caps_kernels.fit_caps`)."""
    from telefringe.metrology.bga._caps_kernels import fit_caps

    nb, npar, N = balls.size, theta.size, packed["pts"].shape[0]
    out = {"status": np.empty(nb, dtype=np.int64), "centre": np.zeros((nb, 3)),
           "cov": np.zeros((nb, 3, 3)), "rms": np.zeros(nb), "form": np.zeros(nb),
           "n_inl": np.zeros(nb, dtype=np.int64), "inl": np.zeros(N, dtype=bool),
           "q": np.zeros((N, 3)), "A": np.zeros((nb, npar, npar)), "b": np.zeros((nb, npar)),
           "chi2": np.zeros(nb), "dof": np.zeros(nb, dtype=np.int64),
           "dc": np.zeros((nb, 3, npar)), "schur_ok": np.zeros(nb, dtype=bool)}
    fit_caps(packed["pts"], packed["R"], packed["w"], packed["off"], packed["counts"],
             packed["c0"], np.ascontiguousarray(balls, dtype=np.int64),
             np.ascontiguousarray(theta, dtype=np.float64), packed["view"], float(r), 4.0,
             _MAD,
             out["status"], out["centre"], out["cov"], out["rms"], out["form"],
             out["n_inl"], out["inl"], out["q"], out["A"], out["b"], out["chi2"],
             out["dof"], out["dc"], out["schur_ok"])
    return out


_REASONS = {1: "too_few_points", 2: "fit_failed", 3: "too_few_points_facing_camera"}


def _pack_caps(caps, view, r: float, cos_min: float, npar: int) -> dict:
    """The caps packed one after another and prepared for the point-spread fits
    (:func:`telefringe.metrology.bga._caps_kernels.prepare_caps`: finite points, a robust
    sphere of radius r, the points facing the camera, their regressors and weights).
    ``view``: (3,) toward the camera for every point, or per cap (m, 3)."""
    from telefringe.metrology.bga._caps_kernels import prepare_caps

    nb = len(caps)
    off = np.zeros(nb + 1, dtype=np.int64)
    np.cumsum([c[0].shape[0] for c in caps], out=off[1:])
    N = int(off[-1])

    def cat(i, width):
        if not nb:
            return np.zeros((0, width)) if width else np.zeros(0)
        return np.ascontiguousarray(np.concatenate([np.asarray(c[i], dtype=np.float64)
                                                    for c in caps]))

    p = {"off": off, "pts": np.zeros((N, 3)), "R": np.zeros((N, npar)), "w": np.zeros(N),
         "view": np.zeros((N, 3)), "counts": np.zeros(nb, dtype=np.int64),
         "c0": np.zeros((nb, 3)), "status": np.empty(nb, dtype=np.int64)}
    v = np.asarray(view, dtype=np.float64) if not isinstance(view, list) else None
    if v is not None and v.shape == (3,):
        views = np.ascontiguousarray(np.broadcast_to(v, (N, 3)))
    else:
        views = np.ascontiguousarray(np.concatenate(view) if nb else np.zeros((0, 3)),
                                     dtype=np.float64).reshape(N, 3)
    prepare_caps(cat(0, 3).reshape(N, 3), cat(1, 0), cat(2, 3).reshape(N, 3), views, off,
                 float(r), float((r * np.sin(np.radians(80.0))) ** 2), float(cos_min),
                 int(npar), 4.0, _MAD, p["pts"], p["R"], p["w"], p["view"], p["counts"],
                 p["c0"], p["status"])
    return p


def _rows_of(given: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """The row of each point of ``kept`` (k, 3) among ``given`` (m, 3), of which
    :func:`_pack_caps` copied it unchanged (in order; every pixel's point is its own)."""
    where = {tuple(p): i for i, p in enumerate(np.asarray(given, dtype=np.float64))}
    return np.array([where[tuple(p)] for p in kept], dtype=np.int64)


def _fit_caps_smoothed(caps, view: np.ndarray, r: float, *, max_view_angle_deg: float,
                       free_gradient: bool, sub_every: int = 4,
                       rounds: int = 6, with_index: bool = False) -> PSFCapFits:
    """Fixed-radius cap fits that model the camera's point spread, and its variance.

    ``caps``: list of (pts (m, 3), sig (m,), B (m, 3)) per ball (B: see
    :func:`_brightness_gradient_terms`, zeros when no image); ``view``: the unit vector
    toward the camera, (3,) for every point (a telecentric camera) or a list of (m, 3)
    per ball (each point's own: a pinhole camera). The points of each ball are
    moved up their viewing direction by s^2 (g + B0) + a . (B1, B2) (g: see
    :func:`_smoothing_shape`; a = 0 unless ``free_gradient``) and fitted with a sphere of
    radius ``r`` weighted by 1 / (sigma_line cos(tilt))^2. The global parameters
    theta = (s^2[, a1, a2]), common to every ball (one camera, one rig), are estimated by
    Gauss-Newton on all balls' residuals at once (Schur complement of the per-ball
    centres, :func:`_schur_normal_equations`), on every ``sub_every``-th ball.

    The balls are fitted in parallel by compiled kernels
    (:mod:`telefringe.metrology.bga._caps_kernels`; the NumPy forms of their steps are
    :func:`_smoothing_shape`, :func:`_cap_residuals` and :func:`_schur_normal_equations`).

    When the common parameters cannot be estimated (a singular system), a
    :class:`PSFSolveWarning` is issued, theta and its covariance are NaN and the caps are
    fitted with theta = 0 (no point-spread correction). Without any usable cap nothing
    is solved (theta NaN, no warning: there is no ball to measure).

    ``with_index``: each CapFit's ``index`` (its points' rows among the cap's given
    points), ``regressors`` and ``views`` (for the stereo matches' noise), else None.

    Returns
    -------
    PSFCapFits
    """
    from telefringe.metrology.spheres import SphereFit

    cos_min = np.cos(np.radians(max_view_angle_deg))
    npar = 3 if free_gradient else 1
    packed = _pack_caps(caps, view, r, cos_min, npar)
    status = packed["status"]
    usable = np.flatnonzero(status == 0)
    theta = np.zeros(npar)
    cov = np.full((npar, npar), np.nan)
    sub = usable[::max(int(sub_every), 1)]
    if not sub.size:  # no cap to fit: each keeps its reason (the caller has no ball)
        return PSFCapFits([CapFit(None, _REASONS[int(s)]) for s in status],
                          np.full(npar, np.nan), np.full((npar, npar), np.nan), 0, False, 0)
    converged = False
    failed = False
    n_rounds = 0
    for _ in range(rounds):
        n_rounds += 1
        A, bvec, chi2, dof = _reduced_system(_fit_packed(packed, sub, theta, r), npar)
        try:
            step = -np.linalg.solve(A, bvec)
            cov = chi2 / max(dof - npar, 1) * np.linalg.inv(A)
        except np.linalg.LinAlgError:
            failed = True
            break
        theta = theta + step
        # stop well inside the estimate's own uncertainty
        if abs(step[0]) < 0.05 * np.sqrt(cov[0, 0]):
            converged = True
            break
    if failed or not np.all(np.isfinite(theta)):
        warnings.warn(
            f"the point-spread variance could not be estimated from {len(sub)} ball(s) "
            "(singular system): the caps are fitted without the point-spread correction, "
            "psf_variance is NaN", PSFSolveWarning, stacklevel=3)
        theta_fit = np.zeros(npar)
        theta = np.full(npar, np.nan)
        cov = np.full((npar, npar), np.nan)
    else:
        theta_fit = theta
        if not converged:
            warnings.warn(f"the point-spread variance did not converge in {n_rounds} rounds",
                          PSFConvergenceWarning, stacklevel=3)
    fits = _fit_packed(packed, usable, theta_fit, r)
    out = [None if s == 0 else CapFit(None, _REASONS[int(s)]) for s in status]
    off, counts = packed["off"], packed["counts"]
    for t, k in enumerate(usable):
        if fits["status"][t] != 0 or not fits["schur_ok"][t]:
            out[k] = CapFit(None, "fit_failed")
            continue
        rows = slice(off[k], off[k] + counts[k])
        inl = fits["inl"][rows]
        c4 = np.zeros((4, 4))
        c4[:3, :3] = fits["cov"][t]
        f = SphereFit(fits["centre"][t], float(r), float(fits["rms"][t]),
                      float(fits["form"][t]), int(counts[k]), int(fits["n_inl"][t]), inl,
                      c4)
        out[k] = CapFit(f, None, points=fits["q"][rows][inl], weights=packed["w"][rows][inl],
                        dcentre_dtheta=fits["dc"][t],
                        index=(_rows_of(caps[k][0], packed["pts"][rows][inl]) if with_index
                               else None),
                        regressors=packed["R"][rows][inl] if with_index else None,
                        views=packed["view"][rows][inl] if with_index else None)
    return PSFCapFits(out, theta, cov, n_rounds, converged, len(sub), sub)
