"""`telefringe capture ...` with the sim driver: scans, HDR, latency, devices,
calibration sets driven from stdin, clear failures with nothing written; and the whole
chain capture -> calibrate -> reconstruct -> measure against the same scenes rendered
directly."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from telefringe.cli import main

SIM = ["--camera", "sim", "--projector", "sim:preset=fast,crop=96x80+112+88"]


def _snapshot(folder):
    return sorted(p.name for p in folder.iterdir())


def test_capture_scan_writes_a_verified_scan_with_its_provenance(tmp_path, capsys):
    out = tmp_path / "s"
    lat = tmp_path / "lat.json"
    assert main(["capture", "latency", *SIM, "--latency-file", str(lat)]) == 0
    printed = capsys.readouterr().out
    assert "latency 25.00 ms" in printed and "2 refresh period(s)" in printed
    assert main(["capture", "scan", str(out), *SIM, "--periods", "1,8,64", "--axes", "u",
                 "--exposures", "2,0.5", "--pixel-format", "Mono12",
                 "--latency-file", str(lat)]) == 0
    doc = json.loads((out / "scan.json").read_text())
    cap = doc["capture"]
    # measured in steps of half the 4.167 ms exposure: the first step past 25 ms
    assert cap["latency"] == {"latency_s": pytest.approx(0.025, abs=2.1e-3),
                              "source": "measured", "wait_periods": 2,
                              "wait_s": pytest.approx(1 / 30)}
    assert cap["latency"]["latency_s"] >= 0.025 - 20e-6     # never short (trigger delay)
    assert [s["exposure_s"] for s in cap["settings"]] == [0.066667, 0.016667]
    assert cap["settings"][0]["pixel_format"] == "Mono12" and cap["stored"].startswith("uint16")
    assert len(cap["frames"]) == 2 * 12 + 2 and cap["retries"] == 0
    assert sorted({g["exposure"] for g in doc["patterns"]}) == [0.5, 2.0]
    # it reads and decodes like any scan
    from telefringe.fringes.decode import decode
    from telefringe.io.scan_json import read_scan

    scan = read_scan(out)
    assert scan.max_value == 65535 and scan.stacks[0].dtype == np.uint16
    coords = decode(scan)
    assert coords.mask.mean() > 0.5
    # no overwrite without --force; nothing half-written after a failure
    assert main(["capture", "scan", str(out), *SIM]) == 2
    assert "already exists" in capsys.readouterr().err
    bad = tmp_path / "bad"
    code = main(["capture", "scan", str(bad), "--camera", "sim:drop=1", "--projector",
                 "sim:preset=fast,crop=96x80+112+88", "--axes", "u"])
    err = capsys.readouterr().err
    assert code == 1 and "4 attempts failed (4 x timeout" in err
    assert len([ln for ln in err.splitlines() if ln.strip()]) == 1
    assert not bad.exists() and _snapshot(tmp_path) == ["lat.json", "s"]


@pytest.mark.parametrize("args, code, token", [
    (["--camera", "nosuch"], 2, "unknown camera driver 'nosuch'"),
    (["--projector", "sim:bogus=1"], 1, "unknown option 'bogus'"),
    (["--camera", "sim:preset=fast"], 1, "belongs to the sim projector"),
    (["--exposures", "1,x"], 2, "--exposures"),
    (["--periods", "1,400"], 2, "--periods"),
])
def test_capture_scan_bad_input_is_one_line(tmp_path, capsys, args, code, token):
    argv = ["capture", "scan", str(tmp_path / "o"), *SIM, *args]
    assert main(argv) == code
    err = capsys.readouterr().err
    assert token in err and "Traceback" not in err, err
    assert not (tmp_path / "o").exists()


def test_capture_devices_lists_each_driver(capsys):
    assert main(["capture", "devices"]) == 0
    out = capsys.readouterr().out
    assert "sim:preset=fast" in out and "virtual camera (fast rig)" in out
    for name in ("aravis", "pylon", "gentl", "window", "lightcrafter"):
        assert f"  {name}" in out


def test_capture_calibration_waits_for_enter_and_stops_cleanly(tmp_path, capsys, monkeypatch):
    out = tmp_path / "cal"
    spec = "sim:preset=fast,scene=calibration,poses=4,seed=3"
    few = ["--axes", "u", "--periods", "1,8", "--latency", "0.025"]
    # q at the second pose: nothing written
    monkeypatch.setattr("sys.stdin", io.StringIO("\nq\n"))
    code = main(["capture", "calibration", str(out), "--camera", "sim", "--projector", spec,
                 "--poses", "4", *few])
    assert code == 130 and not out.exists()
    assert "stopped at pose 2 of 4" in capsys.readouterr().err
    # the half-hidden fourth pose: the grid is not found, the user is asked again; the
    # sim plate has no pose left -> a clear error, nothing written
    monkeypatch.setattr("sys.stdin", io.StringIO("\n" * 6))
    code = main(["capture", "calibration", str(out), "--camera", "sim", "--projector", spec,
                 "--poses", "4", *few])
    printed = capsys.readouterr()
    assert code == 1 and not out.exists(), printed.err
    assert "grid NOT found" in printed.out and "no pose left" in printed.err
    assert "tilt axes in" in printed.out and "field covered" in printed.out


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    """Capture a calibration set and a plate scan with the sim pair, and render the same
    poses and plate directly; calibrate and reconstruct both."""
    import sys

    from telefringe.io.scan_json import write_scan
    from telefringe.simulate.presets import get_preset
    from telefringe.simulate.render import default_groups, render_scan
    from telefringe.simulate.scenes import plate_at_z

    tmp = tmp_path_factory.mktemp("chain")
    spec = "sim:preset=fast,scene=calibration,poses=6,seed=3"
    old = sys.stdin
    sys.stdin = io.StringIO("\n" * 5)
    try:
        assert main(["-q", "capture", "calibration", str(tmp / "cal"), "--camera", "sim",
                     "--projector", spec, "--poses", "5", "--latency", "0.025",
                     "--periods", "1,8,64"]) == 0
    finally:
        sys.stdin = old
    # the same 6 poses rendered (the sixth, half-hidden, is skipped by calibrate)
    assert main(["-q", "simulate", "calibration", str(tmp / "rend"), "--rig", "fast",
                 "--poses", "6", "--seed", "3"]) == 0
    out = {}
    for name, cal in (("captured", tmp / "cal"), ("rendered", tmp / "rend" / "calibration")):
        assert main(["-q", "calibrate", str(cal), "-o", str(tmp / f"rig_{name}.json"),
                     "--no-gamma", "--projector-side", "right"]) == 0
    assert main(["-q", "capture", "scan", str(tmp / "plate_c"), "--camera", "sim",
                 "--projector", "sim:preset=fast,scene=plate,z=-0.5,seed=4",
                 "--latency", "0.025", "--axes", "u,v", "--periods", "1,8,48"]) == 0
    vr = get_preset("fast")
    scan, _ = render_scan(vr, plate_at_z(-0.5),
                          default_groups(vr, periods_u=(1, 8, 48), periods_v=(1, 8, 48)),
                          seed=4)
    write_scan(tmp / "plate_r", scan)
    for name, sc in (("captured", "plate_c"), ("rendered", "plate_r")):
        assert main(["-q", "reconstruct", str(tmp / sc), "--rig", str(tmp / f"rig_{name}.json"),
                     "-o", str(tmp / f"rec_{name}")]) == 0
        assert main(["-q", "measure", "plate", str(tmp / f"rec_{name}"), "--json",
                     str(tmp / f"plate_{name}.json")]) == 0
        out[name] = (json.loads((tmp / f"rig_{name}.json").read_text()),
                     json.loads((tmp / f"plate_{name}.json").read_text()))
    return out


def test_captured_calibration_is_as_good_as_rendered(chain):
    rc = chain["captured"][0]["calibration"]
    rr = chain["rendered"][0]["calibration"]
    # measured: camera 0.0070 vs 0.0069 px, projector 0.0044 vs 0.0044 px (seed 3)
    for dev in ("camera", "projector"):
        c, r = rc["rms_px"][dev], rr["rms_px"][dev]
        assert c < 2 * r, (dev, c, r)
    # the magnification against the truth (0.1597): 2.7e-5 off for both; the bound of
    # test_calibrate_cli for rendered sets
    for name in ("captured", "rendered"):
        assert abs(chain[name][0]["camera"]["m"] / 0.1597 - 1) < 6.5e-5, name
    used_c = [p["used"] for p in rc["poses"]]
    assert sum(used_c) == 5


def test_captured_plate_measures_like_the_rendered_one(chain):
    pc, pr = chain["captured"][1], chain["rendered"][1]
    # each within 4 sigma of the truth (-0.5 mm); the captured no worse than twice the
    # rendered's error or its sigma
    for p in (pc, pr):
        assert abs(p["z_mm"] + 0.5) < 4 * p["sigma_z_mm"] + 2e-3, p
    assert abs(pc["z_mm"] + 0.5) < 2 * max(abs(pr["z_mm"] + 0.5), 4 * pr["sigma_z_mm"])
    for ax in ("x", "y"):
        ec = abs(pc["spacing"][f"mean_{ax}_mm"] - 3.0)
        er = abs(pr["spacing"][f"mean_{ax}_mm"] - 3.0)
        se = pr["spacing"][f"std_{ax}_mm"] / np.sqrt(pr["spacing"][f"n_{ax}"])
        assert ec < 2 * max(er, 4 * se), (ax, ec, er, se)
