"""Step gauges: parallel levels fitted jointly."""

from __future__ import annotations

import numpy as np
import pytest
from test_metrology import camera_grid, cloud_from

from telefringe.metrology import MetrologyError, measure_steps


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


def _perspective_steps(shape=(160, 240), sigma=(0.002, 0.006), seed=3):
    """A staircase seen by a pinhole camera 60 mm above it (rays fanning out by up to
    11 deg), noise along each ray with a sigma growing across the image; levels 0-2 mm
    in x strips of 2.4 mm. Returns (cloud, tops, level index of every pixel)."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    centre = np.array([6.0, 4.0, 60.0])
    # the ray of pixel (u, v) passes through the base point (0.05 u, 0.05 v, 0)
    base = np.stack([0.05 * u, 0.05 * v, np.zeros_like(u)], axis=-1)
    d = base - centre
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    tops = np.array([0.0, 0.5, 1.0, 1.5, 2.0])
    # the level under each ray: found where the ray meets the staircase (x strips)
    level = np.zeros(shape, dtype=int)
    for k in range(len(tops) - 1, -1, -1):
        t = (tops[k] - centre[2]) / d[..., 2]
        x = centre[0] + t * d[..., 0]
        hit = (np.clip((x // 2.4).astype(int), 0, 4) == k) & (level == 0)
        level[hit] = k
    t = (tops[level] - centre[2]) / d[..., 2]
    s_line = np.linspace(sigma[0], sigma[1], shape[1])[None, :] * np.ones(shape)
    t = t + s_line * rng.standard_normal(shape)
    xyz = centre + t[..., None] * d
    from telefringe.reconstruction.cloud import PointCloud

    cloud = PointCloud.from_xyz(xyz, sigma_z=s_line * np.abs(d[..., 2]), direction=d)
    return cloud, tops, level


def test_step_heights_pinhole_cloud():
    """Per-pixel viewing directions and per-pixel sigmas (a pinhole camera): each level's
    band is its points' own noise along the normal, so the heights come out within 4 sigma,
    nearly every point away from the walls is used, and no sigma at all also works."""
    cloud, tops, level = _perspective_steps()
    m = measure_steps(cloud)
    assert len(m.heights) == 5
    assert np.all(np.abs(m.heights - tops) < 4 * m.sigma_heights + 1e-12)
    assert np.all(np.abs(m.step_heights - np.diff(tops)) < 4 * m.sigma_steps)
    # a k = 4 band loses 6e-5 of a level's points; the walls cost the margin (< 4 px
    # each side of a strip about 47 px wide, plus the image border)
    for k in range(1, 4):
        strip = level == k
        assert m.n_points[k] > 0.75 * np.count_nonzero(strip)
    assert 2.0 < m.edge_px < 4.0
    # without sigmas: each level's robust spread sets its band
    bare = type(cloud).from_xyz(cloud.xyz, direction=cloud.directions)
    mb = measure_steps(bare)
    assert np.all(np.abs(mb.heights - tops) < 4 * mb.sigma_heights + 1e-12)
    assert np.all(mb.n_points[1:4] > 0.75 * np.array([np.count_nonzero(level == k)
                                                      for k in range(1, 4)]))


def test_edge_margin_from_the_footprint():
    """The margin grows with the blur and the step, shrinks with the noise; a sharp
    pixel (no blur) needs only its own half width beyond the foreign pixel's."""
    from telefringe.metrology.steps import _footprint_tail, edge_margin_px

    # the tail of the footprint: half of it beyond an edge through its centre
    assert _footprint_tail(0.0, 0.5)[0] == pytest.approx(0.5, abs=1e-12)
    assert _footprint_tail(0.0, 0.0)[0] == pytest.approx(0.5, abs=1e-12)
    assert edge_margin_px(2.0, 0.008, 0.0) == pytest.approx(1.5, abs=0.011)
    m = edge_margin_px(2.0, 0.008, 0.5)
    assert 2.5 < m < 3.5
    assert edge_margin_px(2.0, 0.008, 1.0) > m > edge_margin_px(0.5, 0.008, 0.5)
    assert edge_margin_px(2.0, 0.0008, 0.5) > m
    # at the margin, a pixel's share of the other level times the step is a tenth of
    # its noise (within the 0.01 px grid)
    assert 2.0 * _footprint_tail(m - 1.0, 0.5)[0] <= 0.1 * 0.008
    assert 2.0 * _footprint_tail(m - 1.02, 0.5)[0] > 0.1 * 0.008


