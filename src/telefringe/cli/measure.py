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
_RIG_HELP = ("rig.json of the calibration that made the reconstruction: adds the "
             "calibration's uncertainty (its parameter covariance, shared by every point) "
             "to each result's u and U (k = 2). Without it u holds the noise only.")


def _load_calibration(rig: Path | None):
    """The RigCalibration of ``--rig`` (None without it). User problems raise InputError."""
    if rig is None:
        return None
    import numpy as np

    from telefringe.io.errors import InputError
    from telefringe.io.rig_json import load_rig

    cal = load_rig(rig)
    if not np.any(np.isfinite(cal.covariance)):
        raise InputError(f"{rig}: the rig has no parameter covariance (a bare rig.json): "
                         "the calibration's uncertainty is unknown; leave --rig out")
    return cal


def _with_calibration(out, fn, m, cloud, cal):
    """``fn(m, cloud, cal)`` (the measurement with its uncertainty), or ``m`` without a
    calibration; a rig that does not fit the cloud raises InputError."""
    if cal is None:
        info("[yellow]note:[/yellow] u and U hold the noise only (give --rig rig.json for "
             "the calibration's part)")
        return m
    size = cal.rig.camera.image_size
    if size is not None and tuple(size) != (cloud.shape[1], cloud.shape[0]):
        _fail(out, f"the rig's camera is {size[0]} x {size[1]} px but the reconstruction is "
                   f"{cloud.shape[1]} x {cloud.shape[0]}: --rig must be the rig that made it")
    try:
        return fn(m, cloud, cal)
    except (ValueError, _linalg_error()) as exc:
        _fail(out, f"the calibration's uncertainty cannot be propagated with this rig: {exc}")


def _linalg_error():
    import numpy as np

    return np.linalg.LinAlgError


def _u_line(name: str, q, *, scale: float = 1000.0, unit: str = "um") -> str:
    """``name: u = .. (noise .., calibration ..), U (k=2) = ..``."""
    import numpy as np

    def f(x):
        return "n/a" if not np.isfinite(x) else f"{float(x) * scale:.3g} {unit}"

    return (f"{name}: u = {f(q.u)} (noise {f(q.u_noise)}, calibration {f(q.u_calibration)}),"
            f" U (k={q.k:g}) = {f(q.U)}")


def _metrology_errors():
    from telefringe.metrology import MetrologyError

    return MetrologyError


def _fail(out, exc):
    from telefringe.io.errors import InputError

    raise InputError(f"{out}: {exc}") from None


def _is_stereo(out: Path) -> bool:
    """The reconstruction's summary.json names a second camera's scan."""
    import json

    try:
        return "second_scan" in json.loads((Path(out) / "summary.json").read_text())
    except (OSError, ValueError, TypeError):
        return False


def _stereo_noise(out: Path, pf, what: str):
    """The StereoNoiseMaps points.npz keeps for a two-camera match, or None (one camera's
    cloud; a note when the folder is a two-camera one written before it was kept)."""
    if pf.stereo_noise is not None:
        return pf.stereo_noise
    if _is_stereo(out):
        info(f"[yellow]note:[/yellow] u of {what} treats neighbouring points as "
             "independent, which understates it for two cameras (neighbouring matches "
             "share the second camera's pixels): points.npz holds no stereo noise (written "
             "before 'reconstruct --second' kept it; reconstruct again to include it)")
    return None


def _expand(maps):
    """The StereoNoise of StereoNoiseMaps (None stays None)."""
    return None if maps is None else maps.expand()


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
                         dark: bool = True, calibration=None, diameter: float | None = None):
    """Detect the circle grid in ``out``'s texture and measure the plate
    (PlateMeasurement; with a ``calibration``, a RigCalibration, the detected centres
    corrected through its camera for the circle-image bias (markers of ``diameter`` mm,
    default half the pitch) and the uncertainty including the calibration's). User
    problems raise InputError."""
    from telefringe.io.points_npz import load_points
    from telefringe.metrology import measure_plate
    from telefringe.targets.circle_grid import detect_circle_grid

    out = Path(out)
    pf = load_points(out)
    cloud, texture = pf.cloud, pf.texture
    if texture is None:
        _fail(out, "points.npz has no 'texture' image to find the markers in "
                   "(reconstruct the scan again with this version)")
    det = detect_circle_grid(texture, rows=rows, cols=cols, dark=dark)
    if not det:
        _fail(out, f"the {rows} x {cols} circle grid was not found: {det.reason}")
    try:
        m = measure_plate(cloud, det.centers, rows=rows, cols=cols, pitch_mm=pitch,
                          camera=None if calibration is None else calibration.rig.camera,
                          marker_diameter_mm=0.5 * pitch if diameter is None else diameter,
                          noise=_expand(_stereo_noise(out, pf, "the plane's Z and tilt")),
                          centres_sigma_px=det.center_sigma)
    except _metrology_errors() as exc:
        _fail(out, exc)
    from telefringe.metrology.uncertainty import plate_uncertainty

    return _with_calibration(out, plate_uncertainty, m, cloud, calibration)


