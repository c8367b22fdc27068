"""One ball's cap fitted on its own (robust sphere, free radius when the cap decides it)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from telefringe.metrology._common import MetrologyError
from telefringe.metrology.spheres import SphereFit, fit_sphere


def _apex_sigma(fit: SphereFit, n: np.ndarray) -> float:
    # apex = c + r n: var = n^T C_c n + 2 n^T C_cr + C_rr
    C = fit.covariance
    g = np.concatenate([n, [1.0]])
    return float(np.sqrt(max(g @ C @ g, 0.0)))


class CapFit(NamedTuple):
    """One ball's cap fit, or why there is none.

    fit : SphereFit or None.   reason : None, or a key of
    :data:`telefringe.metrology.bga.result.NOT_MEASURED_REASONS` when ``fit`` is None.
    radius_free : the radius was fitted (else the nominal one was used).
    points, weights : (m, 3), (m,), the points of the fit (moved by the point-spread
        model when it was used) and their weights; dcentre_dtheta : (3, p), the centre's
        sensitivity to the common point-spread parameters (point-spread fits only).
    index : (m,) int, the row of each of ``points`` among the cap points the fit was
        given (its candidate's ``points``; None for point-spread fits unless asked).
    regressors, views : (m, p), (m, 3), the point-spread model's regressors of those
        points and their unit vectors toward the camera (point-spread fits for a
        two-camera match's noise only).
    """

    fit: SphereFit | None
    reason: str | None
    radius_free: bool = False
    points: np.ndarray | None = None
    weights: np.ndarray | None = None
    dcentre_dtheta: np.ndarray | None = None
    index: np.ndarray | None = None
    regressors: np.ndarray | None = None
    views: np.ndarray | None = None


def _fit_cap(pts: np.ndarray, sig: np.ndarray, view: np.ndarray, D: float, *,
             weighted: bool, max_view_angle_deg: float | None, fixed_radius: bool):
    """Fit one ball's cap; returns (SphereFit, radius_was_free) or None.

    A first robust fit with the nominal radius gives each point's surface normal; points
    whose surface is tilted more than ``max_view_angle_deg`` from facing the camera
    (``view``: unit vector toward the camera, (3,), or (m, 3) per point) are dropped
    (the pixel footprint and the camera's point spread average a range of depths there,
    and the average of a convex surface lies below it, increasingly so as 1 / cos^3 of
    the tilt). The final fit
    weights each point by 1 / sigma_r^2, sigma_r = sigma_line * cos(tilt) its
    uncertainty along the radius (points move along the viewing direction only). The
    radius is free when the cap determines it (0.7 D < diameter < 1.4 D and
    sigma_radius < 5 % D), else the nominal D / 2.
    """
    ok = np.all(np.isfinite(pts), axis=1)
    if weighted:
        ok &= np.isfinite(sig) & (sig > 0)
    rows = np.flatnonzero(ok)  # each fitted point's row among the given ones
    pts, sig = pts[ok], sig[ok]
    view = np.asarray(view, dtype=np.float64)
    if view.ndim == 2:
        view = view[ok]
    if pts.shape[0] < 10:
        return CapFit(None, "too_few_points")
    w = None
    if weighted or max_view_angle_deg is not None:
        f0 = fit_sphere(pts, robust=True, radius=D / 2)
        nn = pts - f0.centre
        nn /= np.linalg.norm(nn, axis=1)[:, None]
        cos_t = np.clip(nn @ view if view.ndim == 1 else np.einsum("ij,ij->i", nn, view),
                        1e-3, 1.0)
        keep = np.ones(pts.shape[0], dtype=bool)
        if max_view_angle_deg is not None:
            keep = cos_t >= np.cos(np.radians(max_view_angle_deg))
        if np.count_nonzero(keep) < 10:
            return CapFit(None, "too_few_points_facing_camera")
        pts, cos_t, sig, rows = pts[keep], cos_t[keep], sig[keep], rows[keep]
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
            return CapFit(None, "fit_rms_too_large")
    inl = np.asarray(f.inliers, dtype=bool)
    return CapFit(f, None, radius_free=free, points=pts[inl],
                  weights=np.ones(int(inl.sum())) if w is None else w[inl], index=rows[inl])


def fit_caps_alone(caps, view, D: float, *, weighted: bool,
                   max_view_angle_deg: float | None, fixed_radius: bool) -> list[CapFit]:
    """Each cap of ``caps`` (list of (pts (m, 3), sigma_line (m,), _)) fitted on its own
    (see :func:`_fit_cap`); ``view``: (3,) toward the camera for every point, or a list
    of (m, 3) per cap. A fit that raises is reported as ``fit_failed``."""
    out = []
    for k, (pts, sig, _) in enumerate(caps):
        v = view[k] if isinstance(view, list) else view
        try:
            out.append(_fit_cap(pts, sig, v, D, weighted=weighted,
                                max_view_angle_deg=max_view_angle_deg,
                                fixed_radius=fixed_radius))
        except MetrologyError:
            out.append(CapFit(None, "fit_failed"))
    return out