def test_step_heights_smooth_in_the_calibration():
    """A calibration a little different (the projector's magnification over +-2e-4,
    which moves the steps by +-0.1 um) moves the measured steps smoothly: their
    deviation from a quadratic in the change stays below 5 % of their noise uncertainty
    (a jump of the point set, as when levels were bands around a histogram's bins, moved
    them by up to 0.7 um = 4 sigma here), and fewer than 0.1 % of the pixels change level.
    """
    from telefringe.devices.rig import Rig
    from telefringe.fringes.decode import decode
    from telefringe.reconstruction.telecentric import triangulate
    from telefringe.simulate.presets import get_preset
    from telefringe.simulate.render import default_groups, render_scan
    from telefringe.simulate.scenes import default_steps

    vrig = get_preset("fast")
    scan, _ = render_scan(vrig, default_steps(), default_groups(vrig), seed=7)
    coords = decode(scan, gamma_correction=False)
    cam, proj = vrig.rig.camera, vrig.rig.projector
    p0 = proj.to_params()
    i = proj.param_names.index("m")
    ts = np.linspace(-1.0, 1.0, 9)
    steps, labels, sig = [], [], None
    for t in ts:
        p = p0.copy()
        p[i] *= 1.0 + 2e-4 * t
        m = measure_steps(triangulate(Rig(cam, proj.from_params(p)), coords))
        steps.append(m.step_heights)
        labels.append(m.labels)
        sig = m.sigma_steps
    steps = np.array(steps)
    A = np.vander(ts, 3)
    coef = np.linalg.lstsq(A, steps, rcond=None)[0]
    assert np.all(np.ptp(steps, axis=0) > 1e-4)  # the change did move them (by ~0.2 um)
    assert np.all(np.abs(steps - A @ coef).max(axis=0) < 0.05 * sig)
    n_valid = np.count_nonzero(labels[4] >= 0)
    assert max(np.count_nonzero(lab != labels[4]) for lab in labels) < 1e-3 * n_valid


def test_step_sigma_holds_a_ripple():
    """A ripple across the levels (amplitude 3 um like the noise, period 1.3 mm on 3 mm
    levels: each level's mean keeps part of a period) is spatially correlated: the
    white-noise figure does not cover the steps' errors, the figure from the residuals'
    autocovariance does (k = 2), and stays below the largest error such a ripple can
    give a step (two levels' partial periods: 2 A P / (pi W)). With white noise alone
    the two figures agree."""
    from telefringe.metrology.steps import _joint_parallel_planes

    shape = (200, 300)
    x, y = camera_grid(shape, pixel=0.05, origin=(0.0, 10.0))
    level = np.clip((x // 3.0).astype(int), 0, 4)
    tops = np.array([0.0, 0.5, 1.0, 1.5, 2.0])
    A, P = 0.003, 1.3

    def measure(z):
        cloud = cloud_from(x, y, z, sigma=0.003, seed=9)
        m = measure_steps(cloud)
        lab = np.asarray(m.labels)
        cov = _joint_parallel_planes([cloud.xyz[lab == k] for k in range(5)], m.normal)[3]
        c = cov[2:, 2:]
        white = np.sqrt([c[k + 1, k + 1] + c[k, k] - 2 * c[k + 1, k] for k in range(4)])
        return m, m.step_heights - np.diff(tops), white

    m, err, white = measure(tops[level])
    assert np.all(m.sigma_steps <= 1.1 * white)
    m, err, white = measure(tops[level] + A * np.sin(2 * np.pi * x / P + 0.3))
    assert np.any(np.abs(err) > 3 * white)
    assert np.all(np.abs(err) <= 2 * m.sigma_steps)
    assert np.all(m.sigma_steps < 2 * A * P / (np.pi * (3.0 - 2 * m.edge_px * 0.05)))


def test_step_sigma_covers_a_ripple_over_placements():
    """A ripple whose period (1.3 level widths, nearly across the levels) is comparable
    to the levels: each level keeps most of a period, and its mean error depends on where
    the gauge sits under the ripple. Over placements spread evenly along one period (the
    ripple's phase), the steps' RMS error in units of their ``sigma_steps`` is 1 within
    the Monte Carlo goal (0.75-1.25): the autocovariance is used out to every lag the
    fit spans (the ``fast`` virtual rig's step gauge: an 8-bit projector's quantisation
    ripple, 4 fringe periods long, on 5 mm levels). A taper to the narrowest level's width
    gave 1.46 here (1.44 on the virtual rig): it cut the correlation along the levels and
    between neighbours."""
    shape = (200, 360)
    x, y = camera_grid(shape, pixel=0.05, origin=(0.0, 10.0))
    W, P, A = 2.5, 3.25, 0.002
    # a base plate all round 4 blocks 2.5 mm wide and 8 mm long (the ripple's statistics
    # come mostly from the base, as on a real gauge)
    level = np.where((x >= 4) & (x < 4 + 4 * W) & (y > 1) & (y < 9),
                     ((x - 4) // W).astype(int) + 1, 0)
    tops = np.array([0.0, 0.5, 1.0, 1.5, 2.0])
    th = np.radians(5.0)
    z_scores = []
    for i in range(12):
        phase = 2 * np.pi * (i + 0.5) / 12
        ripple = A * np.sin(2 * np.pi * (x * np.cos(th) + y * np.sin(th)) / P + phase)
        m = measure_steps(cloud_from(x, y, tops[level] + ripple, sigma=0.003, seed=100 + i))
        z_scores.append((m.step_heights - np.diff(tops)) / m.sigma_steps)
    rms_z = float(np.sqrt(np.mean(np.square(z_scores))))
    assert 0.75 <= rms_z <= 1.25, rms_z
