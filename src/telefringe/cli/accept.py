"""`telefringe accept`: the acceptance test of VDI/VDE 2634 Part 2 (PF, PS, SD, F) on an
acceptance set (scans of a test sphere, a ball bar and a plane at several positions)."""

from __future__ import annotations

from pathlib import Path

import typer

from telefringe.cli._common import console, detail, info, progress_bar, state

__all__ = ["register", "parse_mpe"]


def parse_mpe(text: str | None) -> dict:
    """``"PF=0.01,PS=0.008,SD=0.012,F=0.01"`` (mm) -> ``{"PF": 0.01, ...}``; any subset.

    >>> parse_mpe("PF=0.01, SD=0.012")
    {'PF': 0.01, 'SD': 0.012}
    """
    from telefringe.io.errors import InputError
    from telefringe.metrology.acceptance import QUANTITIES

    if text is None or not text.strip():
        return {}
    out = {}
    for part in text.split(","):
        key, sep, val = part.partition("=")
        key = key.strip()
        try:
            v = float(val)
        except ValueError:
            v = float("nan")
        if not sep or key not in QUANTITIES or not (v > 0 and v < float("inf")):
            raise InputError(f"--mpe: {part.strip()!r} is not NAME=mm with NAME one of "
                             f"{', '.join(QUANTITIES)} and a positive number (mm), e.g. "
                             "--mpe PF=0.01,PS=0.01,SD=0.015,F=0.01")
        if key in out:
            raise InputError(f"--mpe: {key} given twice")
        out[key] = v
    return out


def _check_cameras(scans, rig_obj, rig_path) -> None:
    """Each position's scans must suit the rig, as for 'reconstruct': a ``second`` scan
    needs two cameras, a single scan a calibrated projector."""
    from telefringe.io.errors import InputError

    inner = getattr(rig_obj, "rig", rig_obj)
    n_cams = len(getattr(inner, "cameras", ()))
    has_proj = getattr(inner, "projector", None) is not None
    for e in scans:
        if e.second is not None and n_cams < 2:
            raise InputError(f"{e.scan}: acceptance.json gives a second camera's scan "
                             f"({e.second}) but {rig_path} has one camera")
        if e.second is None and not has_proj:
            raise InputError(f"{e.scan}: {rig_path} has no calibrated projector: give each "
                             "position the second camera's scan as \"second\" in "
                             "acceptance.json (see docs/acceptance.md)")


def _gamma_notes(rec) -> tuple[str, ...]:
    """What the decoder's fit of the projector nonlinearity could not decide, for every
    camera and axis of a reconstruction (empty when it was clean or not learned)."""
    out = []
    for coords in (rec.coords, getattr(rec, "coords_2", None)):
        for ax in getattr(coords, "axes", {}).values():
            fit = getattr(ax, "phase_errors", None)
            out.extend(f"{ax.axis}: {w}" for w in getattr(fit, "warnings", ()))
    return tuple(dict.fromkeys(out))


def _match_noise(rec, rig_obj, name: str, failed: list):
    """A two-camera reconstruction's matches' noise split (StereoNoise, for the spheres'
    fit uncertainty: neighbouring matches share the second camera's pixels), None for
    one camera; None with ``name`` added to ``failed`` where it cannot be split."""
    if getattr(rec, "match", None) is None or getattr(rec, "coords_2", None) is None:
        return None
    from telefringe.reconstruction.cloud import TriangulationError
    from telefringe.reconstruction.stereo import match_noise

    try:
        return match_noise(rig_obj, rec.coords, rec.coords_2, rec.match)
    except TriangulationError as exc:
        failed.append(name)
        detail(f"{name}: the matches' noise is not split ({exc})")
        return None


