"""The BGA's noise figures with the stereo matches' correlated noise: neighbouring
matches interpolate the same pixels of the second camera, so a cap fit that treats its
points as independent understates its apex's and centre's noise; with the match's noise
split (``measure_bga(..., noise=match_noise(...))``) each cap fit's covariance is the
sandwich of its points' exact covariance. Monte Carlo over noise seeds on a small
render-free stereo BGA (white noise of the decoded sigmas on exact phase maps, the second
camera 2.5 times noisier than the first); ``telefringe measure bga`` and ``telefringe
batch --measure bga --second`` on a rendered two-camera BGA."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from anyrig_rigs import ball_hits, stereo_rig_of, write_stereo_scan
from anyrig_rigs import noisy_coords as _coords
from anyrig_rigs import var_ratio_tol as _var_ratio_tol

from telefringe.metrology import BGANominal, BGAOptions, MetrologyError, measure_bga
from telefringe.metrology.bga.stereo import StereoCorrelationWarning
from telefringe.reconstruction.stereo import StereoNoise, match_noise, match_stereo

# projector px: the decoded sigmas, 3x those of test_stereo_noise_steps.py: at 1x the
# bilinear interpolation of the second camera's exact map across a ball's curvature
# leaves a systematic residual that the residual-scaled figures (with and without the
# noise) take in as noise (the sandwich's scale k = 1.27 on average there, 1.007 at 3x)
_S1, _S2 = 0.06, 0.15
_ROWS, _COLS, _PITCH, _D = 3, 5, 1.2, 0.72  # 12 px balls, 20 px pitch


def _bga_scene(kind="tt", shape=(72, 112)):
    """The two cameras' projector coordinates of a 3 x 5 BGA (balls of 0.72 mm, 0.62 mm
    high) centred under the first camera."""
    rig = stereo_rig_of(kind, shape)
    cams = list(rig.cameras.values())
    o, d = cams[0].backproject(np.array([(shape[1] - 1) / 2]), np.array([(shape[0] - 1) / 2]))
    o, d = np.asarray(o).reshape(-1), np.asarray(d).reshape(-1)
    mid = o - o[2] / d[2] * d
    jj, ii = np.meshgrid(np.arange(_COLS), np.arange(_ROWS))
    centres = np.stack([(jj - (_COLS - 1) / 2).ravel() * _PITCH + mid[0],
                        (ii - (_ROWS - 1) / 2).ravel() * _PITCH + mid[1],
                        np.full(_ROWS * _COLS, _D / 2 - 0.1)], axis=1)
    uv = [rig.projector.project(ball_hits(c, shape, centres, _D / 2)) for c in cams]
    return rig, uv


def test_bga_sigmas_with_correlated_noise_match_monte_carlo():
    """40 noise seeds, 15 balls (cap model "fixed", ~32 cap points a ball): the variance
    of each ball's apex height over the seeds against its mean predicted sigma_height^2,
    averaged over the balls, within 3 sigma of 1 with ``noise=`` (measured 1.02); without
    it (the independent points' figure) more than 3 sigma above (measured 2.84). The same
    for the pitch along the grid's x between the 6 disjoint pairs of neighbours (the
    variance of the pitch against the two centres' x variances summed; measured 0.98 with,
    1.81 without). The balls are independent: no pixel of the second camera is read by two
    balls' caps or by a cap and the substrate (no StereoCorrelationWarning), and the
    substrate's common part of the heights is small (1 700 points against ~32 a cap), so
    the tolerance of a mean of n independent variance ratios is var_ratio_tol / sqrt(n)
    (0.175 for the heights, 0.277 for the pitches).
    The measurement (heights, centres) is the same with and without."""
    rig, ((u1, v1), (u2, v2)) = _bga_scene()
    rng = np.random.default_rng(5)
    nominal = BGANominal(rows=_ROWS, cols=_COLS, pitch_mm=_PITCH, ball_diameter_mm=_D)
    opt = BGAOptions(cap_model="fixed")
    pairs = [(i * _COLS + j, i * _COLS + j + 1) for i in range(_ROWS) for j in (0, 2)]
    n_runs = 40
    h, ph, pi_h, px, pp, pi_p = [], [], [], [], [], []
    for _ in range(n_runs):
        a, b = _coords(u1, v1, _S1, rng), _coords(u2, v2, _S2, rng)
        m = match_stereo(rig, a, b, max_residual=None)
        with warnings.catch_warnings():
            warnings.simplefilter("error", StereoCorrelationWarning)
            mc = measure_bga(m.cloud, nominal, options=opt, noise=match_noise(rig, a, b, m))
        assert mc.n_balls == _ROWS * _COLS
        h.append(mc.height)
        ph.append(mc.sigma_height ** 2)
        # the grid's x is the world x to 0.03 rad here (the camera's tilt): the centres'
        # x sigmas stand for the grid's
        px.append([mc.position[q, 0] - mc.position[p, 0] for p, q in pairs])
        pp.append([mc.sigma_centre[p, 0] ** 2 + mc.sigma_centre[q, 0] ** 2 for p, q in pairs])
        if _ % 4 == 0:
            # the independent points' figure: its mean over every 4th seed (10 x 15
            # balls; it is the measurement's slowest part, the substrate's robust fit)
            mi = measure_bga(m.cloud, nominal, options=opt)
            np.testing.assert_array_equal(mc.height, mi.height)
            np.testing.assert_array_equal(mc.centre, mi.centre)
            pi_h.append(mi.sigma_height ** 2)
            pi_p.append([mi.sigma_centre[p, 0] ** 2 + mi.sigma_centre[q, 0] ** 2
                         for p, q in pairs])
    emp_h = np.var(h, axis=0, ddof=1)
    r_h, ri_h = np.mean(emp_h / np.mean(ph, axis=0)), np.mean(emp_h / np.mean(pi_h, axis=0))
    emp_p = np.var(px, axis=0, ddof=1)
    r_p, ri_p = np.mean(emp_p / np.mean(pp, axis=0)), np.mean(emp_p / np.mean(pi_p, axis=0))
    tol_h = _var_ratio_tol(n_runs) / np.sqrt(_ROWS * _COLS)
    tol_p = _var_ratio_tol(n_runs) / np.sqrt(len(pairs))
    print("apex height variance MC / predicted: correlated", r_h, "independent", ri_h,
          "tol", tol_h)
    print("pitch variance MC / predicted: correlated", r_p, "independent", ri_p, "tol", tol_p)
    assert abs(r_h - 1.0) <= tol_h, r_h
    assert ri_h - 1.0 > tol_h, ri_h
    assert abs(r_p - 1.0) <= tol_p, r_p
    assert ri_p - 1.0 > tol_p, ri_p


def test_noise_must_be_the_clouds():
    """``noise`` of another grid, or not covering the fitted points, is refused."""
    rig, ((u1, v1), (u2, v2)) = _bga_scene()
    a, b = _coords(u1, v1, _S1), _coords(u2, v2, _S2)
    m = match_stereo(rig, a, b, max_residual=None)
    nz = match_noise(rig, a, b, m)
    nominal = BGANominal(rows=_ROWS, cols=_COLS, pitch_mm=_PITCH, ball_diameter_mm=_D)
    with pytest.raises(MetrologyError, match="noise has shape"):
        measure_bga(m.cloud, nominal, noise=StereoNoise(
            np.zeros((2, 2)), np.zeros((2, 2, 1)), np.full((2, 2, 1), -1)))
    holes = np.where(np.arange(m.cloud.shape[1])[None, :] % 7 == 0, np.nan, nz.var_own)
    with pytest.raises(MetrologyError, match="does not cover"):
        measure_bga(m.cloud, nominal, noise=StereoNoise(holes, nz.weights, nz.sources))


_RENDERED = dict(rows=3, cols=4, pitch=6.0, diameter=4.0)


@pytest.fixture(scope="module")
def stereo_bga(tmp_path_factory):
    """The stereo preset binned 8 x 8 (0.3 mm a pixel), a 3 x 4 BGA of 4 mm balls at 6 mm
    pitch (matte: the solder's highlight saturates and splits the balls at this
    binning) rendered by both cameras, written as scan folders ``s0/camera`` and
    ``s0/camera_2`` with the true (bare) rig.json, and the folder ``reconstruct
    --second`` makes of them (no gamma correction: a fast test)."""
    from telefringe.simulate.scenes import BGA

    tmp = tmp_path_factory.mktemp("stereo_bga")
    p = _RENDERED["pitch"]
    scene = BGA(rows=3, cols=4, pitch=p, ball_diameter=4.0, ball_height=2.0,
                ball_specular=0.0, ball_albedo=0.5,
                origin=np.array([15.0 - 1.5 * p, 11.7 - p]),
                height_offsets=np.random.default_rng(1).normal(0, 0.02, (3, 4)))
    scans, cal = write_stereo_scan(tmp, scene, seed=3)
    return tmp, scans, cal


def _bga_args():
    return ["--rows", "3", "--cols", "4", "--pitch", "6", "--diameter", "4"]


def test_measure_bga_cli_u_equals_the_api(stereo_bga, capsys):
    """`measure bga OUT` on the stereo reconstruction reports the heights and sigmas of
    the API with its points.npz's noise (``noise=``) to 1e-12 (no note), larger than the
    independent points' (the same folder's points.npz without the stereo keys: the same
    heights, a note)."""
    from telefringe.cli import main
    from telefringe.io.points_npz import load_points

    tmp, _, _ = stereo_bga
    js = tmp / "b.json"
    with warnings.catch_warnings():
        warnings.simplefilter("error", StereoCorrelationWarning)
        assert main(["measure", "bga", str(tmp / "one"), *_bga_args(), "--json", str(js),
                     "--force"]) == 0
    err = capsys.readouterr()
    text = " ".join((err.out + err.err).split())
    assert "independent" not in text
    doc = json.loads(js.read_text())
    pf = load_points(tmp / "one")
    assert pf.stereo_noise is not None
    nominal = BGANominal(rows=3, cols=4, pitch_mm=6.0, ball_diameter_mm=4.0)
    api = measure_bga(pf.cloud, nominal, image=pf.radiance, noise=pf.stereo_noise.expand())
    ind = measure_bga(pf.cloud, nominal, image=pf.radiance)
    assert api.n_balls == 12
    per = doc["balls"]
    np.testing.assert_allclose(per["height_mm"], api.height, rtol=1e-12)
    np.testing.assert_allclose(per["sigma_height_mm"], api.sigma_height, rtol=1e-12)
    np.testing.assert_allclose(doc["sigma_coplanarity_mm"], api.coplanarity.sigma,
                               rtol=1e-12)
    print("sigma_height um: correlated", api.sigma_height * 1e3, "independent",
          ind.sigma_height * 1e3)
    np.testing.assert_array_equal(api.height, ind.height)
    assert np.all(api.sigma_height > ind.sigma_height)
    # an older points.npz (no stereo keys): the note, the independent sigmas
    with np.load(tmp / "one" / "points.npz") as z:
        arrays = {k: z[k] for k in z.files if not k.startswith("stereo_")}
    old = tmp / "old"
    old.mkdir(exist_ok=True)
    np.savez(old / "points.npz", **arrays)
    (old / "summary.json").write_text((tmp / "one" / "summary.json").read_text())
    assert main(["measure", "bga", str(old), *_bga_args(), "--json", str(js),
                 "--force"]) == 0
    err = capsys.readouterr()
    assert "points.npz holds no stereo noise" in " ".join((err.out + err.err).split())
    doc = json.loads(js.read_text())
    np.testing.assert_allclose(doc["balls"]["sigma_height_mm"], ind.sigma_height,
                               rtol=1e-12)


def test_batch_bga_row_equals_measure_bga(stereo_bga):
    """`batch --measure bga --second ../camera_2`: the row's figures and the scan's
    measurement.json (per ball) equal `measure bga` on the one-scan stereo
    reconstruction (to 1e-9), the matches' noise included (u of the heights larger than
    the independent points' figure: the test above)."""
    from telefringe.batch import measure_many
    from telefringe.batch.job import flatten_summary
    from telefringe.cli import main

    tmp, _, _ = stereo_bga
    frame = measure_many([str(tmp / "s0" / "camera")], tmp / "rig.json", workers=0,
                         output=tmp / "res", second="../camera_2", measure="bga",
                         gamma_correction=False, **_RENDERED)
    row = frame.iloc[0]
    assert row["status"] == "ok", row["error"]
    assert row["warnings"] == ""
    js = tmp / "one.json"
    assert main(["measure", "bga", str(tmp / "one"), *_bga_args(), "--json", str(js),
                 "--force"]) == 0
    one = json.loads(js.read_text())
    want = flatten_summary(one, "bga")
    assert want["bga.sigma_coplanarity_mm"] > 0
    for key, v in want.items():
        if isinstance(v, float):
            # the batch measures its in-memory cloud, `measure bga` the one points.npz
            # gives back, whose pixel directions differ by 1 ulp (3e-16); the cap fits'
            # iterations carry that to 3.4e-10 mm in the centres (pitch error), 6.8e-10
            # deg in the grid's angle: 1e-9 of either, absolute (else 1e-9 relative)
            atol = 1e-9 if key.endswith(("_mm", "_deg")) else 0.0
            np.testing.assert_allclose(row[key], v, rtol=1e-9, atol=atol, err_msg=key)
        elif v is None:  # the table holds a missing number as NaN
            assert row[key] is None or np.isnan(row[key]), key
        else:
            assert row[key] == v, key
    doc = json.loads((tmp / "res" / "scans" / row["scan"] / "measurement.json").read_text())
    for k in ("height_mm", "sigma_height_mm", "sigma_height_noise_mm"):
        np.testing.assert_allclose(doc["balls"][k], one["balls"][k], rtol=1e-9, err_msg=k)


