"""Pinhole (perspective) device with OpenCV's distortion model and conventions.

One model serves cameras and projectors (a projector is an inverse camera).

Forward model (per point ``X`` in world mm)::

    [Xc, Yc, Zc] = R_dev_world @ X + t_dev          # device frame, +z into the scene
    x, y = Xc / Zc, Yc / Zc                          # normalised coordinates
    r2 = x**2 + y**2,  a = 1 + k1 r2 + k2 r2**2 + k3 r2**3
    xd = x a + 2 p1 x y + p2 (r2 + 2 x**2)
    yd = y a + p1 (r2 + 2 y**2) + 2 p2 x y
    u = fx xd + cx,   v = fy yd + cy                 # px, integers at pixel centres

exactly as ``cv2.projectPoints`` with ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` and
``distCoeffs = (k1, k2, p1, p2, k3)``. Points at or behind the device (Zc <= 0) project
to NaN.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from telefringe.devices._checks import (
    check_intrinsics,
    freeze_pose,
    image_size_of,
    points_array,
)
from telefringe.devices.base import ROTATION_NAMES
from telefringe.geometry.distortion import (
    distort_normalized,
    distort_normalized_jacobian,
    undistort_normalized,
)
from telefringe.geometry.rays import Rays
from telefringe.geometry.so3 import rotation_from_rotvec, rotvec_from_rotation, skew

__all__ = ["PINHOLE_INTRINSIC_NAMES", "PINHOLE_POSE_NAMES", "PinholeIntrinsics",
           "PinholeDevice"]

#: The intrinsic parameters of a pinhole device (:meth:`PinholeDevice.to_params`): focal
#: lengths and principal point (px), OpenCV's distortion coefficients (unitless).
PINHOLE_INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
#: Its pose parameters: a left rotation perturbation (rad) and the translation (mm).
PINHOLE_POSE_NAMES = ROTATION_NAMES + ("tx", "ty", "tz")


@dataclass(frozen=True)
class PinholeIntrinsics:
    """Intrinsic parameters of a pinhole device (OpenCV's).

    Attributes
    ----------
    fx, fy : float, focal lengths, px (> 0).
    cx, cy : float, principal point, px.
    k1, k2, p1, p2, k3 : float, distortion coefficients (unitless), OpenCV's order.
    width, height : int, image size in pixels (0: unknown).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0
    width: int = 0
    height: int = 0

    def __post_init__(self):
        check_intrinsics(self, PINHOLE_INTRINSIC_NAMES, ("fx", "fy"))

    @property
    def distortion(self) -> tuple[float, float, float, float, float]:
        """(k1, k2, p1, p2, k3), OpenCV's ``distCoeffs``."""
        return (self.k1, self.k2, self.p1, self.p2, self.k3)

    @property
    def camera_matrix(self) -> np.ndarray:
        """OpenCV's K (3, 3)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True, eq=False)
class PinholeDevice:
    """A pinhole camera or projector: intrinsics and pose.

    Implements the :class:`~telefringe.devices.base.Device` protocol.

    Attributes
    ----------
    intrinsics : PinholeIntrinsics
    R_dev_world : (3, 3) ndarray, proper rotation, world -> device (OpenCV's ``R``).
    t_dev : (3,) ndarray, mm, ``X_dev = R_dev_world X_world + t_dev`` (OpenCV's ``t``).
    """

    intrinsics: PinholeIntrinsics
    R_dev_world: np.ndarray = field(default_factory=lambda: np.eye(3))
    t_dev: np.ndarray = field(default_factory=lambda: np.zeros(3))

    model = "pinhole"
    intrinsic_names = PINHOLE_INTRINSIC_NAMES
    pose_names = PINHOLE_POSE_NAMES
    principal_point_names = ("cx", "cy")
    distortion_names = ("k1", "k2", "p1", "p2", "k3")
    sees_depth = True

    def __post_init__(self):
        freeze_pose(self, "tx, ty, tz")

    @property
    def param_names(self) -> tuple[str, ...]:
        return PINHOLE_INTRINSIC_NAMES + PINHOLE_POSE_NAMES

    @property
    def image_size(self) -> tuple[int, int] | None:
        return image_size_of(self.intrinsics)

    @property
    def rotvec(self) -> np.ndarray:
        """Rotation vector (3,) of ``R_dev_world``, radians (OpenCV's ``rvec``)."""
        return rotvec_from_rotation(self.R_dev_world)

    @property
    def centre_world(self) -> np.ndarray:
        """The projection centre (3,) in world mm: ``-R^T t``."""
        return -self.R_dev_world.T @ self.t_dev

    # -- forward ----------------------------------------------------------------
    def _normalised(self, points_world):
        X = points_array(points_world)
        Y = X @ self.R_dev_world.T + self.t_dev
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(Y[..., 2] > 0, Y[..., 2], np.nan)
            return Y[..., 0] / z, Y[..., 1] / z, Y

    def project(self, points_world):
        """World points (..., 3) mm -> observed pixels (u, v), each (...,); NaN for points
        at or behind the device."""
        x, y, _ = self._normalised(points_world)
        k = self.intrinsics
        xd, yd = distort_normalized(x, y, *k.distortion)
        return k.fx * xd + k.cx, k.fy * yd + k.cy

    def undistort(self, u, v):
        """Observed pixels (...,) -> ideal (undistorted) pixels (...,), to 1e-11 px for a
        1000 px focal length. Raises ConvergenceError where the distortion folds."""
        k = self.intrinsics
        x, y = undistort_normalized((np.asarray(u, dtype=float) - k.cx) / k.fx,
                                    (np.asarray(v, dtype=float) - k.cy) / k.fy,
                                    *k.distortion)
        return k.fx * x + k.cx, k.fy * y + k.cy

    # -- backward ---------------------------------------------------------------
    def backproject(self, u, v) -> Rays:
        """Pixels (...,) -> world rays from the projection centre (origin (3,), direction
        (..., 3)). Raises ConvergenceError where the distortion cannot be inverted."""
        k = self.intrinsics
        x, y = undistort_normalized((np.asarray(u, dtype=float) - k.cx) / k.fx,
                                    (np.asarray(v, dtype=float) - k.cy) / k.fy,
                                    *k.distortion)
        d_dev = np.stack([x, y, np.ones_like(x)], axis=-1)
        d = d_dev @ self.R_dev_world
        return Rays(self.centre_world, d / np.linalg.norm(d, axis=-1, keepdims=True))

    # -- parameters (the Device protocol) ------------------------------------------
    def to_params(self) -> np.ndarray:
        """(15,) ndarray: fx, fy, cx, cy (px), k1, k2, p1, p2, k3, a zero rotation vector
        (rad), tx, ty, tz (mm)."""
        k = self.intrinsics
        return np.array([k.fx, k.fy, k.cx, k.cy, *k.distortion, 0.0, 0.0, 0.0, *self.t_dev])

    def from_params(self, params) -> PinholeDevice:
        """This device with the parameters ``params`` (15,) (see :meth:`to_params`); the
        image size is kept."""
        p = np.asarray(params, dtype=float).reshape(-1)
        if p.shape != (len(self.param_names),):
            raise ValueError(f"params must have {len(self.param_names)} values "
                             f"({', '.join(self.param_names)}), got {p.size}")
        intr = replace(self.intrinsics, **{n: float(v) for n, v in
                                           zip(PINHOLE_INTRINSIC_NAMES, p[:9], strict=True)})
        return PinholeDevice(intr, rotation_from_rotvec(p[9:12]) @ self.R_dev_world, p[12:15])

    def with_pose(self, R_dev_world, t_dev) -> PinholeDevice:
        """This device at rotation ``R_dev_world`` (3, 3) and translation ``t_dev`` (3,) mm."""
        return PinholeDevice(self.intrinsics, R_dev_world, t_dev)

    def project_jacobian(self, points_world):
        """Projection of ``points_world`` (n, 3) mm and its derivatives.

        Returns
        -------
        uv : (n, 2) ndarray, px (NaN behind the device).
        J_params : (n, 2, 15) ndarray, d(u, v)/d(:meth:`to_params`), the rotation as a left
            perturbation of ``R_dev_world`` at zero.
        J_points : (n, 2, 3) ndarray, d(u, v)/d(points_world), px/mm.
        """
        X = points_array(points_world, flat=True)
        k = self.intrinsics
        x, y, Y = self._normalised(X)
        dist = k.distortion
        xd, yd = distort_normalized(x, y, *dist)
        uv = np.stack([k.fx * xd + k.cx, k.fy * yd + k.cy], axis=1)
        n = X.shape[0]
        r2 = x * x + y * y
        J = np.zeros((n, 2, 15))
        J[:, 0, 0] = xd
        J[:, 1, 1] = yd
        J[:, 0, 2] = 1.0
        J[:, 1, 3] = 1.0
        for j, rk in enumerate((r2, r2 * r2)):  # k1, k2
            J[:, 0, 4 + j] = k.fx * x * rk
            J[:, 1, 4 + j] = k.fy * y * rk
        J[:, 0, 6] = k.fx * 2.0 * x * y  # p1
        J[:, 1, 6] = k.fy * (r2 + 2.0 * y * y)
        J[:, 0, 7] = k.fx * (r2 + 2.0 * x * x)  # p2
        J[:, 1, 7] = k.fy * 2.0 * x * y
        J[:, 0, 8] = k.fx * x * r2 ** 3  # k3
        J[:, 1, 8] = k.fy * y * r2 ** 3
        a, b, c, d = distort_normalized_jacobian(x, y, *dist)
        iz = 1.0 / Y[:, 2]
        # d(u, v)/d(Y): diag(fx, fy) @ d(xd, yd)/d(x, y) @ d(x, y)/d(Y)
        J_Y = np.zeros((n, 2, 3))
        J_Y[:, 0, 0] = k.fx * a * iz
        J_Y[:, 0, 1] = k.fx * b * iz
        J_Y[:, 0, 2] = -k.fx * (a * x + b * y) * iz
        J_Y[:, 1, 0] = k.fy * c * iz
        J_Y[:, 1, 1] = k.fy * d * iz
        J_Y[:, 1, 2] = -k.fy * (c * x + d * y) * iz
        J[:, :, 9:12] = J_Y @ (-skew(X @ self.R_dev_world.T))  # the rotation acts before t
        J[:, :, 12:15] = J_Y
        return uv, J, J_Y @ self.R_dev_world