def _with_spread(pos, rec, rig_obj, cert, scan, scan_2, noise, failed: list):
    """The test sphere's position with its size through the cameras' point-spread model
    (:func:`~telefringe.metrology.acceptance.spread_probing_size`); unchanged, with its
    name added to ``failed``, where the rig or the scan cannot give the model."""
    import numpy as np

    from telefringe.metrology._common import MetrologyError
    from telefringe.metrology.acceptance import spread_probing_size
    from telefringe.metrology.spheres import sphere_spread_options
    from telefringe.reconstruction._rig import as_rig

    rig = as_rig(rig_obj)
    opts = sphere_spread_options(rig, rec.radiance, rec.cloud.shape, scan.manifest, scan_2)
    if not opts:
        failed.append(pos.name)
        detail(f"{pos.name}: no point-spread model (the rig has no projector model, or "
               "the scan no brightness image)")
        return pos
    opts.pop("rig")
    try:
        return spread_probing_size(pos, rec.cloud, cert, rig, opts.pop("image"), noise=noise,
                                   **opts)
    except (MetrologyError, ValueError, np.linalg.LinAlgError) as exc:
        failed.append(pos.name)
        detail(f"{pos.name}: no point-spread model ({exc})")
        return pos


def _table(result):
    from rich.table import Table

    t = Table(title="VDI/VDE 2634-2 acceptance test (mm; U: expanded uncertainty of the "
                    "test, k = 2; *: PS differs from the point-spread model's size)")
    cols = ["characteristic", "position", "value", "U", "cap half-angle", "decision"]
    spread = any(p.spread is not None for p in result.positions)
    if spread:  # the test spheres' size error through the cameras' point-spread model
        cols.insert(4, "point-spread model")
    for col in cols:
        t.add_column(col, justify="left" if col in ("characteristic", "position") else "right")
    by_name = {p.name: p for p in result.positions}
    for q, qr in result.quantities.items():
        for k, name in enumerate(qr.positions):
            test = by_name[name].test
            if q in ("PF", "PS"):
                cap = f"{test.cap_half_angle_deg:.0f} deg"
            elif q == "SD":
                cap = " / ".join(f"{s.cap_half_angle_deg:.0f}" for s in test.spheres) + " deg"
            else:
                cap = ""
            row = [q if k == 0 else "", name, f"{qr.values[k]:+.4f}", f"{qr.U[k]:.4f}", cap,
                   qr.decisions[k] if qr.decisions else ""]
            if spread:
                sp = by_name[name].spread
                row.insert(4, "" if q != "PS" or sp is None else
                           f"{sp.PS:+.4f}{' *' if by_name[name].spread_bias() else ''}")
            t.add_row(*row)
        mpe = f"MPE {qr.mpe:.4f}" if qr.mpe is not None else "no MPE"
        last = ["", f"[bold]max ({qr.max_position})[/bold]", f"[bold]{qr.max_value:+.4f}",
                mpe, "", f"[bold]{qr.verdict}" if qr.verdict else ""]
        if spread:
            last.insert(4, "")
        t.add_row(*last, end_section=True)
    return t


