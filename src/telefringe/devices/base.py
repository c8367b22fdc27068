"""The Device protocol: what calibration, reconstruction and the virtual rig need of a
camera or a projector (a projector is an inverse camera), whatever its optics.

A device maps world points (mm) to pixels and pixels back to world lines, and describes
itself by a flat vector of named parameters: first its intrinsics, then its pose. The
pose parameters always start with ``rot_x, rot_y, rot_z``, a small rotation vector
(radians, device frame) applied on the left of ``R_dev_world``:
``R = rotation_from_rotvec(rot) @ R_dev_world``; so ``to_params()`` holds zeros there,
and ``from_params(p)`` composes the rotation. The translation parameters follow
(``tx, ty`` for a telecentric device, whose images do not see depth; ``tx, ty, tz`` for a
pinhole one). Quantities that are known rather than estimated (pixel pitch, image size)
are not parameters: ``from_params`` keeps them from the device it is called on.

Implementations: :class:`telefringe.devices.telecentric.TelecentricDevice`. Code that
works for every device talks to this protocol only; code that belongs to one model lives
in the file named after it.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from telefringe.geometry.rays import Rays

__all__ = ["Device", "ROTATION_NAMES"]

#: The first three pose parameters of every device.
ROTATION_NAMES = ("rot_x", "rot_y", "rot_z")


@runtime_checkable
class Device(Protocol):
    """A camera or projector in a world frame.

    Attributes
    ----------
    model : str
        The model's name as written in files (``"telecentric"``, ``"pinhole"``).
    R_dev_world : (3, 3) ndarray, proper rotation, world -> device frame (x along +u,
        y along +v, z the viewing direction).
    image_size : (width, height) in px, or None where unknown.
    param_names : tuple of str, the names of :meth:`to_params`, intrinsics then pose.
    intrinsic_names, pose_names : tuple of str, the two parts of ``param_names``.
    principal_point_names : the two intrinsics that place the image centre (px).
    distortion_names : the intrinsics that are distortion coefficients.
    sees_depth : bool, whether moving a point along the viewing direction changes its
        image (False for a telecentric device: a pose seen by it alone has no depth).
    """

    model: str
    R_dev_world: np.ndarray

    @property
    def image_size(self) -> tuple[int, int] | None: ...

    @property
    def param_names(self) -> tuple[str, ...]: ...

    @property
    def intrinsic_names(self) -> tuple[str, ...]: ...

    @property
    def pose_names(self) -> tuple[str, ...]: ...

    @property
    def principal_point_names(self) -> tuple[str, str]: ...

    @property
    def distortion_names(self) -> tuple[str, ...]: ...

    @property
    def sees_depth(self) -> bool: ...

    def project(self, points_world) -> tuple[np.ndarray, np.ndarray]:
        """World points (..., 3) mm -> observed pixels (u, v), each (...,) px."""
        ...

    def backproject(self, u, v) -> Rays:
        """Observed pixels (u, v) (...,) px -> world lines (:class:`Rays`, shape (...,))."""
        ...

    def to_params(self) -> np.ndarray:
        """The parameter vector (len(param_names),), rotation part zero."""
        ...

    def from_params(self, params) -> Device:
        """A device of the same model and known constants with parameters ``params``."""
        ...

    def with_pose(self, R_dev_world, t_dev) -> Device:
        """The same device at another pose: ``R_dev_world`` (3, 3), translation ``t_dev``
        (the pose's translation parameters, mm)."""
        ...

    def project_jacobian(self, points_world) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Projection and its derivatives at this device's parameters.

        Parameters
        ----------
        points_world : (n, 3) array_like, mm.

        Returns
        -------
        uv : (n, 2) ndarray, px.
        J_params : (n, 2, len(param_names)) ndarray, d(u, v)/d(params) at
            ``to_params()`` (the rotation part as a left perturbation at zero).
        J_points : (n, 2, 3) ndarray, d(u, v)/d(points_world), px/mm.
        """
        ...
