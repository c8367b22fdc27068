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

__all__ = [
    "ConvergenceError",
    "Intrinsics",
    "TelecentricDevice",
    "Rig",
    "rotation_from_rotvec",
    "rotvec_from_rotation",
    "distort_sensor",
    "undistort_sensor",
]


class ConvergenceError(ValueError):
    """An iterative inversion (e.g. undistortion) did not converge."""


def rotation_from_rotvec(rotvec) -> np.ndarray:
    """Rodrigues: rotation vector (3,) in radians -> rotation matrix (3, 3).

    Raises ``ValueError`` if ``rotvec`` is not 3 finite numbers.
    """
    r = np.asarray(rotvec, dtype=float)
    if r.size != 3 or not np.all(np.isfinite(r)):
        raise ValueError(f"rotvec must be 3 finite numbers (radians), got {rotvec!r}")
    r = r.reshape(3)
    theta = float(np.linalg.norm(r))
    K = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    if theta < 1e-12:
        return np.eye(3) + K
    K = K / theta
    return np.eye(3) + np.sin(theta) * K + (1.0 - np.cos(theta)) * (K @ K)


def rotvec_from_rotation(R) -> np.ndarray:
    """Inverse Rodrigues: rotation matrix (3, 3) -> rotation vector (3,) in radians.

    The angle (the vector's norm) is in [0, pi]. Accurate to rounding error at every
    angle, including near 0 and pi (the angle comes from ``atan2(sin, cos)``; near pi the
    axis comes from the symmetric part of ``R``). At exactly pi the sign of the axis is
    arbitrary (both give the same rotation). Raises ``ValueError`` if ``R`` is not a
    proper rotation.
    """
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise ValueError("R must be a finite (3, 3) array")
    if not np.allclose(R @ R.T, np.eye(3), rtol=0.0, atol=1e-6) or np.linalg.det(R) < 0:
        raise ValueError("R is not a proper rotation (R R^T != I or det < 0)")
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])  # 2 sin(t) axis
    sin_t = 0.5 * float(np.linalg.norm(w))
    cos_t = 0.5 * (float(np.trace(R)) - 1.0)
    theta = float(np.arctan2(sin_t, cos_t))
    if cos_t > -0.7:
        # w is well conditioned here (sin_t / theta >= 0.55); theta / sin(theta) -> 1 at 0
        return (0.5 if sin_t == 0.0 else theta / (2.0 * sin_t)) * w
    # near pi: the symmetric part is cos(t) I + (1 - cos(t)) a a^T
    aaT = (0.5 * (R + R.T) - cos_t * np.eye(3)) / (1.0 - cos_t)
    i = int(np.argmax(np.diag(aaT)))
    axis = aaT[:, i] / np.sqrt(aaT[i, i])
    axis /= np.linalg.norm(axis)
    if np.dot(axis, w) < 0:
        axis = -axis
    return theta * axis


def distort_sensor(xu, yu, k1: float, s1: float, s2: float):
    """Apply radial + thin-prism distortion on the sensor plane.

    Parameters
    ----------
    xu, yu : ndarray of float, any (broadcastable) shape
        Undistorted sensor coordinates in mm, relative to the principal point.
    k1 : float   radial coefficient, 1/mm^2.
    s1, s2 : float   thin-prism coefficients, 1/mm.

    Returns
    -------
    xd, yd : ndarray of float, same shape, distorted sensor mm.
    """
    xu = np.asarray(xu, dtype=float)
    yu = np.asarray(yu, dtype=float)
    r2 = xu * xu + yu * yu
    return xu + k1 * xu * r2 + s1 * r2, yu + k1 * yu * r2 + s2 * r2


