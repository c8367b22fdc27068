"""BGA inspection on synthetic clouds: balls, heights, pitch, missing balls, the
point-spread model, highlights, coplanarity, the spot fit."""

from __future__ import annotations

import numpy as np
import pytest
from test_metrology import bga_cloud, brute_force_coplanarity, camera_grid, cloud_from

from telefringe.metrology import (
    BGANominal,
    BGAOptions,
    MetrologyError,
    Plane,
    measure_bga,
    seating_plane_coplanarity,
)
from telefringe.reconstruction.cloud import PointCloud


# --- BGA --------------------------------------------------------------------------------
def test_bga_balls_heights_pitch_missing():
    cloud, present, offs, apex = bga_cloud()
    nom = BGANominal(rows=6, cols=7, pitch_mm=0.8, ball_diameter_mm=0.45)
    # free-radius sphere fits (no point-spread model)
    m = measure_bga(cloud, nom, options=BGAOptions(cap_model="free"))
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
    assert np.sqrt(np.mean(err**2)) < 0.75e-3  # measured 0.36 um
    assert np.allclose(m.diameter, 0.45, atol=5e-3)  # measured max error 3.9 um
    # pitch: in-plane distances of the fitted centres, nominal 0.8; a distance's
    # sigma is sqrt(2) s_xy (s_xy the centres' in-plane sigma): the largest of the 68
    # errors within 4 of those (measured 2.5), their mean within 4 standard errors
    s_d = np.sqrt(2) * np.median(m.sigma_centre[:, :2])
    assert m.pitch_error_max < 4 * s_d
    assert np.isnan(m.pitch_x[2, 2]) and np.isnan(m.pitch_x[2, 3])
    n_x = np.count_nonzero(np.isfinite(m.pitch_x))
    assert abs(np.nanmean(m.pitch_x) - 0.8) < 4 * s_d / np.sqrt(n_x)
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
    # normalised RMS of 40 errors: within 4 standard errors (4 / sqrt(2 n)) of 1
    # (measured 0.83 and 0.81; pooled over more clouds in test_bga_sigma.py)
    assert abs(np.sqrt(np.mean((err / m.sigma_height) ** 2)) - 1) < 4 / np.sqrt(2 * err.size)
    assert np.sqrt(np.mean(err**2)) < 0.4e-3  # measured 0.19 and 0.20 um
    if s2 > 0:
        plain = measure_bga(cloud, nom, options=BGAOptions(cap_model="fixed"))
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
        # (sigma_height_noise holds the common term too, so this is a little below 1:
        # measured 0.77 and 0.81; the band is 4 standard errors of 40 values). The noise
        # part only: this analytic cloud has none of the rendered caps' per-ball model
        # error that sigma_height adds with an image (sigma_height_model)
        rms = np.sqrt(np.mean((rel / m.sigma_height_noise) ** 2))
        assert abs(rms - 1) < 4 / np.sqrt(2 * rel.size), rms
        assert abs(err.mean()) < 4 * 0.011e-3 * m.sigma_psf_variance * 1e6 + 1e-4
    # the model term: with the image only, 0.023 px, and in the total
    assert np.isnan(m0.sigma_height_model)
    assert np.array_equal(m0.sigma_height, m0.sigma_height_noise)
    px = float(np.nanmedian(np.diff(cloud.x, axis=1)))
    assert m1.sigma_height_model == pytest.approx(0.023 * px, rel=0.02)
    assert np.allclose(m1.sigma_height, np.hypot(m1.sigma_height_noise, m1.sigma_height_model))
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


def test_seating_plane_of_a_rocking_package():
    """On a point-symmetric grid the centre of gravity often lies on the edge shared by
    two seating triangles (the midpoint of two balls placed symmetrically about it): the
    package may rest on either, with different coplanarities. The worst is reported, and
    all of them, whichever side of the edge a rounding error puts the centre."""
    from telefringe.simulate.scenes import default_bga

    bga = default_bga(seed=0, rows=6, cols=6, n_missing=2, centre=(15.0, 12.0))
    apex = bga.apexes_world()[bga.present()]
    flat = Plane.horizontal(0.0)
    g = np.array([15.0, 12.0])
    cop = seating_plane_coplanarity(apex, g, reference=flat)
    assert cop.rocks and cop.alternatives.size == 2  # this grid's truth rocks
    assert cop.value == cop.alternatives[0] > cop.alternatives[1] + 0.01
    # the shared edge runs from ball (0, 5) at (17, 10) to ball (4, 1) at (13.8, 13.2),
    # through the centre: a step of 10 nm across it either way decides the plane
    nv = np.array([1.0, 1.0]) / np.sqrt(2)
    sides = [seating_plane_coplanarity(apex, g + d * nv, reference=flat) for d in (1e-5, -1e-5)]
    assert not any(c.rocks for c in sides)
    assert sorted(c.value for c in sides) == pytest.approx(sorted(cop.alternatives), abs=1e-12)
    # with a tolerance wider than the step, both planes are seen from either side
    for d in (1e-5, -1e-5):
        near = seating_plane_coplanarity(apex, g + d * nv, reference=flat, cog_tolerance=2e-5)
        assert near.value == pytest.approx(cop.value, abs=1e-12)
        assert np.allclose(near.alternatives, cop.alternatives, atol=1e-12)
    # sigma: linear in the heights' sigma, and 0 without it
    s1 = seating_plane_coplanarity(apex, g, reference=flat,
                                   sigma_heights=np.full(len(apex), 1e-3)).sigma
    s2 = seating_plane_coplanarity(apex, g, reference=flat,
                                   sigma_heights=np.full(len(apex), 2e-3)).sigma
    assert 1e-3 <= s1 < 3e-3 and s2 == pytest.approx(2 * s1)
    assert np.isnan(cop.sigma)
    with pytest.raises(MetrologyError, match="cog_tolerance"):
        seating_plane_coplanarity(apex, g, reference=flat, cog_tolerance=-1.0)


def test_bga_errors():
    cloud, present, offs, apex = bga_cloud(rows=3, cols=3, missing=())
    with pytest.raises(MetrologyError, match="span"):
        measure_bga(cloud, BGANominal(rows=2, cols=2, pitch_mm=0.8, ball_diameter_mm=0.45))
    flat = cloud_from(*camera_grid((50, 50)), np.zeros((50, 50)), sigma=0.001)
    with pytest.raises(MetrologyError, match="no ball"):
        measure_bga(flat, BGANominal(rows=2, cols=2, pitch_mm=0.8, ball_diameter_mm=0.45))
    with pytest.raises(MetrologyError):
        BGANominal(rows=0, cols=2, pitch_mm=0.8, ball_diameter_mm=0.45)




def test_gauss_spots_batched_matches_scipy():
    """The batched Levenberg-Marquardt spot fit reaches the least-squares optimum that
    scipy's trust-region solver finds (same model), to far below the fit's uncertainty."""
    from scipy.optimize import least_squares
    from scipy.special import erf

    from telefringe.metrology.bga.highlights import _gauss_spots

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
