"""The step gauge's heights with the stereo matches' correlated noise (issue 11):
neighbouring matches interpolate the same pixels of the second camera, so the levels'
fit that treats the points as independent understates the steps' noise; with the match's
noise split (``measure_steps(..., noise=match_noise(...))``) the noise model's figure is
the sandwich of the points' exact covariance, and the residuals' autocovariance figure
(for a ripple) still applies on top (the larger of the two). Monte Carlo over noise seeds
on a small stereo step (white noise of the decoded sigmas on exact phase maps, the
second camera 2.5 times noisier than the first); and ``telefringe measure steps`` on a
two-camera reconstruction."""

from __future__ import annotations

import json

import numpy as np
import pytest
from anyrig_rigs import noisy_coords as _coords
from anyrig_rigs import step_hits, stereo_rig_of
from anyrig_rigs import var_ratio_tol as _var_ratio_tol

from telefringe.metrology import MetrologyError, measure_steps
from telefringe.reconstruction.stereo import StereoNoise, match_noise, match_stereo

_S1, _S2 = 0.02, 0.05  # projector px: the first and the second camera's decoded sigma


def _step_scene(kind, shape, h=0.3):
    rig = stereo_rig_of(kind, shape)
    cams = list(rig.cameras.values())
    uv = [rig.projector.project(step_hits(c, shape, h)) for c in cams]
    return rig, uv


@pytest.mark.parametrize("kind", ["pp", "tt"])
def test_step_sigma_with_correlated_noise_matches_monte_carlo(kind):
    """A 0.3 mm step matched by two cameras (48 x 64 px, ~1000 points a level), 150 noise
    seeds: the variance of the step height over the seeds within 3 sigma of the mean
    ``sigma_steps^2`` with ``noise=`` (a variance of 150 draws scatters by 12 %;
    measured pp 1.05, tt 1.10); without it (the independent points' figure or the
    autocovariance's, the larger) the spread exceeds the prediction by more than 3 sigma
    (measured pp 1.60, tt 1.59; with 200 seeds pp 0.98 and 1.48, the independent points'
    figure alone 1.98 (tt 2.34 with 150), the autocovariance's alone 2.0: estimated
    from the residuals it catches little of this short-range correlation and scatters
    widely, 0.0-1.4 times the sandwich, 5-95 %). The levels and heights are the same
    with and without."""
    shape = (48, 64)
    rig, ((u1, v1), (u2, v2)) = _step_scene(kind, shape)
    rng = np.random.default_rng(5)
    n_runs = 150
    vals, pred, indep = [], [], []
    for _ in range(n_runs):
        a, b = _coords(u1, v1, _S1, rng), _coords(u2, v2, _S2, rng)
        m = match_stereo(rig, a, b, max_residual=None)
        sc = measure_steps(m.cloud, noise=match_noise(rig, a, b, m), min_points=100)
        si = measure_steps(m.cloud, min_points=100)
        assert sc.correlated and not si.correlated
        np.testing.assert_array_equal(sc.labels, si.labels)
        assert sc.step_heights.size == 1 and sc.step_heights[0] == si.step_heights[0]
        vals.append(sc.step_heights[0])
        pred.append(sc.sigma_steps[0] ** 2)
        indep.append(si.sigma_steps[0] ** 2)
    emp = np.var(vals, ddof=1)
    r, ri = emp / np.mean(pred), emp / np.mean(indep)
    tol = _var_ratio_tol(n_runs)
    print(kind, "step variance MC / predicted: correlated", r, "independent", ri, "tol", tol)
    assert abs(r - 1.0) <= tol, r
    assert ri - 1.0 > tol, ri


def test_noise_must_be_the_clouds():
    """``noise`` of another grid, or not covering the fitted points, is refused."""
    shape = (48, 64)
    rig, ((u1, v1), (u2, v2)) = _step_scene("pp", shape)
    a, b = _coords(u1, v1, _S1), _coords(u2, v2, _S2)
    m = match_stereo(rig, a, b, max_residual=None)
    nz = match_noise(rig, a, b, m)
    with pytest.raises(MetrologyError, match="noise has shape"):
        measure_steps(m.cloud, min_points=100, noise=StereoNoise(
            np.zeros((2, 2)), np.zeros((2, 2, 1)), np.full((2, 2, 1), -1)))
    holes = np.where(np.arange(shape[1])[None, :] % 7 == 0, np.nan, nz.var_own)
    with pytest.raises(MetrologyError, match="does not cover"):
        measure_steps(m.cloud, min_points=100,
                      noise=StereoNoise(holes, nz.weights, nz.sources))


