"""`telefringe batch --second` on a two-camera rig: each scan is matched with its second
camera's scan as ``reconstruct --second`` does, points.npz keeps the matches' noise split,
and the row's figures carry the matches' correlated noise (neighbouring matches share the
second camera's pixels): the same u as ``telefringe measure steps`` reports on the
one-scan reconstruction, larger than the independent points' figure.

In this process (``workers=0``), on the stereo preset binned 8 x 8 (as
test_stereo_noise_steps.py), a bare rig.json (the u hold the noise alone)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from telefringe.batch import measure_many
from telefringe.io.errors import InputError

OPTS = {"measure": "steps", "gamma_correction": False}


@pytest.fixture(scope="module")
def stereo_steps(tmp_path_factory):
    """The step gauge seen by both cameras, written as scan folders ``camera`` and
    ``camera_2`` with the true (bare) rig.json, and the folder ``reconstruct --second``
    makes of them."""
    from telefringe.cli.reconstruct import reconstruct_to_folder
    from telefringe.io.rig_json import bare_rig_json, load_rig
    from telefringe.io.scan_json import write_scan
    from telefringe.simulate.anyrig import scan_scene
    from telefringe.simulate.presets import bin_camera_any, get_preset
    from telefringe.simulate.scenes import default_steps

    tmp = tmp_path_factory.mktemp("batch_stereo")
    vrig = bin_camera_any(get_preset("stereo"), 8)
    scans, _ = scan_scene(vrig, default_steps(), seed=3)
    names = vrig.rig.camera_names
    assert names == ("camera", "camera_2")
    (tmp / "s0").mkdir()
    for n in names:
        write_scan(tmp / "s0" / n, scans[n])
    (tmp / "rig.json").write_text(json.dumps(bare_rig_json(vrig.rig)))
    reconstruct_to_folder(tmp / "s0" / names[0], load_rig(tmp / "rig.json"), tmp / "one",
                          second=tmp / "s0" / names[1], ply=False, gamma_correction=False,
                          read=lambda f: scans[f.name])
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
