"""The Device seam, proved with a minimal pinhole device written here (no distortion; the
real OpenCV pinhole model comes with the any-rig issue): it satisfies the protocol, and
the generic bundle adjustment, which has never seen it, calibrates a telecentric camera
with a pinhole projector from noisy target views, with a Jacobian that matches finite
differences and errors within the covariance's uncertainty."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from telefringe.calibration.device import _obs_from_array
from telefringe.calibration.problem import BundleProblem
from telefringe.devices.base import ROTATION_NAMES, Device
from telefringe.devices.telecentric import Intrinsics, TelecentricDevice
from telefringe.geometry.rays import Rays
from telefringe.geometry.so3 import rotation_from_rotvec, skew


@dataclass(frozen=True, eq=False)
class TinyPinhole:
    """u = fx X/Z + cx, v = fy Y/Z + cy with (X, Y, Z) = R X_world + t."""

    f: tuple  # (fx, fy, cx, cy) px
    R_dev_world: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))

    model = "pinhole"
    intrinsic_names = ("fx", "fy", "cx", "cy")
    pose_names = ROTATION_NAMES + ("tx", "ty", "tz")
    principal_point_names = ("cx", "cy")
    distortion_names = ()
    sees_depth = True
    image_size = (800, 600)

    @property
    def param_names(self):
        return self.intrinsic_names + self.pose_names

    def project(self, points_world):
        Y = np.asarray(points_world, dtype=float) @ self.R_dev_world.T + self.t
        fx, fy, cx, cy = self.f
        return fx * Y[..., 0] / Y[..., 2] + cx, fy * Y[..., 1] / Y[..., 2] + cy

    def backproject(self, u, v):
        fx, fy, cx, cy = self.f
        d_dev = np.stack([(np.asarray(u) - cx) / fx, (np.asarray(v) - cy) / fy,
                          np.ones(np.shape(u))], axis=-1)
        d = d_dev @ self.R_dev_world
        return Rays(-self.R_dev_world.T @ self.t, d / np.linalg.norm(d, axis=-1)[..., None])

    def to_params(self):
        return np.array([*self.f, 0.0, 0.0, 0.0, *self.t])

    def from_params(self, p):
        p = np.asarray(p, dtype=float)
        return TinyPinhole(tuple(p[:4]), rotation_from_rotvec(p[4:7]) @ self.R_dev_world,
                           p[7:10].copy())

    def with_pose(self, R, t):
        return TinyPinhole(self.f, np.asarray(R, float), np.asarray(t, float))

    def project_jacobian(self, points_world):
        X = np.asarray(points_world, dtype=float)
        Y = X @ self.R_dev_world.T + self.t
        fx, fy, cx, cy = self.f
        iz = 1.0 / Y[:, 2]
        n = X.shape[0]
        uv = np.stack([fx * Y[:, 0] * iz + cx, fy * Y[:, 1] * iz + cy], axis=1)
        J_Y = np.zeros((n, 2, 3))
        J_Y[:, 0, 0] = fx * iz
        J_Y[:, 0, 2] = -fx * Y[:, 0] * iz**2
        J_Y[:, 1, 1] = fy * iz
        J_Y[:, 1, 2] = -fy * Y[:, 1] * iz**2
        J = np.zeros((n, 2, 10))
        J[:, 0, 0] = Y[:, 0] * iz
        J[:, 1, 1] = Y[:, 1] * iz
        J[:, 0, 2] = 1.0
        J[:, 1, 3] = 1.0
        Y0 = X @ self.R_dev_world.T  # the rotation acts before the translation
        J[:, :, 4:7] = J_Y @ (-skew(Y0))
        J[:, :, 7:10] = J_Y
        return uv, J, J_Y @ self.R_dev_world


def _rig():
    cam = TelecentricDevice(
        Intrinsics(m=0.16, du=0.0052, dv=0.0052, u0=640.0, v0=512.0, k1=2e-4, s1=3e-4,
                   s2=-2e-4, width=1280, height=1024),
        rotation_from_rotvec([np.pi, 0.0, 0.0]), [-15.0, 12.0])
    R_p = rotation_from_rotvec([np.pi, 0.0, 0.0]) @ rotation_from_rotvec([0.0, 0.5, 0.0])
    centre = np.array([15.0, 12.0, 0.0])
    t_p = np.array([0.0, 0.0, 120.0]) - R_p @ centre
    return cam, TinyPinhole((1500.0, 1500.0, 400.0, 300.0), R_p, t_p)


def _poses(n, rng):
    Rs, Ts = [np.eye(3)], [np.zeros(3)]
    c = np.array([15.0, 12.0, 0.0])
    for i in range(1, n):
        phi = 2 * np.pi * i / (n - 1)
        R = rotation_from_rotvec(np.radians(15) * np.array([np.cos(phi), np.sin(phi), 0]))
        Rs.append(R)
        Ts.append(c - R @ c + rng.normal(0, 1.0, 3))
    return np.array(Rs), np.array(Ts)


def _problem(rng, sigmas=(0.02, 0.01), n_poses=8):
    cam, proj = _rig()
    assert isinstance(proj, Device) and isinstance(cam, Device)
    r, c = np.mgrid[0:9, 0:11]
    P = np.stack([c.ravel() * 3.0, r.ravel() * 3.0, np.zeros(r.size)], axis=1)
    Rs, Ts = _poses(n_poses, rng)
    obs = []
    for dev, s in zip((cam, proj), sigmas, strict=True):
        uv = np.array([np.stack(dev.project(P @ R.T + T), 1) for R, T in zip(Rs, Ts,
                                                                              strict=True)])
        uv += rng.normal(0, s, uv.shape)
        obs.append(_obs_from_array(uv, range(n_poses), np.ones(uv.shape[:2], bool)))
    return cam, proj, P, Rs, Ts, obs


def test_pinhole_backprojection_is_consistent_with_projection():
    _, proj = _rig()
    u, v = np.meshgrid(np.linspace(0, 799, 5), np.linspace(0, 599, 4))
    rays = proj.backproject(u, v)
    uu, vv = proj.project(rays.point_at(np.full(u.shape, 100.0)))
    np.testing.assert_allclose(uu, u, atol=1e-9)
    np.testing.assert_allclose(vv, v, atol=1e-9)


def test_generic_problem_jacobian_with_a_pinhole_device(jacobian_error):
    rng = np.random.default_rng(1)
    cam, proj, P, Rs, Ts, obs = _problem(rng, n_poses=4)
    layout_size = 11 + 10 + 6 * 4
    free = np.ones(layout_size, dtype=bool)
    free[21:27] = False
    prob = BundleProblem(P, obs, [cam, proj], Rs, Ts, sigmas=[0.02, 0.01], free=free)
    assert prob.layout.index("projector.tz") == 11 + 9
    assert prob.layout.index("pose_1.z") == 21 + 6 + 5
    x = prob.x0 + rng.normal(0, 1e-4, prob.x0.size) * np.maximum(np.abs(prob.x0), 1e-2)
    assert jacobian_error(prob, x) < 1e-5


def test_generic_adjustment_calibrates_a_mixed_rig_within_its_uncertainty():
    rng = np.random.default_rng(7)
    cam, proj, P, Rs, Ts, obs = _problem(rng)
    n_poses = len(Rs)
    free = np.ones(21 + 6 * n_poses, dtype=bool)
    free[21:27] = False  # the reference pose is the world frame
    # a start off the truth by many sigma in every parameter
    p_c = cam.to_params() * (1 + 1e-3)
    p_c[6:9] = [2e-3, -1e-3, 1e-3]
    p_p = proj.to_params() * (1 + 1e-3)
    p_p[4:7] = [1e-3, 2e-3, -1e-3]
    Rs0 = np.array([rotation_from_rotvec([1e-3, 0, -1e-3]) @ R for R in Rs])
    Rs0[0] = Rs[0]
    prob = BundleProblem(P, obs, [cam.from_params(p_c), proj.from_params(p_p)], Rs0,
                         Ts + 0.01 * np.arange(n_poses)[:, None] * (np.arange(n_poses) > 0
                                                                    )[:, None],
                         sigmas=[0.02, 0.01], free=free)
    x = prob.solve().x
    prob, x = prob.rebased(x)
    cov, chi2 = prob.covariance(x)
    assert 0.8 < chi2 < 1.2  # 2 x 2 x 99 x 8 residuals: chi2 within ~4 sigma of 1
    sd = np.sqrt(np.diag(prob.device_covariance(cov)))
    devs, _, _ = prob.unpack(x)
    est = np.concatenate([d.to_params() for d in devs])
    truth = np.concatenate([cam.to_params(), proj.to_params()])
    for d, (e_dev, t_dev) in enumerate(zip(devs, (cam, proj), strict=True)):
        dR = t_dev.R_dev_world @ e_dev.R_dev_world.T
        w = 0.5 * np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]])
        i = prob.layout.index(f"{prob.layout.device_names[d]}.rot_x")
        truth[i:i + 3] = w  # truth = R(w) est
    z = (est - truth) / sd
    names = prob.layout.device_parameter_names
    assert np.all(np.abs(z) < 5), {n: round(float(v), 1) for n, v in zip(names, z,
                                                                         strict=True)}
