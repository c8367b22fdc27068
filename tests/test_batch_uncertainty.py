"""`telefringe batch` with a calibrated rig (a parameter covariance): each row's figures
carry the calibration's part of their uncertainty, the same as `telefringe measure
--rig` computes for one scan; with a bare rig they hold the noise alone and say so.

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
from telefringe.io.rig_json import bare_rig_json, load_rig, save_rig
from telefringe.io.scan_json import read_scan, write_scan
from telefringe.metrology import measure_sphere
from telefringe.metrology.uncertainty import sphere_uncertainty
from telefringe.reconstruction.pipeline import reconstruct_scan
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
    # the one-scan computation: the same reconstruction, fit and propagation
    cal = load_rig(data / "rig.json")
    rec = reconstruct_scan(read_scan(data / "s0" / "scan"), cal, gamma_correction=False)
    want = sphere_uncertainty(measure_sphere(rec.cloud), rec.cloud, cal).uncertainty["radius"]
    assert want.u_calibration > 0
    for key in ("u_noise", "u_calibration", "u", "U"):
        np.testing.assert_allclose(row[f"sphere.uncertainty.radius.{key}"],
                                   getattr(want, key), rtol=1e-9, err_msg=key)
    assert row["sphere.uncertainty.radius.u"] > row["sphere.uncertainty.radius.u_noise"]


def test_a_bare_rig_gives_the_noise_alone(data):
    frame = measure_many([str(data / "s0" / "scan")], data / "bare.json", workers=0, **OPTS)
    row = frame.iloc[0]
    assert row["status"] == "ok", row["error"]
    assert not bool(row["sphere.uncertainty_includes_calibration"])
    assert not any(c.startswith("sphere.uncertainty.") for c in frame.columns)
