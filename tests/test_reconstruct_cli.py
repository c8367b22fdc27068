"""`telefringe reconstruct` / `telefringe measure` on a simulated scan folder."""

from __future__ import annotations

import json

import numpy as np
import pytest

import telefringe.simulate.render as sim
from telefringe.cli import main
from telefringe.cli.reconstruct import reconstruct_to_folder
from telefringe.io.errors import InputError
from telefringe.io.scan_json import write_scan
from telefringe.simulate import scenes
from telefringe.simulate.presets import get_preset


@pytest.fixture(scope="module")
def plate_out(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("recon")
    vr = get_preset("fast")
    scan, truth = sim.render_scan(vr, scenes.plate_at_z(-0.5), sim.default_groups(vr), seed=2)
    write_scan(tmp / "scan", scan)
    out = tmp / "out"
    rec = reconstruct_to_folder(tmp / "scan", vr.rig, out, gamma_correction=False)
    return tmp, out, rec, vr


def test_reconstruct_folder_outputs(plate_out):
    tmp, out, rec, vr = plate_out
    names = {p.name for p in out.iterdir()}
    assert {"points.npz", "cloud.ply", "heightmap.tif", "heightmap.json", "heightmap.png",
            "summary.json"} <= names
    summary = json.loads((out / "summary.json").read_text())
    assert summary["valid"] == rec.cloud.count > 0
    # measured 7.35 um for seeds 2 (this one), 3, 4: within 2x either way
    assert 3.7e-3 < summary["sigma_z_median_mm"] < 14.7e-3, summary["sigma_z_median_mm"]
    # no overwrite without force, and nothing half-written on failure
    with pytest.raises(InputError, match="already exists"):
        reconstruct_to_folder(tmp / "scan", vr.rig, out)
    # a rig whose projector does not match the scan's patterns
    from dataclasses import replace

    from telefringe.devices.rig import Rig
    from telefringe.devices.telecentric import TelecentricDevice

    p = vr.rig.projector
    bad = Rig(vr.rig.camera, TelecentricDevice(replace(p.intrinsics, width=800, height=600),
                                               p.R_dev_world, p.t_dev))
    with pytest.raises(InputError, match="projector"):
        reconstruct_to_folder(tmp / "scan", bad, tmp / "bad")
    assert not (tmp / "bad").exists()
    c = vr.rig.camera
    bad = Rig(TelecentricDevice(replace(c.intrinsics, width=640, height=512), c.R_dev_world,
                                c.t_dev), vr.rig.projector)
    with pytest.raises(InputError, match="does not belong"):
        reconstruct_to_folder(tmp / "scan", bad, tmp / "bad")
    assert not (tmp / "bad").exists()


def test_measure_plate_cli(plate_out, capsys):
    tmp, out, rec, vr = plate_out
    js = tmp / "plate.json"
    assert main(["measure", "plate", str(out), "--json", str(js)]) == 0
    res = json.loads(js.read_text())
    # the true rig: Z against the fit's sigma (0.032 um; measured errors 2.3, 0.6, 2.0
    # sigma for seeds 2 (this one), 3, 4), the mean distances against their standard
    # error std / sqrt(n) ~ 0.10 um (measured 0.6-0.9 of it)
    assert abs(res["z_mm"] + 0.5) < 4 * res["sigma_z_mm"], (res["z_mm"], res["sigma_z_mm"])
    sp = res["spacing"]
    assert sp["n_x"] == 90 and sp["n_y"] == 88
    for ax in ("x", "y"):
        se = sp[f"std_{ax}_mm"] / np.sqrt(sp[f"n_{ax}"])
        assert abs(sp[f"mean_{ax}_mm"] - 3.0) < 4 * se, (ax, sp[f"mean_{ax}_mm"], se)
    printed = capsys.readouterr().out
    assert "Z = -0.499" in printed or "Z = -0.500" in printed
    # an existing JSON is not replaced without --force
    assert main(["measure", "plate", str(out), "--json", str(js)]) == 2
    assert main(["measure", "plate", str(out), "--json", str(js), "--force"]) == 0


def test_measure_errors(plate_out, tmp_path, capsys):
    tmp, out, rec, vr = plate_out
    assert main(["measure", "steps", str(tmp_path)]) == 2
    assert "not found" in capsys.readouterr().err
    # a plate has no balls
    assert main(["measure", "bga", str(out), "--rows", "4", "--cols", "4", "--csv",
                 str(tmp_path / "b.csv"), "--map", str(tmp_path / "b.png")]) == 2
    assert "no ball" in capsys.readouterr().err.replace("\n", " ")
    assert not (tmp_path / "b.csv").exists()
    # the wrong grid size
    assert main(["measure", "plate", str(out), "--rows", "5", "--cols", "5"]) == 2
    assert main(["measure", "--help"]) == 0


def test_height_map_of_the_plate(plate_out):
    from telefringe.io.tiff import read_height_tiff

    tmp, out, rec, vr = plate_out
    hm = read_height_tiff(out / "heightmap.tif")
    z = hm.z[np.isfinite(hm.z)]
    # the plate at -0.5 mm fills most of the map; markers' edges add a few outliers.
    # Measured median error +0.074, +0.004, +0.098 um (seeds 2 (this one), 3, 4; the
    # median's standard error is ~0.03 um, the markers' edges skew it): bound 2x the largest
    assert np.median(z) == pytest.approx(-0.5, abs=0.2e-3)
    assert hm.pixel_mm == pytest.approx(0.0208 / 0.1597, rel=0.02)


def write_rig_json(path, rig):
    """A rig.json of a Rig without a calibration report."""
    from telefringe.io.rig_json import bare_rig_json

    path.write_text(json.dumps(bare_rig_json(rig, reference_pose="truth")))
    return path


def test_reconstruct_command_refuses_the_rig_of_another_projector(plate_out, tmp_path,
                                                                  capsys):
    """The projector-size check is reconstruct_scan's (the command has none of its own):
    the user sees one line naming the scan and both sizes, status 2, nothing written."""
    from dataclasses import replace

    from telefringe.devices.rig import Rig
    from telefringe.devices.telecentric import TelecentricDevice

    tmp, out, rec, vr = plate_out
    p = vr.rig.projector
    w, h = p.intrinsics.width + 16, p.intrinsics.height + 8
    bad = Rig(vr.rig.camera, TelecentricDevice(replace(p.intrinsics, width=w, height=h),
                                               p.R_dev_world, p.t_dev))
    rig_json = write_rig_json(tmp_path / "rig.json", bad)
    capsys.readouterr()
    assert main(["reconstruct", str(tmp / "scan"), "--rig", str(rig_json), "-o",
                 str(tmp_path / "o"), "--no-gamma-correction"]) == 2
    err = capsys.readouterr().err  # the finished "reading images" bar, then the error
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1] == (
        f"error: {tmp / 'scan'}: the scan's patterns are for a {p.intrinsics.width} x "
        f"{p.intrinsics.height} projector but the rig's projector is {w} x {h}: use the "
        "rig.json of the rig that took this scan")
    assert not (tmp_path / "o").exists()


