"""`telefringe calibrate`: a calibration set folder -> rig.json (+ report plots, drawn by
:mod:`telefringe.io.figures.calibration_report`)."""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path

import numpy as np
import typer

from telefringe.cli._common import console, detail, info, progress_bar, state

__all__ = ["register", "parameter_table"]


class _Side(StrEnum):
    left = "left"
    right = "right"
    top = "top"
    bottom = "bottom"


class _PP(StrEnum):
    estimate = "estimate"
    fixed = "fixed"


_UNITS = {"m": "", "u0": "px", "v0": "px", "k1": "1/mm^2", "s1": "1/mm", "s2": "1/mm",
          "rot_x": "rad", "rot_y": "rad", "rot_z": "rad", "tx": "mm", "ty": "mm",
          "fx": "px", "fy": "px", "cx": "px", "cy": "px", "k2": "", "p1": "", "p2": "",
          "k3": "", "tz": "mm"}
_PINHOLE_UNITS = {"k1": ""}  # OpenCV's coefficients act on normalised coordinates


def _devices(calib) -> dict:
    devs = dict(calib.rig.cameras)
    if calib.rig.projector is not None:
        devs["projector"] = calib.rig.projector
    return devs


def _fmt(v: float, s: float) -> str:
    if not np.isfinite(s):
        return f"{v:.6g} (fixed)"
    return f"{v:.6g} ± {s:.2g}"


def parameter_table(calib):
    """A rich Table of both devices' parameters (by name) with their standard deviations."""
    from rich.table import Table

    table = Table(title="rig parameters (± one standard deviation)")
    table.add_column("parameter")
    table.add_column("unit")
    devices = _devices(calib)
    for dname, dev in devices.items():
        table.add_column(dname if dev.model == "telecentric" else f"{dname} ({dev.model})",
                         justify="right")
    names = list(dict.fromkeys(n for d in devices.values() for n in d.param_names))

    def cell(dname, pname):
        dev = devices[dname]
        if pname not in dev.param_names:
            return "-"
        i = calib.parameter_names.index(f"{dname}.{pname}")
        value = calib.parameters[i]
        if pname.startswith("rot_"):  # the rotation vector itself, not its perturbation
            value = dev.rotvec["xyz".index(pname[-1])]
        return _fmt(value, calib.std[i])

    models = {d.model for d in devices.values()}
    for name in names:
        label = f"rotation vector {name[-1]}" if name.startswith("rot_") else name
        unit = "rad" if name.startswith("rot_") else _UNITS.get(name, "mm")
        if name in _PINHOLE_UNITS and "pinhole" in models:
            unit = f"{unit} / {_PINHOLE_UNITS[name] or '-'}" if unit else unit
        table.add_row(label, unit, *(cell(d, name) for d in devices))
    table.add_row("RMS reprojection", "px", *(f"{_rms_of(calib, d):.4f}" for d in devices))
    return table


def _rms_of(calib, dname: str) -> float:
    if calib.devices:
        return calib.devices[dname].rms
    return float(getattr(calib, f"rms_{dname}", float("nan")))


def _pose_table(calib):
    from rich.table import Table

    table = Table(title="per-pose RMS reprojection error (px)")
    table.add_column("pose")
    devices = list(_devices(calib))
    for d in devices:
        table.add_column(d, justify="right")
    for i, name in enumerate(calib.pose_names):
        if calib.used[i]:
            vals = list(calib.rms_per_pose[i])  # one column per device, in order
            table.add_row(name + (" (reference)" if name == calib.reference_pose else ""),
                          *(f"{v:.4f}" for v in vals))
        else:
            table.add_row(name, *(["not used"] * len(devices)))
    return table


def _projector_side(man, option, calib_dir):
    """The projector's side (or None) and where it came from, from ``--projector-side``
    and calibration.json's ``projector_side``. Stops (InputError: exit 2, nothing
    written) when they disagree, or when neither gives it for a rig of two telecentric
    devices, which a flat target cannot tell from its mirror image."""
    from telefringe.calibration.start_telecentric import MIRROR_HELP
    from telefringe.io.errors import InputError

    given = None if option is None else option.value
    noted = getattr(man, "projector_side", None)
    if given is not None and noted is not None and given != noted:
        raise InputError(f"--projector-side {given} contradicts \"projector_side\": "
                         f"\"{noted}\" in {calib_dir}/calibration.json: check which is right")
    if given is not None:
        return given, "given by --projector-side"
    if noted is not None:
        return noted, "from calibration.json"
    models = set(getattr(man, "models", {"camera": "telecentric"}).values())
    if models == {"telecentric"}:
        raise InputError(f"{calib_dir}: {MIRROR_HELP}")
    return None, ""


