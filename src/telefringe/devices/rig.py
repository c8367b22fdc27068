"""A rig: named cameras and an optional projector in one world frame (mm).

The world frame of a calibrated rig is the calibration target at its reference pose
(x along the grid's columns, y along its rows, z toward the camera).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

from telefringe.devices.base import Device

__all__ = ["Rig"]


@dataclass(frozen=True, eq=False, init=False)
class Rig:
    """Cameras (one, or two for stereo) and an optional projector, in one world frame.

    ``Rig(camera, projector)`` is a one-camera rig (its camera named ``"camera"``);
    ``Rig(cameras={"camera": c1, "camera_2": c2}, projector=p)`` names each camera (the
    first is the reference camera, on whose pixel grid point clouds are given).

    Attributes
    ----------
    cameras : read-only mapping of str -> Device, in order.
    projector : Device or None (a two-camera rig may have no calibrated projector).
    """

    cameras: Mapping[str, Device]
    projector: Device | None

    def __init__(self, camera: Device | None = None, projector: Device | None = None, *,
                 cameras: Mapping[str, Device] | None = None):
        if (camera is None) == (cameras is None):
            raise ValueError("Rig: give either camera (one camera) or cameras (a mapping of "
                             "names to devices)")
        cams = {"camera": camera} if cameras is None else dict(cameras)
        if not cams:
            raise ValueError("Rig: at least one camera")
        for name, dev in list(cams.items()) + [("projector", projector)]:
            if name != "projector" and not (isinstance(name, str) and name):
                raise ValueError(f"Rig: camera names must be non-empty strings, got {name!r}")
            if dev is not None and not isinstance(dev, Device):
                raise TypeError(f"Rig: {name} must be a Device (see telefringe.devices.base),"
                                f" got {type(dev).__name__}")
        object.__setattr__(self, "cameras", MappingProxyType(cams))
        object.__setattr__(self, "projector", projector)

    def __reduce__(self):  # pickles (for worker processes) despite the read-only mapping
        return (_rebuild, (dict(self.cameras), self.projector))

    @property
    def camera(self) -> Device:
        """The reference (first) camera."""
        return next(iter(self.cameras.values()))

    @property
    def camera_names(self) -> tuple[str, ...]:
        return tuple(self.cameras)


def _rebuild(cameras, projector) -> Rig:
    return Rig(cameras=cameras, projector=projector)
