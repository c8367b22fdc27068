"""`telefringe measure plate|sphere|bga|steps OUT`: measurements on a reconstruction."""

from __future__ import annotations

from pathlib import Path

import typer

from telefringe.cli._common import info

measure_app = typer.Typer(
    name="measure",
    help="Measure a reconstruction (the OUT folder of 'telefringe reconstruct', which holds "
         "points.npz).\n\nExample: telefringe measure bga part_3d --rows 24 --cols 24",
    no_args_is_help=True,
    context_settings={"help_option_names": ["-h", "--help"]},
)

_JSON_HELP = "Also write the results to this JSON file."


def _load(out: Path):
    from telefringe.io.points_npz import read_points

    return read_points(out)


def _metrology_errors():
    from telefringe.metrology import MetrologyError

    return MetrologyError


def _fail(out, exc):
    from telefringe.io.errors import InputError

    raise InputError(f"{out}: {exc}") from None


def _um(x) -> str:
    return f"{float(x) * 1000:.2f} um"


def _save_json(path: Path | None, obj, force: bool) -> None:
    if path is None:
        return
    from telefringe.io.jsonable import write_json

    write_json(path, obj, force=force)
    info(f"wrote {path}")


def _check_outputs(paths, force: bool) -> None:
    from telefringe.io.atomic import check_can_write

    for p in paths:
        if p is not None:
            check_can_write(p, force=force)


# --------------------------------------------------------------------------------------
def measure_plate_folder(out, *, rows: int = 9, cols: int = 11, pitch: float = 3.0,
                         dark: bool = True):
    """Detect the circle grid in ``out``'s texture and measure the plate
    (PlateMeasurement). User problems raise InputError."""
    from telefringe.metrology import measure_plate
    from telefringe.targets.circle_grid import detect_circle_grid

    out = Path(out)
    cloud, texture = _load(out)
    if texture is None:
        _fail(out, "points.npz has no 'texture' image to find the markers in "
                   "(reconstruct the scan again with this version)")
    det = detect_circle_grid(texture, rows=rows, cols=cols, dark=dark)
    if not det:
        _fail(out, f"the {rows} x {cols} circle grid was not found: {det.reason}")
    try:
        return measure_plate(cloud, det.centers, rows=rows, cols=cols, pitch_mm=pitch)
    except _metrology_errors() as exc:
        _fail(out, exc)


def plate_cmd(
    out: Path = typer.Argument(..., help="Reconstruction folder (points.npz)."),
    rows: int = typer.Option(9, "--rows", help="Marker rows of the plate."),
    cols: int = typer.Option(11, "--cols", help="Marker columns of the plate."),
    pitch: float = typer.Option(3.0, "--pitch", help="Nominal marker pitch (mm)."),
    dark: bool = typer.Option(True, "--dark/--light", help="Dark markers on a light plate."),
    json_path: Path = typer.Option(None, "--json", help=_JSON_HELP),
    force: bool = typer.Option(False, "--force", help="Replace existing output files."),
):
    """Circle-marker plate: plane height above the reference (Z), flatness, and distances
    between neighbouring markers along X and Y (mean, abs error, std), as in the paper's
    Table 3.

    Example: telefringe measure plate plate_3d --json plate.json
    """
    from telefringe.io.reports import plate_summary

    _check_outputs([json_path], force)
    m = measure_plate_folder(out, rows=rows, cols=cols, pitch=pitch, dark=dark)
    sp = m.spacing
    info(f"plane: Z = {m.z.distance:.5f} mm (+- {_um(m.z.sigma)}), tilt "
         f"{m.z.angle_deg:.4f} deg, flatness {_um(m.plane.flatness)}, rms {_um(m.plane.rms)}")
    info(f"markers measured: {int(m.centres.valid.sum())} of {rows * cols}")
    info(f"X: mean {sp.mean_x:.4f} mm, abs err {_um(sp.abs_err_x)}, std {_um(sp.std_x)} "
         f"({sp.n_x} distances)")
    info(f"Y: mean {sp.mean_y:.4f} mm, abs err {_um(sp.abs_err_y)}, std {_um(sp.std_y)} "
         f"({sp.n_y} distances)")
    _save_json(json_path, plate_summary(m), force)


