"""The pinhole device (OpenCV's model): projection against ``cv2.projectPoints``,
undistortion against its own forward model and ``cv2.undistortPoints`` (iterated to
1e-15), a clear error where the distortion folds, the Jacobian against finite differences,
rays against projection."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from telefringe.devices.base import Device
from telefringe.devices.pinhole import PinholeDevice, PinholeIntrinsics
from telefringe.geometry.distortion import ConvergenceError
from telefringe.geometry.so3 import rotation_from_rotvec

coef = st.floats(-1.0, 1.0)


def _device(f=1200.0, dist=(-0.12, 0.05, 1e-3, -8e-4, -0.01), rv=(0.1, -0.2, 0.05),
            t=(3.0, -2.0, 150.0)):
    intr = PinholeIntrinsics(f, 1.02 * f, 641.5, 511.25, *dist, width=1280, height=1024)
    return PinholeDevice(intr, rotation_from_rotvec(rv), t)


def _points(dev, rng, n=200):
    """World points in front of the device, inside a 0.8 x 0.6 normalised field."""
    xn = rng.uniform(-0.4, 0.4, n)
    yn = rng.uniform(-0.3, 0.3, n)
    z = rng.uniform(80.0, 300.0, n)
    Y = np.stack([xn * z, yn * z, z], axis=1)
    return (Y - dev.t_dev) @ dev.R_dev_world  # X = R^T (Y - t)


def test_is_a_device_and_params_round_trip():
    dev = _device()
    assert isinstance(dev, Device) and dev.model == "pinhole" and dev.sees_depth
    assert dev.image_size == (1280, 1024)
    p = dev.to_params()
    assert p.shape == (len(dev.param_names),) == (15,)
    back = dev.from_params(p)
    np.testing.assert_array_equal(back.to_params(), p)
    np.testing.assert_allclose(back.R_dev_world, dev.R_dev_world, atol=1e-15)
    with pytest.raises(ValueError, match="15 values"):
        dev.from_params(p[:3])
    with pytest.raises(ValueError, match="fx"):
        PinholeIntrinsics(0.0, 1.0, 0.0, 0.0)


@settings(max_examples=60, deadline=None)
@given(f=st.floats(300.0, 3000.0), k1=coef, k2=coef, p1=st.floats(-0.01, 0.01),
       p2=st.floats(-0.01, 0.01), k3=coef, rx=st.floats(-1, 1), ry=st.floats(-1, 1),
       rz=st.floats(-3, 3), seed=st.integers(0, 2**16))
def test_projection_equals_opencv(f, k1, k2, p1, p2, k3, rx, ry, rz, seed):
    dev = _device(f, (k1 * 0.3, k2 * 0.1, p1, p2, k3 * 0.05), (rx, ry, rz))
    X = _points(dev, np.random.default_rng(seed), 50)
    u, v = dev.project(X)
    k = dev.intrinsics
    ref, _ = cv2.projectPoints(X.reshape(-1, 1, 3), dev.rotvec, dev.t_dev, k.camera_matrix,
                               np.array(k.distortion))
    ref = ref.reshape(-1, 2)
    # rounding only: measured 1.1e-12 px at worst over 300 random devices (pixels up to a
    # few thousand, whose ulp is 4.5e-13)
    np.testing.assert_allclose(u, ref[:, 0], rtol=0, atol=5e-12)
    np.testing.assert_allclose(v, ref[:, 1], rtol=0, atol=5e-12)


@settings(max_examples=60, deadline=None)
@given(k1=coef, k2=coef, p1=st.floats(-0.01, 0.01), p2=st.floats(-0.01, 0.01), k3=coef,
       seed=st.integers(0, 2**16))
def test_undistortion_inverts_the_model_and_agrees_with_opencv(k1, k2, p1, p2, k3, seed):
    dist = (k1 * 0.3, k2 * 0.1, p1, p2, k3 * 0.05)
    dev = _device(dist=dist)
    rng = np.random.default_rng(seed)
    u, v = dev.project(_points(dev, rng, 80))
    ui, vi = dev.undistort(u, v)
    # back through the forward model: the ideal pixel's distortion is the observed one
    k = dev.intrinsics
    from telefringe.geometry.distortion import distort_normalized

    xd, yd = distort_normalized((ui - k.cx) / k.fx, (vi - k.cy) / k.fy, *dist)
    # to 1e-12 px (measured 2.3e-13 over 300 random distortions)
    np.testing.assert_allclose(k.fx * xd + k.cx, u, rtol=0, atol=1e-12)
    np.testing.assert_allclose(k.fy * yd + k.cy, v, rtol=0, atol=1e-12)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    ref = cv2.undistortPoints(np.stack([u, v], 1).reshape(-1, 1, 2), k.camera_matrix,
                              np.array(dist), R=None, P=k.camera_matrix,
                              criteria=crit).reshape(-1, 2)
    np.testing.assert_allclose(ui, ref[:, 0], rtol=0, atol=2e-12)  # measured 4.5e-13
    np.testing.assert_allclose(vi, ref[:, 1], rtol=0, atol=2e-12)


def test_undistortion_refuses_beyond_the_fold():
    dev = _device(dist=(-0.6, 0.0, 0.0, 0.0, 0.0))
    k = dev.intrinsics
    # the barrel folds at r^2 = 1 / (3 * 0.6): its largest distorted radius is 0.50;
    # a point at 0.6 has no undistorted counterpart
    with pytest.raises(ConvergenceError, match="distortion"):
        dev.undistort(k.cx + 0.6 * k.fx, k.cy)
    x, _ = dev.undistort(k.cx + 0.3 * k.fx, k.cy)  # inside: fine
    assert np.isfinite(x)


@pytest.mark.parametrize("dist", [(0, 0, 0, 0, 0), (-0.12, 0.05, 1e-3, -8e-4, -0.01)])
def test_project_jacobian_matches_finite_differences(dist):
    dev = _device(dist=dist)
    X = _points(dev, np.random.default_rng(2), 30)
    uv, J, J_X = dev.project_jacobian(X)
    np.testing.assert_allclose(uv, np.stack(dev.project(X), 1), rtol=0, atol=1e-12)
    p0 = dev.to_params()
    steps = np.array([1e-3, 1e-3, 1e-4, 1e-4] + [1e-7] * 5 + [1e-8] * 3 + [1e-5] * 3)
    for j, h in enumerate(steps):
        e = np.zeros_like(p0)
        e[j] = h
        num = (np.stack(dev.from_params(p0 + e).project(X), 1)
               - np.stack(dev.from_params(p0 - e).project(X), 1)) / (2 * h)
        np.testing.assert_allclose(J[:, :, j], num, rtol=1e-6,
                                   atol=1e-5 * np.abs(num).max() + 1e-9,
                                   err_msg=dev.param_names[j])
    for j in range(3):
        e = np.zeros(3)
        e[j] = 1e-4
        num = (np.stack(dev.project(X + e), 1) - np.stack(dev.project(X - e), 1)) / 2e-4
        np.testing.assert_allclose(J_X[:, :, j], num, rtol=1e-6, atol=1e-7)


def test_rays_start_at_the_centre_and_project_back():
    dev = _device()
    u, v = np.meshgrid(np.linspace(0, 1279, 6), np.linspace(0, 1023, 5))
    rays = dev.backproject(u, v)
    np.testing.assert_allclose(rays.origin, dev.centre_world)
    for s in (50.0, 400.0):
        uu, vv = dev.project(rays.point_at(np.full(u.shape, s)))
        np.testing.assert_allclose(uu, u, atol=1e-9)
        np.testing.assert_allclose(vv, v, atol=1e-9)
    behind = dev.centre_world - 10.0 * dev.R_dev_world[2]
    assert np.all(np.isnan(dev.project(behind)))


def test_generic_problem_jacobian_with_the_pinhole_device(jacobian_error):
    """The bundle adjustment assembles the pinhole device's 15-parameter block."""
    from telefringe.calibration.device import _obs_from_array
    from telefringe.calibration.problem import BundleProblem

    dev = _device()
    rng = np.random.default_rng(4)
    r, c = np.mgrid[0:5, 0:6]
    P = np.stack([c.ravel() * 5.0, r.ravel() * 5.0, np.zeros(r.size)], axis=1)
    Rs = np.array([rotation_from_rotvec(rng.normal(0, 0.2, 3)) for _ in range(3)])
    Ts = rng.normal(0, 2.0, (3, 3))
    uv = np.array([np.stack(dev.project(P @ R.T + T), 1) for R, T in zip(Rs, Ts,
                                                                          strict=True)])
    obs = [_obs_from_array(uv, range(3), np.ones(uv.shape[:2], bool))]
    free = np.ones(15 + 18, dtype=bool)
    free[15:21] = False
    prob = BundleProblem(P, obs, [dev], Rs, Ts, sigmas=[0.1], free=free,
                         device_names=["camera"])
    assert prob.layout.index("camera.tz") == 14 and prob.layout.index("pose_2.z") == 32
    x = prob.x0 + rng.normal(0, 1e-5, prob.x0.size) * np.maximum(np.abs(prob.x0), 1e-2)
    # k3's column is small (x r^6): steps of 1e-4 of each parameter keep rounding out of
    # the differences (measured 1.4e-6 worst; 1.2e-4 on k3 with 1e-6 steps)
    assert jacobian_error(prob, x, rel_step=1e-4) < 1e-5
