"""`telefringe decode`: a scan folder -> projector coordinates per camera pixel (.npz)."""

from __future__ import annotations

from pathlib import Path

import typer

from telefringe.cli._common import detail, info, read_scan_with_progress, warn_nonlinearity_kept


def decode_cmd(
    scan: Path = typer.Argument(..., help="Scan folder (with scan.json)."),
    output: Path = typer.Option(..., "-o", "--output", help="Output .npz file."),
    force: bool = typer.Option(False, "--force", help="Replace an existing output."),
    method: str = typer.Option("auto", "--method",
                               help="Unwrapping: auto, hierarchical, heterodyne, "
                                    "number-theoretic or gray."),
    gamma: bool = typer.Option(True, "--gamma-correction/--no-gamma-correction",
                               help="Learn and remove the projector nonlinearity from the "
                                    "fringe ladder."),
    rig: Path = typer.Option(None, "--rig",
                             help="A rig.json whose projector nonlinearity (learned at "
                                  "calibration) removes the scan's instead of learning it "
                                  "from the scan (axes without a model for every group are "
                                  "still learned)."),
    min_modulation: float = typer.Option(None, "--min-modulation",
                                         help="Modulation threshold in DN (default 2% of "
                                              "the sensor maximum)."),
):
    """Decode a scan into projector coordinates per camera pixel (u_p, v_p, mask,
    modulation, sigma_u_p, sigma_v_p in an .npz).

    Example: telefringe decode scans/part -o part_coords.npz --rig rig.json
    """
    from telefringe.fringes.decode import DecodeError, decode
    from telefringe.fringes.phase import PhaseInputError
    from telefringe.io.atomic import check_can_write
    from telefringe.io.coords_npz import write_coords
    from telefringe.io.errors import InputError
    from telefringe.io.scan_json import load_scan_manifest, scan_image_names

    check_can_write(output, force=force)
    phase_errors = None
    man = load_scan_manifest(scan)
    # (--force never replaces one of the inputs: an image, scan.json or the rig)
    check_can_write(output, force=force, inputs=[Path(scan) / "scan.json", rig,
                                                 *(Path(scan) / n for n in
                                                   scan_image_names(man))])
    if rig is not None:
        from telefringe.io.rig_json import load_rig

        calib = load_rig(rig)
        kp = calib.rig.projector.intrinsics
        if (kp.width, kp.height) != (man.projector_width, man.projector_height):
            raise InputError(f"{rig}: its projector is {kp.width} x {kp.height} but the scan's "
                             f"patterns are for {man.projector_width} x "
                             f"{man.projector_height}: use the rig.json of the rig that took "
                             "this scan")
        phase_errors = calib.phase_errors
        if not phase_errors:
            info(f"[yellow]warning:[/yellow] {rig} holds no projector nonlinearity: it is "
                 "learned from the scan")
    data = read_scan_with_progress(scan, man)
    try:
        coords = decode(data, method=method, gamma_correction=gamma,
                        min_modulation=min_modulation, phase_errors=phase_errors)
    except (DecodeError, PhaseInputError) as exc:
        msg = str(exc)
        if msg.startswith(f"{data.source}: "):
            msg = msg[len(data.source) + 2:]
        raise InputError(f"{scan}: {msg}") from None
    for ax, r in coords.axes.items():
        if not r.valid.any():  # an all-invalid coordinate file is no result: say why
            if r.low_modulation.all():
                mm = 0.02 * float(data.max_value) if min_modulation is None else min_modulation
                raise InputError(f"{scan}: no pixel shows the fringes on axis {ax} (modulation "
                                 f"below {mm:.3g} DN everywhere): is the projector on, the "
                                 "scene lit and the exposure long enough?")
            raise InputError(f"{scan}: no pixel could be decoded on axis {ax}")
    write_coords(output, coords, force=force)
    warn_nonlinearity_kept(coords.axes, gamma)
    for ax, r in coords.axes.items():
        good = r.valid
        frac = float(good.mean())
        info(f"{ax}: {r.method} over periods {list(r.periods)}, {frac:.1%} of pixels valid")
        if good.any():
            import numpy as np

            detail(f"  median modulation {float(np.median(r.modulation[good])):.1f} DN, "
                   f"median sigma {float(np.median(r.sigma[good])):.4f} projector px")
            if r.phase_errors is not None and any(m.harmonics for m in r.phase_errors.models):
                peaks = ", ".join(f"{m.periods}: {m.peak:.4f}" for m in r.phase_errors.models)
                src = "learned from the scan" if r.phase_errors.n_samples else "the rig's model"
                detail(f"  nonlinearity phase error removed ({src}; peak rad per group) "
                       f"{peaks}")
    info(f"wrote {output}")


def register(app: typer.Typer) -> None:
    """Add ``decode`` to the app."""
    app.command("decode")(decode_cmd)