def sphere_cmd(
    out: Path = typer.Argument(..., help="Reconstruction folder (points.npz)."),
    min_height: float = typer.Option(None, "--min-height",
                                     help="Height above the base plane (mm) from which a "
                                          "point belongs to the sphere (default: automatic)."),
    json_path: Path = typer.Option(None, "--json", help=_JSON_HELP),
    force: bool = typer.Option(False, "--force", help="Replace existing output files."),
):
    """Sphere standing on a plane: radius, centre and form error (algebraic start,
    geometric least squares, robust).

    Example: telefringe measure sphere sphere_3d --json sphere.json
    """
    from telefringe.io.reports import sphere_summary
    from telefringe.metrology import measure_sphere

    _check_outputs([json_path], force)
    cloud, _ = _load(out)
    try:
        sm = measure_sphere(cloud, min_height=min_height)
    except _metrology_errors() as exc:
        _fail(out, exc)
    f, base = sm.sphere, sm.base
    if base is None:
        info("[yellow]warning:[/yellow] no base plane holds 20 % of the points: every point "
             "was fitted as sphere")
    c = f.centre
    info(f"radius {f.radius:.4f} mm (+- {_um(f.sigma_radius)}), diameter {f.diameter:.4f} mm")
    info(f"centre ({c[0]:.4f}, {c[1]:.4f}, {c[2]:.4f}) mm")
    info(f"form error {_um(f.form_error)} (peak-to-valley), rms {_um(f.rms)}, "
         f"{f.n_inliers} points")
    _save_json(json_path, sphere_summary(f, base, region=sm.region), force)


def measure_bga_folder(out, *, rows: int | None = None, cols: int | None = None,
                       pitch: float = 0.8, diameter: float = 0.45, free_radius: bool = False):
    """Measure the BGA in ``out`` (BGAMeasurement). User problems raise InputError.
    ``free_radius``: fit each cap's radius too (diameters reported, apex heights less
    accurate) instead of the nominal-radius fit through the point-spread model."""
    from telefringe.io.points_npz import load_points
    from telefringe.metrology import BGANominal, BGAOptions, measure_bga

    out = Path(out)
    pf = load_points(out)
    try:
        nominal = BGANominal(rows=rows, cols=cols, pitch_mm=pitch, ball_diameter_mm=diameter)
        # the radiance image locates each ball by its specular highlight (better pitch)
        options = BGAOptions(cap_model="free" if free_radius else "psf")
        return measure_bga(pf.cloud, nominal, image=pf.radiance, options=options)
    except _metrology_errors() as exc:
        _fail(out, exc)


