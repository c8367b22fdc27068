"""Which closed-form start serves which device model, and how a rig's relative rotation
is settled: the one place where generic calibration code meets the models.

Each model's start lives in ``start_<model>.py``; ``calibrate_device`` and
``calibrate_rig`` reach them only through :func:`device_start` and
:func:`rig_rotations` (checked by an import contract).
"""

from __future__ import annotations

from telefringe.calibration import start_pinhole, start_telecentric
from telefringe.calibration.errors import CalibrationError

__all__ = ["MODELS", "PROJECTOR_SIDES", "device_start", "rig_rotations"]

#: Models whose devices can be calibrated from planar target views.
MODELS = ("telecentric", "pinhole")
#: Where the projector can be, seen in the camera image (settles a telecentric rig's
#: mirror ambiguity).
PROJECTOR_SIDES = tuple(start_telecentric.PROJECTOR_SIDES)
_STARTS = {"telecentric": start_telecentric.start_device,
           "pinhole": start_pinhole.start_device}


def device_start(model: str):
    """The start function of ``model``: ``start(points_target, observations, *,
    pixel_size, image_size, principal_point, min_points) -> (device, start, used, R, T)``
    (see :func:`telefringe.calibration.start_telecentric.start_device`)."""
    try:
        return _STARTS[model]
    except KeyError:
        raise CalibrationError(f"no calibration start for a {model!r} device (known: "
                               f"{', '.join(MODELS)})") from None


def rig_rotations(camera_model: str, projector_model: str, R_cam_target, R_proj_target,
                  projector_side: str | None):
    """The target -> device rotations of both devices on one rigid branch, their mean
    relative rotation, how a mirror ambiguity was settled, and warnings (see
    :func:`telefringe.calibration.start_telecentric.resolve_rotations`)."""
    if (camera_model, projector_model) == ("telecentric", "telecentric"):
        return start_telecentric.resolve_rotations(R_cam_target, R_proj_target,
                                                   projector_side)
    raise CalibrationError(f"no joint start for a {camera_model} camera with a "
                           f"{projector_model} projector")
