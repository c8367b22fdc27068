"""`telefringe capture calibration` writes each device's model (pinhole or telecentric),
the telecentric devices' pixel sizes and the projector's side into calibration.json, so
that a set captured with a pinhole camera calibrates as pinhole (issue 11/13).

The macro preset (pinhole camera + pinhole projector) through the sim driver, binned 4 x 4
(320 x 256 px, the field unchanged) for speed; the focal length calibrated from the
captured set must lie within 4 of its stated standard uncertainties of the truth.
"""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from telefringe.cli import main


def test_device_models_from_the_sim_rig_and_the_options():
    from telefringe.cli.capture import _device_models
    from telefringe.io.errors import InputError
    from telefringe.simulate.presets import get_preset

    fast = get_preset("fast")
    models, sizes, side = _device_models(fast, None, None, None, None, None)
    assert models == {"camera": "telecentric", "projector": "telecentric"}
    assert sizes["camera"] == (fast.camera.intrinsics.du,) * 2 and side == "right"
    macro = get_preset("macro")
    models, sizes, side = _device_models(macro, None, None, None, None, None)
    assert models == {"camera": "pinhole", "projector": "pinhole"} and sizes == {}
    # a real pair: telecentric by default (needs the sizes), or as told
    with pytest.raises(InputError, match="--camera-pixel-size"):
        _device_models(None, None, None, None, None, None)
    models, sizes, side = _device_models(None, "pinhole", "telecentric", None, 0.01, "top")
    assert models == {"camera": "pinhole", "projector": "telecentric"}
    assert sizes == {"projector": (0.01, 0.01)} and side == "top"
    with pytest.raises(InputError, match="telecentric or pinhole"):
        _device_models(None, "fisheye", "pinhole", None, None, None)
    with pytest.raises(InputError, match="is for a telecentric camera"):
        _device_models(None, "pinhole", "pinhole", 0.005, None, None)
    with pytest.raises(InputError, match="--projector-side"):
        _device_models(None, "pinhole", "pinhole", None, None, "up")


def test_a_pinhole_capture_calibrates_as_pinhole(tmp_path, monkeypatch, capsys):
    from telefringe.simulate.presets import bin_camera_any, get_preset

    spec = "sim:preset=macro,scene=calibration,poses=8,seed=1,bin=4"
    out = tmp_path / "cal"
    monkeypatch.setattr("sys.stdin", io.StringIO("\n" * 8))
    assert main(["-q", "capture", "calibration", str(out), "--camera", "sim", "--projector",
                 spec, "--poses", "5", "--latency", "0.025", "--periods", "1,8,64"]) == 0
    doc = json.loads((out / "calibration.json").read_text())
    assert doc["camera"] == {"model": "pinhole"} and doc["projector"] == {"model": "pinhole"}
    assert len(doc["poses"]) == 5
    # a pixel size for a pinhole camera is refused: one line, exit 2, nothing written
    monkeypatch.setattr("sys.stdin", io.StringIO("\n" * 8))
    assert main(["capture", "calibration", str(tmp_path / "bad"), "--camera", "sim",
                 "--projector", spec, "--poses", "5", "--camera-pixel-size", "0.005"]) == 2
    assert "telecentric camera" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
    rig = tmp_path / "rig.json"
    assert main(["-q", "calibrate", str(out), "-o", str(rig), "--no-gamma"]) == 0
    r = json.loads(rig.read_text())
    assert r["camera"]["model"] == "pinhole" and r["projector"]["model"] == "pinhole"
    true = bin_camera_any(get_preset("macro"), 4).camera.intrinsics
    fx = r["camera"]["fx"]
    u = _stated_sigma(r, "camera", "fx")
    assert abs(fx - true.fx) < 4 * u, (fx, true.fx, u)


def _stated_sigma(rig: dict, device: str, name: str) -> float:
    """The standard uncertainty rig.json states for a device parameter."""
    par = rig["calibration"]["parameters"]
    val = par["std"][par["names"].index(f"{device}.{name}")]
    assert np.isfinite(val) and val > 0
    return float(val)
