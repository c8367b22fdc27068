"""What a calibration set holds (the content of ``calibration.json``)."""

from __future__ import annotations

from dataclasses import dataclass

from telefringe.targets.grid import CircleGridTarget

__all__ = ["CalibrationSetManifest"]


@dataclass(frozen=True)
class CalibrationSetManifest:
    """Content of ``calibration.json``: the target, pixel sizes and pose scan folders.

    ``projector_side`` ("left", "right", "top", "bottom" or None): where the projector is,
    seen in the camera image (shadows fall away from it); settles the mirror ambiguity of
    a rig of two telecentric devices calibrated from a flat target.
    """

    target: CircleGridTarget
    camera_pixel_size: tuple[float, float]
    projector_pixel_size: tuple[float, float]
    poses: tuple[str, ...]
    reference_pose: str
    folder: str = ""
    projector_side: str | None = None
