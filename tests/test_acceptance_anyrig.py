"""The acceptance test on every rig of the any-rig issue: the measuring volume and the
artefacts of the pinhole presets, and `telefringe accept` end to end on a sphere, a ball
bar and a plane seen by the mixed, macro and stereo rigs (cameras binned 8 x 8; the
stereo rig reads both cameras' scans of each position, as `reconstruct --second`)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from telefringe.cli import main
from telefringe.io.acceptance_json import SetEntry, load_acceptance_set, write_acceptance_set
from telefringe.io.rig_json import bare_rig_json
from telefringe.io.scan_json import write_scan
from telefringe.simulate.acceptance import (
    U_CERTIFICATE_MM,
    acceptance_positions,
    iter_acceptance_scans,
    measuring_volume,
)
from telefringe.simulate.presets import bin_camera_any, get_preset

_BIN = 8
#: One position of each artefact: a sphere at a corner, a ball bar along a space
#: diagonal, a tilted plane.
_PICK = (3, 12, 20)

#: |max| (um) of each characteristic on each rig here (true rig, seed 1, bin 8, one
#: position each); the test allows twice that. The stereo PS carries the cameras'
#: point-spread bias of the points (docs/acceptance.md, "PS and the cameras' point
#: spread"): the sphere comes out too large, more so with coarser pixels (PS +13..+24 um
#: at bin 4 over the 10 positions, +65 um here).
_SEEN_UM = {
    "mixed": {"PF": 29.7, "PS": 6.0, "SD": 3.7, "F": 31.2},
    "macro": {"PF": 29.3, "PS": 9.7, "SD": 4.3, "F": 29.0},
    "stereo": {"PF": 22.2, "PS": 65.5, "SD": 3.1, "F": 27.6},
}


def _small(name):
    return bin_camera_any(get_preset(name), _BIN)


@pytest.mark.parametrize("name", ["mixed", "macro", "stereo"])
def test_every_rig_has_a_volume_that_holds_the_artefacts_in_every_camera(name):
    vrig = _small(name)
    vol = measuring_volume(vrig)
    art, pos = acceptance_positions(vrig, vol)
    assert 0.1 * vol.L0 <= art.sphere_diameter <= 0.2 * vol.L0
    assert art.bar_distance >= 0.3 * vol.L0 and art.plane_length >= 0.5 * vol.L0
    assert len(pos) == 23
    # every sphere's top and every plane's corners are inside every camera's image
    for p in pos:
        sc = p.scene
        pts = (sc.corners() if p.artefact == "plane"
               else sc.centres + np.array([0.0, 0.0, 1.0]) * sc.radii[:, None])
        for cam in (*vrig.rig.cameras.values(), vrig.projector):
            u, v = cam.project(pts)
            w, h = cam.image_size
            assert np.all((u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)), (p.name, cam)


def _write_set(vrig, folder, picks):
    """Render the picked positions (every camera) into an acceptance set like
    `simulate acceptance` writes it; returns the certificate's JSON path."""
    from telefringe.io.acceptance_json import write_artefacts
    from telefringe.metrology.acceptance import Artefacts

    art, pos = acceptance_positions(vrig)
    chosen = [pos[k] for k in picks]
    cams = vrig.camera_names
    two = len(cams) > 1
    folder.mkdir(parents=True)
    for cam in cams:
        for p, scan, _truth in iter_acceptance_scans(vrig, chosen, seed=1, camera=cam):
            dest = folder / p.name / cam if two else folder / p.name
            dest.parent.mkdir(parents=True, exist_ok=True)
            write_scan(dest, scan)
    write_acceptance_set(folder, [
        (f"{p.name}/{cams[0]}" if two else p.name, p.artefact, p.description,
         f"{p.name}/{cams[1]}" if two else None) for p in chosen])
    u = U_CERTIFICATE_MM
    cert = Artefacts(art.sphere_diameter, u, 0.0, u, art.bar_distance, u,
                     (art.sphere_diameter, art.sphere_diameter), 0.0, u, art.plane_length,
                     art.plane_width)
    write_artefacts(folder.parent / "artefacts.json", cert)
    return folder.parent / "artefacts.json"


@pytest.mark.parametrize("name", ["mixed", "macro", "stereo"])
def test_accept_on_every_rig(name, tmp_path, capsys):
    vrig = _small(name)
    cert = _write_set(vrig, tmp_path / "acc", _PICK)
    (tmp_path / "rig.json").write_text(json.dumps(bare_rig_json(vrig.rig)))
    entries = load_acceptance_set(tmp_path / "acc")
    names = [e.name for e in entries]
    assert names == ["sphere_03", "ball_bar_02", "plane_03"]
    assert all((e.second is not None) == (name == "stereo") for e in entries)
    rc = main(["-q", "accept", str(tmp_path / "acc"), "--rig", str(tmp_path / "rig.json"),
               "--artefacts", str(cert), "--no-gamma-correction",
               "--json", str(tmp_path / "result.json")])
    assert rc == 0
    doc = json.loads((tmp_path / "result.json").read_text())
    got = {q: abs(doc[q]["max"]) * 1000 for q in ("PF", "PS", "SD", "F")}
    print(f"{name} (bin {_BIN}, true rig): " + ", ".join(f"{q} {v:.1f} um"
                                                          for q, v in got.items()))
    assert [doc[q]["positions"][0]["position"] for q in ("PF", "SD", "F")] == [
        "sphere_03", "ball_bar_02", "plane_03"]
    for q, v in got.items():
        assert v <= 2 * _SEEN_UM[name][q], (q, v)
    sp = doc["PS"]["positions"][0]["spread_model"]
    print(f"  PS through the point-spread model {sp['value'] * 1e3:+.1f} um, sigma "
          f"{sp['u_fit_diameter'] * 1e3:.1f} um, differs from PS: {sp['differs_from_PS']}")
    # accept fits every rig's test sphere through the cameras' point-spread model; at bin 8
    # its size is within 3 sigma of zero (measured mixed +6.6 / 8.6, macro +2.8 / 9.1,
    # stereo +22.8 / 23.3 um: with 130 points and a variance per camera the model cannot
    # tell the stereo PS of +65 um from its own, so it is not flagged here; at bin 4 it
    # is, tests/test_sphere_spread_stereo.py)
    assert abs(sp["value"]) <= 3.0 * sp["u_fit_diameter"], sp
    assert len(sp["psf_variance_px2"]) == (2 if name == "stereo" else 1)


def test_a_set_must_suit_the_rig(tmp_path):
    """A second camera's scan needs a two-camera rig, a single scan a projector: one
    line, exit 2 (as 'reconstruct --second')."""
    vrig = _small("stereo")
    cert = _write_set(vrig, tmp_path / "acc", (3,))
    one = bin_camera_any(get_preset("macro"), _BIN)
    (tmp_path / "one.json").write_text(json.dumps(bare_rig_json(one.rig)))
    argv = ["-q", "accept", str(tmp_path / "acc"), "--artefacts", str(cert),
            "--no-gamma-correction"]
    assert main([*argv, "--rig", str(tmp_path / "one.json")]) == 2
    from telefringe.devices.rig import Rig

    no_proj = Rig(cameras=dict(vrig.rig.cameras))
    (tmp_path / "np.json").write_text(json.dumps(bare_rig_json(no_proj)))
    write_acceptance_set(tmp_path / "acc", [SetEntry("sphere_03/camera", "sphere")])
    assert main([*argv, "--rig", str(tmp_path / "np.json")]) == 2