@pytest.fixture(scope="module")
def stereo_steps_folder(tmp_path_factory):
    """The stereo preset binned 8 x 8, its default step gauge rendered by both cameras,
    written as scan folders with the true (bare) rig.json, and the folder
    ``reconstruct --second`` makes of them (no gamma correction: a fast test)."""
    from telefringe.cli.reconstruct import reconstruct_to_folder
    from telefringe.io.rig_json import bare_rig_json, load_rig
    from telefringe.io.scan_json import write_scan
    from telefringe.simulate.anyrig import scan_scene
    from telefringe.simulate.presets import bin_camera_any, get_preset
    from telefringe.simulate.scenes import default_steps

    tmp = tmp_path_factory.mktemp("stereo_steps")
    vrig = bin_camera_any(get_preset("stereo"), 8)
    scans, _ = scan_scene(vrig, default_steps(), seed=3)
    names = vrig.rig.camera_names
    for n in names:
        write_scan(tmp / n, scans[n])
    (tmp / "rig.json").write_text(json.dumps(bare_rig_json(vrig.rig)))
    cal = load_rig(tmp / "rig.json")
    reconstruct_to_folder(tmp / names[0], cal, tmp / "out", second=tmp / names[1],
                          ply=False, gamma_correction=False, read=lambda f: scans[f.name])
    return tmp, vrig, scans, cal


def test_measure_steps_cli_u_equals_the_api(stereo_steps_folder, capsys):
    """`measure steps OUT` on the stereo reconstruction reports the sigmas of the API
    with ``noise=`` to 1e-12 (no note); the same folder with points.npz written without
    the stereo keys (an older file) measures the same steps with the independent points'
    sigmas and a note."""
    from telefringe.cli import main
    from telefringe.reconstruction.pipeline import reconstruct_stereo_scans

    tmp, vrig, scans, cal = stereo_steps_folder
    names = vrig.rig.camera_names
    out = tmp / "out"
    js = tmp / "s.json"
    assert main(["measure", "steps", str(out), "--json", str(js), "--force"]) == 0
    err = capsys.readouterr()
    text = " ".join((err.out + err.err).split())
    assert "independent" not in text and "does not" not in text
    doc = json.loads(js.read_text())
    rec = reconstruct_stereo_scans(scans[names[0]], scans[names[1]], cal,
                                   with_height_map=False, gamma_correction=False)
    api = measure_steps(rec.cloud, noise=match_noise(cal.rig, rec.coords, rec.coords_2,
                                                     rec.match))
    ind = measure_steps(rec.cloud)
    assert api.correlated and len(doc["step_heights_mm"]) == api.step_heights.size == 4
    np.testing.assert_allclose(doc["step_heights_mm"], api.step_heights, rtol=1e-12)
    np.testing.assert_allclose(doc["sigma_steps_mm"], api.sigma_steps, rtol=1e-12)
    np.testing.assert_allclose(doc["sigma_heights_mm"], api.sigma_heights, rtol=1e-12)
    print("sigma_steps um: correlated", api.sigma_steps * 1e3, "independent",
          ind.sigma_steps * 1e3)
    assert np.all(api.sigma_steps >= ind.sigma_steps) and np.any(
        api.sigma_steps > ind.sigma_steps)
    # an older points.npz (no stereo keys): measured, the note, the independent sigmas
    with np.load(out / "points.npz") as z:
        arrays = {k: z[k] for k in z.files if not k.startswith("stereo_")}
    old = tmp / "old"
    old.mkdir()
    np.savez(old / "points.npz", **arrays)
    (old / "summary.json").write_text((out / "summary.json").read_text())
    assert main(["measure", "steps", str(old), "--json", str(js), "--force"]) == 0
    err = capsys.readouterr()
    assert "points.npz holds no stereo noise" in " ".join((err.out + err.err).split())
    doc = json.loads(js.read_text())
    np.testing.assert_allclose(doc["sigma_steps_mm"], ind.sigma_steps, rtol=1e-12)
