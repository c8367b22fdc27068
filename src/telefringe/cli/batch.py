"""`telefringe batch SCANS... --rig rig.json --measure ... -o OUT`: many scans on Dask."""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path

import typer

from telefringe.cli._common import info, progress_bar

__all__ = ["register"]


class _Measure(StrEnum):
    none = "none"
    bga = "bga"
    plate = "plate"
    sphere = "sphere"
    steps = "steps"


#: the exit status counts failed scans up to this
MAX_EXIT = 125


def batch_cmd(
    scans: list[str] = typer.Argument(..., help="Scan folders, glob patterns (quote them: "
                                      "'runs/*/scan') or text files listing them, one a "
                                      "line."),
    rig: Path = typer.Option(..., "--rig", help="rig.json written by 'telefringe calibrate'."),
    measure: _Measure = typer.Option(_Measure.none, "--measure",
                                     help="Measurement per scan (as 'telefringe measure')."),
    output: Path = typer.Option(..., "-o", "--output",
                                help="Output folder (created; an existing one is resumed)."),
    scheduler: str = typer.Option(None, "--scheduler",
                                  help="Address of a running Dask scheduler "
                                       "(tcp://host:8786). Default: a local cluster."),
    workers: int = typer.Option(None, "--workers",
                                help="Worker processes of the local cluster (default: the "
                                     "cores, at most one per scan; 0: no Dask, one scan "
                                     "after another in this process)."),
    threads: int = typer.Option(None, "--threads",
                                help="Compiled-kernel threads per scan (default: cores / "
                                     "workers)."),
    force: bool = typer.Option(False, "--force",
                               help="Redo scans whose outputs are complete and current."),
    rows: int = typer.Option(None, "--rows", help="bga: ball rows; plate: marker rows (9)."),
    cols: int = typer.Option(None, "--cols", help="bga: ball columns; plate: marker "
                                                  "columns (11)."),
    pitch: float = typer.Option(None, "--pitch", help="Nominal pitch, mm (bga 0.8, plate 3)."),
    diameter: float = typer.Option(0.45, "--diameter", help="bga: nominal ball diameter, mm."),
    free_radius: bool = typer.Option(False, "--free-radius",
                                     help="bga: fit each ball's radius too (see 'telefringe "
                                          "measure bga --help')."),
    dark: bool = typer.Option(True, "--dark/--light", help="plate: dark markers on a light "
                                                           "plate."),
    min_height: float = typer.Option(None, "--min-height",
                                     help="sphere: height above the base plane (mm) from "
                                          "which a point belongs to the sphere."),
    min_step: float = typer.Option(0.05, "--min-step", help="steps: smallest step (mm)."),
    gamma: bool = typer.Option(True, "--gamma-correction/--no-gamma-correction",
                               help="Remove the projector nonlinearity (the rig's model, "
                                    "else learned from each scan)."),
    refit_gamma: bool = typer.Option(False, "--refit-gamma",
                                     help="Learn the nonlinearity from each scan even when "
                                          "the rig has a model."),
    method: str = typer.Option("auto", "--method", help="Unwrapping method."),
    max_residual: float = typer.Option(1.0, "--max-residual",
                                       help="u/v consistency limit (projector px)."),
    pixel_mm: float = typer.Option(None, "--pixel-mm", help="Height-map spacing (mm)."),
    points: bool = typer.Option(True, "--points/--no-points",
                                help="Keep each scan's points.npz and height map."),
    ply: bool = typer.Option(False, "--ply/--no-ply", help="Also write each scan's "
                                                           "cloud.ply."),
    second: str = typer.Option(None, "--second",
                               help="A two-camera rig.json: the second camera's scan folder "
                                    "of each scan, relative to the scan's folder (e.g. "
                                    "../camera_2); the two are matched as 'reconstruct "
                                    "--second' does and the fits take the matches' "
                                    "correlated noise, as 'measure' does."),
):
    """Decode, reconstruct and measure many scans on Dask, with a table of the results.

    Every scan goes through decode -> reconstruct -> measure on a Dask cluster (a local
    one on this machine by default, or the running one at --scheduler); the rig is read
    once and sent once to each worker. Writes OUT/results.parquet and OUT/results.csv (a
    row per scan: status, one-line error, timings, the measurement's figures and their
    uncertainties as '<measure>.<field>'; with a calibrated rig.json, which carries its
    parameter covariance, the uncertainties include the calibration's part as `telefringe
    measure --rig` gives them, '<measure>.uncertainty.<quantity>.u' etc.) and
    OUT/scans/NAME/ per scan (points.npz,
    height map, measurement.json, bga.csv, row.json). Each output appears complete or not
    at all; OUT/results.partial.jsonl holds the finished rows while the batch runs.

    Run it again to resume: scans whose outputs are complete and current (same images,
    rig and options) are not redone (--force redoes them). A scan that fails is recorded
    and the batch goes on; a worker that dies is replaced and its scan run again. Exit
    status: 0 when every scan was measured, else the number of failed scans (at most
    125); 2 for a bad command line, rig or output folder (nothing run).

    Example (the virtual rig; the calibration takes a few minutes):

      telefringe simulate calibration cal --rig fast
      telefringe calibrate cal/calibration -o rig.json
      telefringe simulate scan s1 --scene sphere --rig fast --seed 1
      telefringe simulate scan s2 --scene sphere --rig fast --seed 2
      telefringe batch 's*/scan' --rig rig.json --measure sphere -o results
    """
    from rich.markup import escape

    from telefringe.batch import BatchOptions, measure_many
    from telefringe.io.errors import InputError

    if workers is not None and workers < 0:
        raise InputError(f"--workers must be >= 0, got {workers}")
    if threads is not None and threads < 1:
        raise InputError(f"--threads must be >= 1, got {threads}")
    if workers is not None and scheduler is not None:
        raise InputError("--workers is for the local cluster; the cluster at --scheduler "
                         "has its own workers")
    options = BatchOptions(measure=measure.value, rows=rows, cols=cols, pitch=pitch,
                           diameter=diameter, dark=dark, min_height=min_height,
                           min_step=min_step, free_radius=free_radius,
                           gamma_correction=gamma, refit_gamma=refit_gamma, method=method,
                           max_residual=max_residual, pixel_mm=pixel_mm, write_points=points,
                           ply=ply, second=second)
    from telefringe.batch.scans import expand_scans

    total = len(expand_scans(scans))
    failed = []
    with progress_bar(f"measuring {total} scans ({measure.value})", total) as advance:
        def progress(done, n, row):
            if row["status"] != "ok":
                failed.append((row["scan"], row["error"]))
            advance()

        frame = measure_many(scans, rig, output=output, force=force, scheduler=scheduler,
                             workers=workers, threads=threads, progress=progress,
                             options=options)
    n_ok = int((frame["status"] == "ok").sum())
    n_reused = int(frame["reused"].fillna(False).sum())
    info(f"{n_ok} of {len(frame)} scans measured ({n_reused} reused), {len(failed)} failed")
    for name, err in failed[:20]:
        info(f"  [red]failed[/red] {escape(name)}: {escape(err)}")
    if len(failed) > 20:
        info(f"  ... and {len(failed) - 20} more (see the table)")
    info(f"wrote {output / 'results.parquet'} and {output / 'results.csv'}")
    if failed:
        raise typer.Exit(min(len(failed), MAX_EXIT))


def register(app: typer.Typer) -> None:
    """Add ``telefringe batch``."""
    app.command("batch")(batch_cmd)
