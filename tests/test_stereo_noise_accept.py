"""The acceptance test's fit uncertainty with the stereo matches' correlated noise
(issue 11): neighbouring matches interpolate the same pixels of the second camera, so the
least-squares spheres of PS and SD, fitted as independent points, understate their
noise; with the match's noise split (``evaluate_position(..., noise=match_noise(...),
directions=)``) their covariance is the sandwich of the points' exact covariance. Monte
Carlo over noise seeds on small stereo scenes (white noise of the decoded sigmas on exact
phase maps, the second camera 2.5 times noisier than the first), the centres'
covariance through shared sources, and ``telefringe accept`` on a two-camera set."""

from __future__ import annotations

import json

import numpy as np
import pytest
from anyrig_rigs import noisy_coords as _coords
from anyrig_rigs import stereo_rig_of
from anyrig_rigs import var_ratio_tol as _var_ratio_tol

from telefringe.metrology import MetrologyError
from telefringe.metrology.acceptance import (
    Artefacts,
    evaluate_position,
    ls_sphere,
    sphere_spacing_error,
)
from telefringe.metrology.acceptance.fits import PointNoise, correlated_covariance
from telefringe.reconstruction.stereo import match_noise, match_stereo

_S1, _S2 = 0.02, 0.05  # projector px: the first and the second camera's decoded sigma


