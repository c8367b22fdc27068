"""`telefringe simulate` commands: calibration sets and scans from the virtual rig.

Output layout (OUT is a new folder; ground truth is never inside a scan folder)::

    OUT/calibration/           a calibration set (calibration.json + pose_00, pose_01, ...)
    OUT/scan/                  a scan folder (scan.json + PNG images)
    OUT/truth/                 rig_true.json and, per scan, NAME.npz + NAME.json

A two-camera rig (``stereo``) writes one scan per camera: ``pose_00/camera/`` and
``pose_00/camera_2/`` in a calibration set, ``OUT/scan/camera/`` and
``OUT/scan/camera_2/`` for a scan; its truth files are named ``NAME_camera``,
``NAME_camera_2``.
"""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path

import typer

from telefringe.cli._common import detail, info, progress_bar

__all__ = ["register"]


class _Rig(StrEnum):
    paper = "paper"
    fast = "fast"
    mixed = "mixed"
    macro = "macro"
    stereo = "stereo"


class _Scene(StrEnum):
    plate = "plate"
    steps = "steps"
    sphere = "sphere"
    bga = "bga"
    tilted_plane = "tilted-plane"


def _advance_by(advance):
    """Adapt a bar's ``advance(n)`` to a ``progress(done, total)`` callback."""
    state = {"done": 0}

    def progress(done, total):
        del total
        if done > state["done"]:
            advance(done - state["done"])
            state["done"] = done

    return progress


def _check_options(*, seed: int, poses: int | None = None, z: float | None = None,
                   bit_depth: int | None = None):
    from telefringe.io.errors import InputError

    if seed < 0:
        raise InputError(f"--seed must be >= 0, got {seed}")
    if poses is not None and not 4 <= poses <= 200:
        raise InputError(f"--poses must be between 4 and 200, got {poses}")
    if z is not None and not -10.0 <= z <= 10.0:
        raise InputError(f"--z must be within +-10 mm, got {z}")
    if bit_depth is not None and bit_depth not in (8, 12, 16):
        raise InputError(f"--bit-depth must be 8, 12 or 16, got {bit_depth}")


def calibration(
    out: Path = typer.Argument(..., help="New folder to create (OUT/calibration, OUT/truth)."),
    rig: _Rig = typer.Option(_Rig.paper, "--rig", help="Virtual rig preset."),
    poses: int = typer.Option(12, "--poses", help="Number of plate poses (reference first)."),
    seed: int = typer.Option(0, "--seed", help="Seed of poses and noise."),
    bit_depth: int = typer.Option(8, "--bit-depth", help="Camera bit depth: 8, 12 or 16."),
    force: bool = typer.Option(False, "--force", help="Replace OUT if it exists."),
):
    """Simulate a calibration set: the 9 x 11 circle plate at several poses.

    Rigs: paper and fast (telecentric camera and projector), mixed (telecentric camera,
    pinhole projector), macro (pinhole camera and projector), stereo (two pinhole
    cameras and a pinhole projector: one scan per camera in pose_NN/camera and
    pose_NN/camera_2).

    Example: telefringe simulate calibration sim_cal --rig paper --poses 12
    """
    from telefringe.io.atomic import atomic_dir, check_can_write
    from telefringe.io.calibration_json import write_calibration_manifest
    from telefringe.io.scan_json import write_scan
    from telefringe.io.truth import write_rig_truth, write_truth
    from telefringe.simulate.calibration import (
        calibration_manifest,
        iter_calibration_set,
        simulate_calibration_poses,
    )
    from telefringe.simulate.presets import get_preset

    _check_options(seed=seed, poses=poses, bit_depth=bit_depth)
    check_can_write(out, force=force)
    vrig = get_preset(rig.value)
    if bit_depth != vrig.photometry.bit_depth:
        vrig = vrig.with_photometry(bit_depth=bit_depth)
    pose_list = simulate_calibration_poses(vrig, n_poses=poses, seed=seed)
    man = calibration_manifest(vrig, pose_list)
    with atomic_dir(out, force=force) as tmp:
        cal_dir = tmp / "calibration"
        truth_dir = tmp / "truth"
        cal_dir.mkdir()
        truth_dir.mkdir()
        write_rig_truth(truth_dir, vrig)
        cams = vrig.camera_names
        two = len(cams) > 1
        with progress_bar(f"rendering {len(pose_list)} poses ({vrig.name} rig)",
                          len(pose_list) * len(cams)) as advance:
            for cam in cams:
                for name, scan, truth, pose in iter_calibration_set(
                        vrig, pose_list, seed=seed, camera=cam if two else None):
                    dest = cal_dir / man.scan_folder(name, cam)
                    dest.parent.mkdir(parents=True, exist_ok=True)
                    write_scan(dest, scan)
                    write_truth(truth_dir, f"{name}_{cam}" if two else name, truth,
                                extra={"pose": {"kind": pose.kind,
                                                "R_world_target": pose.R_world_target,
                                                "t_world_target": pose.t_world_target}})
                    detail(f"{man.scan_folder(name, cam)}: {pose.kind}")
                    advance(1)
        write_calibration_manifest(cal_dir, man)
    info(f"wrote {out / 'calibration'} ({len(pose_list)} poses) and the ground truth in "
         f"{out / 'truth'}")


