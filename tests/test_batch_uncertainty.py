"""`telefringe batch` with a calibrated rig (a parameter covariance): each row's figures
carry the calibration's part of their uncertainty, the same as `telefringe measure
--rig` reports for one scan (the sphere fitted through the camera's point-spread model);
with a bare rig they hold the noise alone and say so.

In this process (``workers=0``: the Dask side is tested in test_batch.py), on a sphere
read out in a 120 x 100 px window of the fast rig, the covariance that of a synthetic
calibration of a paper-like rig (as test_uncertainty_cli.py)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from test_calibrate import synthetic_calibration

import telefringe.simulate.render as sim
from telefringe.batch import measure_many
from telefringe.batch.job import flatten_summary
from telefringe.cli import main
from telefringe.cli.reconstruct import reconstruct_to_folder
from telefringe.io.rig_json import bare_rig_json, load_rig, save_rig
from telefringe.io.scan_json import write_scan
from telefringe.simulate import scenes
from telefringe.simulate.presets import crop_camera, get_preset

OPTS = {"measure": "sphere", "gamma_correction": False}


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("batch_unc")
    vr = crop_camera(get_preset("fast"), col0=100, row0=80, width=120, height=100)
    scan, _ = sim.render_scan(vr, scenes.make_scene("sphere"), sim.default_groups(vr), seed=0)
    (root / "s0").mkdir()
    write_scan(root / "s0" / "scan", scan)
    cal = synthetic_calibration(11)
    params = np.concatenate([vr.rig.camera.to_params(), vr.rig.projector.to_params()])
    save_rig(root / "rig.json", replace(cal, rig=vr.rig, parameters=params))
    (root / "bare.json").write_text(json.dumps(bare_rig_json(vr.rig)))
    return root


def test_rows_carry_the_calibrations_uncertainty(data):
    frame = measure_many([str(data / "s0" / "scan")], data / "rig.json", workers=0, **OPTS)
    row = frame.iloc[0]
    assert row["status"] == "ok", row["error"]
    assert bool(row["sphere.uncertainty_includes_calibration"])
    # the one-scan commands: reconstruct, then measure sphere --rig (the fit through the
    # camera's point-spread model, the calibration's part): every figure of the row
    cal = load_rig(data / "rig.json")
    reconstruct_to_folder(data / "s0" / "scan", cal, data / "one", ply=False,
                          gamma_correction=False, force=True)
    js = data / "one.json"
    assert main(["measure", "sphere", str(data / "one"), "--rig", str(data / "rig.json"),
                 "--json", str(js), "--force"]) == 0
    want = flatten_summary(json.loads(js.read_text()), "sphere")
    assert want["sphere.uncertainty.radius.u_calibration"] > 0
    assert want["sphere.point_spread.variance_px2"] is not None  # the point-spread model's fit
    for key, v in want.items():
        if isinstance(v, float):
            np.testing.assert_allclose(row[key], v, rtol=1e-9, err_msg=key)
        else:
            assert row[key] == v, key
    assert row["sphere.uncertainty.radius.u"] > row["sphere.uncertainty.radius.u_noise"]


def test_a_bare_rig_gives_the_noise_alone(data):
    frame = measure_many([str(data / "s0" / "scan")], data / "bare.json", workers=0, **OPTS)
    row = frame.iloc[0]
    assert row["status"] == "ok", row["error"]
    assert not bool(row["sphere.uncertainty_includes_calibration"])
    assert not any(c.startswith("sphere.uncertainty.") for c in frame.columns)