def bga_cmd(
    out: Path = typer.Argument(..., help="Reconstruction folder (points.npz)."),
    rows: int = typer.Option(None, "--rows",
                             help="Ball rows of the nominal grid (default: the rows the "
                                  "balls found span; give it to find missing edge balls)."),
    cols: int = typer.Option(None, "--cols", help="Ball columns of the nominal grid."),
    pitch: float = typer.Option(0.8, "--pitch", help="Nominal ball pitch (mm)."),
    diameter: float = typer.Option(0.45, "--diameter", help="Nominal ball diameter (mm)."),
    csv_path: Path = typer.Option(None, "--csv", help="Per-ball CSV (default OUT/bga.csv)."),
    map_path: Path = typer.Option(None, "--map",
                                  help="PNG map coloured by height (default OUT/bga.png)."),
    free_radius: bool = typer.Option(
        False, "--free-radius",
        help="Fit each ball's radius as well and report diameters. By default the balls "
             "are spheres of the nominal diameter seen through the camera's point spread "
             "(estimated from the caps): apex heights about 2x more accurate, no diameters."),
    json_path: Path = typer.Option(None, "--json", help=_JSON_HELP),
    force: bool = typer.Option(False, "--force", help="Replace existing output files."),
):
    """Ball grid array: each ball's apex height above the substrate and position (and
    diameter with --free-radius); pitch to neighbours; missing balls, and balls seen but
    not measured (with the reason); coplanarity against the JEDEC seating plane (the plane
    the package rests on, through three balls around its centre of gravity; every such
    plane when the package may rock, the largest reported). Writes a CSV per ball and a
    PNG map.

    Example: telefringe measure bga bga_3d --rows 24 --cols 24 --json bga.json
    """
    from telefringe.io.bga_csv import write_bga_csv
    from telefringe.io.figures.bga_png import write_bga_png
    from telefringe.io.reports import bga_summary

    out = Path(out)
    csv_path = out / "bga.csv" if csv_path is None else csv_path
    map_path = out / "bga.png" if map_path is None else map_path
    _check_outputs([csv_path, map_path, json_path], force)
    m = measure_bga_folder(out, rows=rows, cols=cols, pitch=pitch, diameter=diameter,
                           free_radius=free_radius)
    import numpy as np

    info(f"balls measured: {m.n_balls} of {int(m.nominal.populated().sum())}; missing: "
         f"{', '.join(f'({i},{j})' for i, j in m.missing) or 'none'}")
    if m.not_measured:
        info(f"seen but not measured: {len(m.not_measured)}: "
             + ", ".join(f"({i},{j}) {why}" for (i, j), why in m.not_measured))
    info(f"apex height: mean {np.mean(m.height):.4f} mm, min {np.min(m.height):.4f}, max "
         f"{np.max(m.height):.4f} (median sigma {_um(np.median(m.sigma_height))})")
    if np.any(np.isfinite(m.diameter)):
        info(f"diameter: mean {np.nanmean(m.diameter):.4f} mm "
             f"({int(np.isfinite(m.diameter).sum())} balls large enough in the image)")
    info(f"pitch: largest error {_um(m.pitch_error_max)}")
    cop = m.coplanarity
    info(f"coplanarity (JEDEC seating plane): {_um(cop.value)}"
         + (f" ± {_um(cop.sigma)}" if np.isfinite(cop.sigma) else ""))
    if cop.rocks:
        info("  the package may rest on "
             f"{cop.alternatives.size} seating planes (its centre of gravity lies on an edge "
             "between them, within the balls' position uncertainty): coplanarity "
             + ", ".join(_um(v) for v in cop.alternatives) + "; the largest is reported")
    write_bga_csv(csv_path, m, force=force)
    write_bga_png(map_path, m, force=force)
    info(f"wrote {csv_path} and {map_path}")
    _save_json(json_path, bga_summary(m), force)


def steps_cmd(
    out: Path = typer.Argument(..., help="Reconstruction folder (points.npz)."),
    min_step: float = typer.Option(0.05, "--min-step", help="Smallest step to detect (mm)."),
    json_path: Path = typer.Option(None, "--json", help=_JSON_HELP),
    force: bool = typer.Option(False, "--force", help="Replace existing output files."),
):
    """Step gauge: the heights of its flat levels (parallel planes fitted jointly) and of
    each step.

    Example: telefringe measure steps steps_3d --json steps.json
    """
    from telefringe.io.reports import steps_summary
    from telefringe.metrology import measure_steps

    _check_outputs([json_path], force)
    cloud, _ = _load(out)
    try:
        m = measure_steps(cloud, min_step=min_step)
    except _metrology_errors() as exc:
        _fail(out, exc)
    for k, (h, s, n) in enumerate(zip(m.heights, m.sigma_heights, m.n_points, strict=True)):
        info(f"level {k}: {h:.4f} mm above level 0 (+- {_um(s)}), {n} points")
    for k, (h, s) in enumerate(zip(m.step_heights, m.sigma_steps, strict=True)):
        info(f"step {k} -> {k + 1}: {h:.4f} mm (+- {_um(s)})")
    _save_json(json_path, steps_summary(m), force)


measure_app.command("plate")(plate_cmd)
measure_app.command("sphere")(sphere_cmd)
measure_app.command("bga")(bga_cmd)
measure_app.command("steps")(steps_cmd)


def register(app: typer.Typer) -> None:
    """Add ``measure`` (plate, sphere, bga, steps) to the app."""
    app.add_typer(measure_app, name="measure")
