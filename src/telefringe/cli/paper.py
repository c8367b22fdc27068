"""`telefringe paper`: the paper's Tables 3 and 4 re-run on the virtual rig."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from telefringe.cli._common import console, info, progress_bar

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


def register(app: typer.Typer) -> None:
    """Add ``telefringe paper``."""
    app.command("paper")(paper)