@pytest.mark.parametrize("free_radius", [False, True])
def test_sandwiches_reduce_to_the_fits_own_covariance(free_radius):
    """With no shared source and each point's own variance that of its weight (var_own =
    1 / (w (n . d)^2): the residuals' covariance the identity), the cap's sandwich is the
    fit's own residual-scaled covariance: fit_sphere's (fixed or free radius) to 1e-12
    (measured 3e-15) and _fit_along_line's depth sigma to 1e-10 (measured 2.4e-11: it
    stops at a step of 1e-9 mm): the linearisations (the residuals' Jacobian and their
    response to a point moving along its line) agree with the fits."""
    from telefringe.metrology.bga.highlights import _fit_along_line
    from telefringe.metrology.bga.stereo import line_sandwich, sphere_sandwich
    from telefringe.metrology.spheres import fit_sphere

    rng = np.random.default_rng(3)
    r, c0 = 0.36, np.array([0.1, -0.2, 0.26])
    t = rng.uniform(0, np.radians(55), 60)
    f = rng.uniform(0, 2 * np.pi, 60)
    nn = np.stack([np.sin(t) * np.cos(f), np.sin(t) * np.sin(f), np.cos(t)], axis=1)
    d = np.array([0.05, -0.03, -1.0])
    d /= np.linalg.norm(d)  # the camera's line, into the scene
    pts = c0 + r * nn + rng.normal(0, 0.002, 60)[:, None] * d
    w = rng.uniform(0.5, 2.0, 60)
    fit = fit_sphere(pts, weights=w, radius=None if free_radius else r)
    assert fit.inliers.all()
    v = pts - fit.centre
    cosd = np.abs((v / np.linalg.norm(v, axis=1)[:, None]) @ d)
    parts = (1.0 / (w / w.mean() * cosd**2), np.zeros((60, 4)), np.full((60, 4), -1),
             np.broadcast_to(d, (60, 3)))
    cov = sphere_sandwich(pts, w / w.mean(), fit.centre, fit.radius, free_radius, parts)
    np.testing.assert_allclose(cov, fit.covariance, rtol=1e-12, atol=1e-20)
    res = _fit_along_line(pts, w, fit.centre + 0.3 * d, d, r, fit.centre)
    assert res is not None
    centre, s_t = res
    v = pts - centre
    cosd = np.abs((v / np.linalg.norm(v, axis=1)[:, None]) @ d)
    parts = (1.0 / (w * cosd**2),) + parts[1:]
    np.testing.assert_allclose(line_sandwich(pts, w, centre, r, d, parts), s_t, rtol=1e-10)