def undistort_sensor(xd, yd, k1: float, s1: float, s2: float, *, tol: float = 1e-12,
                     max_iter: int = 50):
    """Invert :func:`distort_sensor` by Newton's method.

    Parameters
    ----------
    xd, yd : ndarray of float, any (broadcastable) shape, distorted sensor mm.
    k1, s1, s2 : float, distortion coefficients (see :func:`distort_sensor`).
    tol : float
        Convergence tolerance in mm on the residual of the forward model (default
        1e-12 mm, i.e. 2e-10 px for a 5 um pixel).

    Returns
    -------
    xu, yu : ndarray of float, undistorted sensor mm.

    Raises
    ------
    ConvergenceError
        If any finite input point does not converge, or converges only to a root
        beyond the fold of the distortion (where the forward map is not invertible).
        Non-finite inputs give non-finite outputs (NaN stays NaN).
    """
    xd, yd = np.broadcast_arrays(np.asarray(xd, dtype=float), np.asarray(yd, dtype=float))
    xu = xd.copy()
    yu = yd.copy()
    if k1 == 0.0 and s1 == 0.0 and s2 == 0.0:
        return xu, yu
    finite = np.isfinite(xd) & np.isfinite(yd)
    # the residual cannot be smaller than the rounding of the forward model
    thresh = np.maximum(tol, 64.0 * np.finfo(float).eps * (np.abs(xd) + np.abs(yd)))

    def jacobian(xu, yu, r2):
        a = 1.0 + k1 * (r2 + 2.0 * xu * xu) + 2.0 * s1 * xu
        b = 2.0 * k1 * xu * yu + 2.0 * s1 * yu
        c = 2.0 * k1 * xu * yu + 2.0 * s2 * xu
        d = 1.0 + k1 * (r2 + 2.0 * yu * yu) + 2.0 * s2 * yu
        return a, b, c, d

    # diverging points (no inverse) may overflow; they are reported below, not warned
    with np.errstate(all="ignore"):
        for _ in range(max_iter):
            r2 = xu * xu + yu * yu
            fx = xu + k1 * xu * r2 + s1 * r2 - xd
            fy = yu + k1 * yu * r2 + s2 * r2 - yd
            a, b, c, d = jacobian(xu, yu, r2)
            det = a * d - b * c
            dx = (d * fx - b * fy) / det
            dy = (-c * fx + a * fy) / det
            xu = xu - dx
            yu = yu - dy
            err = np.abs(fx) + np.abs(fy)
            if not np.any((err > thresh)[finite]):
                break
        r2 = xu * xu + yu * yu
        res = (np.abs(xu + k1 * xu * r2 + s1 * r2 - xd)
               + np.abs(yu + k1 * yu * r2 + s2 * r2 - yd))
        a, b, c, d = jacobian(xu, yu, r2)
        # A root where the forward map is folded (det <= 0) or flipped (trace <= 0) is
        # not the inverse: it lies beyond the fold of the distortion, e.g. the mirrored
        # outer root of a strong barrel distortion.
        unfolded = (a * d - b * c > 0) & (a + d > 0)
    diverged = finite & ~(res <= 10.0 * thresh)
    folded = finite & ~diverged & ~unfolded
    if np.any(diverged) or np.any(folded):
        parts = []
        if np.any(diverged):
            worst = np.where(np.isnan(res), np.inf, res)[diverged].max()
            parts.append(f"{int(np.count_nonzero(diverged))} did not converge (worst residual "
                         f"{float(worst):.3g} mm)")
        if np.any(folded):
            parts.append(f"{int(np.count_nonzero(folded))} only have a solution beyond the "
                         "fold of the distortion")
        raise ConvergenceError(
            f"undistortion failed for {int(np.count_nonzero(diverged | folded))} of "
            f"{int(np.count_nonzero(finite))} point(s): {' and '.join(parts)}. The distortion "
            f"(k1={k1:g} 1/mm^2, s1={s1:g}, s2={s2:g} 1/mm) is not invertible there; check "
            "the coefficients or keep to the image area"
        )
    return xu, yu


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


@dataclass(frozen=True, eq=False)
class Rig:
    """A telecentric camera and projector expressed in one world frame (mm).

    The world frame of a calibrated rig is the calibration target at its reference pose
    (x along the grid's columns, y along its rows, z toward the camera).
    """

    camera: TelecentricDevice
    projector: TelecentricDevice
