"""Which closed-form start serves which device model, and how a rig's relative rotation
is settled: the one place where generic calibration code meets the models.

Each model's start lives in ``start_<model>.py``; ``calibrate_device`` and
``calibrate_rig`` reach them only through :func:`device_start` and
:func:`rig_rotations` (checked by an import contract).
"""

from __future__ import annotations

import numpy as np

from telefringe.calibration import start_pinhole, start_telecentric
from telefringe.calibration.errors import CalibrationError
from telefringe.geometry.so3 import chordal_mean

__all__ = ["MODELS", "PROJECTOR_SIDES", "device_start", "joint_rotations", "rig_rotations"]

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


#: Models whose planar views leave each pose's tilt two-fold (a mirror pair).
_MIRRORED = ("telecentric",)


def rig_rotations(camera_model: str, projector_model: str, R_cam_target, R_proj_target,
                  projector_side: str | None):
    """The target -> device rotations of both devices on one rigid branch, their mean
    relative rotation (projector from camera), how a mirror ambiguity was settled, and
    warnings (see :func:`joint_rotations`)."""
    Rs, rel, mirror, warns = joint_rotations(
        (camera_model, projector_model), (R_cam_target, R_proj_target), projector_side,
        projector_index=1)
    return Rs[0], Rs[1], rel[1], mirror, warns


def joint_rotations(models, R_dev_target, projector_side: str | None = None, *,
                    projector_index: int | None = None):
    """Put the rotations of devices calibrated alone on one rigid branch.

    Parameters
    ----------
    models : sequence of str, each device's model (device 0 is the reference camera).
    R_dev_target : sequence of (n, 3, 3) target -> device rotations of the same poses
        (the reference pose first), one per device.
    projector_side : where the projector is in the reference camera's image, or None.
        Needed only when every device is telecentric (then the whole rig and its mirror
        image explain a flat target equally well: without it
        :class:`~telefringe.calibration.start_telecentric.MirrorAmbiguityError`); a
        pinhole device sees depth and settles the mirror by itself.
    projector_index : int or None, which device is the projector (for the side).

    Returns
    -------
    R_dev_target : list of (n, 3, 3), on one rigid branch.
    relative : list of (3, 3), each device's mean rotation from device 0's frame.
    mirror : str, how the mirror ambiguity was settled ("projector_side=...",
        "pinhole device" when a pinhole device fixed it, "none" when no device has one).
    warnings : list of str.
    """
    Rs = [np.asarray(R, dtype=float) for R in R_dev_target]
    models = tuple(models)
    if len(Rs) != len(models) or len(Rs) < 2:
        raise CalibrationError("joint_rotations: one rotation set per device, at least two")
    for m in models:
        if m not in MODELS:
            raise CalibrationError(f"no joint start for a {m!r} device (known: "
                                   f"{', '.join(MODELS)})")
    mirrored = [m in _MIRRORED for m in models]
    warns: list[str] = []
    if not any(mirrored):
        mirror = "none"
    else:
        anchors = [d for d, mm in enumerate(mirrored) if not mm]
        if anchors:
            anchor = anchors[0]
            mirror = "pinhole device"
        else:
            k = 1 if projector_index is None else int(projector_index)
            Rs[0], Rs[k] = start_telecentric.choose_branches(Rs[0], Rs[k])
            anchor = 0
            mirrored[k] = False
        for d in range(len(Rs)):
            if mirrored[d] and d != anchor:
                Rs[d] = start_telecentric.branches_against(Rs[anchor], Rs[d])
        if not anchors:
            if projector_index is None:
                raise start_telecentric.MirrorAmbiguityError(
                    "telecentric cameras calibrated from a flat target without a projector "
                    "cannot tell the rig from its mirror image (heights of opposite sign): "
                    "calibrate the projector with them (\"projector\" in calibration.json) "
                    "and give its side, or include a pinhole device")
            if projector_side is None:
                raise start_telecentric.MirrorAmbiguityError(start_telecentric.MIRROR_HELP)
            k = int(projector_index)
            R_kc = chordal_mean(Rs[k] @ np.transpose(Rs[0], (0, 2, 1)))
            if start_telecentric.mirror_needed(R_kc, projector_side):
                Rs = [start_telecentric.mirror_pose(R) for R in Rs]
            mirror = f"projector_side={projector_side}"
    rel = [chordal_mean(R @ np.transpose(Rs[0], (0, 2, 1))) for R in Rs]
    return Rs, rel, mirror, warns
