"""Telecentric (scaled orthographic) device model with radial + thin-prism distortion.

One model serves the camera and the projector (the projector is an inverse camera).

Conventions (see docs/conventions.md)
-------------------------------------
- World and sensor lengths in millimetres, image coordinates in pixels.
- Pixel (u, v) = (column, row); integer values at pixel centres; (0, 0) is the centre
  of the top-left pixel.
- ``R_dev_world`` (3, 3) is a proper rotation mapping world vectors to the device
  frame. The device frame's x axis runs along +u, its y axis along +v, and its z axis
  is the viewing direction (from the device into the scene), like OpenCV.
- ``t_dev`` (2,) mm, the in-plane translation: there is no tz, depth along the optical
  axis does not change the image.

Forward model (per point ``X`` in world mm)::

    [xu, yu] = m * (R_dev_world[0:2] @ X + t_dev)       # undistorted sensor mm
    r2 = xu**2 + yu**2
    xd = xu + k1 * xu * r2 + s1 * r2
    yd = yu + k1 * yu * r2 + s2 * r2
    u = u0 + xd / du,   v = v0 + yd / dv

``k1`` is in 1/mm^2, ``s1`` and ``s2`` in 1/mm (sensor plane).
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
from telefringe.geometry.distortion import distort_sensor, undistort_sensor
from telefringe.geometry.rays import Rays
from telefringe.geometry.so3 import rotation_from_rotvec, rotvec_from_rotation, skew

__all__ = ["INTRINSIC_NAMES", "POSE_NAMES", "Intrinsics", "TelecentricDevice"]

#: The intrinsic parameters of a telecentric device (:meth:`TelecentricDevice.to_params`):
#: magnification, principal point (px), radial (1/mm^2) and thin-prism (1/mm) distortion.
INTRINSIC_NAMES = ("m", "u0", "v0", "k1", "s1", "s2")
#: Its pose parameters: a left rotation perturbation (rad) and the in-plane translation
#: (mm); no tz, depth along the axis does not change the image.
POSE_NAMES = ROTATION_NAMES + ("tx", "ty")


@dataclass(frozen=True)
class Intrinsics:
    """Intrinsic parameters of a telecentric device.

    Attributes
    ----------
    m : float            magnification (sensor mm per world mm), > 0.
    du, dv : float       pixel pitch along u and v, mm.
    u0, v0 : float       principal point, px.
    k1 : float           radial distortion, 1/mm^2 (sensor plane).
    s1, s2 : float       thin-prism distortion, 1/mm (sensor plane).
    width, height : int  image size in pixels (columns, rows).
    """

    m: float
    du: float
    dv: float
    u0: float
    v0: float
    k1: float = 0.0
    s1: float = 0.0
    s2: float = 0.0
    width: int = 0
    height: int = 0

    def __post_init__(self):
        check_intrinsics(self, ("m", "du", "dv", "u0", "v0", "k1", "s1", "s2"),
                         ("m", "du", "dv"))

    @property
    def distortion(self) -> tuple[float, float, float]:
        return (self.k1, self.s1, self.s2)

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape as numpy (rows, cols)."""
        return (int(self.height), int(self.width))


