"""Sphere fits and a sphere standing on a plane."""

from __future__ import annotations

import numpy as np
import pytest
from test_metrology import camera_grid, cap_points, cloud_from

from telefringe.metrology import MetrologyError, fit_sphere, measure_sphere


# --- spheres ----------------------------------------------------------------------------
def test_sphere_exact_and_degenerate():
    p = cap_points(500)
    f = fit_sphere(p)
    assert np.allclose(f.centre, [1.0, -2.0, 0.3], atol=1e-9)
    assert f.radius == pytest.approx(3.0, abs=1e-9)
    assert f.form_error < 1e-9
    assert np.allclose(f.apex(), [1.0, -2.0, 3.3])
    with pytest.raises(MetrologyError, match="at least 4"):
        fit_sphere(p[:3])
    flat = np.column_stack([np.random.default_rng(0).uniform(size=(50, 2)), np.zeros(50)])
    with pytest.raises(MetrologyError, match="coplanar"):
        fit_sphere(flat)


def test_sphere_uncertainty_matches_monte_carlo():
    sigma, trials = 0.005, 60
    rs, sr, cz, scz = [], [], [], []
    for t in range(trials):
        f = fit_sphere(cap_points(800, sigma=sigma, seed=10 + t))
        rs.append(f.radius)
        sr.append(f.sigma_radius)
        cz.append(f.centre[2])
        scz.append(f.sigma_centre[2])
    # std of a std from 60 samples: 9 %; allow 3.5 of them
    assert np.std(rs, ddof=1) == pytest.approx(np.mean(sr), rel=0.32)
    assert np.std(cz, ddof=1) == pytest.approx(np.mean(scz), rel=0.32)
    # unbiased within 4 standard errors
    assert abs(np.mean(rs) - 3.0) < 4 * np.mean(sr) / np.sqrt(trials)


def test_sphere_fixed_radius():
    p = cap_points(30, max_polar_deg=20, sigma=0.003, seed=8)
    free = fit_sphere(p)
    fixed = fit_sphere(p, radius=3.0)
    # a 20 deg cap of 30 points hardly determines the radius; with it fixed the centre
    # is within 4 sigma
    assert free.sigma_radius > 10 * fixed.sigma_centre[2]
    assert fixed.radius == 3.0 and fixed.covariance[3, 3] == 0.0
    assert np.all(np.abs(fixed.centre - [1.0, -2.0, 0.3]) < 4 * fixed.sigma_centre + 1e-12)
    with pytest.raises(MetrologyError, match="radius"):
        fit_sphere(p, radius=-1.0)
    # robust rounds that end before agreeing still return a consistent fit
    rng = np.random.default_rng(2)
    q = cap_points(60, sigma=0.01, seed=9)
    q[rng.choice(60, 10, replace=False)] += 0.05
    f1 = fit_sphere(q, robust=True, max_rounds=1)
    assert f1.n_inliers == 60 and f1.inliers.sum() == 60


def test_sphere_robust():
    rng = np.random.default_rng(3)
    p = cap_points(2000, sigma=0.002, seed=4)
    bad = rng.choice(2000, 100, replace=False)
    p[bad] += rng.normal(0, 0.2, (100, 3))
    f = fit_sphere(p, robust=True)
    assert f.radius == pytest.approx(3.0, abs=5 * f.sigma_radius + 1e-4)
    assert not f.inliers[bad[np.linalg.norm(p[bad] - [1, -2, 0.3], axis=1) - 3 > 0.05]].any()
    assert f.rms == pytest.approx(0.002, rel=0.2)


def test_measure_sphere_on_a_plane():
    shape = (220, 260)
    x, y = camera_grid(shape, pixel=0.03, origin=(-3.9, 3.3))
    c, R = np.array([0.0, 0.0, -1.0]), 2.5
    r2 = (x - c[0]) ** 2 + (y - c[1]) ** 2
    z = np.where(r2 < R * R, c[2] + np.sqrt(np.maximum(R * R - r2, 0)), 0.0)
    z = np.maximum(z, 0.0)
    cloud = cloud_from(x, y, z, sigma=0.003, seed=7)
    sm = measure_sphere(cloud)
    f, base = sm.sphere, sm.base
    assert sm.region == "above the base plane"
    # the base is the plane Z = 0: its offset at the origin within 4 sigma (~15 nm)
    assert base is not None and abs(base.offset) < 4 * base.sigma_at([0.0, 0.0, 0.0])
    assert f.radius == pytest.approx(R, abs=5 * f.sigma_radius)
    assert np.allclose(f.centre, c, atol=5 * f.sigma_centre.max())
    # vertical noise seen radially: scaled by the normal's z component over the cap
    on = z > 0.05
    expect = 0.003 * np.sqrt(np.mean(((z[on] - c[2]) / R) ** 2))
    assert f.rms == pytest.approx(expect, rel=0.1)