def plate_cmd(
    out: Path = typer.Argument(..., help="Reconstruction folder (points.npz)."),
    rows: int = typer.Option(9, "--rows", help="Marker rows of the plate."),
    cols: int = typer.Option(11, "--cols", help="Marker columns of the plate."),
    pitch: float = typer.Option(3.0, "--pitch", help="Nominal marker pitch (mm)."),
    dark: bool = typer.Option(True, "--dark/--light", help="Dark markers on a light plate."),
    diameter: float = typer.Option(None, "--diameter",
                                   help="Marker diameter (mm; default half the pitch). "
                                   "With --rig, corrects the detected centres."),
    rig: Path = typer.Option(None, "--rig", help=_RIG_HELP),
    json_path: Path = typer.Option(None, "--json", help=_JSON_HELP),
    force: bool = typer.Option(False, "--force", help="Replace existing output files."),
):
    """Circle-marker plate: plane height above the reference (Z), flatness, and distances
    between neighbouring markers along X and Y (mean, abs error, std), as in the paper's
    Table 3; with --rig, the standard uncertainty u and expanded U (k = 2) of Z, tilt and
    mean spacings including the calibration's, and the detected marker centres corrected
    through the rig's camera for the circle-image bias (a detected centre is the centre of
    the circle's image, which lens distortion moves off the image of the circle's centre).

    Example: telefringe measure plate plate_3d --rig rig.json --json plate.json
    """
    from telefringe.io.reports import plate_summary

    _check_outputs([json_path], force)
    cal = _load_calibration(rig)
    m = measure_plate_folder(out, rows=rows, cols=cols, pitch=pitch, dark=dark,
                             calibration=cal, diameter=diameter)
    sp = m.spacing
    info(f"plane: Z = {m.z.distance:.5f} mm (+- {_um(m.z.sigma)}), tilt "
         f"{m.z.angle_deg:.4f} deg, flatness {_um(m.plane.flatness)}, rms {_um(m.plane.rms)}")
    info(f"markers measured: {int(m.centres.valid.sum())} of {rows * cols}")
    if m.centre_offsets_px is not None:
        import numpy as np

        off = np.asarray(m.centre_offsets_px)
        off = off[np.all(np.isfinite(off), axis=1)]
        rms = float(np.sqrt(np.mean(np.sum(off**2, axis=1)))) if off.size else float("nan")
        info(f"marker centres corrected for the circle-image bias through the rig's camera "
             f"(RMS {rms:.4f} px)")
    else:
        info("[yellow]note:[/yellow] marker centres as detected (give --rig rig.json to "
             "correct them for the circle-image bias of the lens)")
    info(f"X: mean {sp.mean_x:.4f} mm, abs err {_um(sp.abs_err_x)}, std {_um(sp.std_x)} "
         f"({sp.n_x} distances)")
    info(f"Y: mean {sp.mean_y:.4f} mm, abs err {_um(sp.abs_err_y)}, std {_um(sp.std_y)} "
         f"({sp.n_y} distances)")
    _report_uncertainty(m.uncertainty, {"z": "Z", "tilt_deg": "tilt", "spacing_x": "X mean",
                                        "spacing_y": "Y mean"})
    _save_json(json_path, plate_summary(m), force)


