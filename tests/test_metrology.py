"""Metrology on synthetic point clouds with known truth and seeded noise: planes, and the
synthetic clouds the other metrology tests (test_metrology_*.py, test_bga*.py) share."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from telefringe.metrology import (
    MetrologyError,
    Plane,
    fit_plane,
    plane_distance,
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



# --- synthetic clouds shared by the metrology tests ------------------------------------
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


def cap_points(n, *, c=(1.0, -2.0, 0.3), r=3.0, max_polar_deg=60, sigma=0.0, seed=0):
    rng = np.random.default_rng(seed)
    cosmax = np.cos(np.radians(max_polar_deg))
    ct = rng.uniform(cosmax, 1.0, n)
    ph = rng.uniform(0, 2 * np.pi, n)
    st = np.sqrt(1 - ct**2)
    dirs = np.column_stack([st * np.cos(ph), st * np.sin(ph), ct])
    return np.asarray(c) + (r + sigma * rng.standard_normal(n))[:, None] * dirs


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


def brute_force_coplanarity(m):
    """Seating plane by enumeration: the triples whose plane has every apex below it and
    whose triangle lies within the measurement's ``cog_tolerance`` of the centre of
    gravity (the planes the package may rest on); coplanarity = the largest distance
    from any of them (the worst case, as measure_bga reports it)."""
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
        if np.any(lam < -1e-9) and min(
                _segment_distance(g[:2], q[s], q[t]) for s, t in ((a, b), (b, c), (c, a))
        ) > m.coplanarity.cog_tolerance + 1e-9:
            continue
        abc = np.linalg.solve(P, h[[a, b, c]])
        gap = q @ abc[:2] + abc[2] - h
        if np.all(gap >= -1e-9):
            val = np.max(gap) / np.sqrt(1 + abc[0] ** 2 + abc[1] ** 2)
            best = val if best is None else max(best, val)
    return best


def _segment_distance(g, a, b):
    t = b - a
    s = np.clip((g - a) @ t / (t @ t), 0.0, 1.0)
    return float(np.linalg.norm(g - a - s * t))
