"""Circle-marker plates: 3D marker centres, spacing, plane and height."""

from __future__ import annotations

import numpy as np
import pytest
from test_metrology import plate_cloud

from telefringe.metrology import MetrologyError, grid_spacing, marker_centres_3d, measure_plate


# --- circle plate -----------------------------------------------------------------------
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
    # Z at the point of the fitted plane where the distance is taken, within 4 sigma
    at = np.asarray(m.z.at)
    assert abs(m.z.distance - (0.5 + 0.002 * at[0] - 0.001 * at[1])) < 4 * m.z.sigma
    # truth spacing from the true centres. x, y are exact here; each centre's z error
    # s enters the 3D distance through the plate's slope (linear, 0.002 and 0.001) and
    # as a bias of +(sqrt(2) s)^2 / (2 pitch) = s^2 / pitch (measured errors 1.2e-7 and
    # 1.8e-7 mm, bias 1.7e-7 mm)
    gs_true = grid_spacing(truth, rows=9, cols=11, pitch_mm=0.9)
    s = float(np.median(m.centres.sigma_xyz[:, 2]))
    for mean, true, slope, n in ((m.spacing.mean_x, gs_true.mean_x, 0.002, m.spacing.n_x),
                                 (m.spacing.mean_y, gs_true.mean_y, 0.001, m.spacing.n_y)):
        bias = s**2 / 0.9
        assert abs(mean - true - bias) < 4 * np.sqrt(2) * slope * s / np.sqrt(n) + 0.5 * bias
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
