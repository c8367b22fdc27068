"""`telefringe decode` and `telefringe patterns`."""

from __future__ import annotations

from pathlib import Path

import typer

from telefringe.cli._common import detail, info, progress_bar


def _parse_periods(text: str) -> list[int]:
    from telefringe.io.errors import InputError

    try:
        per = [int(p) for p in text.replace(" ", "").split(",") if p]
    except ValueError:
        raise InputError(f"--periods: expected integers separated by commas, got {text!r}") \
            from None
    if not per or any(p < 1 for p in per):
        raise InputError(f"--periods: period counts must be integers >= 1, got {text!r}")
    if len(set(per)) != len(per):
        raise InputError(f"--periods: period counts must differ, got {text!r}")
    return per


def _parse_axes(text: str) -> list[str]:
    from telefringe.io.errors import InputError

    axes = [a for a in text.replace(" ", "").split(",") if a]
    if not axes or any(a not in ("u", "v") for a in axes) or len(set(axes)) != len(axes):
        raise InputError(f"--axes: give u, v or u,v; got {text!r}")
    return axes


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
    from telefringe.io.scan_json import load_scan_manifest, read_scan

    check_can_write(output, force=force)
    phase_errors = None
    man = load_scan_manifest(scan)
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
    n = sum(len(g.images) for g in man.groups) + bool(man.white) + bool(man.black)
    with progress_bar("reading images", n) as advance:
        done = [0]

        def tick(k, total):
            advance(k - done[0])
            done[0] = k

        data = read_scan(scan, progress=tick)
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


def patterns_cmd(
    out: Path = typer.Argument(..., help="Output folder (a scan folder to capture into)."),
    width: int = typer.Option(800, "--width", help="Projector width (pixels)."),
    height: int = typer.Option(600, "--height", help="Projector height (pixels)."),
    steps: int = typer.Option(4, "--steps", help="Phase steps per group (>= 3)."),
    periods: str = typer.Option("1,8,64", "--periods",
                                help="Period counts of the ladder, comma separated."),
    axes: str = typer.Option("u,v", "--axes", help="u (vertical fringes), v or u,v."),
    gray: int = typer.Option(0, "--gray",
                             help="Also a Gray code with this many bits (its phase group "
                                  "has 2**bits periods and must be in --periods); 0: none."),
    complementary: bool = typer.Option(True, "--complementary/--plain",
                                       help="Complementary Gray code (one more image)."),
    white_black: bool = typer.Option(True, "--white-black/--no-white-black",
                                     help="Add full-on and full-off frames."),
    precompensate_gamma: float = typer.Option(None, "--precompensate-gamma",
                                              help="Pre-distort the fringes for a projector "
                                                   "with this gamma (e.g. 2.2)."),
    force: bool = typer.Option(False, "--force", help="Replace an existing folder."),
):
    """Write the projector images (8-bit PNG) of a fringe pattern set and the scan.json a
    capture of them needs (replace the images by the camera's captures, same names).

    Example: telefringe patterns pats --width 800 --height 600 --steps 4 --periods 1,8,64
    --axes u,v
    """
    from telefringe.fringes.decode import DecodeError, choose_method
    from telefringe.fringes.patterns import pattern_scan
    from telefringe.io.atomic import check_can_write
    from telefringe.io.errors import InputError
    from telefringe.io.scan_json import write_scan

    check_can_write(out, force=force)
    per = _parse_periods(periods)
    ax = _parse_axes(axes)
    if not (1 <= width <= 100_000 and 1 <= height <= 100_000):
        raise InputError(f"--width/--height must be 1..100000, got {width} x {height}")
    if steps < 3:
        raise InputError(f"--steps must be >= 3, got {steps}")
    if gray and not 1 <= gray <= 16:
        raise InputError(f"--gray must be 1..16 bits, got {gray}")
    if gray and 2 ** gray not in per:
        raise InputError(f"--gray {gray} fixes the order of the group with {2 ** gray} periods;"
                         f" add {2 ** gray} to --periods")
    if precompensate_gamma is not None and not 0.1 <= precompensate_gamma <= 10:
        raise InputError(f"--precompensate-gamma must be in 0.1..10, got {precompensate_gamma}")
    for a in ax:
        try:
            choose_method(per, length=width if a == "u" else height,
                          gray_bits=gray or None)
        except DecodeError as exc:
            raise InputError(f"--periods {periods}: {exc}") from None
    scan = pattern_scan(width=width, height=height, steps=steps, periods=per, axes=ax,
                        gray_bits=gray or None, complementary=complementary,
                        white_black=white_black, gamma=precompensate_gamma)
    write_scan(out, scan, force=force)
    n = sum(s.shape[0] for s in scan.stacks) + 2 * white_black
    info(f"wrote {n} patterns ({width} x {height}) and scan.json to {out}")


def register(app: typer.Typer) -> None:
    """Add ``decode`` and ``patterns`` to the app."""
    app.command("decode")(decode_cmd)
    app.command("patterns")(patterns_cmd)