def accept_cmd(
    folder: Path = typer.Argument(..., help="Acceptance set: a folder with acceptance.json "
                                            "and one scan folder per position."),
    rig: Path = typer.Option(..., "--rig", help="rig.json written by 'telefringe calibrate'."),
    artefacts: Path = typer.Option(..., "--artefacts",
                                   help="artefacts.json: the artefacts' calibrated values."),
    mpe: str = typer.Option(None, "--mpe",
                            help="Maximum permissible errors in mm, e.g. "
                                 "PF=0.01,PS=0.01,SD=0.015,F=0.01 (any subset)."),
    json_out: Path = typer.Option(None, "--json", help="Write the result as JSON."),
    figure: Path = typer.Option(None, "--figure",
                                help="Write the page of plots (residual maps per position)."),
    edge_px: int = typer.Option(2, "--edge-px",
                                help="Pixels left out along each artefact's border in the "
                                     "image (the camera's blur mixes it with the "
                                     "background there)."),
    gamma: bool = typer.Option(True, "--gamma-correction/--no-gamma-correction",
                               help="Remove the projector nonlinearity (the rig's model, "
                                    "else learned from each scan), as 'reconstruct' does."),
    spread_model: bool = typer.Option(True, "--spread-model/--no-spread-model",
                                      help="Fit each test sphere also through the "
                                           "cameras' point-spread model and report that "
                                           "size error beside PS (needs the rig's "
                                           "projector)."),
    force: bool = typer.Option(False, "--force", help="Replace existing outputs."),
):
    """Run the VDI/VDE 2634 Part 2 acceptance test on scans of its artefacts.

    Reconstructs every scan listed in FOLDER/acceptance.json with the rig and measures:
    PF (range of the radial residuals of a free-radius least-squares sphere, after
    excluding the 0.3 % largest) and PS (measured minus calibrated diameter) on the test
    sphere, SD (measured minus calibrated centre distance) on the ball bar, F (range of
    the distances to the least-squares plane, same exclusion) on the plane, at each
    position, and their maxima; with --mpe, PASS / FAIL / UNDECIDED by ISO 14253-1 guard
    bands of the test's expanded uncertainty. The cap of every sphere seen is reported (a
    single view sees a cap, which makes PS less certain). A rig with two cameras reads
    both cameras' scans of each position ("second" in acceptance.json) and matches them
    as 'reconstruct --second' does; U of PS and SD then holds the matches' correlated
    noise (neighbouring matches share the second camera's pixels). Each test sphere is
    also fitted through the cameras' point-spread model (--spread-model, where the rig
    has the projector's model): that size error is reported beside PS, and a note says
    where PS differs from it by more than their fit uncertainties (the cameras' blur
    biasing the points on the sphere's curvature; PS keeps the points as measured). See
    docs/acceptance.md.

    Example: telefringe accept acc/acceptance --rig rig.json --artefacts acc/artefacts.json

    (acc from 'telefringe simulate acceptance acc', rig.json from calibrating the same
    virtual rig; add --mpe PF=0.02,PS=0.02,SD=0.02,F=0.03 --json result.json for a verdict
    and a file.)
    """
    from telefringe.fringes.decode import DecodeError
    from telefringe.fringes.phase import PhaseInputError
    from telefringe.io.acceptance_json import (
        load_acceptance_set,
        load_artefacts,
        result_to_json,
    )
    from telefringe.io.atomic import check_can_write
    from telefringe.io.errors import InputError
    from telefringe.io.jsonable import write_json
    from telefringe.io.rig_json import load_rig
    from telefringe.io.scan_json import read_scan
    from telefringe.metrology._common import MetrologyError
    from telefringe.metrology.acceptance import evaluate_position, summarize
    from telefringe.reconstruction.cloud import TriangulationError
    from telefringe.reconstruction.pipeline import reconstruct_scan, reconstruct_stereo_scans

    limits = parse_mpe(mpe)
    if not 0 <= edge_px <= 20:
        raise InputError(f"--edge-px must be between 0 and 20, got {edge_px}")
    for p in (json_out, figure):
        if p is not None:
            check_can_write(p, force=force)
    scans = load_acceptance_set(folder)
    cert = load_artefacts(artefacts)
    rig_obj = load_rig(rig)
    _check_cameras(scans, rig_obj, rig)
    kinds = {e.artefact for e in scans}
    missing = {"sphere", "ball_bar", "plane"} - kinds
    if missing:
        info(f"[yellow]warning:[/yellow] no scan of the {', '.join(sorted(missing))}: "
             "its characteristics are not tested")
    positions = []
    gamma_notes = {}
    no_noise = []
    no_spread = []
    with progress_bar(f"measuring {len(scans)} positions", len(scans)) as advance:
        for entry in scans:
            name, kind, desc = entry.name, entry.artefact, entry.description
            scan = read_scan(Path(folder) / entry.scan)
            scan_2 = None
            try:
                if entry.second is None:
                    rec = reconstruct_scan(scan, rig_obj, with_height_map=False,
                                           gamma_correction=gamma)
                else:  # two cameras: as 'reconstruct SCAN --second SECOND'
                    scan_2 = read_scan(Path(folder) / entry.second)
                    rec = reconstruct_stereo_scans(scan, scan_2, rig_obj,
                                                   with_height_map=False,
                                                   gamma_correction=gamma)
                noise = _match_noise(rec, rig_obj, name, no_noise)
                pos = evaluate_position(name, kind, rec.cloud.xyz, rec.cloud.mask, cert,
                                        erode_px=edge_px, noise=noise,
                                        directions=None if noise is None
                                        else rec.cloud.directions)
                if spread_model and kind == "sphere":
                    pos = _with_spread(pos, rec, rig_obj, cert, scan, scan_2, noise,
                                       no_spread)
            except (DecodeError, PhaseInputError, TriangulationError, MetrologyError) as exc:
                raise InputError(f"{Path(folder) / entry.scan}: {exc}") from None
            notes = _gamma_notes(rec)
            if notes:
                gamma_notes[name] = notes
            positions.append(pos)
            detail(f"{name} ({kind}{', ' + desc if desc else ''}): "
                   f"{rec.cloud.count} points")
            advance()
    if no_noise:
        info(f"[yellow]note:[/yellow] U of PS and SD at {', '.join(no_noise)} treats "
             "neighbouring points as independent, which understates it for two cameras: "
             "the matches' correlated noise could not be split there; -v says why")
    if no_spread:
        info(f"[yellow]note:[/yellow] no point-spread model of the test sphere at "
             f"{', '.join(no_spread)}; -v says why")
    biased = [p for p in positions if p.spread_bias()]
    if biased:
        info(f"[yellow]note:[/yellow] PS at {len(biased)} of "
             f"{sum(p.spread is not None for p in positions)} test spheres differs from the "
             "size through the cameras' point-spread model by more than 2 x their fit "
             "uncertainties (PS through the model: "
             + ", ".join(f"{p.name} {p.test.PS * 1e3:+.1f} -> {p.spread.PS * 1e3:+.1f} um"
                         for p in biased)
             + "): the cameras' blur moves the points on the sphere's curvature, which "
             "makes the fitted sphere larger. PS reports the points as measured (the "
             "guideline's value); see docs/acceptance.md")
    if gamma_notes:
        first = next(iter(gamma_notes.values()))[0]
        info(f"[yellow]warning:[/yellow] the projector nonlinearity learned from "
             f"{len(gamma_notes)} of {len(scans)} scans is incomplete (e.g. "
             f"{next(iter(gamma_notes))}: {first}); the values are measured with what "
             "could be learned. A rig.json that carries the projector's model (from "
             "'telefringe calibrate') does not learn it from small scans; -v lists all")
        for n, notes in gamma_notes.items():
            for note in notes:
                detail(f"{n}: {note}")
    result = summarize(positions, cert, limits)
    if not state.quiet:
        console.print(_table(result))
    for q, qr in result.quantities.items():
        info(f"{q}: max {qr.max_value * 1000:+.2f} um at {qr.max_position}"
             + (f", MPE {qr.mpe * 1000:.2f} um: {qr.verdict}" if qr.mpe is not None else ""))
    if result.verdict:
        info(f"verdict: {result.verdict} (ISO 14253-1 guard bands of U, k = 2)")
    if json_out is not None:
        doc = result_to_json(result, rig=str(rig), folder=str(folder))
        doc["gamma_warnings"] = {n: list(v) for n, v in gamma_notes.items()}
        write_json(json_out, doc, force=force)
        info(f"wrote {json_out}")
    if figure is not None:
        from telefringe.io.figures.acceptance import write_acceptance_figure

        write_acceptance_figure(figure, result, title=Path(folder).name, force=force)
        info(f"wrote {figure}")


def register(app: typer.Typer) -> None:
    """Add ``accept`` to the app."""
    app.command("accept")(accept_cmd)
