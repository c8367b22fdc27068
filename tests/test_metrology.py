"""Metrology on synthetic point clouds with known truth and seeded noise."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from telefringe.metrology.core import (
    BGANominal,
    MetrologyError,
    Plane,
    fit_plane,
    fit_sphere,
    grid_spacing,
    marker_centres_3d,
    measure_bga,
    measure_plate,
    measure_sphere,
    measure_steps,
    plane_distance,
    seating_plane_coplanarity,
)
from telefringe.reconstruction.cloud import PointCloud


def camera_grid(shape, *, pixel=0.0325, origin=(0.0, 0.0), angle_deg=0.0):
    """World x, y of a telecentric camera looking straight down (rows run toward -y)."""
    v, u = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    a = np.radians(angle_deg)
    x = origin[0] + pixel * (np.cos(a) * u + np.sin(a) * v)
    y = origin[1] + pixel * (np.sin(a) * u - np.cos(a) * v)
    return x, y


def cloud_from(x, y, z, *, sigma=0.0, seed=0):
    rng = np.random.default_rng(seed)
    zn = z + sigma * rng.standard_normal(z.shape)
    xyz = np.stack([x, y, zn], axis=-1)
    return PointCloud.from_xyz(xyz, sigma_z=np.full(z.shape, sigma) if sigma > 0 else None)


# --- planes -----------------------------------------------------------------------------
def tilted(x, y, a=0.02, b=-0.01, c=0.5):
    return a * x + b * y + c


def test_plane_exact_and_degenerate():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-5, 5, (100, 2))
    p = np.column_stack([xy, tilted(xy[:, 0], xy[:, 1])])
    f = fit_plane(p)
    n_true = np.array([-0.02, 0.01, 1.0]) / np.linalg.norm([-0.02, 0.01, 1.0])
    assert np.allclose(f.normal, n_true, atol=1e-12)
    assert f.offset == pytest.approx(0.5 * n_true[2], abs=1e-12)
    assert f.rms < 1e-12 and f.flatness < 1e-12
    assert np.allclose(f.z_at(xy[:, 0], xy[:, 1]), p[:, 2])
    # normal toward the camera whatever the order of the points
    assert fit_plane(p[::-1]).normal[2] > 0
    with pytest.raises(MetrologyError, match="at least 3"):
        fit_plane(p[:2])
    line = np.column_stack([np.arange(10.0), 2 * np.arange(10.0), np.zeros(10)])
    with pytest.raises(MetrologyError, match="collinear"):
        fit_plane(line)
    with pytest.raises(MetrologyError, match="collinear"):
        fit_plane(line, robust=True)
    with pytest.raises(MetrologyError, match="shape"):
        fit_plane(np.zeros((4, 2)))
    assert issubclass(MetrologyError, ValueError)


def test_plane_uncertainty_matches_monte_carlo():
    rng = np.random.default_rng(1)
    sigma, n, trials = 0.003, 400, 300
    xy = rng.uniform(-4, 4, (n, 2))
    offs, sig_off, tilts, covs = [], [], [], []
    n_true = np.array([-0.02, 0.01, 1.0]) / np.linalg.norm([-0.02, 0.01, 1.0])
    for _ in range(trials):
        z = tilted(xy[:, 0], xy[:, 1]) + sigma * rng.standard_normal(n)
        f = fit_plane(np.column_stack([xy, z]))
        # position of the fitted plane along the true normal at the (fixed) true centroid
        c0 = np.array([*xy.mean(axis=0), tilted(*xy.mean(axis=0))])
        offs.append(f.distance(c0[None])[0])
        sig_off.append(f.sigma_at(c0))
        tilts.append(f.tangent @ (f.normal - n_true))
        covs.append(f.tilt_covariance)
    # relative standard error of a std from 300 samples: 4 %; allow 4 of them
    assert np.std(offs, ddof=1) == pytest.approx(np.mean(sig_off), rel=0.16)
    emp = np.cov(np.array(tilts).T)
    pred = np.mean(covs, axis=0)
    assert np.sqrt(emp[0, 0]) == pytest.approx(np.sqrt(pred[0, 0]), rel=0.16)
    assert np.sqrt(emp[1, 1]) == pytest.approx(np.sqrt(pred[1, 1]), rel=0.16)
    # flatness and rms of a noisy plane: rms ~ sigma
    assert f.rms == pytest.approx(sigma, rel=0.15)


def test_robust_plane_ignores_outliers():
    rng = np.random.default_rng(2)
    sigma = 0.002
    xy = rng.uniform(-5, 5, (5000, 2))
    z = tilted(xy[:, 0], xy[:, 1]) + sigma * rng.standard_normal(5000)
    out = rng.random(5000) < 0.35  # 35 % of points on bumps 0.05-0.4 mm high
    z[out] += rng.uniform(0.05, 0.4, out.sum())
    p = np.column_stack([xy, z])
    f = fit_plane(p, robust=True, seed=3)
    ls = fit_plane(p)
    c = np.array([0.0, 0.0, 0.5])
    # the robust plane is within 5 sigma of the truth; least squares is pulled up
    n_true = np.array([-0.02, 0.01, 1.0]) / np.linalg.norm([-0.02, 0.01, 1.0])
    true_off = n_true @ c
    assert abs(f.distance(c[None])[0]) < 5 * f.sigma_at(c) + 1e-12
    assert abs(ls.offset - true_off) > 0.05
    assert np.all(~f.inliers[out & (z - tilted(xy[:, 0], xy[:, 1]) > 0.02)])
    assert f.n_inliers > 0.6 * 5000
    assert f.rms == pytest.approx(sigma, rel=0.15)
    # deterministic
    f2 = fit_plane(p, robust=True, seed=3)
    assert f2.offset == f.offset


def test_plane_distance():
    a = fit_plane(np.array([[0, 0, 0.5], [1, 0, 0.5], [0, 1, 0.5], [1, 1, 0.5]], float))
    d = plane_distance(a, Plane.horizontal(0.0))
    assert d.distance == pytest.approx(0.5) and d.angle_deg == pytest.approx(0.0, abs=1e-6)
    d = plane_distance(Plane.horizontal(-1.0), Plane.horizontal(0.0))
    assert d.distance == pytest.approx(-1.0) and d.sigma == 0.0
    tilt = Plane(np.array([0.0, np.sin(0.01), np.cos(0.01)]), 0.0)
    d = plane_distance(tilt, Plane.horizontal(0.0), at=(0.0, 10.0, 0.0))
    assert d.distance == pytest.approx(-np.tan(0.01) * 10.0, rel=1e-3)
    assert d.angle_deg == pytest.approx(np.degrees(0.01))


# --- circle plate -----------------------------------------------------------------------
def plate_cloud(*, z0=0.5, sigma=0.0, seed=0, shape=(300, 400), pitch_px=30.0, rows=9,
                cols=11, marker_r_px=7.5):
    """A plate seen by a slightly distorted camera: the world position of a pixel is a
    quadratic function of (u, v); z on a tilted plane. Markers (circles) at a regular
    pixel grid are masked out (dark markers decode poorly)."""
    v, u = np.mgrid[0:shape[0], 0:shape[1]].astype(float)

    def world(u, v):
        x = 0.03 * u + 1e-4 * v + 2e-7 * (u - 200) ** 2
        y = -0.03 * v + 5e-5 * u + 1e-7 * (u - 200) * (v - 150)
        return x, y, z0 + 0.002 * x - 0.001 * y

    x, y, z = world(u, v)
    rng = np.random.default_rng(seed)
    z = z + sigma * rng.standard_normal(z.shape)
    cu = 50 + pitch_px * np.arange(cols)
    cv = 30 + pitch_px * np.arange(rows)
    centres = np.array([(a, b) for b in cv[::-1] for a in cu])  # row 0 at the bottom
    inside = np.zeros(shape, bool)
    for a, b in centres:
        inside |= (u - a) ** 2 + (v - b) ** 2 < marker_r_px**2
    xyz = np.stack([x, y, z], axis=-1)
    xyz[inside] = np.nan
    cloud = PointCloud.from_xyz(xyz, sigma_z=np.full(shape, sigma) if sigma else None)
    truth = np.stack(world(centres[:, 0], centres[:, 1]), axis=-1)
    return cloud, centres, truth


def test_marker_centres_exact_without_noise():
    cloud, centres, truth = plate_cloud()
    mc = marker_centres_3d(cloud, centres)
    assert mc.valid.all()
    assert np.max(np.abs(mc.xyz - truth)) < 1e-9
    # a missing centre stays missing
    c2 = centres.copy()
    c2[5] = np.nan
    mc2 = marker_centres_3d(cloud, c2)
    assert not mc2.valid[5] and np.isnan(mc2.xyz[5]).all() and mc2.valid.sum() == 98


def test_marker_centres_with_noise_within_their_sigma():
    sigma = 0.004
    cloud, centres, truth = plate_cloud(sigma=sigma, seed=4)
    mc = marker_centres_3d(cloud, centres)
    err = (mc.xyz - truth)[:, 2] / mc.sigma_xyz[:, 2]
    # normalised errors: standard normal (99 markers): RMS within 30 %, none beyond 4.5
    assert np.sqrt(np.mean(err**2)) == pytest.approx(1.0, abs=0.3)
    assert np.max(np.abs(err)) < 4.5
    # an affine fit's value at the annulus' centre is the points' mean: sigma / sqrt(n);
    # the quadratic's extrapolation into the hole costs more
    m1 = marker_centres_3d(cloud, centres, degree=1)
    assert np.allclose(m1.sigma_xyz[:, 2], sigma / np.sqrt(m1.n_points), rtol=0.15)
    assert np.all(mc.sigma_xyz[:, 2] > m1.sigma_xyz[:, 2])


def test_marker_centre_pixel_error_propagates():
    cloud, centres, truth = plate_cloud()
    rng = np.random.default_rng(11)
    s_px = 0.05
    noisy = centres + s_px * rng.standard_normal(centres.shape)
    mc = marker_centres_3d(cloud, noisy, sigma_px=s_px)
    err = (mc.xyz - truth)[:, :2] / mc.sigma_xyz[:, :2]
    # 99 markers: the RMS of standard normal errors lies within 0.75..1.25 (4 sigma)
    assert np.all(np.abs(np.sqrt(np.mean(err**2, axis=0)) - 1.0) < 0.25)
    # about 0.03 mm per px here
    assert np.allclose(mc.sigma_xyz[:, 0], s_px * 0.03, rtol=0.05)


def test_grid_spacing_and_plate():
    cloud, centres, truth = plate_cloud(sigma=0.002, seed=5)
    pitch_mm = np.linalg.norm(truth[1] - truth[0])
    m = measure_plate(cloud, centres, rows=9, cols=11, pitch_mm=0.9)
    assert m.spacing.n_x == 90 and m.spacing.n_y == 88
    assert m.z.distance == pytest.approx(0.5 + 0.002 * 6 - 0.001 * -4.5, abs=0.01)
    # truth spacing from the true centres
    gs_true = grid_spacing(truth, rows=9, cols=11, pitch_mm=0.9)
    assert m.spacing.mean_x == pytest.approx(gs_true.mean_x, abs=5e-4)
    assert m.spacing.mean_y == pytest.approx(gs_true.mean_y, abs=5e-4)
    assert m.spacing.abs_err_x == pytest.approx(abs(m.spacing.mean_x - 0.9))
    assert pitch_mm == pytest.approx(gs_true.dist_x[0, 0])
    with pytest.raises(MetrologyError, match="shape"):
        measure_plate(cloud, centres[:-1], rows=9, cols=11, pitch_mm=3.0)


def test_grid_spacing_statistics():
    rng = np.random.default_rng(6)
    i, j = np.mgrid[0:9, 0:11]
    c = np.stack([3.0 * j, 3.0 * i, np.zeros_like(i, float)], axis=-1).astype(float)
    c[..., :2] += 0.002 * rng.standard_normal(c[..., :2].shape)
    c[4, 5] = np.nan
    gs = grid_spacing(c.reshape(-1, 3), rows=9, cols=11, pitch_mm=3.0)
    assert gs.n_x == 90 - 2 and gs.n_y == 88 - 2
    dx = np.linalg.norm(np.diff(c, axis=1), axis=2)
    assert gs.mean_x == pytest.approx(np.nanmean(dx))
    assert gs.std_x == pytest.approx(np.nanstd(dx, ddof=1))
    # x-distances of independent centre errors: std ~ sqrt(2) * 0.002
    assert gs.std_x == pytest.approx(np.sqrt(2) * 0.002, rel=0.3)
    with pytest.raises(MetrologyError):
        grid_spacing(np.full((99, 3), np.nan), rows=9, cols=11, pitch_mm=3.0)


# --- spheres ----------------------------------------------------------------------------
def cap_points(n, *, c=(1.0, -2.0, 0.3), r=3.0, max_polar_deg=60, sigma=0.0, seed=0):
    rng = np.random.default_rng(seed)
    cosmax = np.cos(np.radians(max_polar_deg))
    ct = rng.uniform(cosmax, 1.0, n)
    ph = rng.uniform(0, 2 * np.pi, n)
    st = np.sqrt(1 - ct**2)
    dirs = np.column_stack([st * np.cos(ph), st * np.sin(ph), ct])
    return np.asarray(c) + (r + sigma * rng.standard_normal(n))[:, None] * dirs


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
    f, base = measure_sphere(cloud)
    assert base is not None and abs(base.offset) < 1e-3
    assert f.radius == pytest.approx(R, abs=5 * f.sigma_radius)
    assert np.allclose(f.centre, c, atol=5 * f.sigma_centre.max())
    # vertical noise seen radially: scaled by the normal's z component over the cap
    on = z > 0.05
    expect = 0.003 * np.sqrt(np.mean(((z[on] - c[2]) / R) ** 2))
    assert f.rms == pytest.approx(expect, rel=0.1)


# --- BGA --------------------------------------------------------------------------------
def bga_cloud(*, rows=6, cols=7, pitch=0.8, D=0.45, h0=0.35, sigma=0.002, seed=0,
              missing=((2, 3), (0, 0)), angle_deg=3.0, tilt=(0.003, -0.002), psf_s2=0.0):
    """A BGA seen straight down; ``psf_s2`` (mm^2) lowers each ball point by the
    first-order effect of a camera point spread of that variance, s^2 lap(z) / 2."""
    rng = np.random.default_rng(seed)
    offs = rng.normal(0, 0.01, (rows, cols))
    offs[min(4, rows - 1), min(5, cols - 1)] = 0.03  # a high ball
    R = D / 2
    a = np.radians(angle_deg)
    ex = np.array([np.cos(a), np.sin(a)])
    ey = np.array([-np.sin(a), np.cos(a)])
    origin = np.array([0.3, 0.2])
    span = pitch * max(rows, cols) + 1.0
    n_px = int(span / 0.0325)
    x, y = camera_grid((n_px, n_px), pixel=0.0325, origin=(-0.6, span - 0.6))

    def sub(x, y):
        return tilt[0] * x + tilt[1] * y

    # nearest grid position of each pixel
    rel = np.stack([x - origin[0], y - origin[1]], axis=-1)
    jj = np.clip(np.round(rel @ ex / pitch).astype(int), 0, cols - 1)
    ii = np.clip(np.round(rel @ ey / pitch).astype(int), 0, rows - 1)
    bx = origin[0] + pitch * (jj * ex[0] + ii * ey[0])
    by = origin[1] + pitch * (jj * ex[1] + ii * ey[1])
    apex_h = h0 + offs[ii, jj]
    cz = sub(bx, by) + apex_h - R  # sphere centre (vertical offset from the substrate)
    r2 = (x - bx) ** 2 + (y - by) ** 2
    present = np.ones((rows, cols), bool)
    for m in missing:
        present[m] = False
    ball = present[ii, jj] & (r2 < R * R)
    zb = cz + np.sqrt(np.maximum(R * R - r2, 0.0))
    rho2 = np.minimum(r2, (R * np.sin(np.radians(80.0))) ** 2)
    zb = zb - psf_s2 * (2 * R * R - rho2) / (2 * (R * R - rho2) ** 1.5)
    z = np.where(ball, np.maximum(zb, sub(x, y)), sub(x, y))
    cloud = cloud_from(x, y, z, sigma=sigma, seed=seed + 1)
    i, j = np.mgrid[0:rows, 0:cols]
    cx = origin[0] + pitch * (j * ex[0] + i * ey[0])
    cyy = origin[1] + pitch * (j * ex[1] + i * ey[1])
    apex = np.stack([cx, cyy, sub(cx, cyy) + h0 + offs], axis=-1)  # vertical apex approx
    return cloud, present, offs, apex


def test_bga_balls_heights_pitch_missing():
    cloud, present, offs, apex = bga_cloud()
    nom = BGANominal(rows=6, cols=7, pitch_mm=0.8, ball_diameter_mm=0.45)
    # free-radius sphere fits (no point-spread model)
    m = measure_bga(cloud, nom, psf_model=False)
    assert m.n_balls == present.sum()
    assert set(m.missing) == {(2, 3), (0, 0)}
    assert m.unexpected == ()
    assert np.array_equal(m.found, present)
    assert m.grid_angle_deg == pytest.approx(3.0, abs=0.05)
    # apex heights above the (tilted) substrate: the truth is h0 + offset measured along
    # the vertical; along the substrate normal it differs by < 1e-5 mm for these tilts
    true_h = (0.35 + offs)[present]
    err = m.height - true_h
    assert np.all(np.abs(err) < 4 * m.sigma_height + 2e-5)
    assert np.sqrt(np.mean(err**2)) < 1e-3
    assert np.allclose(m.diameter, 0.45, atol=5e-3)
    # pitch: in-plane distances of the fitted centres, nominal 0.8
    assert m.pitch_error_max < 2e-3
    assert np.isnan(m.pitch_x[2, 2]) and np.isnan(m.pitch_x[2, 3])
    assert np.nanmean(m.pitch_x) == pytest.approx(0.8, abs=5e-4)
    # coplanarity against a brute-force seating plane on the measured apexes
    cop = m.coplanarity
    assert cop.value == pytest.approx(brute_force_coplanarity(m), abs=1e-9)
    # the package rests on the high ball: the lowest apexes are > 0.03 mm below
    assert cop.value > 0.03
    assert len(cop.contacts) >= 3


@pytest.mark.parametrize("s2", [0.0, 4e-4])
def test_bga_point_spread_model(s2):
    """Caps lowered by a point spread of variance s2 (mm^2, ~0.6 px of 32.5 um): the
    model recovers s2 within its uncertainty and the apex heights within theirs; without
    the model the apexes come out low by about s2 / R (1.8 um here)."""
    cloud, present, offs, apex = bga_cloud(psf_s2=s2, seed=4)
    nom = BGANominal(rows=6, cols=7, pitch_mm=0.8, ball_diameter_mm=0.45)
    m = measure_bga(cloud, nom)
    assert np.all(np.isnan(m.diameter))  # the nominal radius was used
    assert 0 < m.sigma_psf_variance < 5e-5
    assert abs(m.psf_variance - s2) < 4 * m.sigma_psf_variance
    err = m.height - (0.35 + offs)[present]
    assert np.sqrt(np.mean((err / m.sigma_height) ** 2)) < 1.5
    assert np.sqrt(np.mean(err**2)) < 0.6e-3
    if s2 > 0:
        plain = measure_bga(cloud, nom, psf_model=False, fixed_radius=True)
        bias = np.mean(plain.height - (0.35 + offs)[present])
        assert bias < -0.5 * s2 / 0.225


def test_bga_centres_from_highlights():
    cloud, present, offs, apex = bga_cloud(sigma=0.004, seed=3)
    # an image with one specular spot per ball, at the same offset from every centre
    x, y = cloud.x, cloud.y
    xs, ys = np.nan_to_num(x), np.nan_to_num(y)
    img = np.full(cloud.shape, 10.0)
    for a in apex[present]:
        img += 200.0 * np.exp(-((xs - a[0] - 0.04) ** 2 + (ys - a[1] + 0.03) ** 2)
                              / (2 * 0.025**2))
    img += np.random.default_rng(4).normal(0, 0.5, img.shape)
    nom = BGANominal(rows=6, cols=7, pitch_mm=0.8, ball_diameter_mm=0.45)
    m0 = measure_bga(cloud, nom)
    m1 = measure_bga(cloud, nom, image=img)
    assert m1.refined.all() and not m0.refined.any()
    assert np.array_equal(m0.index, m1.index)
    true_xy = apex[present][:, :2]

    def spread(m):
        e = m.centre[:, :2] - true_xy
        return (e - e.mean(axis=0)).std(axis=0)

    # relative positions: the highlight beats the noisy cap fit several times over and
    # agrees with its own uncertainty
    assert np.all(spread(m1) < spread(m0) / 3)
    assert np.all(spread(m1) < 3 * np.median(m1.sigma_centre[:, :2], axis=0))
    assert m1.pitch_error_max < m0.pitch_error_max
    # heights: with the image the cap points at the highlight are left out and the
    # centre is held on the highlight's camera line; both agree with the truth within
    # their uncertainties, ball to ball; the estimated point-spread variance (+-25 um^2
    # here) moves all of them together by ~0.011 um per um^2: their mean within 4 sigma
    for m in (m0, m1):
        err = m.height - (0.35 + offs)[present]
        rel = err - err.mean()
        assert np.sqrt(np.mean((rel / m.sigma_height) ** 2)) < 1.5
        assert abs(err.mean()) < 4 * 0.011e-3 * m.sigma_psf_variance * 1e6 + 1e-4
    with pytest.raises(MetrologyError, match="shape"):
        measure_bga(cloud, nom, image=img[:-1])


def test_bga_small_balls():
    """Balls 7 pixels wide (a binned camera): the nominal radius steps in, no erosion."""
    cloud, present, offs, apex = bga_cloud(sigma=0.004, seed=5)
    # resample the synthetic scene at a coarser pixel: every second pixel
    xyz = cloud.xyz[::2, ::2]
    small = PointCloud.from_xyz(xyz, sigma_z=np.full(xyz.shape[:2], 0.004))
    nom = BGANominal(rows=6, cols=7, pitch_mm=0.8, ball_diameter_mm=0.45)
    m = measure_bga(small, nom)
    assert np.array_equal(m.found, present)
    e = m.height - (0.35 + offs)[present]
    assert np.all(np.abs(e) < 4 * m.sigma_height + 1e-4)


def test_bga_grid_from_the_balls():
    cloud, present, offs, apex = bga_cloud(missing=((2, 3),))
    m = measure_bga(cloud, BGANominal(rows=None, cols=None, pitch_mm=0.8,
                                      ball_diameter_mm=0.45))
    assert (m.nominal.rows, m.nominal.cols) == (6, 7)
    assert m.missing == ((2, 3),) and m.n_balls == 41
    with pytest.raises(MetrologyError, match="both"):
        BGANominal(rows=3, cols=None, pitch_mm=0.8, ball_diameter_mm=0.45)


def brute_force_coplanarity(m):
    """Seating plane by enumeration: the triple whose plane has every apex below it and
    whose triangle contains the centre of gravity; coplanarity = max distance."""
    sub = m.substrate
    T = np.stack([sub.tangent[0], sub.tangent[1]])
    q = m.apex @ T.T
    h = m.apex @ sub.normal - sub.offset
    nom = m.nominal
    # centre of gravity: centre of the nominal grid, from the registered positions
    ij = m.index
    A = np.column_stack([ij[:, 1], ij[:, 0], np.ones(len(ij))])
    # fit the affine map grid index -> q from the measured centres
    qc = m.centre @ T.T
    coef, *_ = np.linalg.lstsq(A, qc, rcond=None)
    g = np.array([(nom.cols - 1) / 2, (nom.rows - 1) / 2, 1.0]) @ coef
    best = None
    for a, b, c in itertools.combinations(range(len(h)), 3):
        P = np.array([[*q[a], 1.0], [*q[b], 1.0], [*q[c], 1.0]])
        if abs(np.linalg.det(P)) < 1e-12:
            continue
        # barycentric test of g in triangle (a, b, c)
        lam = np.linalg.solve(P.T, np.array([g[0], g[1], 1.0]))
        if np.any(lam < -1e-9):
            continue
        abc = np.linalg.solve(P, h[[a, b, c]])
        gap = q @ abc[:2] + abc[2] - h
        if np.all(gap >= -1e-9):
            val = np.max(gap) / np.sqrt(1 + abc[0] ** 2 + abc[1] ** 2)
            best = val if best is None else min(best, val)
    return best


def test_seating_plane_simple_cases():
    # four corners and a centre ball: all at 0.3 except one corner at 0.33 (highest)
    apex = np.array([[0, 0, 0.30], [1, 0, 0.30], [0, 1, 0.30], [1, 1, 0.33], [0.5, 0.5, 0.28]])
    cop = seating_plane_coplanarity(apex, (0.5, 0.5), reference=Plane.horizontal(0.0))
    # the package rocks onto the high corner: the seating plane passes through (1,1,.33)
    # and two adjacent corners; the opposite corner and the centre are below it
    assert 3 in cop.contacts
    assert cop.value > 0.02
    flat = apex.copy()
    flat[:, 2] = 0.3
    cop = seating_plane_coplanarity(flat, (0.5, 0.5), reference=Plane.horizontal(0.0))
    assert cop.value == pytest.approx(0.0, abs=1e-12)
    assert np.allclose(cop.normal, [0, 0, 1]) and cop.offset == pytest.approx(0.3)
    with pytest.raises(MetrologyError, match="centre of gravity"):
        seating_plane_coplanarity(apex, (5.0, 5.0), reference=Plane.horizontal(0.0))
    with pytest.raises(MetrologyError):
        seating_plane_coplanarity(apex[:2], (0.5, 0.5), reference=Plane.horizontal(0.0))


def test_bga_errors():
    cloud, present, offs, apex = bga_cloud(rows=3, cols=3, missing=())
    with pytest.raises(MetrologyError, match="span"):
        measure_bga(cloud, BGANominal(rows=2, cols=2, pitch_mm=0.8, ball_diameter_mm=0.45))
    flat = cloud_from(*camera_grid((50, 50)), np.zeros((50, 50)), sigma=0.001)
    with pytest.raises(MetrologyError, match="no ball"):
        measure_bga(flat, BGANominal(rows=2, cols=2, pitch_mm=0.8, ball_diameter_mm=0.45))
    with pytest.raises(MetrologyError):
        BGANominal(rows=0, cols=2, pitch_mm=0.8, ball_diameter_mm=0.45)


# --- steps ------------------------------------------------------------------------------
def test_step_heights():
    shape = (200, 300)
    x, y = camera_grid(shape, pixel=0.05, origin=(0.0, 10.0))
    level = np.clip((x // 3.0).astype(int), 0, 4)
    tops = np.array([0.0, 0.5, 1.0, 1.5, 2.0])
    tilt = 0.004 * x - 0.002 * y
    z = tops[level] + tilt
    sigma = 0.003
    cloud = cloud_from(x, y, z, sigma=sigma, seed=9)
    m = measure_steps(cloud)
    assert len(m.heights) == 5
    n_true = np.array([-0.004, 0.002, 1.0]) / np.linalg.norm([-0.004, 0.002, 1.0])
    true_h = tops * n_true[2]
    assert np.all(np.abs(m.heights - true_h) < 4 * m.sigma_heights + 1e-12)
    assert np.all(np.abs(m.step_heights - np.diff(true_h)) < 4 * m.sigma_steps)
    assert np.all(m.sigma_steps < 1e-3) and np.all(m.sigma_steps > 0)
    assert np.allclose(m.rms, sigma, rtol=0.2)
    assert np.allclose(m.normal, n_true, atol=1e-4)
    assert set(np.unique(m.labels)) == {-1, 0, 1, 2, 3, 4}
    flat = cloud_from(x, y, tilt, sigma=sigma)
    with pytest.raises(MetrologyError, match="no step"):
        measure_steps(flat)


def test_gauss_spots_batched_matches_scipy():
    """The batched Levenberg-Marquardt spot fit reaches the least-squares optimum that
    scipy's trust-region solver finds (same model), to far below the fit's uncertainty."""
    from scipy.optimize import least_squares
    from scipy.special import erf

    from telefringe.metrology.core import _gauss_spots

    rng = np.random.default_rng(7)
    vv, uu = np.mgrid[0:7, 0:7].astype(float)

    def model(p):
        a, x, y, sg, b = p
        s2 = np.sqrt(2.0) * sg
        ex = 0.5 * (erf((uu + 0.5 - x) / s2) - erf((uu - 0.5 - x) / s2))
        ey = 0.5 * (erf((vv + 0.5 - y) / s2) - erf((vv - 0.5 - y) / s2))
        return a * ex * ey + b

    truth = [(400.0, 3.2, 2.7, 0.9, 20.0), (150.0, 2.6, 3.4, 1.2, 5.0),
             (800.0, 3.0, 3.0, 0.6, 50.0), (60.0, 3.45, 2.55, 1.0, 10.0)]
    wins = np.stack([model(t) + rng.normal(0, 1.0, (7, 7)) for t in truth])
    got = _gauss_spots(wins, 3.0, 3.0)
    for w, g in zip(wins, got, strict=True):
        b0 = w.min()
        p0 = [(w.max() - b0) * 2 * np.pi * 0.49, 3.0, 3.0, 0.7, b0]
        ref = least_squares(lambda p, w=w: (model(p) - w).ravel(), p0, xtol=1e-14,
                            ftol=1e-14, gtol=1e-14,
                            bounds=([0, -1, -1, 0.2, -np.inf], [np.inf, 7, 7, 2.8, np.inf]))
        assert g is not None
        x, y, cov, sg = g
        assert abs(x - ref.x[1]) < 1e-6 and abs(y - ref.x[2]) < 1e-6
        assert abs(sg - ref.x[3]) < 1e-6
        assert np.all(np.sqrt(np.diag(cov)) > 1e-4)  # the uncertainty it reports
    # a flat window has no spot
    assert _gauss_spots(rng.normal(10, 1, (1, 7, 7)), 3.0, 3.0) == [None]
