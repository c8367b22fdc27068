"""`telefringe patterns`: the projector images of a fringe pattern set and its scan.json."""

from __future__ import annotations

from pathlib import Path

import typer

from telefringe.cli._common import info


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
        length = width if a == "u" else height
        if 2 * max(per) > length:
            raise InputError(f"--periods {periods}: {max(per)} periods across the projector's "
                             f"{'width' if a == 'u' else 'height'} of {length} px leave less "
                             "than 2 px per period (at most "
                             f"{length // 2} periods along {a})")
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
    """Add ``patterns`` to the app."""
    app.command("patterns")(patterns_cmd)
