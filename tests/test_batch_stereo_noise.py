"""`telefringe batch --second` on a two-camera rig: each scan is matched with its second
camera's scan as ``reconstruct --second`` does, points.npz keeps the matches' noise split,
and the row's figures carry the matches' correlated noise (neighbouring matches share the
second camera's pixels): the same u as ``telefringe measure steps`` reports on the
one-scan reconstruction, larger than the independent points' figure.

The sphere with a calibrated two-camera rig.json: the row equals ``telefringe measure
sphere --rig`` (the fit through both cameras' point-spread model with the matches' noise,
the calibration's part through both cameras).

In this process (``workers=0``), on the stereo preset binned 8 x 8 (as
test_stereo_noise_steps.py and test_stereo_noise_cli.py, whose calibrated stereo folder
is reused)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from anyrig_rigs import write_stereo_scan
from test_stereo_noise_cli import stereo_folder  # noqa: F401 - the fixture

from telefringe.batch import measure_many
from telefringe.batch.job import flatten_summary
from telefringe.io.errors import InputError

OPTS = {"measure": "steps", "gamma_correction": False}


@pytest.fixture(scope="module")
def stereo_steps(tmp_path_factory):
    """The step gauge seen by both cameras, written as scan folders ``camera`` and
    ``camera_2`` with the true (bare) rig.json, and the folder ``reconstruct --second``
    makes of them."""
    from telefringe.simulate.scenes import default_steps

    tmp = tmp_path_factory.mktemp("batch_stereo")
    write_stereo_scan(tmp, default_steps(), seed=3)
    return tmp


def test_batch_row_equals_measure_steps_with_the_stereo_noise(stereo_steps, capsys):
    """The batch row's step heights and sigmas equal `measure steps` on the one-scan
    stereo reconstruction (to 1e-9); the sigmas exceed the independent points' (the
    same folder's points.npz without the stereo keys) and the batch's points.npz keeps
    the same noise split."""
    from telefringe.cli import main
    from telefringe.io.points_npz import load_points

    tmp = stereo_steps
    res = tmp / "res"
    frame = measure_many([str(tmp / "s0" / "camera")], tmp / "rig.json", workers=0,
                         output=res, second="../camera_2", **OPTS)
    row = frame.iloc[0]
    assert row["status"] == "ok", row["error"]
    assert row["warnings"] == ""
    js = tmp / "one.json"
    assert main(["measure", "steps", str(tmp / "one"), "--json", str(js), "--force"]) == 0
    one = json.loads(js.read_text())
    n = len(one["step_heights_mm"])
    assert n == 4
    # the row's measurement (its per-step arrays are in the scan's measurement.json)
    doc = json.loads((res / "scans" / row["scan"] / "measurement.json").read_text())
    np.testing.assert_allclose(doc["step_heights_mm"], one["step_heights_mm"], rtol=1e-9)
    np.testing.assert_allclose(doc["sigma_steps_mm"], one["sigma_steps_mm"], rtol=1e-9)
    np.testing.assert_allclose(doc["sigma_heights_mm"], one["sigma_heights_mm"], rtol=1e-9)
    # the independent points' figure: the one-scan folder without the stereo keys
    with np.load(tmp / "one" / "points.npz") as z:
        arrays = {k: z[k] for k in z.files if not k.startswith("stereo_")}
    old = tmp / "old"
    old.mkdir(exist_ok=True)
    np.savez(old / "points.npz", **arrays)
    assert main(["measure", "steps", str(old), "--json", str(js), "--force"]) == 0
    ind = json.loads(js.read_text())
    print("sigma_steps um: batch", np.array(doc["sigma_steps_mm"]) * 1e3, "independent",
          np.array(ind["sigma_steps_mm"]) * 1e3)
    assert np.all(np.array(doc["sigma_steps_mm"]) >= np.array(ind["sigma_steps_mm"]))
    assert np.any(np.array(doc["sigma_steps_mm"]) > 1.05 * np.array(ind["sigma_steps_mm"]))
    # the batch's reconstruction keeps the noise split, as reconstruct --second's
    a, b = load_points(res / "scans" / row["scan"]), load_points(tmp / "one")
    assert a.stereo_noise is not None
    for f in ("u2", "v2", "var_own", "coef", "sigma_2"):
        np.testing.assert_array_equal(getattr(a.stereo_noise, f), getattr(b.stereo_noise, f))
    summary = json.loads((res / "scans" / row["scan"] / "summary.json").read_text())
    assert summary["stereo_noise"] is True and summary["second_scan"].endswith("camera_2")


def test_second_needs_two_cameras(stereo_steps, tmp_path):
    """`second` with a one-camera rig is refused before anything runs; a relative folder
    is required."""
    from telefringe.io.rig_json import bare_rig_json
    from telefringe.simulate.presets import get_preset

    one = tmp_path / "one.json"
    one.write_text(json.dumps(bare_rig_json(get_preset("fast").rig)))
    with pytest.raises(InputError, match="two cameras"):
        measure_many([str(stereo_steps / "s0" / "camera")], one, workers=0,
                     second="../camera_2", **OPTS)
    with pytest.raises(InputError, match="relative"):
        measure_many([str(stereo_steps / "s0" / "camera")], stereo_steps / "rig.json",
                     workers=0, second=str(stereo_steps / "s0" / "camera_2"), **OPTS)


def test_batch_sphere_row_equals_measure_sphere_rig_on_two_cameras(stereo_folder):  # noqa: F811
    """A calibrated two-camera rig.json: every figure of the batch's sphere row equals
    `measure sphere --rig` on the one-scan stereo reconstruction (to 1e-9): the sphere
    fitted through both cameras' point-spread model with the matches' correlated noise,
    u_noise larger than the same command's on points.npz without the stereo keys (the
    independent points' figure); the calibration's part through both cameras."""
    from telefringe.cli import main

    tmp, vrig, scans, cal = stereo_folder
    names = vrig.rig.camera_names
    frame = measure_many([str(tmp / names[0])], tmp / "rig.json", measure="sphere",
                         workers=0, second=f"../{names[1]}")
    row = frame.iloc[0]
    assert row["status"] == "ok", row["error"]
    assert row["warnings"] == ""
    js = tmp / "batch_one.json"
    assert main(["measure", "sphere", str(tmp / "out"), "--rig", str(tmp / "rig.json"),
                 "--json", str(js), "--force"]) == 0
    want = flatten_summary(json.loads(js.read_text()), "sphere")
    assert want["sphere.point_spread.variance_2_px2"] is not None  # two cameras' model
    assert want["sphere.uncertainty.radius.u_calibration"] > 0
    for key, v in want.items():
        if key == "sphere.base_plane.tilt_deg":
            # an arccos near 0 (tilt ~3e-6 rad): a rounding of the normal's z (eps) moves
            # it by eps / tilt; 4 eps of it (measured 0.5 eps)
            atol = np.degrees(4 * np.finfo(float).eps / np.radians(v))
            np.testing.assert_allclose(row[key], v, rtol=0, atol=atol, err_msg=key)
        elif isinstance(v, float):
            np.testing.assert_allclose(row[key], v, rtol=1e-9, err_msg=key)
        else:
            assert row[key] == v, key
    # the independent points' figure: the folder without the stereo keys
    with np.load(tmp / "out" / "points.npz") as z:
        arrays = {k: z[k] for k in z.files if not k.startswith("stereo_")}
    old = tmp / "batch_old"
    old.mkdir(exist_ok=True)
    np.savez(old / "points.npz", **arrays)
    (old / "summary.json").write_text((tmp / "out" / "summary.json").read_text())
    assert main(["measure", "sphere", str(old), "--rig", str(tmp / "rig.json"), "--json",
                 str(js), "--force"]) == 0
    ind = json.loads(js.read_text())["uncertainty"]["radius"]["u_noise"]
    print("radius u_noise um: batch", row["sphere.uncertainty.radius.u_noise"] * 1e3,
          "independent", ind * 1e3)
    assert row["sphere.uncertainty.radius.u_noise"] > 1.05 * ind
