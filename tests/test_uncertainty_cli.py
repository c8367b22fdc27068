"""`telefringe measure ... --rig rig.json`: the calibration's uncertainty in the CLI's
output, the JSON summary and bga.csv (the virtual BGA read in a 160 x 160 px window of
the paper rig, with the covariance of a synthetic calibration)."""

from __future__ import annotations

import csv
import json
import shutil
from dataclasses import replace

import numpy as np
import pytest
from test_calibrate import synthetic_calibration

from telefringe.cli import main
from telefringe.io.rig_json import save_rig
from telefringe.simulate.experiments import bga_window
from telefringe.simulate.presets import crop_camera, get_preset


@pytest.fixture(scope="module")
def bga_and_rig(tmp_path_factory, bga_window_reconstruction):
    tmp = tmp_path_factory.mktemp("bga_unc")
    vr, out = bga_window_reconstruction
    shutil.copytree(out, tmp / "out")
    # a covariance of the right kind: a synthetic calibration of a paper-like rig
    cal = synthetic_calibration(11)
    params = np.concatenate([vr.rig.camera.to_params(), vr.rig.projector.to_params()])
    save_rig(tmp / "rig.json", replace(cal, rig=vr.rig, parameters=params))
    paper = get_preset("paper")
    col0, row0 = bga_window(paper, size=160)
    wrong = crop_camera(paper, col0=col0, row0=row0, width=150, height=160)
    save_rig(tmp / "wrong.json", replace(cal, rig=wrong.rig, parameters=params))
    return tmp


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_measure_bga_with_the_calibration(bga_and_rig, capsys):
    tmp = bga_and_rig
    js = tmp / "bga.json"
    assert main(["measure", "bga", str(tmp / "out"), "--rig", str(tmp / "rig.json"),
                 "--json", str(js), "--force"]) == 0
    text = capsys.readouterr()
    said = text.out + text.err
    assert "U (k=2)" in said and "calibration" in said
    res = json.loads(js.read_text())
    assert res["uncertainty_includes_calibration"] is True
    unc = res["uncertainty"]
    assert set(unc) == {"height", "position", "pitch_x", "pitch_y", "pitch_error_max",
                        "coplanarity"}
    h = unc["height"]
    u_cal = np.asarray(h["u_calibration"])
    assert u_cal.shape == (res["balls_found"],) and np.all(u_cal > 0)
    np.testing.assert_allclose(h["U"], 2 * np.asarray(h["u"]))
    np.testing.assert_allclose(h["u"], np.hypot(h["u_noise"], u_cal))
    np.testing.assert_allclose(h["u_noise"], res["balls"]["sigma_height_mm"])
    rows = [r for r in _rows(tmp / "out" / "bga.csv") if r["status"] == "ok"]
    assert len(rows) == res["balls_found"]
    uh = np.array([float(r["u_height_mm"]) for r in rows])
    np.testing.assert_allclose(uh, h["u"], atol=1e-6)
    np.testing.assert_allclose([float(r["U_height_mm"]) for r in rows], 2 * uh, atol=2e-6)
    np.testing.assert_allclose([float(r["u_cal_height_mm"]) for r in rows], u_cal, atol=1e-6)
    assert all(float(r["U_pos_x_mm"]) > 0 for r in rows)
    # without --rig: the noise alone, said so; the CSV's new columns empty
    assert main(["measure", "bga", str(tmp / "out"), "--json", str(js), "--force"]) == 0
    res = json.loads(js.read_text())
    assert res["uncertainty_includes_calibration"] is False and res["uncertainty"] is None
    assert all(r["u_height_mm"] == "" for r in _rows(tmp / "out" / "bga.csv"))


def test_a_rig_of_another_camera_is_refused(bga_and_rig, capsys):
    tmp = bga_and_rig
    js = tmp / "never.json"
    assert main(["measure", "bga", str(tmp / "out"), "--rig", str(tmp / "wrong.json"),
                 "--json", str(js), "--force"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--rig must be the rig that made it" in err[0]
    assert not js.exists()
