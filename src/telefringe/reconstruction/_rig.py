"""What the reconstruction accepts as a rig."""

from __future__ import annotations

from telefringe.devices.rig import Rig
from telefringe.reconstruction.cloud import TriangulationError

__all__ = ["as_rig"]


def as_rig(rig) -> Rig:
    """``rig`` if it is a :class:`~telefringe.devices.rig.Rig`, else its ``.rig`` if that
    is one (e.g. the RigCalibration that ``telefringe.io.rig_json.load_rig`` returns); nothing
    else is taken (no duck typing of ``camera`` / ``projector``): raises
    :class:`TriangulationError`."""
    if isinstance(rig, Rig):
        return rig
    inner = getattr(rig, "rig", None)
    if isinstance(inner, Rig):
        return inner
    what = type(rig).__name__
    if inner is not None:
        what += f" whose .rig is a {type(inner).__name__}"
    raise TriangulationError(
        f"expected a telefringe.devices.rig.Rig, or an object whose .rig is one (e.g. the "
        f"RigCalibration of telefringe.io.rig_json.load_rig), got {what}")