def _first_hit(o, d, c, r):
    oc = o - c
    b = np.sum(d * oc, -1)
    disc = b * b - (np.sum(oc * oc, -1) - r * r)
    with np.errstate(invalid="ignore"):
        t = np.where(disc >= 0, -b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
    return np.where(t > 0, t, np.inf)


def _balls_scene(rig, shape, centres, radius):
    """Each camera's exact projector coordinates of free balls (nothing else in view:
    NaN where a pixel misses them or the projector does not light the point)."""
    out = []
    for cam in rig.cameras.values():
        rows, cols = shape
        v, u = np.mgrid[0:rows, 0:cols].astype(float)
        o, d = cam.backproject(u, v)
        o = np.broadcast_to(o, shape + (3,))
        d = np.broadcast_to(d, shape + (3,))
        t = np.min([_first_hit(o, d, c, radius) for c in centres], axis=0)
        hit = np.isfinite(t)
        X = o + np.where(hit, t, -o[..., 2] / d[..., 2])[..., None] * d  # misses: z = 0
        up, vp = rig.projector.project(X)
        op, dp = rig.projector.backproject(up, vp)
        op = np.broadcast_to(op, X.shape)
        dp = np.broadcast_to(dp, X.shape)
        t_x = np.sum((X - op) * dp, -1)
        t_s = np.min([_first_hit(op, dp, c, radius) for c in centres], axis=0)
        lit = hit & ~(t_s < t_x - 1e-6)
        out.append((np.where(lit, up, np.nan), np.where(lit, vp, np.nan)))
    return out


_SCENES = {  # centres (mm), radius (mm): one test sphere, a ball bar of two
    "sphere": ([(0.1, -0.05, 0.35)], 0.8),
    "ball_bar": ([(-0.85, -0.05, 0.3), (0.85, 0.1, 0.2)], 0.55),
}


@pytest.mark.parametrize("kind", ["sphere", "ball_bar"])
def test_acceptance_sigma_with_correlated_noise_matches_monte_carlo(kind):
    """Free balls matched by two pinhole cameras (60 x 80 px; ~500 points on the
    sphere, ~190 on each ball of the bar), 200 noise seeds: the variances over the seeds
    within 3 sigma of the mean predicted with ``noise=`` (a variance of 200 draws
    scatters by 10 %): sphere centre x, y, z and diameter measured 1.02, 1.01, 0.83,
    0.83, ball bar distance and diameters 1.00, 0.92, 0.78; the independent points'
    prediction is exceeded by more (1.78, 1.29, 1.24, 1.16; 1.60, 1.42, 1.18): beyond
    3 sigma for the centre x and the bar's distance (SD). The values (PS, SD) are the
    same with and without."""
    shape = (60, 80)
    rig = stereo_rig_of("pp", shape)
    centres, radius = _SCENES[kind]
    centres = [np.array(c) for c in centres]
    (u1, v1), (u2, v2) = _balls_scene(rig, shape, centres, radius)
    cert = Artefacts(2 * radius, 0.0, 0.0, 0.0, float(np.linalg.norm(centres[-1] - centres[0]))
                     or 1.0, 0.0, (2 * radius, 2 * radius), 0.0, 0.0)
    rng = np.random.default_rng(5)
    n_runs = 200
    vals, pred, indep = [], [], []
    for k in range(n_runs):
        a, b = _coords(u1, v1, _S1, rng), _coords(u2, v2, _S2, rng)
        m = match_stereo(rig, a, b, max_residual=None)
        cl = m.cloud
        tc = evaluate_position("x", kind, cl.xyz, cl.mask, cert,
                               noise=match_noise(rig, a, b, m), directions=cl.directions).test
        ti = evaluate_position("x", kind, cl.xyz, cl.mask, cert).test
        if kind == "sphere":
            assert tc.PS == ti.PS and tc.PF == ti.PF and tc.fit.correlated
            vals.append([*tc.fit.centre, tc.diameter])
            pred.append([*np.diag(tc.fit.covariance)[:3], tc.u_fit_diameter ** 2])
            indep.append([*np.diag(ti.fit.covariance)[:3], ti.u_fit_diameter ** 2])
            if k == 0:
                assert tc.n_points > 400 and tc.u_fit_diameter > ti.u_fit_diameter
        else:
            assert tc.SD == ti.SD
            vals.append([tc.distance, *(s.diameter for s in tc.spheres)])
            pred.append([tc.u_fit_distance ** 2, *(s.u_fit_diameter ** 2 for s in tc.spheres)])
            indep.append([ti.u_fit_distance ** 2,
                          *(s.u_fit_diameter ** 2 for s in ti.spheres)])
            if k == 0:
                assert min(s.n_points for s in tc.spheres) > 150
                assert tc.u_fit_distance > ti.u_fit_distance
    emp = np.var(np.array(vals), axis=0, ddof=1)
    r = emp / np.mean(pred, axis=0)
    ri = emp / np.mean(indep, axis=0)
    tol = _var_ratio_tol(n_runs)
    print(kind, "variance MC / predicted: correlated", r, "independent", ri, "tol", tol)
    assert np.all(np.abs(r - 1.0) <= tol), r
    assert ri[0] - 1.0 > tol, ri


def _cap(centre, radius, xy):
    """Points on the top of a sphere above the (x, y) offsets (n, 2) from its centre."""
    z = np.sqrt(radius ** 2 - np.sum(xy ** 2, axis=1))
    return np.asarray(centre) + np.column_stack([xy, z])


def test_ball_bar_centres_covariance_through_shared_sources():
    """Two balls seen from +z whose points share their sources pairwise (point i of one
    and point i of the other read the same source, as two matches reading the same pixel
    of a second camera would; the same layout on both): the sources move both centres
    alike, which the distance does not see. ``u_fit_distance`` holds that covariance:
    over 400 draws the distance's variance within 3 sigma of it (measured 1.08), where
    the sum of the two spheres' own variances (no cross term) overstates it 24 times."""
    rng = np.random.default_rng(2)
    n, radius, s_own, w = 250, 1.0, 2e-4, 1e-3
    xy = rng.uniform(-0.7, 0.7, (n, 2))
    ca, cb = np.array([-2.0, 0.0, 0.0]), np.array([2.0, 0.1, 0.0])
    pa, pb = _cap(ca, radius, xy), _cap(cb, radius, xy)
    up = np.tile([0.0, 0.0, 1.0], (n, 1))
    src = np.arange(n)[:, None]
    nz = PointNoise(up, np.full(n, s_own ** 2), np.full((n, 1), w), src)
    diam = (2 * radius, 2 * radius)
    n_runs = 400
    vals, pred = [], []
    for _ in range(n_runs):
        z = rng.normal(size=n)
        da = rng.normal(0, s_own, n) + w * z
        db = rng.normal(0, s_own, n) + w * z
        t = sphere_spacing_error(pa + da[:, None] * up, pb + db[:, None] * up, 4.0, diam,
                                 noise=(nz, nz))
        vals.append(t.distance)
        pred.append(t.u_fit_distance ** 2)
    a, b = (s.fit for s in t.spheres)
    g = (b.centre - a.centre) / t.distance
    no_cross = g @ a.covariance[:3, :3] @ g + g @ b.covariance[:3, :3] @ g
    emp = np.var(vals, ddof=1)
    tol = _var_ratio_tol(n_runs)
    print("distance variance MC / predicted", emp / np.mean(pred), "without the cross "
          "term", emp / no_cross, "tol", tol)
    assert abs(emp / np.mean(pred) - 1.0) <= tol
    assert 1.0 - emp / no_cross > tol


def test_correlated_covariance_is_the_spheres_sandwich():
    """``correlated_covariance`` is ``telefringe.metrology.spheres._sandwich`` (the
    covariance ``measure_sphere(..., noise=)`` takes) with the sources' gains beside it,
    ``gain gain'`` its shared part; with independent points of one sigma moved along
    their normals (``a = 1``) ``ls_sphere(..., noise=)`` gives the usual covariance."""
    from telefringe.metrology.spheres import _sandwich

    rng = np.random.default_rng(4)
    n = 300
    xy = rng.uniform(-0.6, 0.6, (n, 2))
    p = _cap((0.3, -0.2, 1.0), 1.0, xy) + rng.normal(0, 1e-3, (n, 3))
    fit = ls_sphere(p)
    q = p - fit.centre
    radial = q / np.linalg.norm(q, axis=1, keepdims=True)
    J = np.column_stack([-radial, -np.ones(n)])
    a = rng.uniform(0.5, 1.0, n)
    K = 4
    src = rng.integers(0, 60, (n, K))
    src[:, 1:] += 60 * np.arange(1, K)  # distinct within a row
    src[::5, 2] = -1
    wts = np.where(src >= 0, rng.normal(0, 1e-3, (n, K)), 0.0)
    nz = PointNoise(np.tile([0.0, 0.0, 1.0], (n, 1)), rng.uniform(1e-7, 1e-6, n), wts, src)
    cov, s, gain = correlated_covariance(J, a, fit.residuals, nz)
    ref = _sandwich(J, a, np.linalg.inv(J.T @ J), fit.residuals, nz.var_own, wts, src)
    np.testing.assert_allclose(cov, ref, rtol=1e-10, atol=0)
    np.testing.assert_array_equal(s, np.unique(src[src >= 0]))
    # the rest is the points' own part, scaled by the same factor as the shared
    Ninv = np.linalg.inv(J.T @ J)
    Ja = J * a[:, None]
    own = Ninv @ ((Ja * nz.var_own[:, None]).T @ Ja) @ Ninv
    k = (cov - gain @ gain.T) / own
    assert k[0, 0] > 0
    np.testing.assert_allclose(k, k[0, 0], rtol=1e-8)
    # independent points of one sigma along their normals: the usual covariance
    flat = PointNoise(radial, np.full(n, 1e-6), np.zeros((n, 1)), np.full((n, 1), -1))
    np.testing.assert_allclose(ls_sphere(p, noise=flat).covariance, fit.covariance,
                               rtol=1e-9)
    with pytest.raises(MetrologyError, match="noise of 3 points"):
        ls_sphere(p, noise=flat.take(slice(0, 3)))
    with pytest.raises(MetrologyError, match="inconsistent shapes"):
        PointNoise(radial, np.zeros(n), np.zeros((n, 1)), np.zeros((n, 2), dtype=int))
    with pytest.raises(MetrologyError, match="go together"):
        evaluate_position("x", "sphere", np.zeros((4, 4, 3)), np.ones((4, 4), bool),
                          None, noise=nz)


def test_accept_cli_u_equals_the_api(tmp_path, capsys):
    """`telefringe accept` on a two-camera set (the stereo preset binned 8 x 8, a sphere
    and a ball bar, the true rig) reports the U of the API with the matches' noise split
    (``evaluate_position(..., noise=match_noise(...))``, ``summarize``) to 1e-12, larger
    than the independent points' U."""
    from test_acceptance_anyrig import _small, _write_set

    from telefringe.cli import main
    from telefringe.io.acceptance_json import load_acceptance_set, load_artefacts
    from telefringe.io.rig_json import bare_rig_json, load_rig
    from telefringe.io.scan_json import read_scan
    from telefringe.metrology.acceptance import summarize
    from telefringe.reconstruction.pipeline import reconstruct_stereo_scans

    vrig = _small("stereo")
    cert_path = _write_set(vrig, tmp_path / "acc", (3, 12))
    (tmp_path / "rig.json").write_text(json.dumps(bare_rig_json(vrig.rig)))
    assert main(["accept", str(tmp_path / "acc"), "--rig", str(tmp_path / "rig.json"),
                 "--artefacts", str(cert_path), "--no-gamma-correction", "--json",
                 str(tmp_path / "result.json")]) == 0
    err = capsys.readouterr()
    assert "independent" not in " ".join((err.out + err.err).split())
    doc = json.loads((tmp_path / "result.json").read_text())
    cert = load_artefacts(cert_path)
    rig = load_rig(tmp_path / "rig.json")
    with_noise, without = [], []
    for e in load_acceptance_set(tmp_path / "acc"):
        rec = reconstruct_stereo_scans(read_scan(tmp_path / "acc" / e.scan),
                                       read_scan(tmp_path / "acc" / e.second), rig,
                                       with_height_map=False, gamma_correction=False)
        cl = rec.cloud
        nz = match_noise(rig, rec.coords, rec.coords_2, rec.match)
        with_noise.append(evaluate_position(e.name, e.artefact, cl.xyz, cl.mask, cert,
                                            noise=nz, directions=cl.directions))
        without.append(evaluate_position(e.name, e.artefact, cl.xyz, cl.mask, cert))
    api, ind = summarize(with_noise, cert), summarize(without, cert)
    for q in ("PS", "SD"):
        got = [p["U"] for p in doc[q]["positions"]]
        np.testing.assert_allclose(got, api.quantities[q].U, rtol=1e-12)
        np.testing.assert_allclose([p["value"] for p in doc[q]["positions"]],
                                   ind.quantities[q].values, rtol=1e-12)
        print(q, "U um: correlated", api.quantities[q].U * 1e3, "independent",
              ind.quantities[q].U * 1e3)
        assert np.all(api.quantities[q].U > ind.quantities[q].U)
