"""What a calibration set holds (the content of ``calibration.json``)."""

from __future__ import annotations

from dataclasses import dataclass

from telefringe.targets.grid import CircleGridTarget

__all__ = ["CalibrationSetManifest"]


@dataclass(frozen=True)
class CalibrationSetManifest:
    """Content of ``calibration.json``: the target, pixel sizes and pose scan folders."""

    target: CircleGridTarget
    camera_pixel_size: tuple[float, float]
    projector_pixel_size: tuple[float, float]
    poses: tuple[str, ...]
    reference_pose: str
    folder: str = ""