def scan(
    out: Path = typer.Argument(..., help="New folder to create (OUT/scan, OUT/truth)."),
    scene: _Scene = typer.Option(..., "--scene", help="What to scan."),
    rig: _Rig = typer.Option(_Rig.paper, "--rig", help="Virtual rig preset."),
    z: float = typer.Option(0.0, "--z", help="Raise the scene by this many mm (not bga)."),
    hdr: bool = typer.Option(False, "--hdr", help="Three exposures per group: 4, 0.6 and 0.1 times "
                             "the base exposure."),
    seed: int = typer.Option(0, "--seed", help="Seed of the scene (bga) and the noise."),
    bit_depth: int = typer.Option(8, "--bit-depth", help="Camera bit depth: 8, 12 or 16."),
    force: bool = typer.Option(False, "--force", help="Replace OUT if it exists."),
):
    """Simulate one scan of a scene (4-step fringes, 1/8/64 periods along u, 1/8/48
    along v, white and black frames). A two-camera rig (stereo) writes OUT/scan/camera
    and OUT/scan/camera_2.

    Example: telefringe simulate scan sim_bga --scene bga --hdr
    """
    from telefringe.io.atomic import atomic_dir, check_can_write
    from telefringe.io.errors import InputError
    from telefringe.io.scan_json import write_scan
    from telefringe.io.truth import write_rig_truth, write_truth
    from telefringe.simulate.presets import HDR_EXPOSURES, get_preset
    from telefringe.simulate.render import default_groups, render_scan
    from telefringe.simulate.scenes import make_scene

    _check_options(seed=seed, z=z, bit_depth=bit_depth)
    check_can_write(out, force=force)
    if scene is _Scene.bga and z != 0.0:
        raise InputError("--z is not available for the bga scene (it sits at Z = 0)")
    vrig = get_preset(rig.value)
    if bit_depth != vrig.photometry.bit_depth:
        vrig = vrig.with_photometry(bit_depth=bit_depth)
    sc = make_scene(scene.value, z=z, seed=seed)
    exposures = HDR_EXPOSURES if hdr else (1.0,)
    groups = default_groups(vrig)
    total = sum(g.count for g in groups) * len(exposures) + 2 + 4
    cams = vrig.camera_names
    two = len(cams) > 1
    n = 0
    with atomic_dir(out, force=force) as tmp:
        (tmp / "truth").mkdir()
        write_rig_truth(tmp / "truth", vrig)
        for ci, cam in enumerate(cams):
            view = vrig.for_camera(cam) if two else vrig
            label = f"rendering {scene.value} ({vrig.name} rig{', ' + cam if two else ''})"
            with progress_bar(label, total) as advance:
                result, truth = render_scan(view, sc, groups, exposures=exposures,
                                            seed=seed + 1000003 * ci,
                                            progress=_advance_by(advance))
            dest = tmp / "scan" / cam if two else tmp / "scan"
            dest.parent.mkdir(parents=True, exist_ok=True)
            write_scan(dest, result)
            write_truth(tmp / "truth", f"scan_{cam}" if two else "scan", truth,
                        extra={"scene": scene.value, "z_mm": z, "exposures": list(exposures),
                               "seed": seed, "camera": cam})
            n += sum(s.shape[0] for s in result.stacks) + 2
    info(f"wrote {out / 'scan'} ({n} images) and the ground truth in {out / 'truth'}")


