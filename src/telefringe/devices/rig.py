"""A rig: its devices in one world frame."""

from __future__ import annotations

from dataclasses import dataclass

from telefringe.devices.telecentric import TelecentricDevice

__all__ = ["Rig"]


@dataclass(frozen=True, eq=False)
class Rig:
    """A telecentric camera and projector expressed in one world frame (mm).

    The world frame of a calibrated rig is the calibration target at its reference pose
    (x along the grid's columns, y along its rows, z toward the camera).
    """

    camera: TelecentricDevice
    projector: TelecentricDevice
