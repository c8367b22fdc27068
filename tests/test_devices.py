"""The Device protocol: the telecentric device implements it, its parameter vector round-
trips, its projection Jacobian matches finite differences, and backprojected rays are
consistent with projection. Rays validate and never alias the caller's arrays."""

from __future__ import annotations

import numpy as np
import pytest

from telefringe.devices.base import ROTATION_NAMES, Device
from telefringe.devices.telecentric import Intrinsics, TelecentricDevice
from telefringe.geometry.rays import Rays
from telefringe.geometry.so3 import rotation_from_rotvec


def _device(k1=-2e-3, s1=4e-4, s2=-3e-4):
    intr = Intrinsics(m=0.5, du=0.0052, dv=0.0055, u0=641.3, v0=508.7, k1=k1, s1=s1, s2=s2,
                      width=1280, height=1024)
    return TelecentricDevice(intr, rotation_from_rotvec([0.3, -0.2, 0.1]), [0.4, -0.7])


def test_telecentric_is_a_device():
    dev = _device()
    assert isinstance(dev, Device)
    assert dev.model == "telecentric"
    assert dev.param_names == dev.intrinsic_names + dev.pose_names
    assert dev.pose_names[:3] == ROTATION_NAMES
    assert set(dev.principal_point_names) | set(dev.distortion_names) <= set(dev.intrinsic_names)
    assert dev.image_size == (1280, 1024)
    assert TelecentricDevice(Intrinsics(m=1, du=1, dv=1, u0=0, v0=0)).image_size is None


def test_params_round_trip_and_rotation_perturbation():
    dev = _device()
    p = dev.to_params()
    assert p.shape == (len(dev.param_names),)
    np.testing.assert_array_equal(p[6:9], 0.0)
    same = dev.from_params(p)
    np.testing.assert_allclose(same.R_dev_world, dev.R_dev_world, atol=1e-15)
    np.testing.assert_array_equal(same.to_params(), p)
    q = p.copy()
    q[6:9] = [0.01, -0.02, 0.03]
    moved = dev.from_params(q)
    np.testing.assert_allclose(moved.R_dev_world,
                               rotation_from_rotvec(q[6:9]) @ dev.R_dev_world, atol=1e-15)
    assert moved.intrinsics.du == dev.intrinsics.du and moved.image_size == dev.image_size
    with pytest.raises(ValueError, match="11 values"):
        dev.from_params(p[:-1])


@pytest.mark.parametrize("distorted", [False, True])
def test_project_jacobian_matches_finite_differences(distorted):
    dev = _device() if distorted else _device(0.0, 0.0, 0.0)
    rng = np.random.default_rng(3)
    X = rng.uniform(-4, 4, size=(25, 3))
    uv, J, J_X = dev.project_jacobian(X)
    u, v = dev.project(X)
    np.testing.assert_allclose(uv, np.stack([u, v], axis=1), rtol=0, atol=1e-9)
    p0 = dev.to_params()
    steps = np.array([1e-7, 1e-5, 1e-5, 1e-5, 1e-5, 1e-5, 1e-8, 1e-8, 1e-8, 1e-6, 1e-6])
    for j, h in enumerate(steps):
        e = np.zeros_like(p0)
        e[j] = h
        up = np.stack(dev.from_params(p0 + e).project(X), axis=1)
        um = np.stack(dev.from_params(p0 - e).project(X), axis=1)
        num = (up - um) / (2 * h)
        # central differences: error ~ h^2 f''' + rounding (1e-13 px / h)
        np.testing.assert_allclose(J[:, :, j], num, rtol=1e-6,
                                   atol=1e-4 * np.abs(num).max() + 1e-6,
                                   err_msg=dev.param_names[j])
    for j in range(3):
        e = np.zeros(3)
        e[j] = 1e-5
        num = (np.stack(dev.project(X + e), axis=1)
               - np.stack(dev.project(X - e), axis=1)) / 2e-5
        np.testing.assert_allclose(J_X[:, :, j], num, rtol=1e-6, atol=1e-6)


def test_backprojected_rays_project_back_to_their_pixels():
    dev = _device()
    u, v = np.meshgrid(np.linspace(0, 1279, 7), np.linspace(0, 1023, 5))
    rays = dev.backproject(u, v)
    assert isinstance(rays, Rays) and rays.shape == u.shape
    origin, direction = rays
    np.testing.assert_allclose(direction, dev.R_dev_world[2])
    for s in (-3.0, 0.0, 5.0):
        uu, vv = dev.project(rays.point_at(np.full(u.shape, s)))
        np.testing.assert_allclose(uu, u, atol=1e-8)
        np.testing.assert_allclose(vv, v, atol=1e-8)


def test_rays_validate_and_copy():
    o = np.zeros((4, 3))
    d = np.array([0.0, 0.0, 1.0])
    r = Rays(o, d)
    o[0, 0] = 5.0
    assert r.origin[0, 0] == 0.0 and o.flags.writeable  # a copy; the caller's stays writable
    assert not r.origin.flags.writeable
    assert r.directions().shape == (4, 3)
    with pytest.raises(ValueError, match="unit"):
        Rays(o, [0.0, 0.0, 2.0])
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        Rays(np.zeros((4, 2)), d)
    with pytest.raises(ValueError, match="broadcast"):
        Rays(np.zeros((4, 3)), np.tile(d, (5, 1)))