def acceptance(
    out: Path = typer.Argument(..., help="New folder to create (OUT/acceptance, "
                                         "OUT/artefacts.json, OUT/truth)."),
    rig: _Rig = typer.Option(_Rig.paper, "--rig", help="Virtual rig preset."),
    seed: int = typer.Option(0, "--seed", help="Seed of the noise."),
    force: bool = typer.Option(False, "--force", help="Replace OUT if it exists."),
):
    """Simulate the scans of a VDI/VDE 2634 Part 2 acceptance test: a matte test sphere
    at 10 positions, a ball bar at 7 and a plane at 6, sized and placed in the rig's
    measuring volume (L0 = its diagonal; see docs/acceptance.md).

    Writes OUT/acceptance (a scan folder per position and acceptance.json naming each
    one's artefact; a two-camera rig (stereo) writes OUT/acceptance/NAME/camera and
    OUT/acceptance/NAME/camera_2 per position), OUT/artefacts.json (the artefacts'
    calibrated values, as a certificate gives them) and OUT/truth (true rig, volume and
    scenes). Calibrate the same rig with 'telefringe simulate calibration', then run
    'telefringe accept'.

    Example: telefringe simulate acceptance sim_acc --rig fast
    """
    from telefringe.io.acceptance_json import write_acceptance_set, write_artefacts
    from telefringe.io.atomic import atomic_dir, check_can_write
    from telefringe.io.jsonable import write_json
    from telefringe.io.scan_json import write_scan
    from telefringe.io.truth import write_rig_truth, write_truth
    from telefringe.metrology.acceptance import Artefacts
    from telefringe.simulate.acceptance import (
        U_CERTIFICATE_MM,
        acceptance_positions,
        iter_acceptance_scans,
        measuring_volume,
    )
    from telefringe.simulate.presets import get_preset

    _check_options(seed=seed)
    check_can_write(out, force=force)
    from telefringe.io.errors import InputError

    vrig = get_preset(rig.value)
    cams = vrig.camera_names
    two = len(cams) > 1
    try:
        vol = measuring_volume(vrig)
        art, positions = acceptance_positions(vrig, vol)
    except ValueError as exc:  # a rig whose volume cannot hold the artefacts
        raise InputError(str(exc)) from None
    u = U_CERTIFICATE_MM
    cert = Artefacts(sphere_diameter=art.sphere_diameter, u_sphere_diameter=u, sphere_form=0.0,
                     u_sphere_form=u, bar_distance=art.bar_distance, u_bar_distance=u,
                     bar_diameters=(art.sphere_diameter, art.sphere_diameter),
                     plane_flatness=0.0, u_plane_flatness=u, plane_length=art.plane_length,
                     plane_width=art.plane_width)
    with atomic_dir(out, force=force) as tmp:
        acc = tmp / "acceptance"
        truth_dir = tmp / "truth"
        acc.mkdir()
        truth_dir.mkdir()
        write_rig_truth(truth_dir, vrig)
        write_json(truth_dir / "volume.json", {
            "measuring_volume_mm": {"x": [vol.x0, vol.x1], "y": [vol.y0, vol.y1],
                                    "z": [vol.z0, vol.z1]},
            "L0_mm": vol.L0, "artefacts": art})
        for cam in cams:  # a two-camera rig: OUT/acceptance/NAME/camera, .../camera_2
            label = f"rendering {len(positions)} positions ({vrig.name} rig" + (
                f", {cam})" if two else ")")
            with progress_bar(label, len(positions)) as advance:
                for pos, result, truth in iter_acceptance_scans(
                        vrig, positions, seed=seed, progress=_advance_by(advance),
                        camera=cam):
                    dest = acc / pos.name / cam if two else acc / pos.name
                    dest.parent.mkdir(parents=True, exist_ok=True)
                    write_scan(dest, result)
                    write_truth(truth_dir, f"{pos.name}_{cam}" if two else pos.name, truth,
                                extra={"artefact": pos.artefact,
                                       "description": pos.description, "camera": cam})
                    detail(f"{pos.name}: {pos.artefact}, {pos.description}"
                           + (f" ({cam})" if two else ""))
        write_acceptance_set(acc, [
            (f"{p.name}/{cams[0]}" if two else p.name, p.artefact, p.description,
             f"{p.name}/{cams[1]}" if two else None) for p in positions])
        write_artefacts(tmp / "artefacts.json", cert,
                        meta={"source": f"virtual rig {vrig.name!r}: exact artefacts; u is a "
                                        "typical certificate's"})
    info(f"wrote {out / 'acceptance'} ({len(positions)} scans; L0 = {vol.L0:.2f} mm, sphere "
         f"{art.sphere_diameter:.2f} mm, ball bar {art.bar_distance:.1f} mm, plane "
         f"{art.plane_length:.1f} mm), {out / 'artefacts.json'} and the ground truth in "
         f"{out / 'truth'}")


def register(app: typer.Typer) -> None:
    """Add ``telefringe simulate calibration|scan|acceptance``."""
    sim = typer.Typer(name="simulate", no_args_is_help=True,
                      help="Render calibration sets and scans with the virtual rig.")
    sim.command("calibration")(calibration)
    sim.command("scan")(scan)
    sim.command("acceptance")(acceptance)
    app.add_typer(sim, name="simulate")