@dataclass(frozen=True, eq=False)
class TelecentricDevice:
    """A telecentric camera or projector: intrinsics and pose.

    Implements the :class:`~telefringe.devices.base.Device` protocol.

    Attributes
    ----------
    intrinsics : Intrinsics
    R_dev_world : (3, 3) ndarray of float, proper rotation, world -> device.
    t_dev : (2,) ndarray of float, mm, in-plane translation (no tz).
    """

    intrinsics: Intrinsics
    R_dev_world: np.ndarray = field(default_factory=lambda: np.eye(3))
    t_dev: np.ndarray = field(default_factory=lambda: np.zeros(2))

    model = "telecentric"

    def __post_init__(self):
        freeze_pose(self, "tx, ty")

    # -- construction helpers -------------------------------------------------
    @classmethod
    def from_rotvec(cls, intrinsics: Intrinsics, rotvec, t_dev) -> TelecentricDevice:
        return cls(intrinsics, rotation_from_rotvec(rotvec), np.asarray(t_dev, dtype=float))

    @property
    def rotvec(self) -> np.ndarray:
        """Rotation vector (3,) of ``R_dev_world``, radians."""
        return rotvec_from_rotation(self.R_dev_world)

    @property
    def axis_world(self) -> np.ndarray:
        """Unit viewing direction (3,) in world coordinates (device z axis)."""
        return self.R_dev_world[2].copy()

    def with_(self, **changes) -> TelecentricDevice:
        """A copy with some fields replaced."""
        return replace(self, **changes)

    # -- sensor <-> pixel -----------------------------------------------------
    def sensor_to_pixel(self, xd, yd):
        """Distorted sensor mm (...,) -> pixel (u, v) (...,)."""
        k = self.intrinsics
        return k.u0 + np.asarray(xd) / k.du, k.v0 + np.asarray(yd) / k.dv

    def pixel_to_sensor(self, u, v):
        """Pixel (u, v) (...,) -> distorted sensor mm (xd, yd) (...,)."""
        k = self.intrinsics
        u = np.asarray(u, dtype=float)
        v = np.asarray(v, dtype=float)
        return (u - k.u0) * k.du, (v - k.v0) * k.dv

    # -- forward --------------------------------------------------------------
    def world_to_sensor(self, points_world):
        """World points (..., 3) mm -> undistorted sensor coordinates (xu, yu), each (...,) mm."""
        X = points_array(points_world)
        m = self.intrinsics.m
        R = self.R_dev_world
        xu = m * (X @ R[0] + self.t_dev[0])
        yu = m * (X @ R[1] + self.t_dev[1])
        return xu, yu

    def project(self, points_world):
        """Project world points to pixels.

        Parameters
        ----------
        points_world : (..., 3) array_like of float, mm.

        Returns
        -------
        u, v : (...,) ndarray of float, px (distortion applied).
        """
        xu, yu = self.world_to_sensor(points_world)
        xd, yd = distort_sensor(xu, yu, *self.intrinsics.distortion)
        return self.sensor_to_pixel(xd, yd)

    def project_undistorted(self, points_world):
        """Like :meth:`project` without distortion: the ideal pixel (..., ) (u, v)."""
        xu, yu = self.world_to_sensor(points_world)
        return self.sensor_to_pixel(xu, yu)

    def distort(self, u, v):
        """Ideal (undistorted) pixels (...,) -> observed (distorted) pixels (...,)."""
        xu, yu = self.pixel_to_sensor(u, v)
        xd, yd = distort_sensor(xu, yu, *self.intrinsics.distortion)
        return self.sensor_to_pixel(xd, yd)

    def undistort(self, u, v):
        """Observed (distorted) pixels (...,) -> ideal pixels (...,), to better than 1e-9 px.

        Raises :class:`ConvergenceError` where the distortion cannot be inverted.
        """
        xd, yd = self.pixel_to_sensor(u, v)
        xu, yu = undistort_sensor(xd, yd, *self.intrinsics.distortion)
        return self.sensor_to_pixel(xu, yu)

    # -- backward -------------------------------------------------------------
    def backproject(self, u, v) -> Rays:
        """Pixels -> world lines.

        Parameters
        ----------
        u, v : (...,) array_like of float, observed pixels.

        Returns
        -------
        Rays
            ``origin`` (..., 3) mm, the point of each line with zero depth along the
            device axis (the line's point nearest the world origin's axis line);
            ``direction`` (3,), the unit viewing direction in world coordinates, the same
            for every pixel (the device is telecentric). Unpacks as ``origin, direction``.

        Raises :class:`~telefringe.geometry.distortion.ConvergenceError` where the
        distortion cannot be inverted.
        """
        xd, yd = self.pixel_to_sensor(u, v)
        xu, yu = undistort_sensor(xd, yd, *self.intrinsics.distortion)
        m = self.intrinsics.m
        a = xu / m - self.t_dev[0]
        b = yu / m - self.t_dev[1]
        R = self.R_dev_world
        origin = a[..., None] * R[0] + b[..., None] * R[1]
        return Rays(origin, R[2])

    # -- parameters (the Device protocol) ---------------------------------------
    @property
    def image_size(self) -> tuple[int, int] | None:
        """(width, height) px, or None where the intrinsics do not give it."""
        return image_size_of(self.intrinsics)

    @property
    def param_names(self) -> tuple[str, ...]:
        """``INTRINSIC_NAMES + POSE_NAMES``: (m, u0, v0, k1, s1, s2, rot_x, rot_y, rot_z,
        tx, ty)."""
        return INTRINSIC_NAMES + POSE_NAMES

    intrinsic_names = INTRINSIC_NAMES
    pose_names = POSE_NAMES
    principal_point_names = ("u0", "v0")
    distortion_names = ("k1", "s1", "s2")
    sees_depth = False

    def to_params(self) -> np.ndarray:
        """(11,) ndarray: m, u0 (px), v0 (px), k1 (1/mm^2), s1, s2 (1/mm), a zero
        rotation vector (rad), tx, ty (mm)."""
        k = self.intrinsics
        return np.array([k.m, k.u0, k.v0, k.k1, k.s1, k.s2, 0.0, 0.0, 0.0,
                         self.t_dev[0], self.t_dev[1]])

    def from_params(self, params) -> TelecentricDevice:
        """This device with the parameters ``params`` (11,) (see :meth:`to_params`); the
        pixel pitch and the image size are kept. Raises ``ValueError`` for a wrong
        length or invalid values (e.g. m <= 0)."""
        p = np.asarray(params, dtype=float).reshape(-1)
        if p.shape != (len(self.param_names),):
            raise ValueError(f"params must have {len(self.param_names)} values "
                             f"({', '.join(self.param_names)}), got {p.size}")
        intr = replace(self.intrinsics, m=float(p[0]), u0=float(p[1]), v0=float(p[2]),
                       k1=float(p[3]), s1=float(p[4]), s2=float(p[5]))
        R = rotation_from_rotvec(p[6:9]) @ self.R_dev_world
        return TelecentricDevice(intr, R, p[9:11])

    def with_pose(self, R_dev_world, t_dev) -> TelecentricDevice:
        """This device at rotation ``R_dev_world`` (3, 3) and in-plane translation
        ``t_dev`` (2,) mm."""
        return TelecentricDevice(self.intrinsics, R_dev_world, t_dev)

    def project_jacobian(self, points_world):
        """Projection of ``points_world`` (n, 3) mm and its derivatives.

        Returns
        -------
        uv : (n, 2) ndarray, px.
        J_params : (n, 2, 11) ndarray, d(u, v)/d(:meth:`to_params`), the rotation as a
            left perturbation of ``R_dev_world`` at zero.
        J_points : (n, 2, 3) ndarray, d(u, v)/d(points_world), px/mm.
        """
        X = points_array(points_world, flat=True)
        k = self.intrinsics
        m, u0, v0, k1, s1, s2, du, dv = k.m, k.u0, k.v0, k.k1, k.s1, k.s2, k.du, k.dv
        R = self.R_dev_world
        Y = X @ R.T
        a = Y[:, 0] + self.t_dev[0]
        b = Y[:, 1] + self.t_dev[1]
        xu = m * a
        yu = m * b
        r2 = xu * xu + yu * yu
        xd = xu + k1 * xu * r2 + s1 * r2
        yd = yu + k1 * yu * r2 + s2 * r2
        uv = np.stack([u0 + xd / du, v0 + yd / dv], axis=1)
        n = X.shape[0]
        # distortion Jacobian d(xd, yd)/d(xu, yu), scaled to pixels
        G = np.empty((n, 2, 2))
        G[:, 0, 0] = (1.0 + k1 * (r2 + 2.0 * xu * xu) + 2.0 * s1 * xu) / du
        G[:, 0, 1] = (2.0 * k1 * xu * yu + 2.0 * s1 * yu) / du
        G[:, 1, 0] = (2.0 * k1 * xu * yu + 2.0 * s2 * xu) / dv
        G[:, 1, 1] = (1.0 + k1 * (r2 + 2.0 * yu * yu) + 2.0 * s2 * yu) / dv
        J = np.zeros((n, 2, 11))
        J[:, :, 0] = G[:, :, 0] * a[:, None] + G[:, :, 1] * b[:, None]
        J[:, 0, 1] = 1.0
        J[:, 1, 2] = 1.0
        J[:, 0, 3] = xu * r2 / du
        J[:, 1, 3] = yu * r2 / dv
        J[:, 0, 4] = r2 / du
        J[:, 1, 5] = r2 / dv
        J_t = m * G  # d(u, v)/d(tx, ty) = d(u, v)/d(Y_x, Y_y); Y_z is not seen
        J_Y = np.zeros((n, 2, 3))
        J_Y[:, :, :2] = J_t
        J[:, :, 6:9] = J_Y @ (-skew(Y))  # d Y / d rot = -[Y]x at a zero perturbation
        J[:, :, 9:11] = J_t
        return uv, J, J_Y @ R
