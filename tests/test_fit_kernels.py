"""The compiled fit kernels (telefringe.metrology._fit_kernels) against independent
references: the sphere fit's Levenberg-Marquardt against scipy's least squares (the
plane's kernels: tests/test_plane_kernels.py)."""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from telefringe.metrology.spheres import _sphere_geometric


def _cap(rng, n=60, r=0.225, noise=1e-3):
    """Points of a sphere cap (the top 60 deg, as a BGA ball's) with radial noise."""
    th = rng.uniform(0, np.radians(60), n)
    ph = rng.uniform(0, 2 * np.pi, n)
    c = np.array([15.0, 12.0, 0.1])
    d = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=1)
    return c + (r + rng.normal(0, noise, n))[:, None] * d, c


def test_sphere_lm_kernel_matches_scipy_least_squares():
    rng = np.random.default_rng(1)
    worst = 0.0
    for k in range(20):
        p, c = _cap(rng)
        w = rng.uniform(0.5, 2.0, p.shape[0])
        fixed = k % 2 == 0
        start = c + rng.normal(0, 0.01, 3)
        cc, r, f, J = _sphere_geometric(p, w, start, 0.225, fixed_radius=fixed)

        def res(x, p=p, w=w, fixed=fixed):
            rad = 0.225 if fixed else x[3]
            return np.sqrt(w) * (np.linalg.norm(p - x[:3], axis=1) - rad)

        x0 = start if fixed else np.r_[start, 0.225]
        ref = least_squares(res, x0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
        worst = max(worst, float(np.max(np.abs(cc - ref.x[:3]))))
        if not fixed:
            worst = max(worst, abs(r - ref.x[3]))
        # the returned residuals and weighted Jacobian belong to the solution
        np.testing.assert_allclose(f, np.linalg.norm(p - cc, axis=1) - r, atol=1e-15)
        assert J.shape == (p.shape[0], 3 if fixed else 4)
        np.testing.assert_allclose(J[:, :3], -np.sqrt(w)[:, None] * (p - cc)
                                   / np.linalg.norm(p - cc, axis=1)[:, None], atol=1e-14)
    assert worst < 1e-9  # mm (the noise is 1e-3 mm)
