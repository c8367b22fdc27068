"""End to end on the virtual rig with the TRUE rig: render -> decode -> triangulate ->
measure, against the simulator's ground truth.

Tolerances: the per-point uncertainty must explain the per-point errors (normalised RMS
near 1) where the surface is smooth; fitted quantities are compared with their own
standard uncertainties (k = 4). Where the physics of the rig biases a quantity beyond
its noise (camera blur over a shading gradient shifts the centres of shiny or curved
objects, partial shadows near walls), the allowance is stated with the figure measured.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import telefringe.fringes.decode as decode_module
import telefringe.fringes.nonlinearity as nl
import telefringe.simulate.render as sim
from telefringe.devices.rig import Rig
from telefringe.devices.telecentric import TelecentricDevice
from telefringe.fringes.decode import decode
from telefringe.fringes.images import fringe_free_image, scan_radiance
from telefringe.metrology import (
    BGANominal,
    Plane,
    measure_bga,
    measure_plate,
    measure_sphere,
    measure_steps,
    seating_plane_coplanarity,
)
from telefringe.reconstruction.telecentric import triangulate
from telefringe.simulate import scenes
from telefringe.simulate.presets import HDR_EXPOSURES, get_preset
from telefringe.targets.circle_grid import detect_circle_grid

K = 4.0


def _run(vrig, scene, *, seed=1, exposures=(1.0,), with_coords=False, **decode_options):
    scan, truth = sim.render_scan(vrig, scene, sim.default_groups(vrig), seed=seed,
                                  exposures=exposures)
    coords = decode(scan, **decode_options)
    cloud = triangulate(vrig.rig, coords)
    return (scan, truth, cloud, coords) if with_coords else (scan, truth, cloud)


@pytest.fixture(scope="module")
def fast():
    return get_preset("fast")


@pytest.fixture(scope="module")
def plate(fast, rig_noise):
    # decoded with the rig's own camera noise, so that sigma can be held to the errors
    return _run(fast, scenes.plate_at_z(0.5), noise=rig_noise(fast))


def test_plate_points_errors_match_their_sigma(plate, fast):
    scan, truth, cloud = plate
    err = cloud.z - truth.xyz_world[..., 2]
    # away from the markers (dark discs: edges mix phases) the surface is smooth
    v, u = np.mgrid[0:cloud.shape[0], 0:cloud.shape[1]]
    k = fast.camera.intrinsics
    r_px = 0.5 * truth.features["diameter_mm"] * k.m / k.du
    far = np.ones(cloud.shape, bool)
    for cu, cv in truth.features["circle_centres_px"]:
        far &= (u - cu) ** 2 + (v - cv) ** 2 > (r_px + 3) ** 2
    # and inside the grid's outer markers: within ~5 px of the plate's own edge (3 mm
    # beyond the outer centres) the blur mixes the plate with the unlit floor, and errors
    # there reach 2x sigma (rms(z) 2.1 beyond 12 px from every marker; not flagged)
    from matplotlib.path import Path

    g = truth.features["circle_centres_px"].reshape(9, 11, 2)
    corners = Path(np.array([g[0, 0], g[0, -1], g[-1, -1], g[-1, 0]]))
    inside = corners.contains_points(np.stack([u.ravel(), v.ravel()], 1)).reshape(u.shape)
    ok = far & inside & np.isfinite(err)
    assert ok.sum() > 0.25 * cloud.mask.size
    z = err[ok] / cloud.sigma_z[ok]
    # measured rms(z) = 1.004, 1.018, 1.014 (seeds 1 (this one), 2, 3); n = 23254 pixels:
    # sampling error 1 / sqrt(2 n) = 0.46 %, 4 of them, plus 1 % for the model (first-order
    # propagation, the correction's noise factor). With the default noise model instead of
    # the rig's it is 0.85: sigma is only as good as the noise model it is given.
    rms = np.sqrt(np.mean(z**2))
    assert abs(rms - 1) < 4 / np.sqrt(2 * ok.sum()) + 0.01, rms
    assert abs(np.mean(err[ok])) < K * np.sqrt(np.mean(cloud.sigma_z[ok] ** 2) / ok.sum())
    # nearly every lit pixel is valid
    assert cloud.mask[truth.lit].mean() > 0.98


def test_plate_height_and_marker_spacing(plate):
    scan, truth, cloud = plate
    det = detect_circle_grid(fringe_free_image(scan), rows=9, cols=11)
    assert det, det.reason
    m = measure_plate(cloud, det.centers, rows=9, cols=11, pitch_mm=3.0)
    # Z of the plate against the fit's own sigma (~0.032 um): measured 0.009, 0.066,
    # 0.015 um (0.3, 2.0, 0.5 sigma; seeds 1-3)
    assert abs(m.z.distance - 0.5) < K * m.z.sigma
    # its tilt: measured 2.4-2.9e-5 rad (0.7 um over the 30 mm plate, seeds 1-3), several
    # times the fit's sigma: allow 5e-5 rad (< 2x)
    assert np.radians(m.z.angle_deg) < 5e-5
    sp = m.spacing
    assert sp.n_x == 90 and sp.n_y == 88
    # the mean distance is exact to its standard error; fast rig: ~1.5 um std
    assert sp.abs_err_x < K * sp.std_x / np.sqrt(sp.n_x)
    assert sp.abs_err_y < K * sp.std_y / np.sqrt(sp.n_y)
    # (measured std 0.90-1.02 um over seeds 1-3: bound 2x)
    assert sp.std_x < 2e-3 and sp.std_y < 2e-3
    # 3D centres against the truth: image-centre error (~0.005 px x 0.13 mm/px) dominates;
    # measured RMS 0.69-0.73 um (seeds 1-3): bound 2x
    ce = m.centres.xyz - truth.features["circle_centres_world"]
    assert np.sqrt(np.mean(ce[:, :2] ** 2)) < 1.5e-3
    # heights against their sigma: measured rms 1.17, 0.89, 1.04; n = 99 centres, sampling
    # error 1 / sqrt(2 n) = 7 %, 4 of them either side
    zc = np.sqrt(np.mean((ce[:, 2] / m.centres.sigma_xyz[:, 2]) ** 2))
    assert abs(zc - 1) < 4 / np.sqrt(2 * ce.shape[0]), zc


def test_sphere_radius(fast):
    # (4-step fringes: the decoder's gamma correction is at the noise floor; it is
    # exercised by the plate above and tested in its own module; off here for time)
    scan, truth, cloud = _run(fast, scenes.default_sphere(), gamma_correction=False)
    sm = measure_sphere(cloud)
    f, base = sm.sphere, sm.base
    assert sm.region == "above the base plane"
    r_true = truth.features["radius_mm"]
    assert abs(f.radius - r_true) < K * f.sigma_radius
    # the base plane (true z = 0) at its centroid, against its own sigma (~0.028 um):
    # measured 0.020, 0.084 um (seeds 1, 2)
    assert base is not None and abs(base.centroid[2]) < K * base.sigma_offset
    # the centre is pulled toward the projector by camera blur over the shading
    # gradient (measured +4.0 / -2.0 / -5.7 um in x / y / z, seed 1; -6.3 um in z for
    # seed 2; 10x its noise): allow 10 um (< 2x)
    assert np.all(np.abs(f.centre - truth.features["center_world"]) < 10e-3)
    assert f.rms < 2.0 * np.nanmedian(cloud.sigma_z)


def test_step_heights(fast):
    scan, truth, cloud = _run(fast, scenes.default_steps(), gamma_correction=False)
    m = measure_steps(cloud)
    tops = truth.features["top_heights_mm"]
    assert len(m.heights) == len(tops) + 1
    # structured errors appear on the base plate of this scene (a flat plate alone shows
    # none beyond its sigma): heights and steps measured within 1.1 um (seeds 1, 2; sigma
    # 0.13-0.17 um). Allow 1.5 um beyond 4 sigma (2.1 um in all, < 2x the measured)
    assert np.all(np.abs(m.heights[1:] - tops) < K * m.sigma_heights[1:] + 1.5e-3)
    assert np.all(np.abs(m.step_heights - np.diff(np.concatenate([[0.0], tops])))
                  < K * m.sigma_steps + 1.5e-3)


@pytest.fixture(scope="module")
def paper_bga():
    """A 6 x 6 BGA seen by a 200 x 200 pixel window of the paper's camera (same optics
    and pixels as the full sensor, so the balls are 14 px wide), HDR, measured."""
    vr = get_preset("paper")
    cam = vr.rig.camera
    bga = scenes.default_bga(seed=0, rows=6, cols=6, n_missing=2, centre=(15.0, 12.0))
    u, v = cam.project(np.array([15.0, 12.0, 0.2]))
    n = 200
    c0, r0 = int(round(float(u) - n / 2)), int(round(float(v) - n / 2))
    k = cam.intrinsics
    roi = replace(k, u0=k.u0 - c0, v0=k.v0 - r0, width=n, height=n)
    vr_roi = replace(vr, name="paper-window",
                     rig=Rig(TelecentricDevice(roi, cam.R_dev_world, cam.t_dev),
                             vr.rig.projector))
    # the decode's nonlinearity fits (their inputs and results kept for
    # test_the_paper_window_gamma_fits_converge); a fit that did not converge would warn,
    # and warnings are errors here
    fits = []
    learn = decode_module.fit_phase_errors

    def kept(*args, **kwargs):
        fit = learn(*args, **kwargs)
        fits.append((args, kwargs, fit))
        return fit

    decode_module.fit_phase_errors = kept
    try:
        scan, truth, cloud, coords = _run(vr_roi, bga, seed=3, exposures=HDR_EXPOSURES,
                                          with_coords=True)
    finally:
        decode_module.fit_phase_errors = learn
    nominal = BGANominal(rows=6, cols=6, pitch_mm=0.8, ball_diameter_mm=0.45)
    m = measure_bga(cloud, nominal, image=scan_radiance(scan))
    return truth.features, m, fits


def _next_step(args, kwargs, fit):
    """One more Gauss-Newton step of the ladder's estimating equations (the samples and
    weights ``fit_phase_errors`` takes from ``args``, ``kwargs``; an integer ladder, every
    sample used) from the models of ``fit``: the largest move of a coefficient in its
    standard errors. Zero at a root of those equations."""
    per = [int(p) for p in args[1]]
    ph = [np.asarray(p, dtype=np.float64).ravel() for p in args[0]]
    valid = np.asarray(kwargs["mask"], dtype=bool).ravel().copy()
    for p in ph:
        valid &= np.isfinite(p)
    idx = np.flatnonzero(valid)
    assert idx.size <= kwargs["max_samples"]
    samp = [p[idx] for p in ph]
    sig = [np.asarray(x, dtype=np.float64).ravel()[idx] for x in kwargs["sigmas"]]
    order = [int(i) for i in np.argsort(per)]
    pairs = [(a, b, per[b] // per[a], sig[a], sig[b], None, None)
             for a, b in zip(order[:-1], order[1:], strict=True)]
    harm = [list(m.harmonics) for m in fit.models]
    offs = np.cumsum([0] + [2 * len(h) for h in harm])
    coef = np.concatenate([np.column_stack([m.cos_coef, m.sin_coef]).ravel()
                           for m in fit.models])
    lad = nl._Ladder(samp, per, harm, [np.asarray(h, dtype=np.int64) for h in harm], offs,
                     pairs)
    ev = lad.evaluate(coef, 4.0, True)
    se = np.sqrt(ev.chi2 / (ev.n_keep - coef.size) * np.diag(np.linalg.inv(ev.ata)))
    return float(np.max(np.abs(np.linalg.solve(ev.ata, ev.atb)) / se))


def test_the_paper_window_gamma_fits_converge(paper_bga):
    """The window's nonlinearity fits (periods 1, 8, 64 along u and 1, 8, 48 along v; the
    1-period phase covers 11 % and 17 % of its circle) end at a root of their estimating
    equations. Along v Gauss-Newton used to cycle there between two models 78 standard
    errors apart whatever its number of steps (the errors-in-variables terms, which its
    normal matrix leaves out, gave its map an eigenvalue of -1.0 on this coverage; it
    warned); Newton's method now takes over and converges. Measured one more step from the
    models returned: 0.0062 (u) and 0.0006 (v) standard errors (the old code's: 0.011 and
    55); bound 2x what the convergence test allows (0.02 standard errors still to come, a
    Gauss-Newton step up to twice that with an eigenvalue of -1)."""
    *_, fits = paper_bga
    assert len(fits) == 2
    # (neither warned: the fixture's decode would have raised; an earlier pass's note may
    # stay in ``fit.warnings``)
    for args, kwargs, fit in fits:
        assert _next_step(args, kwargs, fit) < 0.08


def _true_apex_heights(f, m):
    true_h = {tuple(i): a[2] for i, a in zip(f["ball_index"], f["apexes_world"], strict=True)}
    return np.array([true_h[tuple(i)] for i in m.index])


def test_bga_on_the_paper_rig(paper_bga):
    f, m, _ = paper_bga
    assert m.refined.all()
    assert sorted(m.missing) == sorted(tuple(x) for x in f["missing"])
    assert m.n_balls == len(f["ball_index"]) and m.unexpected == ()
    th = _true_apex_heights(f, m)
    e = m.height - th
    # apex heights against their sigma, two-sided from the sampling error: n = 34 balls,
    # 1 / sqrt(2 n) = 12 %, 4 of them. sigma_height holds the cap model's per-ball term
    # (0.023 px = 0.75 um here, measured on other scenes and noise seeds of this rig:
    # see SIGMA_HEIGHT_MODEL_PX); measured 0.97 (0.97 with noise seed 4); with the noise
    # part alone 1.37
    assert m.sigma_height_model == pytest.approx(0.75e-3, rel=0.05)
    zh = np.sqrt(np.mean((e / m.sigma_height) ** 2))
    assert abs(zh - 1) < 4 / np.sqrt(2 * e.size), zh
    # RMS error: measured 1.03 um, bound 2x
    assert np.sqrt(np.mean(e**2)) < 2.1e-3
    # pitch: from the specular highlights (measured RMS 0.16 um, largest 0.34 um over 53
    # pairs with the mean of every phase image; 0.25 / 0.61 um with the finest group's
    # background alone)
    cw = {tuple(i): c for i, c in zip(f["ball_index"], f["centres_world"], strict=True)}
    grid = np.full((6, 6, 2), np.nan)
    for (i, j), c in cw.items():
        grid[i, j] = c[:2]
    pe = []
    for axis, meas in ((1, m.pitch_x), (0, m.pitch_y)):
        true_p = np.linalg.norm(np.diff(grid, axis=axis), axis=2)
        ok = np.isfinite(meas) & np.isfinite(true_p)
        pe.append(meas[ok] - true_p[ok])
    pe = np.concatenate(pe)
    assert pe.size > 40
    assert np.sqrt(np.mean(pe**2)) < 0.35e-3  # measured 0.16 um: 2x
    # the measured apex heights give the truth's coplanarity (the true apexes on the true
    # substrate): measured 69.95 vs 70.01 um; within 2x the largest apex error (2.8 um)
    xy = np.array([cw[tuple(i)][:2] for i in m.index])
    flat = Plane.horizontal(0.0)
    truth_cop = seating_plane_coplanarity(np.column_stack([xy, th]), np.array([15.0, 12.0]),
                                          reference=flat).value
    from_heights = seating_plane_coplanarity(np.column_stack([xy, m.height]),
                                             np.array([15.0, 12.0]), reference=flat).value
    assert abs(from_heights - truth_cop) < 2 * np.max(np.abs(e)), (from_heights, truth_cop)


def test_bga_coplanarity_on_the_paper_rig(paper_bga):
    f, m, _ = paper_bga
    cw = {tuple(i): c for i, c in zip(f["ball_index"], f["centres_world"], strict=True)}
    xy = np.array([cw[tuple(i)][:2] for i in m.index])
    truth = seating_plane_coplanarity(np.column_stack([xy, _true_apex_heights(f, m)]),
                                      np.array([15.0, 12.0]),
                                      reference=Plane.horizontal(0.0))
    cop = m.coplanarity
    # this window's centre of gravity lies on the edge from ball (0, 5) to ball (4, 1)
    # shared by two seating triangles (truth: 70.0 and 56.8 um); the measured centre is
    # 0.13 um off it, well within the balls' in-plane sigma, and once decided the plane
    # by that alone (56.2 um reported). Both planes are now found, the worst reported:
    # measured 69.95 / 56.17 um against the truth's 70.01 / 56.83 um
    assert truth.rocks and cop.rocks
    assert cop.alternatives.size == truth.alternatives.size
    # each within K sigma of the coplanarity (from the apexes' sigma_height: 1.8 um;
    # measured differences 0.06 and 0.66 um)
    assert np.all(np.abs(cop.alternatives - truth.alternatives) < K * cop.sigma), (
        cop.alternatives, truth.alternatives, cop.sigma)
    assert 0 < cop.sigma < 3 * np.max(m.sigma_height)