def sphere_cmd(
    out: Path = typer.Argument(..., help="Reconstruction folder (points.npz)."),
    min_height: float = typer.Option(None, "--min-height",
                                     help="Height above the base plane (mm) from which a "
                                          "point belongs to the sphere (default: automatic)."),
    rig: Path = typer.Option(None, "--rig", help=_RIG_HELP),
    second: Path = typer.Option(None, "--second",
                                help="A two-camera rig: the second camera's scan folder "
                                     "(default: the one the reconstruction's summary.json "
                                     "names, as 'reconstruct --second' wrote it); its "
                                     "brightness enters the point-spread model and its "
                                     "decoded phase the calibration's uncertainty."),
    json_path: Path = typer.Option(None, "--json", help=_JSON_HELP),
    force: bool = typer.Option(False, "--force", help="Replace existing output files."),
):
    """Sphere standing on a plane: radius, centre and form error (algebraic start,
    geometric least squares, robust); with --rig, u and U (k = 2) of radius and centre
    including the calibration's, and the sphere fitted through the cameras' point-spread
    model (one camera + projector, or two cameras with the second's scan).

    Example: telefringe measure sphere sphere_3d --rig rig.json --json sphere.json
    """
    from telefringe.io.reports import sphere_summary
    from telefringe.metrology import measure_sphere
    from telefringe.metrology.uncertainty import sphere_uncertainty

    _check_outputs([json_path], force)
    cal = _load_calibration(rig)
    from telefringe.io.points_npz import load_points

    pf = load_points(out)
    cloud = pf.cloud
    two = cal is not None and len(cal.rig.cameras) == 2
    if second is not None and not two:
        from telefringe.io.errors import InputError

        raise InputError(f"--second needs --rig with two cameras"
                         f"{'' if rig is None else f' ({rig} has one)'}")
    scan_2 = _second_scan(out, second) if two else None
    spread = _sphere_spread_options(out, cal, pf, scan_2)
    noise = _stereo_noise(out, pf, "radius and centre")
    if noise is not None and spread.get("image_2") is not None:
        spread["noise"] = noise.expand()
    elif noise is not None:
        info("[yellow]note:[/yellow] u of radius and centre treats neighbouring points as "
             "independent, which understates it for two cameras: the matches' correlated "
             "noise (in points.npz) enters the fit through the cameras' point-spread model "
             "(give --rig with the two-camera rig.json and the second camera's scan)")
    try:
        sm = measure_sphere(cloud, min_height=min_height, **spread)
    except _metrology_errors() as exc:
        _fail(out, exc)
    ucal = cal
    if two:
        ucal = None if scan_2 is None else _stereo_calibration(out, cal, scan_2)
        if ucal is None:
            info("[yellow]note:[/yellow] u and U hold the noise only: the calibration's part "
                 "of a two-camera rig needs the second camera's scan (--second)")
    if not two or ucal is not None:
        sm = _with_calibration(out, sphere_uncertainty, sm, cloud, ucal)
    if sm.spread is not None:
        sp = sm.spread
        if sp.cameras == 2 and not sp.shared:
            var = (f"variances {sp.variance_px2:.3f} and {sp.variance_2_px2:.3f} px^2 (first "
                   f"and second camera)"
                   + (f" +- {sp.sigma_variance_px2:.3f} and {sp.sigma_variance_2_px2:.3f} "
                      "(estimated with the sphere)" if sp.estimated else " (given)"))
        else:
            var = (f"variance {sp.variance_px2:.3f} px^2"
                   + (" (one for both cameras)" if sp.cameras == 2 else "")
                   + (f" +- {sp.sigma_variance_px2:.3f} (estimated with the sphere)"
                      if sp.estimated else " (given)"))
        info(f"fitted through the camera{'s' if sp.cameras == 2 else ''}' point-spread model"
             f": {var}, points facing the camera{'s' if sp.cameras == 2 else ''} within "
             f"{sp.max_view_deg:g} deg")
        low = [v for v, e in ((sp.variance_px2, sp.sigma_variance_px2),
                              (sp.variance_2_px2, sp.sigma_variance_2_px2))
               if v is not None and e is not None and v < -3.0 * e]
        if sp.estimated and low:
            info("[yellow]warning:[/yellow] the point-spread variance came out negative "
                 "beyond 3 sigma: the model does not describe this sphere (not matte, not "
                 "lit by the projector alone?); compare with a fit without --rig")
    elif cal is not None:
        info("[yellow]note:[/yellow] fitted without the point-spread model (it needs a "
             "camera + projector rig, or two cameras, the projector and the second "
             "camera's scan; the same image size and the radiance in points.npz): "
             "a blurring camera biases radius and centre by about s^2 / R")
    f, base = sm.sphere, sm.base
    if base is None:
        info("[yellow]warning:[/yellow] no base plane holds 20 % of the points: every point "
             "was fitted as sphere")
    c = f.centre
    info(f"radius {f.radius:.4f} mm (+- {_um(f.sigma_radius)}), diameter {f.diameter:.4f} mm")
    info(f"centre ({c[0]:.4f}, {c[1]:.4f}, {c[2]:.4f}) mm")
    info(f"form error {_um(f.form_error)} (peak-to-valley), rms {_um(f.rms)}, "
         f"{f.n_inliers} points")
    _report_uncertainty(sm.uncertainty, {"radius": "radius", "centre": "centre"})
    _save_json(json_path, sphere_summary(f, base, region=sm.region,
                                         uncertainty=sm.uncertainty, spread=sm.spread), force)


