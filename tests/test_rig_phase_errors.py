"""The projector nonlinearity learned once (at calibration) and reused: stored in rig.json,
given to the decoder so that a scan is corrected without learning it again."""

from __future__ import annotations

import json

import numpy as np
import pytest

from telefringe.calibration.from_scans import calibrate_from_scans
from telefringe.fringes.decode import decode
from telefringe.fringes.nonlinearity import PhaseErrorModel, mean_model, periodic_error
from telefringe.fringes.phase import wrapped_phase
from telefringe.io.errors import InputError
from telefringe.io.rig_json import rig_from_json, rig_to_json
from telefringe.simulate.calibration import iter_calibration_set, simulate_calibration_poses
from telefringe.simulate.presets import get_preset
from telefringe.simulate.render import default_groups, render_scan
from telefringe.simulate.scenes import plate_at_z


@pytest.fixture(scope="module")
def fast_rig():
    return get_preset("fast")


@pytest.fixture(scope="module")
def calib(fast_rig):
    poses = simulate_calibration_poses(fast_rig, n_poses=5, seed=1)
    k = fast_rig.rig
    return calibrate_from_scans(
        ((name, scan) for name, scan, _, _ in iter_calibration_set(fast_rig, poses, seed=1)),
        fast_rig.target, (k.camera.intrinsics.du,) * 2, (k.projector.intrinsics.du,) * 2,
        "pose_00", projector_side="right")


def test_calibration_learns_a_model_per_fringe_group_and_rig_json_keeps_it(calib):
    groups = {(g.axis, g.periods, g.steps) for g in default_groups(get_preset("fast"))}
    assert set(calib.phase_errors) == groups
    # gamma 2.2 seen through 4 steps: the 4th harmonic of the coarsest group is there
    assert 4 in calib.phase_errors[("u", 1, 4)].harmonics
    back = rig_from_json(json.loads(json.dumps(rig_to_json(calib))))
    assert set(back.phase_errors) == groups
    for key, m in calib.phase_errors.items():
        b = back.phase_errors[key]
        assert b.periods == m.periods and b.harmonics == m.harmonics
        assert np.array_equal(b.cos_coef, m.cos_coef) and np.array_equal(b.sin_coef, m.sin_coef)


def test_a_scan_decoded_with_the_rigs_model_learns_nothing(calib, fast_rig):
    scan, truth = render_scan(fast_rig, plate_at_z(0.3), default_groups(fast_rig), seed=8)
    given = decode(scan, phase_errors=calib.phase_errors)
    fitted = decode(scan)
    for axis in ("u", "v"):
        assert given.axes[axis].phase_errors.n_samples == 0
        assert fitted.axes[axis].phase_errors.n_samples > 0
    # both remove the same nonlinearity: the coordinates agree to well within the noise
    both = given.mask & fitted.mask
    assert both.sum() > 0.9 * fitted.mask.sum()
    d = (given.u_p - fitted.u_p)[both]
    assert np.sqrt(np.mean(d ** 2)) < 0.3 * np.median(fitted.sigma_u_p[both])
    # no model for a group: that axis is learned from the scan as before
    partial = {k: m for k, m in calib.phase_errors.items() if k[0] == "u"}
    mixed = decode(scan, phase_errors=partial)
    assert mixed.axes["u"].phase_errors.n_samples == 0
    assert mixed.axes["v"].phase_errors.n_samples > 0


def test_a_three_step_model_learned_on_one_scan_corrects_another(fast_rig):
    groups = default_groups(fast_rig, axes=("u",), steps=3)
    width = fast_rig.projector.intrinsics.width
    first, _ = render_scan(fast_rig, plate_at_z(0.0), groups, seed=3, white=False, black=False)
    learned = {("u", m.periods, 3): m for m in decode(first).axes["u"].phase_errors.models}
    scan, truth = render_scan(fast_rig, plate_at_z(0.4), groups, seed=5, white=False,
                              black=False)
    lit = truth.lit & np.isin(truth.part, (0, 1))
    fine = wrapped_phase(scan.stacks[2], steps=3).phase  # the 64-period group
    true = 2 * np.pi * 64 * truth.u_p / width
    harm = range(1, 25)
    before = periodic_error(fine[lit], true[lit], harmonics=harm)
    after = periodic_error(learned[("u", 64, 3)].correct(fine)[lit], true[lit],
                           harmonics=harm)
    assert after.peak < before.peak / 10, (before.peak, after.peak)
    coords = decode(scan, phase_errors=learned)
    assert coords.axes["u"].phase_errors.n_samples == 0
    # every lit plate pixel valid and no wrong fringe order (a period is 6.25 px)
    err = (coords.u_p - truth.u_p)[lit]
    assert np.all(np.isfinite(err)) and np.max(np.abs(err)) < 1.0