def test_reconstruct_command(plate_out, tmp_path, capsys):
    tmp, out, rec, vr = plate_out
    rig_json = write_rig_json(tmp_path / "rig.json", vr.rig)
    out2 = tmp_path / "out2"
    assert main(["reconstruct", str(tmp / "scan"), "--rig", str(rig_json), "-o", str(out2),
                 "--no-gamma-correction", "--no-ply"]) == 0
    assert (out2 / "points.npz").exists() and not (out2 / "cloud.ply").exists()
    from telefringe.io.points_npz import read_points

    cloud, texture = read_points(out2)
    assert cloud.count == rec.cloud.count
    assert np.allclose(cloud.xyz, rec.cloud.xyz, equal_nan=True, atol=1e-9)
    assert "points" in capsys.readouterr().out
    # user errors: one line, exit status 2, nothing written
    assert main(["reconstruct", str(tmp / "scan"), "--rig", str(tmp_path / "nope.json"),
                 "-o", str(tmp_path / "o3")]) == 2
    assert main(["reconstruct", str(tmp / "scan"), "--rig", str(rig_json), "-o",
                 str(tmp_path / "o4"), "--pixel-mm", "-1"]) == 2
    assert not (tmp_path / "o3").exists() and not (tmp_path / "o4").exists()
