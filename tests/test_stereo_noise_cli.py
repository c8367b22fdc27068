"""The stereo matches' correlated noise from the command line (issue 11): the folder
``reconstruct --second`` writes keeps the match's noise split in points.npz, and
``telefringe measure sphere --rig`` fits with it: the same u as the API's
``measure_sphere(..., noise=match_noise(...))``; a folder written before (no stereo keys)
still measures, with a note that the correlation is not included."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest


@pytest.fixture(scope="module")
def stereo_folder(tmp_path_factory):
    """The stereo preset binned 8 x 8, its default sphere rendered by both cameras,
    written as scan folders, a rig.json with a covariance (a calibration of this rig from
    synthetic corners, its parameters replaced by the true rig's, the projector's
    nonlinearity model the identity so that decoding learns nothing: a fast test), and the
    folder ``reconstruct --second`` makes of them."""
    from test_anyrig_sim import _observations

    from telefringe.calibration.rig import calibrate_devices
    from telefringe.cli.reconstruct import reconstruct_to_folder
    from telefringe.fringes.nonlinearity import PhaseErrorModel
    from telefringe.fringes.scan import PhaseGroup
    from telefringe.io.rig_json import load_rig, save_rig
    from telefringe.io.scan_json import write_scan
    from telefringe.simulate.anyrig import scan_scene
    from telefringe.simulate.calibration import simulate_calibration_poses
    from telefringe.simulate.presets import bin_camera_any, get_preset
    from telefringe.simulate.scenes import default_sphere

    tmp = tmp_path_factory.mktemp("stereo_cli")
    vrig = bin_camera_any(get_preset("stereo"), 8)
    scans, _ = scan_scene(vrig, default_sphere(), seed=3)
    names = vrig.rig.camera_names
    for n in names:
        write_scan(tmp / n, scans[n])
    poses = simulate_calibration_poses(vrig, n_poses=6, seed=3, half_hidden=False)
    P, obs, devs = _observations(vrig.rig, vrig.target, poses, 0.03, seed=6)
    cal = calibrate_devices(P, obs, models={"camera": "pinhole", "camera_2": "pinhole",
                                            "projector": "pinhole"},
                            pixel_sizes={}, image_sizes={k: d.image_size
                                                         for k, d in devs.items()})
    params = np.concatenate([d.to_params() for d in devs.values()])
    identity = {(g.axis, int(g.periods), int(g.steps)): PhaseErrorModel.zero(g.periods)
                for g in scans[names[0]].manifest.groups if isinstance(g, PhaseGroup)}
    save_rig(tmp / "rig.json", replace(cal, rig=vrig.rig, parameters=params,
                                       phase_errors=identity))
    cal = load_rig(tmp / "rig.json")
    reconstruct_to_folder(tmp / names[0], cal, tmp / "out", second=tmp / names[1],
                          ply=False, noise="auto", read=lambda f: scans[f.name])
    return tmp, vrig, scans, cal


def test_measure_sphere_cli_u_equals_the_api(stereo_folder, capsys):
    """`measure sphere OUT --rig` on the stereo reconstruction reports the u (noise part)
    of the API with ``noise=`` to 1e-12, larger than the independent points'; the same
    folder with points.npz written without the stereo keys (an older file) measures the
    same sphere with the independent points' u and a note."""
    from telefringe.cli import main
    from telefringe.fringes.images import scan_radiance
    from telefringe.io.points_npz import load_points
    from telefringe.metrology import measure_sphere
    from telefringe.metrology.spheres import finest_fringe_periods
    from telefringe.reconstruction.pipeline import reconstruct_stereo_scans
    from telefringe.reconstruction.stereo import match_noise

    tmp, vrig, scans, cal = stereo_folder
    names = vrig.rig.camera_names
    out = tmp / "out"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stereo_noise"] is True
    assert load_points(out).stereo_noise is not None
    js = tmp / "s.json"
    assert main(["measure", "sphere", str(out), "--rig", str(tmp / "rig.json"), "--json",
                 str(js), "--force"]) == 0
    err = capsys.readouterr()
    assert "independent" not in err.out + err.err
    doc = json.loads(js.read_text())
    # the API: the same decoding and match as 'reconstruct --second', the noise split
    rec = reconstruct_stereo_scans(scans[names[0]], scans[names[1]], cal,
                                   with_height_map=False, noise="auto")
    kw = {"rig": cal.rig, "image": rec.radiance, "image_2": scan_radiance(scans[names[1]]),
          "fringe_periods": finest_fringe_periods(scans[names[0]].manifest)}
    # the cloud as the command reads it back from points.npz: with the same xyz, the
    # fit's covariance on it and on the in-memory cloud differed by 6e-11 relative
    # (measured), so the API is given the cloud the command measures
    cloud = load_points(out).cloud
    np.testing.assert_array_equal(cloud.xyz, rec.cloud.xyz)
    api = measure_sphere(cloud, noise=match_noise(cal.rig, rec.coords, rec.coords_2,
                                                  rec.match), **kw).sphere
    ind = measure_sphere(cloud, **kw).sphere
    u = doc["uncertainty"]["radius"]["u_noise"]
    assert doc["radius_mm"] == pytest.approx(api.radius, rel=1e-12)
    assert u == pytest.approx(api.sigma_radius, rel=1e-12)
    np.testing.assert_allclose(doc["uncertainty"]["centre"]["u_noise"], api.sigma_centre,
                               rtol=1e-12)
    assert api.sigma_radius > ind.sigma_radius
    # an older points.npz (no stereo keys): measured, the note, the independent u
    with np.load(out / "points.npz") as z:
        arrays = {k: z[k] for k in z.files if not k.startswith("stereo_")}
    old = tmp / "old"
    old.mkdir()
    np.savez(old / "points.npz", **arrays)
    (old / "summary.json").write_text((out / "summary.json").read_text())
    assert main(["measure", "sphere", str(old), "--rig", str(tmp / "rig.json"), "--json",
                 str(js), "--force"]) == 0
    err = capsys.readouterr()
    assert "points.npz holds no stereo noise" in " ".join((err.out + err.err).split())
    doc = json.loads(js.read_text())
    assert doc["radius_mm"] == pytest.approx(api.radius, rel=1e-12)
    assert doc["uncertainty"]["radius"]["u_noise"] == pytest.approx(ind.sigma_radius,
                                                                    rel=1e-12)