def test_mean_model_and_bad_rig_json_entries():
    a = PhaseErrorModel(8, (4, 8), np.array([0.01, 0.0]), np.array([0.02, 0.004]))
    b = PhaseErrorModel(8, (4,), np.array([0.03]), np.array([0.0]))
    m = mean_model([a, b])
    assert m.harmonics == (4, 8)
    assert np.allclose(m.cos_coef, [0.02, 0.0]) and np.allclose(m.sin_coef, [0.01, 0.002])
    with pytest.raises(ValueError, match="different periods"):
        mean_model([a, PhaseErrorModel(1, (4,), np.zeros(1), np.zeros(1))])
    doc = {"format": "telefringe-rig", "version": 1, "world_frame": {},
           "camera": _device(), "projector": _device()}
    good = {"axis": "u", "periods": 8, "steps": 4, "harmonics": [4], "cos_rad": [0.01],
            "sin_rad": [0.0]}
    assert rig_from_json({**doc, "phase_errors": {"groups": [good]}}).phase_errors[
        ("u", 8, 4)].harmonics == (4,)
    for bad, token in (({"axis": "w"}, "axis"), ({"steps": 2}, "steps"),
                       ({"harmonics": [4, 4]}, "harmonics"), ({"cos_rad": [0.0, 1.0]}, "cos"),
                       ({"sin_rad": [None]}, "finite"), ({"sin_rad": [0.5]}, "invertible")):
        with pytest.raises(InputError, match=token):
            rig_from_json({**doc, "phase_errors": {"groups": [{**good, **bad}]}})
    with pytest.raises(InputError, match="second model"):
        rig_from_json({**doc, "phase_errors": {"groups": [good, good]}})


def _device():
    return {"width": 320, "height": 256, "pixel_size_mm": [0.005, 0.005], "m": 0.1,
            "principal_point_px": [160.0, 128.0], "distortion": {"k1": 0.0, "s1": 0.0,
                                                                 "s2": 0.0},
            "rotation_vector": [3.14159, 0.0, 0.0], "t_mm": [0.0, 0.0]}


def test_decode_command_uses_a_rigs_model(calib, fast_rig, tmp_path, capsys):
    from telefringe.cli import main
    from telefringe.io.rig_json import save_rig
    from telefringe.io.scan_json import write_scan

    scan, _ = render_scan(fast_rig, plate_at_z(0.2), default_groups(fast_rig), seed=9)
    write_scan(tmp_path / "scan", scan)
    save_rig(tmp_path / "rig.json", calib)
    capsys.readouterr()
    assert main(["-v", "decode", str(tmp_path / "scan"), "-o", str(tmp_path / "c.npz"),
                 "--rig", str(tmp_path / "rig.json")]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "the rig's model" in out and "learned from the scan" not in out
    # a rig.json without the model: said, and learned from the scan
    doc = json.loads((tmp_path / "rig.json").read_text())
    del doc["phase_errors"]
    (tmp_path / "bare.json").write_text(json.dumps(doc))
    assert main(["-v", "decode", str(tmp_path / "scan"), "-o", str(tmp_path / "d.npz"),
                 "--rig", str(tmp_path / "bare.json")]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "holds no projector nonlinearity" in out and "learned from the scan" in out
    # the rig of another projector: refused, nothing written
    doc["projector"]["width"] = 2 * doc["projector"]["width"]
    (tmp_path / "other.json").write_text(json.dumps(doc))
    assert main(["decode", str(tmp_path / "scan"), "-o", str(tmp_path / "e.npz"),
                 "--rig", str(tmp_path / "other.json")]) == 2
    assert "use the rig.json of the rig that took this scan" in " ".join(
        capsys.readouterr().err.split())
    assert not (tmp_path / "e.npz").exists()


def test_reconstruct_command_uses_a_rigs_model_unless_told_to_refit(calib, fast_rig,
                                                                     tmp_path, capsys):
    from telefringe.cli import main
    from telefringe.io.rig_json import save_rig
    from telefringe.io.scan_json import write_scan

    scan, _ = render_scan(fast_rig, plate_at_z(0.2), default_groups(fast_rig), seed=10)
    write_scan(tmp_path / "scan", scan)
    save_rig(tmp_path / "rig.json", calib)
    base = ["-v", "reconstruct", str(tmp_path / "scan"), "--rig", str(tmp_path / "rig.json"),
            "--no-ply"]
    capsys.readouterr()
    assert main([*base, "-o", str(tmp_path / "a")]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "the rig's model" in out and "learned from the scan" not in out
    assert main([*base, "-o", str(tmp_path / "b"), "--refit-gamma"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "learned from the scan" in out and "the rig's model" not in out