def calibrate_cmd(
    calib_dir: Path = typer.Argument(..., help="Calibration set folder (with calibration.json)."),
    output: Path = typer.Option(..., "-o", "--output", help="rig.json to write."),
    report: Path | None = typer.Option(None, "--report",
                                       help="Folder to create with residual plots (PNG)."),
    projector_side: _Side | None = typer.Option(
        None, "--projector-side",
        help="Where the projector is, seen in the camera image (the shadow of an upright "
             "pin falls away from it). A rig of two telecentric devices calibrated from a "
             "flat target cannot tell itself from its mirror image (heights of opposite "
             "sign): it needs this, or \"projector_side\" in calibration.json. A rig with a "
             "pinhole device needs no side."),
    principal_point: _PP = typer.Option(
        _PP.estimate, "--principal-point",
        help="estimate: free with a weak prior at the image centre; fixed: at the centre."),
    gamma: bool = typer.Option(True, "--gamma/--no-gamma",
                               help="Learn the projector's nonlinearity (gamma) from each "
                                    "pose's fringes, remove it when decoding, and keep the "
                                    "mean model in rig.json for reconstruction."),
    force: bool = typer.Option(False, "--force", help="Replace OUTPUT (and the report)."),
):
    """Calibrate camera and projector from a calibration set (one scan per plate pose).

    Detects the circle grid in each pose, reads the projector coordinates of each circle
    centre from the decoded fringes, calibrates each device alone with the closed form
    of its model (telecentric or pinhole, from calibration.json) and adjusts them all
    jointly. A two-camera set (camera_2 in calibration.json) calibrates both cameras,
    and the projector too when calibration.json names it. Poses whose grid cannot be
    found are skipped with a warning.

    Example: telefringe calibrate sim_cal/calibration -o rig.json --report cal_report
    """
    from telefringe.calibration.errors import CalibrationError
    from telefringe.calibration.from_scans import calibrate_from_scans
    from telefringe.io.atomic import atomic_dir, check_can_write
    from telefringe.io.calibration_json import load_calibration_set
    from telefringe.io.errors import InputError
    from telefringe.io.figures.calibration_report import write_calibration_report
    from telefringe.io.rig_json import save_rig
    from telefringe.io.scan_json import read_scan

    check_can_write(output, force=force, inputs=(Path(calib_dir) / "calibration.json",))
    if report is not None:
        check_can_write(report, force=force, inputs=(calib_dir,))
    man = load_calibration_set(calib_dir)
    side, mirror_source = _projector_side(man, projector_side, calib_dir)
    detail(f"{len(man.poses)} poses, target {man.target.rows} x {man.target.cols} at "
           f"{man.target.pitch_mm} mm, reference {man.reference_pose}")
    with progress_bar("calibration poses", len(man.poses)) as advance:
        def scans():
            for name in man.poses:
                if len(man.cameras) == 1:
                    yield name, read_scan(Path(calib_dir) / name)
                else:
                    yield name, {cam: read_scan(Path(calib_dir) / man.scan_folder(name, cam))
                                 for cam in man.cameras}
                advance()

        try:
            calib = calibrate_from_scans(
                scans(), man.target, man.camera_pixel_size, man.projector_pixel_size,
                man.reference_pose, projector_side=side,
                principal_point=principal_point.value,
                decode_options={"gamma_correction": bool(gamma)}, models=man.models,
                pixel_sizes=man.pixel_sizes)
        except CalibrationError as exc:
            raise InputError(f"{calib_dir}: {exc}") from None
    if side is not None and calib.mirror == f"projector_side={side}":
        # rig.json records where the side came from (calibration.mirror)
        from dataclasses import replace

        calib = replace(calib, mirror=f"projector_side={side} ({mirror_source})")
    for w in calib.warnings:
        info(f"[yellow]warning:[/yellow] {w}")
    if not state.quiet:
        console.print(parameter_table(calib))
        console.print(_pose_table(calib))
    if calib.outliers:
        info(f"{len(calib.outliers)} observation(s) rejected as outliers:")
        for o in calib.outliers:
            info(f"  {o.device} {o.pose} marker (row {o.marker[0]}, col {o.marker[1]}): "
                 f"residual ({o.residual[0]:+.3f}, {o.residual[1]:+.3f}) px")
    if calib.phase_errors:
        peaks = ", ".join(f"{a} {p}: {m.peak:.4f}" for (a, p, _), m in calib.phase_errors.items())
        info(f"projector nonlinearity learned for {len(calib.phase_errors)} fringe groups "
             f"(peak phase error, rad: {peaks}); kept in the rig for reconstruction")
    save_rig(output, calib, force=force)
    info(f"wrote {output}")
    if report is not None:
        with atomic_dir(report, force=force, inputs=(calib_dir,)) as tmp:
            names = write_calibration_report(Path(tmp), calib)
        info(f"wrote {report}/ ({', '.join(names)})")


def register(app: typer.Typer) -> None:
    """Add ``calibrate`` to the app."""
    app.command("calibrate")(calibrate_cmd)
