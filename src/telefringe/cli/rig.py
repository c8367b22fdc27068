"""`telefringe rig import-opencv | export-opencv`: rig.json from and to OpenCV calibration
files (:mod:`telefringe.io.opencv_yaml`)."""

from __future__ import annotations

import inspect
from enum import StrEnum
from pathlib import Path

import numpy as np
import typer

from telefringe.cli._common import detail, info

__all__ = ["register"]

_EXAMPLE_FILE = "../shared/realdata/slmaster_mono_relief/caliInfo.yml"
_IMPORT_EXAMPLE = (f"telefringe rig import-opencv {_EXAMPLE_FILE} --projector-size 1920x1080 "
                   "-o relief_rig.json")


class _World(StrEnum):
    camera = "camera"
    toward_camera = "toward-camera"


class _Unit(StrEnum):
    mm = "mm"
    cm = "cm"
    m = "m"
    um = "um"
    inch = "in"


def _describe(name: str, dev, ref) -> str:
    k = dev.intrinsics
    w, h = dev.image_size or (0, 0)
    text = (f"{name}: pinhole {w}x{h} px, fx {k.fx:.1f} fy {k.fy:.1f} cx {k.cx:.1f} "
            f"cy {k.cy:.1f} px")
    if dev is not ref:
        c = ref.R_dev_world @ (dev.centre_world - ref.centre_world)  # in the camera's frame
        angle = np.degrees(np.arccos(np.clip(dev.R_dev_world[2] @ ref.R_dev_world[2], -1, 1)))
        text += (f"; centre at ({c[0]:.1f}, {c[1]:.1f}, {c[2]:.1f}) mm from the camera "
                 f"(baseline {np.linalg.norm(c):.1f} mm), axes {angle:.1f} deg apart")
    return text


def import_opencv(
    files: list[Path] = typer.Argument(
        ..., metavar="FILE.yml...",
        help="OpenCV FileStorage file(s) (.yml, .xml, .json), e.g. stereo_calib's "
             "intrinsics.yml and extrinsics.yml, or SLMaster's caliInfo.yml."),
    out: Path = typer.Option(..., "-o", "--output", help="The rig.json to write."),
    camera_size: str = typer.Option(
        None, "--camera-size", metavar="WxH",
        help="The camera's image size in px, where the file has no S."),
    camera_2_size: str = typer.Option(
        None, "--camera-2-size", metavar="WxH",
        help="The second camera's image size, where the file has no S2 (default: the "
             "first camera's)."),
    projector_size: str = typer.Option(
        None, "--projector-size", metavar="WxH",
        help="The projector's image size in px, where the file has no S4 (e.g. 1920x1080)."),
    unit: _Unit = typer.Option(_Unit.mm, "--unit",
                               help="Length unit of the file's translations (T, Tlp)."),
    world: _World = typer.Option(
        _World.camera, "--world",
        help="The rig's world frame: 'camera' (the first camera's: Z is the depth along its "
             "view) or 'toward-camera' (turned 180 deg about its x axis: y up the image, z "
             "toward the camera, so heights are positive toward it as in a telefringe "
             "calibration)."),
    force: bool = typer.Option(False, "--force", help="Replace an existing output."),
):
    """Make a rig.json from an OpenCV calibration (pinhole devices).

    Reads the names of OpenCV's stereo_calib sample for two cameras (M1 D1 M2 D2 R T,
    X2 = R X1 + T; SLMaster's Rlr Tlr too) and SLMaster's for a camera and a projector
    (M1 D1 camera, M4 D4 projector, Rlp Tlp: X_projector = Rlp X_camera + Tlp); both may
    be in one file. M is the camera matrix, D the distortion (4, 5, 8, 12 or 14
    coefficients; beyond k1 k2 p1 p2 k3 they must be 0). Image sizes come from S (the
    cameras), S2, S4 or the options. The world frame of the rig is the first camera's
    (or, with --world toward-camera, that frame turned so that z points toward the
    camera), lengths in mm. Anything missing or inconsistent is refused and nothing is written.

    Example (from the repository, with the shared real data): see _IMPORT_EXAMPLE.
    """
    from telefringe.io.opencv_yaml import read_opencv_rig
    from telefringe.io.rig_json import save_rig

    imp = read_opencv_rig(files, camera_size=camera_size, camera_2_size=camera_2_size,
                          projector_size=projector_size, unit=unit.value, world=world.value)
    save_rig(out, imp.rig, force=force, source=imp.source(files),
             world_definition=imp.world_definition)
    rig = imp.rig
    info(f"wrote {out}: {imp.names}")
    for name, dev in list(rig.cameras.items()) + [("projector", rig.projector)]:
        if dev is not None:
            info("  " + _describe(name, dev, rig.camera)
                 + f" (size from {imp.sizes[name]})")
    if imp.unused:
        detail(f"not used: {', '.join(imp.unused)}")


def export_opencv(
    rig: Path = typer.Argument(..., metavar="RIG.json", help="A rig.json of pinhole devices."),
    out: Path = typer.Option(..., "-o", "--output", help="The OpenCV .yml file to write."),
    force: bool = typer.Option(False, "--force", help="Replace an existing output."),
):
    """Write a rig.json of pinhole devices as an OpenCV calibration file.

    The names are those import-opencv reads: M1 D1 S (camera), M2 D2 S2 R T (a second
    camera, X2 = R X1 + T), M4 D4 S4 Rlp Tlp (projector, X_projector = Rlp X_camera +
    Tlp); lengths in mm, poses relative to the first camera (the rig's world frame is
    not kept). A rig with a telecentric device is refused: OpenCV's files describe
    pinhole devices only. The calibration report (uncertainties) is not written.

    Example (after the example of import-opencv):

        telefringe rig export-opencv relief_rig.json -o relief_cal.yml
    """
    from telefringe.io.errors import InputError
    from telefringe.io.opencv_yaml import write_opencv_rig
    from telefringe.io.rig_json import load_rig

    calib = load_rig(rig)
    try:
        write_opencv_rig(out, calib.rig, force=force, comment=f"from {rig.name}")
    except InputError as exc:
        raise InputError(f"{rig}: {exc}") from None
    names = "M1 D1 S" + (" M2 D2 S2 R T" if "camera_2" in calib.rig.cameras else "") + (
        " M4 D4 S4 Rlp Tlp" if calib.rig.projector is not None else "")
    info(f"wrote {out} ({names}; mm, poses relative to the camera)")


def register(app: typer.Typer) -> None:
    """Add ``telefringe rig import-opencv|export-opencv``."""
    rig_app = typer.Typer(
        name="rig", no_args_is_help=True,
        help=f"Rig files: OpenCV calibrations in and out of rig.json.\n\nExample: "
             f"{_IMPORT_EXAMPLE}",
        context_settings={"help_option_names": ["-h", "--help"]})
    doc = import_opencv.__doc__.replace(
        "Example (from the repository, with the shared real data): see _IMPORT_EXAMPLE.",
        f"Example (from the repository, with the shared real data):\n\n    {_IMPORT_EXAMPLE}")
    rig_app.command("import-opencv", help=inspect.cleandoc(doc))(import_opencv)
    rig_app.command("export-opencv")(export_opencv)
    app.add_typer(rig_app, name="rig")
