"""What the reconstruction accepts as a rig."""

from __future__ import annotations

from telefringe.devices.rig import Rig
from telefringe.reconstruction.cloud import TriangulationError

__all__ = ["as_rig"]


def as_rig(rig) -> Rig:
    """A Rig from a Rig or anything holding one as ``.rig`` (e.g. the RigCalibration
    that ``telefringe.io.rig.load_rig`` returns)."""
    if isinstance(rig, Rig):
        return rig
    inner = getattr(rig, "rig", None)
    if isinstance(inner, Rig):
        return inner
    raise TriangulationError(f"expected a telefringe.devices.rig.Rig, got {type(rig).__name__}")


