"""`telefringe paper` (the paper's Tables 3 and 4 re-run) and `telefringe demo`."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from telefringe.cli._common import console, info, progress_bar, state

__all__ = ["register"]


def _um(x: float) -> str:
    return f"{float(x) * 1000:.2f}"


def _print_tables(result) -> None:
    from rich.console import Console
    from rich.table import Table

    from telefringe.simulate.experiments import PAPER_TABLE3, PAPER_TABLE4

    cal = result.calibration
    console.print(f"\n[bold]Calibration[/bold] ({result.rig_name}, "
                  f"{int(cal.used.sum())} poses): reprojection RMS camera "
                  f"{cal.rms_camera:.4f} px, projector {cal.rms_projector:.4f} px")
    t = Table(title="Table 3: circle plate on a stage (distances in 3D between neighbouring "
                    "markers; Z of the fitted plane). Errors and std in um.",
              title_justify="left")
    for col in ("Z stage mm", "", "mean X mm", "mean Y mm", "Z mm", "|err X|", "|err Y|",
                "|err Z|", "std X", "std Y"):
        t.add_column(col, justify="right")
    for r in result.plate:
        p = PAPER_TABLE3.get(r.position)
        t.add_row(f"{r.position:+.1f}", "telefringe", f"{r.mean_x:.5f}", f"{r.mean_y:.5f}",
                  f"{r.z:+.5f}", _um(r.err_x), _um(r.err_y), _um(r.err_z), _um(r.std_x),
                  _um(r.std_y))
        if p is not None:
            t.add_row("", "[dim]paper[/dim]", f"{p[0]:.3f}", f"{p[1]:.3f}", f"{p[2]:+.3f}",
                      _um(p[3]), _um(p[4]), _um(p[5]), _um(p[6]), _um(p[7]), style="dim")
        t.add_row("", "[dim]truth[/dim]", "3.00000", "3.00000", f"{r.position:+.5f}",
                  "0", "0", "0", "0", "0", style="dim")
    wide = Console(width=max(console.width, 120), highlight=False,
                   force_terminal=console.is_terminal)
    wide.print(t)
    b = result.bga
    t4 = Table(title="Table 4: BGA (HDR), fitted centre distance of adjacent balls",
               title_justify="left")
    for col in ("pair", "balls", "telefringe mm", "error um", "paper mm", "paper error um"):
        t4.add_column(col, justify="right")
    for k, pair in enumerate(b.pairs):
        pd, pe = PAPER_TABLE4[k] if k < len(PAPER_TABLE4) else (float("nan"), float("nan"))
        t4.add_row(str(k + 1), f"{pair.a}-{pair.b}", f"{pair.distance:.5f}",
                   f"{pair.error * 1000:+.2f}", f"{pd:.3f}", f"{pe * 1000:+.0f}")
    wide.print(t4)
    console.print(
        f"All {b.n_pairs} adjacent pairs: largest |pitch error| {b.pitch_error_max * 1000:.2f} "
        f"um. Apex height above the substrate: RMS error {b.apex_rms_error * 1000:.2f} um, "
        f"largest {b.apex_max_error * 1000:.2f} um. Coplanarity {b.coplanarity * 1000:.1f} um "
        f"(truth {b.coplanarity_truth * 1000:.1f} um). Balls found {b.n_found} of "
        f"{b.n_present}; missing reported {list(b.missing_reported)} (truth "
        f"{list(b.missing_truth)}). Valid ball pixels {100 * b.valid_fraction_balls:.2f} %.")
    tm = result.timings
    console.print("Times: " + ", ".join(f"{k[:-2]} {v:.1f} s" for k, v in tm.items()))


def paper(
    quick: bool = typer.Option(False, "--quick", help="Camera binned 2 x 2 and 8 poses: "
                               "the same experiments in about a minute."),
    seed: int = typer.Option(0, "--seed", help="Seed of poses, scenes and noise."),
    json_path: Path = typer.Option(None, "--json", help="Write the tables to this JSON file."),
    figures: Path = typer.Option(None, "--figures", help="Folder for the Fig. 4-style "
                                 "histograms of neighbour distances (created)."),
    force: bool = typer.Option(False, "--force", help="Replace existing outputs."),
):
    """Re-run the paper's experiments (Tables 3 and 4) on the virtual rig.

    Simulates a calibration set of the 'paper' rig, calibrates from its images, measures
    the circle plate raised to Z = -1, -0.5, 0.5, 1 mm and a BGA scanned with HDR (gamma
    2.2 projector, compensated from the data), and prints the tables beside the paper's
    figures and the truth.

    Example: telefringe paper --quick --json tables.json --figures paper_figs
    """
    from telefringe.io.atomic import atomic_dir, check_can_write
    from telefringe.io.errors import InputError
    from telefringe.io.figures.histograms import write_spacing_histograms
    from telefringe.io.jsonable import write_json
    from telefringe.io.reports import paper_result_to_json
    from telefringe.simulate.experiments import run_paper

    if seed < 0:
        raise InputError(f"--seed must be >= 0, got {seed}")
    for p in (json_path, figures):
        if p is not None:
            check_can_write(p, force=force)
    n_poses = 8 if quick else 12
    total = n_poses + 4 + 1
    t0 = time.perf_counter()
    with progress_bar("calibration poses, plate positions, BGA", total) as advance:
        result = run_paper(quick=quick, seed=seed, progress=lambda stage, d, n: advance(1))
    _print_tables(result)
    info(f"total {time.perf_counter() - t0:.1f} s")
    if json_path is not None:
        write_json(json_path, paper_result_to_json(result), force=force)
        info(f"wrote {json_path}")
    if figures is not None:
        with atomic_dir(figures, force=force) as tmp:
            write_spacing_histograms(tmp / "neighbour_distances.png", result.plate,
                                     pitch_mm=3.0)
        info(f"wrote {figures / 'neighbour_distances.png'}")


# --------------------------------------------------------------------------- demo
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
    """Add ``telefringe paper`` and ``telefringe demo``."""
    app.command("paper")(paper)
    app.command("demo")(demo)