def _summary_scan(out: Path, key: str):
    """The scan folder the reconstruction's summary.json names under ``key`` (relative
    to the working directory, else to the folder), or None."""
    import json

    try:
        doc = json.loads((Path(out) / "summary.json").read_text())
        scan_dir = Path(doc[key])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if not scan_dir.is_absolute() and not scan_dir.exists():
        scan_dir = Path(out) / scan_dir
    return scan_dir


def _second_scan(out: Path, second: Path | None):
    """The second camera's Scan: ``--second``, else the summary's ``second_scan`` when
    still readable (None then). A given folder that cannot be read raises InputError."""
    from telefringe.io.errors import InputError
    from telefringe.io.scan_json import read_scan

    folder = second if second is not None else _summary_scan(out, "second_scan")
    if folder is None:
        return None
    try:
        return read_scan(folder)
    except (OSError, ValueError) as exc:
        if second is not None:
            raise InputError(f"{second}: {exc}") from None
        info(f"[yellow]note:[/yellow] the second camera's scan {folder} named in "
             f"{Path(out) / 'summary.json'} cannot be read ({exc}): give --second")
        return None


def _stereo_calibration(out: Path, cal, scan_2):
    """The two-camera calibration for the uncertainty of a matched cloud (the second
    scan decoded as 'reconstruct --second' decodes it)."""
    from telefringe.fringes.decode import DecodeError
    from telefringe.metrology.uncertainty import for_stereo_scan

    try:
        return for_stereo_scan(cal, scan_2)
    except (DecodeError, ValueError) as exc:
        _fail(out, f"the second camera's scan: {exc}")


def _sphere_spread_options(out: Path, cal, pf, scan_2=None) -> dict:
    """measure_sphere's point-spread options from the rig, the folder's radiance (and,
    two cameras, the second camera's scan's) and the fringe periods of the scan its
    summary.json names (when still readable); {} where the model cannot be used
    (:func:`telefringe.metrology.spheres.sphere_spread_options`)."""
    if cal is None or pf.radiance is None:
        return {}
    from telefringe.metrology.spheres import sphere_spread_options

    manifest = None
    try:
        from telefringe.io.scan_json import load_scan_manifest

        scan_dir = _summary_scan(out, "scan")
        if scan_dir is not None:
            manifest = load_scan_manifest(scan_dir)
    except (OSError, ValueError, KeyError, TypeError):  # they refine the second order only
        manifest = None
    try:
        return sphere_spread_options(cal.rig, pf.radiance, pf.cloud.shape, manifest, scan_2)
    except ValueError as exc:
        _fail(out, exc)


