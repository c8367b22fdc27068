"""A pinhole camera calibrated alone from planar views: Zhang's start, then the generic
bundle adjustment; every intrinsic within 5 of its own standard deviations of the truth,
and the reprojection RMS at the noise."""

from __future__ import annotations

import numpy as np
import pytest

from telefringe.calibration.device import calibrate_device
from telefringe.calibration.errors import CalibrationError
from telefringe.devices.pinhole import PinholeDevice, PinholeIntrinsics
from telefringe.geometry.so3 import rotation_from_rotvec

SIGMA = 0.05  # px


def _views(rng, n_poses=10):
    intr = PinholeIntrinsics(1500.0, 1505.0, 652.0, 498.0, -0.15, 0.12, 8e-4, -5e-4, 0.0,
                             width=1280, height=1024)
    cam = PinholeDevice(intr)
    r, c = np.mgrid[0:9, 0:11]
    P = np.stack([c.ravel() * 3.0, r.ravel() * 3.0, np.zeros(r.size)], axis=1)
    centre = np.array([15.0, 12.0, 0.0])
    obs = []
    for i in range(n_poses):
        phi = 2 * np.pi * i / n_poses
        tilt = np.radians(25.0) * np.array([np.cos(phi), np.sin(phi), 0.0])
        R = rotation_from_rotvec(tilt) @ rotation_from_rotvec([0, 0, 0.2 * rng.normal()])
        t = np.array([0.0, 0.0, 110.0 + 10 * rng.normal()]) - R @ centre
        uv = np.stack(cam.with_pose(R, t).project(P), axis=1)
        obs.append(uv + rng.normal(0.0, SIGMA, uv.shape))
    return cam, P, np.array(obs)


def test_pinhole_camera_calibrated_alone_recovers_the_truth():
    rng = np.random.default_rng(11)
    cam, P, obs = _views(rng)
    cal = calibrate_device(P, obs, image_size=(1280, 1024), model="pinhole",
                           outlier_threshold=np.inf)
    est = cal.device.to_params()[:9]
    truth = cam.to_params()[:9]
    z = (est - truth) / cal.std
    free = np.isfinite(cal.std)
    assert free[:8].all()  # k3 too is estimated
    assert np.all(np.abs(z[free]) < 5), dict(zip(cal.device.intrinsic_names, z.round(2),
                                                 strict=True))
    # 2-D error length of Gaussian noise: RMS sqrt(2) sigma, within 5 % (2 x 99 x 10 points)
    assert abs(cal.rms / (np.sqrt(2) * SIGMA) - 1) < 0.05
    assert cal.t_dev.shape == (10, 3) and not cal.principal_point_weak


def test_pinhole_start_needs_three_views_and_telecentric_needs_a_pixel_size():
    rng = np.random.default_rng(2)
    _, P, obs = _views(rng, n_poses=2)
    with pytest.raises(CalibrationError, match="at least 3"):
        calibrate_device(P, obs, image_size=(1280, 1024), model="pinhole")
    with pytest.raises(CalibrationError, match="pixel size"):
        calibrate_device(P, obs, image_size=(1280, 1024))
    with pytest.raises(CalibrationError, match="no calibration start"):
        calibrate_device(P, obs, image_size=(1280, 1024), model="fisheye")