@pytest.mark.parametrize("cap_model", ["psf", "fixed"])
def test_independent_noise_gives_the_independent_figures(cap_model):
    """A one-camera cloud (test_metrology's analytic BGA) with a ``noise`` of independent
    points whose variance is each point's sigma_line^2 (no shared source): the weighted
    cap fits' sandwiches, the point-spread parameters' and the substrate's, are the
    independent points' figures. Heights' and centres' sigmas within 0.5 % (measured
    largest 0.21 % / 0.45 % for "psf", where the common parameters' scale divides the
    residuals by sum(m - 3) instead of sum(m - 3) - 1; 0.07 % for "fixed"), the
    measurement the same."""
    from test_metrology import bga_cloud

    cloud = bga_cloud(seed=10, psf_s2=2e-4)[0]
    nz = StereoNoise(np.where(cloud.mask, cloud.sigma_line ** 2, np.nan),
                     np.zeros(cloud.shape + (4,)), np.full(cloud.shape + (4,), -1))
    nominal = BGANominal(rows=6, cols=7, pitch_mm=0.8, ball_diameter_mm=0.45)
    opt = BGAOptions(cap_model=cap_model, weighted=True if cap_model == "fixed" else None)
    a = measure_bga(cloud, nominal, options=opt)
    b = measure_bga(cloud, nominal, options=opt, noise=nz)
    np.testing.assert_array_equal(a.height, b.height)
    np.testing.assert_array_equal(a.centre, b.centre)
    np.testing.assert_allclose(b.sigma_height, a.sigma_height, rtol=5e-3)
    np.testing.assert_allclose(b.sigma_centre, a.sigma_centre, rtol=5e-3)
    np.testing.assert_allclose(b.substrate.sigma_offset, a.substrate.sigma_offset,
                               rtol=1e-9)