def measure_bga_folder(out, *, rows: int | None = None, cols: int | None = None,
                       pitch: float = 0.8, diameter: float = 0.45, free_radius: bool = False,
                       calibration=None):
    """Measure the BGA in ``out`` (BGAMeasurement; with a ``calibration``, a
    RigCalibration, its uncertainty including the calibration's). User problems raise
    InputError. A two-camera reconstruction's matches' noise (kept in points.npz) enters
    the noise figures (``measure_bga(..., noise=)``).
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
        noise = _expand(_stereo_noise(out, pf, "the apex heights, positions, pitch and "
                                               "coplanarity"))
        m = measure_bga(pf.cloud, nominal, image=pf.radiance, options=options, noise=noise)
    except _metrology_errors() as exc:
        _fail(out, exc)
    from telefringe.metrology.uncertainty import bga_uncertainty

    return _with_calibration(out, bga_uncertainty, m, pf.cloud, calibration)


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
    rig: Path = typer.Option(None, "--rig", help=_RIG_HELP),
    json_path: Path = typer.Option(None, "--json", help=_JSON_HELP),
    force: bool = typer.Option(False, "--force", help="Replace existing output files."),
):
    """Ball grid array: each ball's apex height above the substrate and position (and
    diameter with --free-radius); pitch to neighbours; missing balls, and balls seen but
    not measured (with the reason); coplanarity against the JEDEC seating plane (the plane
    the package rests on, through three balls around its centre of gravity; every such
    plane when the package may rock, the largest reported). Writes a CSV per ball and a
    PNG map. With --rig, u and U (k = 2) of heights, positions, pitch and coplanarity
    include the calibration's uncertainty (in the CSV and the JSON too).

    Example: telefringe measure bga bga_3d --rows 24 --cols 24 --rig rig.json --json bga.json
    """
    from telefringe.io.bga_csv import write_bga_csv
    from telefringe.io.figures.bga_png import write_bga_png
    from telefringe.io.reports import bga_summary

    out = Path(out)
    csv_path = out / "bga.csv" if csv_path is None else csv_path
    map_path = out / "bga.png" if map_path is None else map_path
    _check_outputs([csv_path, map_path, json_path], force)
    cal = _load_calibration(rig)
    m = measure_bga_folder(out, rows=rows, cols=cols, pitch=pitch, diameter=diameter,
                           free_radius=free_radius, calibration=cal)
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
    if m.uncertainty is not None:
        from telefringe.metrology.uncertainty import Uncertainty

        h = m.uncertainty["height"]
        med = Uncertainty(np.nan, np.median(h.u_noise), np.median(h.u_calibration))
        _report_uncertainty({"height": med, "pitch_error_max": m.uncertainty["pitch_error_max"],
                             "coplanarity": m.uncertainty["coplanarity"]},
                            {"height": "apex height (median over balls)",
                             "pitch_error_max": "pitch (the pair of the largest error)",
                             "coplanarity": "coplanarity"})
    write_bga_csv(csv_path, m, force=force)
    write_bga_png(map_path, m, force=force)
    info(f"wrote {csv_path} and {map_path}")
    _save_json(json_path, bga_summary(m), force)


def steps_cmd(
    out: Path = typer.Argument(..., help="Reconstruction folder (points.npz)."),
    min_step: float = typer.Option(0.05, "--min-step", help="Smallest step to detect (mm)."),
    rig: Path = typer.Option(None, "--rig", help=_RIG_HELP),
    json_path: Path = typer.Option(None, "--json", help=_JSON_HELP),
    force: bool = typer.Option(False, "--force", help="Replace existing output files."),
):
    """Step gauge: the heights of its flat levels (parallel planes fitted jointly) and of
    each step; with --rig, u and U (k = 2) including the calibration's.

    Example: telefringe measure steps steps_3d --rig rig.json --json steps.json
    """
    from telefringe.io.reports import steps_summary
    from telefringe.metrology import measure_steps
    from telefringe.metrology.uncertainty import steps_uncertainty

    _check_outputs([json_path], force)
    cal = _load_calibration(rig)
    from telefringe.io.points_npz import load_points

    pf = load_points(out)
    cloud = pf.cloud
    # two cameras: the matches' correlated noise (points.npz) in the levels' fit
    noise = _expand(_stereo_noise(out, pf, "the heights"))
    try:
        m = measure_steps(cloud, min_step=min_step, noise=noise)
    except _metrology_errors() as exc:
        _fail(out, exc)
    m = _with_calibration(out, steps_uncertainty, m, cloud, cal)
    for k, (h, s, n) in enumerate(zip(m.heights, m.sigma_heights, m.n_points, strict=True)):
        info(f"level {k}: {h:.4f} mm above level 0 (+- {_um(s)}), {n} points")
    for k, (h, s) in enumerate(zip(m.step_heights, m.sigma_steps, strict=True)):
        info(f"step {k} -> {k + 1}: {h:.4f} mm (+- {_um(s)})")
    if m.uncertainty is not None:
        q = m.uncertainty["step_heights"]
        from telefringe.metrology.uncertainty import Uncertainty

        _report_uncertainty({f"step {k} -> {k + 1}": Uncertainty(
            q.value[k], q.u_noise[k], q.u_calibration[k]) for k in range(q.value.size)})
    _save_json(json_path, steps_summary(m), force)


def _report_uncertainty(unc, labels=None) -> None:
    """One line per quantity of a measurement's ``uncertainty`` (nothing without one)."""
    if unc is None:
        return
    import numpy as np

    labels = labels or {}
    for name, q in unc.items():
        label = labels.get(name, name)
        if np.ndim(q.value) == 0:
            deg = name.endswith("_deg")
            info(_u_line(label, q, scale=1.0 if deg else 1000.0, unit="deg" if deg else "um"))
        else:  # a vector (a centre): one line per coordinate
            for c, axis in enumerate("xyz"[:np.size(q.value)]):
                from telefringe.metrology.uncertainty import Uncertainty

                info(_u_line(f"{label} {axis}", Uncertainty(
                    np.ravel(q.value)[c], np.ravel(q.u_noise)[c],
                    np.ravel(q.u_calibration)[c])))


measure_app.command("plate")(plate_cmd)
measure_app.command("sphere")(sphere_cmd)
measure_app.command("bga")(bga_cmd)
measure_app.command("steps")(steps_cmd)


def register(app: typer.Typer) -> None:
    """Add ``measure`` (plate, sphere, bga, steps) to the app."""
    app.add_typer(measure_app, name="measure")
