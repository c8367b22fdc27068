"""Cap fits through a model of the camera's point spread (its variance common to every
ball), and the brightness-gradient terms of that model."""

from __future__ import annotations

import warnings
from typing import NamedTuple

import numpy as np

from telefringe.metrology._common import MetrologyError
from telefringe.metrology.bga.caps import CapFit
from telefringe.metrology.spheres import fit_sphere
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
    """

    caps: list
    theta: np.ndarray
    cov_theta: np.ndarray
    rounds: int
    converged: bool
    n_balls: int


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
    B = np.zeros(cloud.shape + (3,))
    if projector is not None:
        gi_v, gi_u = np.gradient(ln_i)
        up = np.asarray(projector.project(xyz)[0], dtype=np.float64)
        x0 = np.nanmedian(xyz.reshape(-1, 3), axis=0)
        du_dt = float((np.asarray(projector.project(x0 + 0.01 * d)[0])
                       - np.asarray(projector.project(x0)[0])) / 0.01)  # px / mm
        gu_v, gu_u = np.gradient(up)
        B[..., 0] = (gi_u * gu_u + gi_v * gu_v) / du_dt / px_mm**2
        return B, True
    t = xyz @ d
    if min(t.shape) >= 2:  # (one compiled pass, the same arithmetic as below)
        from telefringe.metrology.bga._kernels import gradient_terms

        gradient_terms(np.ascontiguousarray(ln_i), np.ascontiguousarray(t),
                       float(px_mm**2), B)
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


def _fit_caps_smoothed(caps, view: np.ndarray, r: float, *, max_view_angle_deg: float,
                       free_gradient: bool, sub_every: int = 4,
                       rounds: int = 6) -> PSFCapFits:
    """Fixed-radius cap fits that model the camera's point spread, and its variance.

    ``caps``: list of (pts (m, 3), sig (m,), B (m, 3)) per ball (B: see
    :func:`_brightness_gradient_terms`, zeros when no image). The points of each ball are
    moved up the viewing direction by s^2 (g + B0) + a . (B1, B2) (g: see
    :func:`_smoothing_shape`; a = 0 unless ``free_gradient``) and fitted with a sphere of
    radius ``r`` weighted by 1 / (sigma_line cos(tilt))^2. The global parameters
    theta = (s^2[, a1, a2]), common to every ball (one camera, one rig), are estimated by
    Gauss-Newton on all balls' residuals at once (Schur complement of the per-ball
    centres, :func:`_schur_normal_equations`), on every ``sub_every``-th ball.

    When the common parameters cannot be estimated (a singular system), a
    :class:`PSFSolveWarning` is issued, theta and its covariance are NaN and the caps are
    fitted with theta = 0 (no point-spread correction). Without any usable cap nothing
    is solved (theta NaN, no warning: there is no ball to measure).

    Returns
    -------
    PSFCapFits
    """
    cos_min = np.cos(np.radians(max_view_angle_deg))
    npar = 3 if free_gradient else 1
    sel = []
    reasons = []
    for pts, sig, bg in caps:
        ok = (np.all(np.isfinite(pts), axis=1) & np.isfinite(sig) & (sig > 0)
              & np.all(np.isfinite(bg), axis=1))
        pts, sig, bg = pts[ok], sig[ok], bg[ok]
        item, why = None, None
        if pts.shape[0] < 10:
            why = "too_few_points"
        else:
            try:
                f0 = fit_sphere(pts, robust=True, radius=r)
            except MetrologyError:
                why = "fit_failed"
            else:
                cos_t, _ = _smoothing_shape(pts, f0.centre, r, view)
                keep = cos_t >= cos_min
                if np.count_nonzero(keep) < 10:
                    why = "too_few_points_facing_camera"
                else:
                    pts, sig, bg = pts[keep], sig[keep], bg[keep]
                    # (theta-independent: computed once, not in every round)
                    cos_t, g = _smoothing_shape(pts, f0.centre, r, view)
                    R = np.column_stack([g + bg[:, 0], bg[:, 1], bg[:, 2]])[:, :npar]
                    item = (pts, f0.centre, R, 1.0 / (sig * cos_t) ** 2)
        sel.append(item)
        reasons.append(why)

    def fit_one(item, theta):
        pts, c, R, w = item
        q = pts + np.outer(R @ theta, view)  # moved up, toward the camera
        f = fit_sphere(q, weights=w, robust=True, radius=r, start=c)
        m = f.inliers
        res, J, K = _cap_residuals(pts[m], R[m], f.centre, theta, r, view)
        return f, q, w, J, K, res

    theta = np.zeros(npar)
    cov = np.full((npar, npar), np.nan)
    sub = [k for k, it in enumerate(sel) if it is not None][::max(int(sub_every), 1)]
    if not sub:  # no cap to fit: each keeps its reason (the caller has no ball)
        return PSFCapFits([CapFit(None, why) for why in reasons], np.full(npar, np.nan),
                          np.full((npar, npar), np.nan), 0, False, 0)
    converged = False
    failed = False
    n_rounds = 0
    for _ in range(rounds):
        n_rounds += 1
        terms = []
        for k in sub:
            try:
                f, q, w, J, K, res = fit_one(sel[k], theta)
            except MetrologyError:
                continue
            terms.append((res, J, K, w[f.inliers]))
        A, bvec, chi2, dof = _schur_normal_equations(terms, npar)
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
    out = []
    for it, why in zip(sel, reasons, strict=True):
        if it is None:
            out.append(CapFit(None, why))
            continue
        try:
            f, q, w, J, K, _ = fit_one(it, theta_fit)
            wk = w[f.inliers]
            # the centre's sensitivity to theta (at its optimum: H dc = -J^T W K dth)
            H = J.T @ (wk[:, None] * J)
            dc = -np.linalg.solve(H, J.T @ (wk[:, None] * K))
        except (MetrologyError, np.linalg.LinAlgError):
            out.append(CapFit(None, "fit_failed"))
            continue
        out.append(CapFit(f, None, points=q[f.inliers], weights=wk, dcentre_dtheta=dc))
    return PSFCapFits(out, theta, cov, n_rounds, converged, len(sub))
