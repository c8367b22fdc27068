"""Virtual rig outputs: calibration poses, scan folders, ground truth on disk, the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from telefringe.cli import main
from telefringe.io.calibration_json import load_calibration_set
from telefringe.io.errors import InputError
from telefringe.io.scan_json import read_scan, write_scan
from telefringe.io.truth import read_truth, write_truth
from telefringe.simulate.calibration import (
    mirror_pose,
    render_calibration_set,
    simulate_calibration_poses,
)
from telefringe.simulate.presets import get_preset
from telefringe.simulate.render import default_groups, render_scan
from telefringe.simulate.scenes import plate_from_target, tilted_plane


@pytest.fixture(scope="module")
def fast():
    return get_preset("fast")


def _camera_image(vrig, pose):
    pts = plate_from_target(vrig.target, pose.R_world_target,
                            pose.t_world_target).circle_centres_world()
    return np.stack(vrig.camera.project(pts), -1), np.stack(vrig.projector.project(pts), -1), pts


@pytest.mark.parametrize("name", ["paper", "fast"])
def test_calibration_poses(name):
    vr = get_preset(name)
    poses = simulate_calibration_poses(vr, n_poses=12, seed=3)
    assert [p.name for p in poses] == [f"pose_{i:02d}" for i in range(12)]
    assert poses[0].kind == "reference"
    np.testing.assert_array_equal(poses[0].R_world_target, np.eye(3))
    np.testing.assert_array_equal(poses[0].t_world_target, np.zeros(3))
    kinds = [p.kind for p in poses]
    assert kinds.count("mirror-a") == 1 and kinds.count("mirror-b") == 1
    assert kinds[-1] == "half-hidden"
    tilts = []
    for p in poses:
        cam, proj, pts = _camera_image(vr, p)
        assert np.abs(pts[:, 2]).max() <= vr.depth_of_field_mm / 2 + 0.5
        assert np.all((proj[:, 0] > 0) & (proj[:, 0] < vr.projector.intrinsics.width))
        inside = ((cam[:, 0] > 0) & (cam[:, 0] < vr.camera.intrinsics.width - 1)
                  & (cam[:, 1] > 0) & (cam[:, 1] < vr.camera.intrinsics.height - 1))
        if p.kind == "half-hidden":
            assert 0.3 < inside.mean() < 0.85
        else:
            assert inside.all()
        tilts.append(np.degrees(np.arccos(p.R_world_target[2, 2])))
    assert max(tilts) > 8.0 and sorted(tilts)[1] >= 4.9
    # the mirror pair: identical camera images, different projector images
    a, b = (poses[kinds.index(k)] for k in ("mirror-a", "mirror-b"))
    ca, pa, _ = _camera_image(vr, a)
    cb, pb, _ = _camera_image(vr, b)
    np.testing.assert_allclose(ca, cb, atol=1e-9)
    assert np.abs(pa - pb).max() > 1.0
    R2, t2 = mirror_pose(vr, b.R_world_target, b.t_world_target)
    np.testing.assert_allclose(R2, a.R_world_target, atol=1e-12)
    np.testing.assert_allclose(t2, a.t_world_target, atol=1e-9)
    # deterministic
    again = simulate_calibration_poses(vr, n_poses=12, seed=3)
    for p, q in zip(poses, again, strict=True):
        np.testing.assert_array_equal(p.R_world_target, q.R_world_target)


def test_calibration_poses_refuse_too_few():
    with pytest.raises(ValueError, match="n_poses"):
        simulate_calibration_poses(get_preset("fast"), n_poses=3)


def test_render_calibration_set_in_memory(fast):
    groups = default_groups(fast, periods_u=(1, 8), periods_v=(1, 8))
    poses, man = render_calibration_set(fast, n_poses=4, seed=1, groups=groups)
    assert man.poses == tuple(name for name, _, _ in poses)
    assert man.reference_pose == "pose_00"
    assert man.target == fast.target
    assert man.camera_pixel_size == (0.0208, 0.0208)
    ref_truth = poses[0][2]
    np.testing.assert_allclose(ref_truth.features["circle_centres_world"][:, 2], 0.0)
    assert ref_truth.features["circle_in_image"].all()
    assert poses[-1][2].features["pose_kind"] == "half-hidden"
    assert not poses[-1][2].features["circle_in_image"].all()


def test_truth_round_trip_and_never_inside_a_scan(tmp_path, fast):
    scan, truth = render_scan(fast, tilted_plane(5.0), default_groups(fast)[:1], seed=0)
    folder = write_scan(tmp_path / "scan", scan)
    write_truth(tmp_path / "truth", "scan", truth, extra={"note": "x"})
    back = read_truth(tmp_path / "truth", "scan")
    np.testing.assert_array_equal(back.lit, truth.lit)
    np.testing.assert_allclose(back.u_p, truth.u_p, rtol=6e-8)           # stored as float32
    np.testing.assert_allclose(back.xyz_world, truth.xyz_world, rtol=6e-8, atol=1e-9)
    assert np.array_equal(np.isnan(back.u_p), np.isnan(truth.u_p))
    np.testing.assert_allclose(back.features["normal"], truth.features["normal"])
    doc = json.loads((tmp_path / "truth" / "scan.json").read_text())
    assert doc["features"]["type"] == "tilted-plane" and doc["note"] == "x"
    with pytest.raises(InputError, match="inside a scan folder"):
        write_truth(folder, "t", truth)
    with pytest.raises(InputError, match="inside a scan folder"):
        write_truth(folder / "sub", "t", truth)
    reread = read_scan(folder)
    assert reread.manifest.groups[0].key == scan.manifest.groups[0].key
    np.testing.assert_array_equal(reread.stacks[0], scan.stacks[0])
    np.testing.assert_array_equal(reread.white, scan.white)
    with pytest.raises(InputError, match="not found"):
        read_truth(tmp_path / "truth", "missing")


def test_cli_simulate_scan(tmp_path, capsys):
    out = tmp_path / "sim"
    assert main(["-q", "simulate", "scan", str(out), "--rig", "fast", "--scene", "sphere",
                 "--seed", "2"]) == 0
    scan = read_scan(out / "scan")
    assert len(scan.manifest.groups) == 6 and scan.white is not None
    assert scan.shape == (256, 320)
    assert not any(p.suffix in (".npz",) or "truth" in p.name for p in (out / "scan").iterdir())
    truth = read_truth(out / "truth", "scan")
    assert truth.lit.shape == scan.shape
    rig = json.loads((out / "truth" / "rig_true.json").read_text())
    assert rig["camera"]["intrinsics"]["width"] == 320
    # refuses to overwrite without --force, with one line and status 2
    capsys.readouterr()
    assert main(["simulate", "scan", str(out), "--rig", "fast", "--scene", "plate"]) == 2
    err = capsys.readouterr().err
    assert "already exists" in err and "Traceback" not in err
    assert main(["simulate", "scan", str(tmp_path / "x"), "--rig", "fast", "--scene", "bga",
                 "--z", "1"]) == 2
    assert main(["simulate", "scan", str(tmp_path / "y"), "--rig", "fast", "--scene",
                 "plate", "--z", "50"]) == 2
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_cli_simulate_calibration(tmp_path):
    out = tmp_path / "cal"
    assert main(["-q", "simulate", "calibration", str(out), "--rig", "fast", "--poses", "4",
                 "--seed", "1"]) == 0
    man = load_calibration_set(out / "calibration")
    assert man.poses == ("pose_00", "pose_01", "pose_02", "pose_03")
    assert man.reference_pose == "pose_00"
    scan = read_scan(out / "calibration" / "pose_02")
    assert scan.shape == (256, 320)
    for p in man.poses:
        assert (out / "truth" / f"{p}.npz").is_file()
        assert not list((out / "calibration" / p).glob("*.npz"))
    doc = json.loads((out / "truth" / "pose_01.json").read_text())
    assert doc["pose"]["kind"] in ("mirror-a", "random")
    assert len(doc["features"]["circle_centres_px"]) == 99
    assert main(["simulate", "calibration", str(tmp_path / "z"), "--poses", "2"]) == 2


def test_cli_hdr_help_names_the_exposures_the_rig_uses(capsys):
    from telefringe.simulate.presets import HDR_EXPOSURES

    assert main(["simulate", "scan", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert ", ".join(f"{e:g}" for e in HDR_EXPOSURES[:-1]) + f" and {HDR_EXPOSURES[-1]:g}" \
        in text, text


def test_rig_true_json_holds_the_exact_true_rig():
    """rig_true.json (through the one JSON converter) keeps every intrinsic and the pose of
    both devices exactly, and the photometry and target as their dataclasses' fields."""
    import dataclasses

    from telefringe.devices.telecentric import Intrinsics
    from telefringe.io.truth import true_rig_to_json
    from telefringe.simulate.presets import get_preset

    vr = get_preset("paper")
    doc = json.loads(json.dumps(true_rig_to_json(vr), allow_nan=False))
    assert doc["format"] == "telefringe-truth-rig" and doc["version"] == 1
    for name in ("camera", "projector"):
        dev, d = getattr(vr, name), doc[name]
        assert Intrinsics(**d["intrinsics"]) == dev.intrinsics
        assert np.array_equal(d["R_dev_world"], dev.R_dev_world)
        assert np.array_equal(d["rotvec"], dev.rotvec)
        assert np.array_equal(d["t_dev_mm"], dev.t_dev)
        assert np.array_equal(d["axis_world"], dev.axis_world)
    assert doc["photometry"] == json.loads(json.dumps(dataclasses.asdict(vr.photometry)))
    assert doc["target"] == json.loads(json.dumps(dataclasses.asdict(vr.target)))
