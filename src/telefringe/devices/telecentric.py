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

from telefringe.geometry.distortion import distort_sensor, undistort_sensor
from telefringe.geometry.so3 import rotation_from_rotvec, rotvec_from_rotation

__all__ = ["Intrinsics", "TelecentricDevice"]


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
        for name in ("m", "du", "dv", "u0", "v0", "k1", "s1", "s2"):
            val = getattr(self, name)
            ok = (isinstance(val, int | float | np.integer | np.floating)
                  and not isinstance(val, bool) and bool(np.isfinite(val)))
            if not ok:
                raise ValueError(f"Intrinsics.{name} must be a finite number, got {val!r}")
        for name in ("m", "du", "dv"):
            if getattr(self, name) <= 0:
                raise ValueError(f"Intrinsics.{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("width", "height"):
            val = getattr(self, name)
            ok = (isinstance(val, int | float | np.integer | np.floating)
                  and not isinstance(val, bool) and bool(np.isfinite(val))
                  and float(val) == int(val) and int(val) >= 0)
            if not ok:
                raise ValueError(f"Intrinsics.{name} must be an integer >= 0 (pixels), "
                                 f"got {val!r}")
            object.__setattr__(self, name, int(val))

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

    Attributes
    ----------
    intrinsics : Intrinsics
    R_dev_world : (3, 3) ndarray of float, proper rotation, world -> device.
    t_dev : (2,) ndarray of float, mm, in-plane translation (no tz).
    """

    intrinsics: Intrinsics
    R_dev_world: np.ndarray = field(default_factory=lambda: np.eye(3))
    t_dev: np.ndarray = field(default_factory=lambda: np.zeros(2))

    def __post_init__(self):
        R = np.array(self.R_dev_world, dtype=float)
        t = np.array(self.t_dev, dtype=float).reshape(-1)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)):
            raise ValueError("R_dev_world must be a finite (3, 3) array")
        if not np.allclose(R @ R.T, np.eye(3), rtol=0.0, atol=1e-9) or np.linalg.det(R) < 0:
            raise ValueError("R_dev_world must be a proper rotation")
        if t.shape != (2,) or not np.all(np.isfinite(t)):
            raise ValueError("t_dev must be a finite (2,) array (tx, ty) in mm")
        R.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(self, "R_dev_world", R)
        object.__setattr__(self, "t_dev", t)

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
        X = np.asarray(points_world, dtype=float)
        if X.shape[-1] != 3:
            raise ValueError(f"points_world must have shape (..., 3), got {X.shape}")
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
    def backproject(self, u, v):
        """Pixels -> world lines.

        Parameters
        ----------
        u, v : (...,) array_like of float, observed pixels.

        Returns
        -------
        origin : (..., 3) ndarray, mm, the point of each line closest to the world
            origin's axis line (the point with zero depth along the device axis).
        direction : (3,) ndarray, unit viewing direction in world coordinates (the same
            for every pixel: the device is telecentric).
        """
        xd, yd = self.pixel_to_sensor(u, v)
        xu, yu = undistort_sensor(xd, yd, *self.intrinsics.distortion)
        m = self.intrinsics.m
        a = xu / m - self.t_dev[0]
        b = yu / m - self.t_dev[1]
        R = self.R_dev_world
        origin = a[..., None] * R[0] + b[..., None] * R[1]
        return origin, R[2].copy()
