"""Degenerate data, tried on purpose (issue 6): the real ``telefringe`` command, run in a
subprocess on inputs made with the small "fast" virtual rig, must end each case with exit
status 2 and one error line naming the input and the problem -- never a traceback."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

import telefringe.simulate.render as sim
from telefringe.io.rig_json import bare_rig_json
from telefringe.io.scan_json import write_scan
from telefringe.simulate.presets import get_preset
from telefringe.simulate.scenes import plate_at_z


def _run(*args, cwd):
    return subprocess.run([sys.executable, "-m", "telefringe.cli", *map(str, args)],
                          capture_output=True, text=True, cwd=cwd, timeout=300)


def _error_line(proc) -> str:
    """The one error line of a failed run (checks status 2 and no traceback)."""
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1, proc.stderr
    return errors[0]


def _map_images(scan, f):
    return replace(scan, stacks=[f(s) for s in scan.stacks],
                   white=None if scan.white is None else f(scan.white),
                   black=None if scan.black is None else f(scan.black))


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """A folder with a plate scan of the fast rig (``scan``) and that rig's true devices
    as a hand-written rig.json (the file format allows leaving out the calibration
    report), made once."""
    tmp = tmp_path_factory.mktemp("degenerate")
    vr = get_preset("fast")
    scan, _ = sim.render_scan(vr, plate_at_z(0.0), sim.default_groups(vr), seed=6)
    write_scan(tmp / "scan", scan)
    (tmp / "rig.json").write_text(json.dumps(bare_rig_json(vr.rig, reference_pose="pose_00"),
                                             indent=1))
    return tmp, scan, vr


def test_all_dark_scan_decode(work):
    tmp, scan, _ = work
    write_scan(tmp / "dark", _map_images(scan, np.zeros_like))
    line = _error_line(_run("decode", "dark", "-o", "dark.npz", cwd=tmp))
    assert "dark" in line and "no pixel shows the fringes" in line
    assert not (tmp / "dark.npz").exists()


def test_all_saturated_scan_decode(work):
    tmp, scan, _ = work
    assert scan.max_value == 255
    write_scan(tmp / "bright", _map_images(scan, lambda s: np.full_like(s, 255)))
    line = _error_line(_run("decode", "bright", "-o", "bright.npz", cwd=tmp))
    assert "bright" in line and "saturated" in line
    assert not (tmp / "bright.npz").exists()


def test_projector_size_mismatch_reconstruct(work):
    tmp, _, vr = work
    shutil.copytree(tmp / "scan", tmp / "otherproj")
    man = json.loads((tmp / "otherproj" / "scan.json").read_text())
    k = vr.projector.intrinsics
    assert man["projector"] == {"width": k.width, "height": k.height}
    man["projector"] = {"width": 2 * k.width, "height": 2 * k.height}
    (tmp / "otherproj" / "scan.json").write_text(json.dumps(man))
    line = _error_line(_run("reconstruct", "otherproj", "--rig", "rig.json", "-o", "out_p",
                            cwd=tmp))
    assert "otherproj" in line and "projector" in line
    assert f"{2 * k.width} x {2 * k.height}" in line and f"{k.width} x {k.height}" in line
    assert not (tmp / "out_p").exists()


def test_camera_size_mismatch_reconstruct(work):
    tmp, scan, vr = work
    k = vr.camera.intrinsics
    w, h = k.width - 80, k.height - 56
    write_scan(tmp / "cropped", _map_images(scan, lambda s: s[..., :h, :w].copy()))
    line = _error_line(_run("reconstruct", "cropped", "--rig", "rig.json", "-o", "out_c",
                            cwd=tmp))
    assert "cropped" in line and "camera" in line
    assert f"{w} x {h}" in line and f"{k.width} x {k.height}" in line
    assert not (tmp / "out_c").exists()


def test_calibration_set_of_one_repeated_pose(work):
    tmp = work[0]
    proc = _run("simulate", "calibration", "cal", "--rig", "fast", "--poses", "4", "--seed", "6",
                cwd=tmp)
    assert proc.returncode == 0, proc.stderr
    cal = tmp / "cal" / "calibration"
    poses = sorted(p for p in cal.iterdir() if p.is_dir())
    assert [p.name for p in poses] == ["pose_00", "pose_01", "pose_02", "pose_03"]
    for p in poses[1:]:
        shutil.rmtree(p)
        shutil.copytree(poses[0], p)
    line = _error_line(_run("calibrate", cal, "-o", "same.json", "--no-gamma", cwd=tmp))
    assert str(cal) in line and "same tilt in every pose" in line
    assert not (tmp / "same.json").exists()
