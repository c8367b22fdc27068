"""The circle-centre bias from lens distortion and its correction in the calibration.

A distorted circle's image is not an ellipse about the image of the circle's centre: a
detector's centre is off the projected centre (under radial distortion x (1 + k1 r^2) by
3 k1 rho^2 times its distance from the axis, rho the circle's radius on the sensor: like a
magnification error). ``calibration.rig._circle_image_centre`` predicts the detector's
centre from the device's full model (the area centroid of the projected boundary, which
to first order in the departure from an ellipse is the centre an ellipse fit finds);
``calibrate_devices(marker_radius=...)`` subtracts the predicted bias and adjusts again.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from telefringe.calibration.rig import _circle_image_centre, calibrate_devices
from telefringe.devices.rig import Rig
from telefringe.simulate.calibration import simulate_calibration_poses
from telefringe.simulate.presets import get_preset

STRONG = 10.0  # distortion of the fast rig's camera multiplied by this


def _strong_fast_rig():
    vrig = get_preset("fast")
    cam = vrig.rig.camera
    i = cam.intrinsics
    cam = replace(cam, intrinsics=replace(i, k1=i.k1 * STRONG, s1=i.s1 * STRONG,
                                          s2=i.s2 * STRONG))
    return replace(vrig, rig=Rig(cam, vrig.rig.projector))


def _scale(d, r):
    """Least-squares relative scale s of the offsets d (n, 2) about r (n, 2): d ~ s r."""
    return float(np.sum(d * r) / np.sum(r * r))


def test_predicted_centres_match_the_detector_on_rendered_markers():
    """The fast rig's camera with 10x its distortion (k1 0.006 /mm^2, thin prism),
    the plate rendered at the reference pose and detected: the detected centres are off
    the projected centres by a radial scale of 2.5e-4 (0.0185 px RMS, measured); off the
    predicted image centres by 0.0050 px RMS (the detection noise: 0.0053 px at the
    preset's own distortion) and a scale of 1e-5 (the detector's remaining bias without
    distortion is 4e-6). Bounds: 2x (RMS 1.5x) what is achieved."""
    from telefringe.fringes.images import fringe_free_image
    from telefringe.fringes.scan import PhaseGroup
    from telefringe.simulate.render import render_scan
    from telefringe.simulate.scenes import plate_from_target
    from telefringe.targets.circle_grid import detect_circle_grid

    vrig = _strong_fast_rig()
    cam, T = vrig.rig.camera, vrig.target
    scan, tr = render_scan(vrig, plate_from_target(T, np.eye(3), np.zeros(3)),
                           [PhaseGroup(axis="u", periods=8, steps=3)], seed=5)
    det = detect_circle_grid(fringe_free_image(scan), rows=T.rows, cols=T.cols)
    ok = np.all(np.isfinite(det.centers), axis=1)
    assert ok.sum() >= 90
    Xw = tr.features["circle_centres_world"]
    n = len(Xw)
    pred = _circle_image_centre(cam, np.broadcast_to(np.eye(3), (n, 3, 3)), np.zeros((n, 3)),
                                Xw, 0.5 * T.diameter_mm)
    true = tr.features["circle_centres_px"]
    r = (true - [cam.intrinsics.u0, cam.intrinsics.v0])[ok]
    before, after = (det.centers - true)[ok], (det.centers - pred)[ok]
    assert _scale(before, r) > 2e-4  # the effect is there
    assert abs(_scale(after, r)) < 2.5e-5
    assert np.sqrt(np.mean(np.sum(after**2, axis=1) / 2)) < 0.0075


@pytest.fixture(scope="module")
def synthetic():
    """Detector-like observations of the strongly distorted fast rig: each camera
    observation the centre of the circle's image (0.005 px noise); each projector
    observation the projector's image of the plate point the camera sees there (the
    projector coordinate is read at the camera's detected centre; 0.005 px noise)."""
    vrig = _strong_fast_rig()
    cam, proj, T = vrig.rig.camera, vrig.rig.projector, vrig.target
    poses = simulate_calibration_poses(vrig, n_poses=8, seed=0)
    r, c = np.mgrid[0:T.rows, 0:T.cols]
    P = np.stack([c.ravel() * T.pitch_mm, r.ravel() * T.pitch_mm, np.zeros(r.size)], 1)
    rng = np.random.default_rng(3)
    obs = {"camera": [], "projector": []}
    for p in poses:
        R = np.broadcast_to(p.R_world_target, (len(P), 3, 3))
        Tt = np.broadcast_to(p.t_world_target, (len(P), 3))
        e = _circle_image_centre(cam, R, Tt, P, T.diameter_mm / 2)
        o, d = cam.backproject(e[:, 0], e[:, 1])
        nrm = p.R_world_target[:, 2]
        s = ((p.t_world_target - o) @ nrm) / (d @ nrm)
        Xs = o + s[:, None] * d
        obs["camera"].append(e + rng.normal(0, 0.005, e.shape))
        obs["projector"].append(np.stack(proj.project(Xs), 1) + rng.normal(0, 0.005, e.shape))
    obs = {k: np.array(v) for k, v in obs.items()}
    kw = dict(models={"camera": "telecentric", "projector": "telecentric"},
              pixel_sizes={"camera": (cam.intrinsics.du, cam.intrinsics.dv),
                           "projector": (proj.intrinsics.du, proj.intrinsics.dv)},
              image_sizes={"camera": (cam.intrinsics.width, cam.intrinsics.height),
                           "projector": (proj.intrinsics.width, proj.intrinsics.height)},
              projector_side="right")
    return vrig, P, obs, kw


def test_telecentric_calibration_corrects_the_distortion_bias(synthetic):
    """With the markers' radius the camera magnification is within 3 of its standard
    deviations of the truth (measured -1.4); without, off by many (measured +88)."""
    vrig, P, obs, kw = synthetic
    m_true = vrig.rig.camera.intrinsics.m
    fixed = calibrate_devices(P, obs, marker_radius=vrig.target.diameter_mm / 2,
                              centre_bias="full", **kw)
    plain = calibrate_devices(P, obs, **kw)
    z_fixed = (fixed.camera.intrinsics.m - m_true) / fixed.std_of("camera.m")
    z_plain = (plain.camera.intrinsics.m - m_true) / plain.std_of("camera.m")
    assert abs(z_fixed) < 3.0
    assert z_plain > 10.0
