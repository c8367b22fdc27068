"""`telefringe demo`: the main job end to end on the virtual rig, one command at a time."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from telefringe.cli._common import info, state

__all__ = ["register"]


def _step(title: str, args: list[str]) -> None:
    """Run one telefringe command in this process, as a user would type it."""
    from telefringe.cli import app

    info(f"\n[bold cyan]$ telefringe {' '.join(args)}[/bold cyan]  [dim]({title})[/dim]")
    extra = ["-q"] if state.quiet else []
    app(args=extra + args, prog_name="telefringe", standalone_mode=False)


def demo(
    out: Path = typer.Argument(Path("telefringe-demo"), help="Folder for everything the "
                               "demo makes (created)."),
    poses: int = typer.Option(12, "--poses", help="Calibration poses to simulate."),
    force: bool = typer.Option(False, "--force", help="Replace OUT if it exists."),
):
    """The main job, end to end on the virtual rig: simulate a calibration set,
    calibrate, scan a BGA (HDR) and a plate, reconstruct, measure, and report against the
    truth. Each step is the command a user would type (printed as it runs).

    Example: telefringe demo telefringe-demo
    """
    import json
    import shutil

    from telefringe.io.atomic import check_can_write

    check_can_write(out, force=force)
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    rig = "paper"
    t0 = time.perf_counter()
    sim = out / "simulated"
    sim.mkdir()
    _step(f"render {poses} poses of the 9 x 11 circle plate",
          ["simulate", "calibration", str(sim / "calibration-set"), "--rig", rig,
           "--poses", str(poses)])
    # the projector's gamma is learned from the poses' fringes and kept in rig.json: the
    # scans below are corrected with it instead of learning it again
    _step("calibrate camera and projector jointly (and learn the projector's gamma)",
          ["calibrate", str(sim / "calibration-set" / "calibration"), "-o",
           str(out / "rig.json"), "--report", str(out / "calibration-report"),
           "--projector-side", "right"])
    _step("render a BGA with three exposures (HDR)",
          ["simulate", "scan", str(sim / "bga"), "--scene", "bga", "--hdr", "--rig", rig])
    _step("decode + triangulate the BGA (gamma removed with the rig's model)",
          ["reconstruct", str(sim / "bga" / "scan"), "--rig", str(out / "rig.json"), "-o",
           str(out / "bga")])
    _step("inspect the BGA (nominal 24 x 24 grid, 0.8 mm pitch)",
          ["measure", "bga", str(out / "bga"), "--rows", "24", "--cols", "24", "--json",
                              str(out / "bga" / "measurement.json")])
    _step("render the plate raised by 0.5 mm",
          ["simulate", "scan", str(sim / "plate"), "--scene", "plate", "--z", "0.5", "--rig",
           rig])
    _step("decode + triangulate the plate",
          ["reconstruct", str(sim / "plate" / "scan"), "--rig", str(out / "rig.json"), "-o",
           str(out / "plate")])
    _step("measure the plate", ["measure", "plate", str(out / "plate"), "--json",
                                str(out / "plate" / "measurement.json")])
    elapsed = time.perf_counter() - t0
    _demo_report(out, json.loads((out / "bga" / "measurement.json").read_text()),
                 json.loads((out / "plate" / "measurement.json").read_text()), elapsed)


def _demo_report(out: Path, bga: dict, plate: dict, elapsed: float) -> None:
    import json

    def um(x):
        return "n/a" if not isinstance(x, int | float) else f"{x * 1000:.2f} um"

    truth = {}
    tfile = out / "simulated" / "bga" / "truth" / "scan.json"
    if tfile.is_file():
        truth = json.loads(tfile.read_text()).get("features", {})
    info("\n[bold]Demo report[/bold] (virtual rig; the truth is kept apart in "
         f"{out / 'simulated'}/*/truth)")
    z = json_get(plate, "z_mm")
    info(f"  plate raised by 0.5 mm: measured Z {z if isinstance(z, str) else f'{z:+.5f} mm'}"
         f" (error {um(abs(z - 0.5)) if not isinstance(z, str) else 'n/a'}); neighbour "
         f"distance std X {um(json_get(plate, 'spacing', 'std_x_mm'))}, "
         f"Y {um(json_get(plate, 'spacing', 'std_y_mm'))}")
    info(f"  BGA: {json_get(bga, 'balls_found')} balls found, missing "
         f"{json_get(bga, 'missing')} (truth {truth.get('missing', 'n/a')}), largest pitch "
         f"error {um(json_get(bga, 'pitch_error_max_mm'))}, coplanarity "
         f"{um(json_get(bga, 'coplanarity_mm'))}")
    info(f"  outputs: {out}/rig.json, {out}/calibration-report/, {out}/bga/ (points.npz, "
         f"cloud.ply, heightmap.tif/png, bga.csv, bga.png), {out}/plate/")
    info(f"  total time {elapsed:.0f} s")


def json_get(d: dict, *keys):
    """A nested value of a JSON report, or 'n/a'."""
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return "n/a"
        d = d[k]
    return d


def register(app: typer.Typer) -> None:
    """Add ``telefringe demo``."""
    app.command("demo")(demo)
