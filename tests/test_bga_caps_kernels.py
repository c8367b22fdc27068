"""The ball-parallel compiled cap fits (telefringe.metrology.bga._caps_kernels, through
psf._fit_caps_smoothed) against the NumPy form they replaced (fit_sphere per cap, the
NumPy residuals and Schur complement of psf), on synthetic caps seen through a point
spread: the same balls fitted or refused (with the same reasons), the same inliers, and
centres, covariances and the common parameters equal to rounding."""

from __future__ import annotations

import numpy as np
import pytest

from telefringe.metrology._common import MetrologyError
from telefringe.metrology.bga.caps import CapFit
from telefringe.metrology.bga.psf import (
    _cap_residuals,
    _fit_caps_smoothed,
    _schur_normal_equations,
    _smoothing_shape,
)
from telefringe.metrology.spheres import fit_sphere


def _reference(caps, view, r, *, max_view_angle_deg, free_gradient, rounds=6, sub_every=4):
    """The NumPy form: (caps as list of CapFit, theta)."""
    cos_min = np.cos(np.radians(max_view_angle_deg))
    npar = 3 if free_gradient else 1
    sel, reasons = [], []
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
                    cos_t, g = _smoothing_shape(pts, f0.centre, r, view)
                    R = np.column_stack([g + bg[:, 0], bg[:, 1], bg[:, 2]])[:, :npar]
                    item = (pts, f0.centre, R, 1.0 / (sig * cos_t) ** 2)
        sel.append(item)
        reasons.append(why)

    def fit_one(item, theta):
        pts, c, R, w = item
        q = pts + np.outer(R @ theta, view)
        f = fit_sphere(q, weights=w, robust=True, radius=r, start=c)
        res, J, K = _cap_residuals(pts[f.inliers], R[f.inliers], f.centre, theta, r, view)
        return f, q, w, J, K, res

    theta = np.zeros(npar)
    sub = [k for k, it in enumerate(sel) if it is not None][::sub_every]
    for _ in range(rounds):
        terms = []
        for k in sub:
            f, q, w, J, K, res = fit_one(sel[k], theta)
            terms.append((res, J, K, w[f.inliers]))
        A, b, chi2, dof = _schur_normal_equations(terms, npar)
        step = -np.linalg.solve(A, b)
        cov = chi2 / max(dof - npar, 1) * np.linalg.inv(A)
        theta = theta + step
        if abs(step[0]) < 0.05 * np.sqrt(cov[0, 0]):
            break
    out = []
    for it, why in zip(sel, reasons, strict=True):
        if it is None:
            out.append(CapFit(None, why))
            continue
        f, q, w, J, K, _ = fit_one(it, theta)
        wk = w[f.inliers]
        H = J.T @ (wk[:, None] * J)
        dc = -np.linalg.solve(H, J.T @ (wk[:, None] * K))
        out.append(CapFit(f, None, points=q[f.inliers], weights=wk, dcentre_dtheta=dc))
    return out, theta, cov


def _caps(rng, n=24, r=0.225, s2=4e-4, view=(0.02, -0.01, 1.0)):
    """Caps of radius r seen along ``view`` (to the camera), lowered along it by the
    point spread's first-order effect s2 g; a few with too few points or facing away."""
    view = np.asarray(view) / np.linalg.norm(view)
    caps = []
    for k in range(n):
        c = np.array([k * 0.8, 0.1 * k, 0.1 + rng.normal(0, 0.01)])
        m = 5 if k == 3 else 80
        th = np.arccos(rng.uniform(np.cos(np.radians(85 if k != 7 else 89)), 1.0, m))
        if k == 7:  # only a steep flank: too few points facing the camera
            th = np.radians(rng.uniform(75, 88, m))
        ph = rng.uniform(0, 2 * np.pi, m)
        e1 = np.cross(view, [1.0, 0, 0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(view, e1)
        u = (np.cos(th)[:, None] * view + np.sin(th)[:, None]
             * (np.cos(ph)[:, None] * e1 + np.sin(ph)[:, None] * e2))
        p = c + r * u
        _, g = _smoothing_shape(p, c, r, view)
        bg = rng.normal(0, 1.0, (m, 3)) * [20.0, 0.5, 0.5]
        p = p - (s2 * (g + bg[:, 0]))[:, None] * view + rng.normal(0, 1e-3, (m, 1)) * view
        sig = np.full(m, 1e-3) * rng.uniform(0.8, 1.2, m)
        if k == 5:
            p[:3] = np.nan  # dropped points
            p[10, 2] += 0.05  # an outlier
        caps.append((p, sig, bg))
    return caps, view


@pytest.mark.parametrize("free_gradient", [False, True])
def test_compiled_cap_fits_match_their_numpy_form(free_gradient):
    rng = np.random.default_rng(5)
    caps, view = _caps(rng)
    kw = dict(max_view_angle_deg=60.0, free_gradient=free_gradient)
    got = _fit_caps_smoothed(caps, view, 0.225, **kw)
    ref, theta, cov = _reference(caps, view, 0.225, **kw)
    assert [c.reason for c in got.caps] == [c.reason for c in ref]
    assert got.caps[3].reason == "too_few_points"
    assert got.caps[7].reason == "too_few_points_facing_camera"
    # the point spread's variance is found (true 4e-4 mm^2), as by the NumPy form
    assert abs(got.theta[0] - 4e-4) < 4 * np.sqrt(got.cov_theta[0, 0])
    # bounds: twice the largest differences seen (seed 5): the fits agree to the
    # sphere Levenberg-Marquardt's own stopping point (cost changes below 1e-15 of
    # itself, ~1e-11 mm in a centre); everything else to rounding
    np.testing.assert_allclose(got.theta, theta, rtol=3e-11)
    np.testing.assert_allclose(got.cov_theta, cov, rtol=1e-9)
    for a, b in zip(got.caps, ref, strict=True):
        if b.fit is None:
            continue
        np.testing.assert_array_equal(a.fit.inliers, b.fit.inliers)
        assert a.fit.n_points == b.fit.n_points and a.fit.n_inliers == b.fit.n_inliers
        np.testing.assert_allclose(a.fit.centre, b.fit.centre, rtol=0, atol=3e-11)
        np.testing.assert_allclose(a.fit.covariance, b.fit.covariance, rtol=0,
                                   atol=1.5e-10 * np.max(np.abs(b.fit.covariance)))
        assert a.fit.rms == pytest.approx(b.fit.rms, rel=0, abs=3e-12)
        assert a.fit.form_error == pytest.approx(b.fit.form_error, rel=0, abs=2e-11)
        np.testing.assert_allclose(a.points, b.points, rtol=0, atol=1.2e-14)
        np.testing.assert_allclose(a.weights, b.weights, rtol=1e-14)
        np.testing.assert_allclose(a.dcentre_dtheta, b.dcentre_dtheta, rtol=0,
                                   atol=1.5e-10 * np.max(np.abs(b.dcentre_dtheta)))
