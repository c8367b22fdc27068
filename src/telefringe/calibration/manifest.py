"""What a calibration set holds (the content of ``calibration.json``)."""

from __future__ import annotations

from dataclasses import dataclass, field

from telefringe.targets.grid import CircleGridTarget

__all__ = ["CalibrationSetManifest"]


@dataclass(frozen=True)
class CalibrationSetManifest:
    """Content of ``calibration.json``: the target, the devices and the pose scan folders.

    Attributes
    ----------
    target : CircleGridTarget
    camera_pixel_size, projector_pixel_size : (du, dv) mm, or None (a pinhole device, or
        no projector calibrated).
    poses : tuple of str, pose folder names; reference_pose : str.
    folder : str, the set's folder ("" in memory).
    models : mapping device name -> model ("telecentric", "pinhole"): ``camera``, then
        ``camera_2`` for a two-camera set, then ``projector`` unless a two-camera set
        leaves the projector uncalibrated.
    pixel_sizes : mapping device name -> (du, dv) mm, for the telecentric devices.
    projector_side : "left" | "right" | "top" | "bottom" or None, where the projector is
        seen in the camera image (settles the mirror ambiguity of a telecentric pair).
    """

    target: CircleGridTarget
    camera_pixel_size: tuple[float, float] | None
    projector_pixel_size: tuple[float, float] | None
    poses: tuple[str, ...]
    reference_pose: str
    folder: str = ""
    models: dict = field(default_factory=lambda: {"camera": "telecentric",
                                                  "projector": "telecentric"})
    pixel_sizes: dict = field(default_factory=dict)
    projector_side: str | None = None

    def __post_init__(self):
        if not self.pixel_sizes:
            sizes = {k: v for k, v in (("camera", self.camera_pixel_size),
                                       ("projector", self.projector_pixel_size))
                     if v is not None}
            object.__setattr__(self, "pixel_sizes", sizes)

    @property
    def cameras(self) -> tuple[str, ...]:
        """The camera names: ("camera",) or ("camera", "camera_2")."""
        return tuple(k for k in self.models if k != "projector")

    @property
    def has_projector(self) -> bool:
        """Whether the projector is calibrated (always for one camera)."""
        return "projector" in self.models

    def scan_folder(self, pose: str, camera: str = "camera") -> str:
        """The scan folder of ``camera`` at ``pose``, relative to the set: the pose folder
        itself for a one-camera set, ``<pose>/<camera>`` for a two-camera set."""
        if camera not in self.cameras:
            raise KeyError(f"no camera {camera!r} in this calibration set")
        return pose if len(self.cameras) == 1 else f"{pose}/{camera}"
