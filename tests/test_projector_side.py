"""No silent sign flips: a rig of two telecentric devices calibrated from a flat target
takes the projector's side from the user (or the virtual rig), never from a convention,
and heights come out with the right sign wherever the projector is."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_calibrate import (
    CAM_PIX,
    CAM_SIZE,
    PROJ_PIX,
    PROJ_SIZE,
    grid_points,
    observe,
    paper_like_rig,
    side_of,
    target_poses,
    triangulate,
)

from telefringe.calibration.rig import calibrate_rig
from telefringe.calibration.start_telecentric import MirrorAmbiguityError
from telefringe.devices.rig import Rig
from telefringe.devices.telecentric import TelecentricDevice
from telefringe.geometry.so3 import rotation_from_rotvec
from telefringe.io.calibration_json import parse_calibration_manifest
from telefringe.io.errors import InputError
from telefringe.simulate.calibration import projector_side
from telefringe.simulate.presets import get_preset


def turned_projector(rig: Rig, quarter_turns: int) -> Rig:
    """The rig with its projector carried round the camera's axis (through the plate
    centre) by ``quarter_turns`` x 90 deg, re-aimed at the plate centre."""
    cam, proj = rig.camera, rig.projector
    centre = np.array([15.0, 12.0, 0.0])
    Q = rotation_from_rotvec(np.pi / 2 * quarter_turns * cam.axis_world)
    R = proj.R_dev_world @ Q.T
    k = proj.intrinsics
    t = (np.array([(k.width - 1) / 2, (k.height - 1) / 2]) - (k.u0, k.v0)) \
        * (k.du, k.dv) / k.m - R[:2] @ centre
    return Rig(cam, TelecentricDevice(k, R, t))


@pytest.mark.parametrize("turns", [0, 1, 2, 3])
def test_heights_have_the_right_sign_with_the_projector_on_any_side(turns):
    rig = turned_projector(paper_like_rig(), turns)
    side = side_of(rig)
    assert side == projector_side(rig)  # the virtual rig's notion agrees
    rng = np.random.default_rng(100 + turns)
    P = grid_points()
    Rs, Ts = target_poses(8, rng)
    cam, proj = observe(rig, P, Rs, Ts, rng)
    kw = dict(camera_pixel_size=CAM_PIX, projector_pixel_size=PROJ_PIX, camera_size=CAM_SIZE,
              projector_size=PROJ_SIZE)
    with pytest.raises(MirrorAmbiguityError, match="--projector-side"):
        calibrate_rig(P, cam, proj, **kw)
    cal = calibrate_rig(P, cam, proj, projector_side=side, **kw)
    assert cal.mirror == f"projector_side={side}"
    # a held-out step gauge of sorts: the plate raised by +0.1 .. +2 mm and tilted
    for dz in (0.1, 0.5, 2.0):
        X = P + [0.0, 0.0, dz]
        c, p = observe(rig, P, np.eye(3)[None], np.array([[0.0, 0.0, dz]]), rng, sc=0, sp=0)
        z = triangulate(cal.rig, c[0], p[0])[:, 2]
        # the calibration's error is a few um; a flip would give -dz
        assert np.max(np.abs(z - X[:, 2])) < 5e-3, (side, dz)
    R = rotation_from_rotvec([0.0, np.radians(5.0), 0.0])  # rises toward +x
    c, p = observe(rig, P, R[None], np.zeros((1, 3)), rng, sc=0, sp=0)
    xyz = triangulate(cal.rig, c[0], p[0])
    slope = np.polyfit(xyz[:, 0], xyz[:, 2], 1)[0]
    assert slope == pytest.approx(-np.tan(np.radians(5.0)), abs=2e-3)  # Ry(+5) lowers +x


def test_the_four_sides_are_all_reached():
    assert sorted(side_of(turned_projector(paper_like_rig(), k)) for k in range(4)) == [
        "bottom", "left", "right", "top"]


def test_presets_note_their_projector_side():
    for name in ("paper", "fast"):
        assert projector_side(get_preset(name)) == "right"


def _doc(**extra):
    doc = {"format": "telefringe-calibration-set", "version": 1,
           "target": {"type": "circle-grid", "rows": 9, "cols": 11, "pitch_mm": 3.0,
                      "diameter_mm": 1.5},
           "camera": {"pixel_size_mm": [0.0052, 0.0052]},
           "projector": {"pixel_size_mm": [0.0137, 0.0137]},
           "poses": ["pose_00"]}
    doc.update(extra)
    return doc


def test_calibration_json_projector_side():
    assert parse_calibration_manifest(_doc()).projector_side is None
    assert parse_calibration_manifest(_doc(projector_side="top")).projector_side == "top"
    with pytest.raises(InputError, match="'projector_side' must be one of left, right"):
        parse_calibration_manifest(_doc(projector_side="up"))


def test_calibration_json_written_with_the_side(tmp_path):
    from telefringe.io.calibration_json import write_calibration_manifest
    from telefringe.simulate.calibration import calibration_manifest, simulate_calibration_poses

    vrig = get_preset("fast")
    man = calibration_manifest(vrig, simulate_calibration_poses(vrig, n_poses=4, seed=1))
    assert man.projector_side == "right"
    write_calibration_manifest(tmp_path, man)
    doc = json.loads((tmp_path / "calibration.json").read_text())
    assert doc["projector_side"] == "right"
    assert parse_calibration_manifest(doc).projector_side == "right"


@pytest.mark.parametrize("turns", [0, 1, 2, 3])
def test_an_upright_pins_shadow_falls_away_from_the_projector(turns):
    """What the message tells the user to look at, checked with the renderer: the
    shadow of a pin on the plate lies on the side of the pin opposite ``projector_side``."""
    from dataclasses import replace

    from telefringe.simulate.render import trace_geometry
    from telefringe.simulate.scenes import StepGauge

    base = get_preset("fast")
    vrig = replace(base, rig=turned_projector(base.rig, turns))
    pin = StepGauge(blocks=np.array([[14.7, 15.3, 11.7, 12.3, 0.0, 3.0]]))
    t = trace_geometry(vrig, pin).truth
    shadow = t.visible & ~t.lit & (t.part == 0)
    top = t.part == 1
    assert shadow.sum() > 20
    offset = (np.array(np.nonzero(shadow))[::-1].mean(axis=1)
              - np.array(np.nonzero(top))[::-1].mean(axis=1))  # (du, dv) px
    toward = {"left": (-1, 0), "right": (1, 0), "top": (0, -1), "bottom": (0, 1)}
    side = projector_side(vrig)
    along = float(offset @ np.array(toward[side]))
    assert along < -5.0, (side, offset)  # clearly away from the projector
    assert abs(along) > 2 * abs(float(offset @ np.array(toward[side])[::-1])), (side, offset)
