"""`telefringe reconstruct`: scan + rig.json -> points, PLY, height map."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import typer

from telefringe.cli._common import (
    detail,
    info,
    progress_bar,
    read_scan_with_progress,
    state,
    warn_nonlinearity_kept,
)


def reconstruct_to_folder(scan_dir, rig, output, *, force: bool = False,
                          pixel_mm: float | None = None, max_residual: float | None = 1.0,
                          ply: bool = True, title: str | None = None, second=None,
                          read=None, **decode_options):
    """Read a scan folder, reconstruct it with ``rig`` (a Rig, or a RigCalibration whose
    projector nonlinearity is then used) and write ``output``. With ``second`` (the scan
    folder of the rig's second camera), match the two cameras' phases instead (stereo).

    Writes atomically (the folder appears complete or not at all): ``points.npz`` (with
    ``second``, with the matches' noise split, :func:`match_noise_maps`), ``cloud.ply``,
    ``heightmap.tif`` + ``heightmap.json`` (+ ``heightmap_sigma.tif``),
    ``heightmap.png`` and ``summary.json``. User problems raise ``InputError``.
    ``read(folder) -> Scan`` reads each scan folder (default
    :func:`telefringe.cli._common.read_scan_with_progress`; the command passes scans
    it began reading beforehand).

    Returns
    -------
    telefringe.reconstruct.Reconstruction
    """
    from telefringe.fringes.decode import DecodeError
    from telefringe.fringes.phase import PhaseInputError
    from telefringe.io.atomic import atomic_dir, check_can_write
    from telefringe.io.errors import InputError
    from telefringe.io.reconstruction_folder import write_reconstruction
    from telefringe.io.reports import cloud_summary
    from telefringe.reconstruction.cloud import TriangulationError
    from telefringe.reconstruction.heightmap import height_map
    from telefringe.reconstruction.pipeline import reconstruct_scan, reconstruct_stereo_scans

    output = Path(output)
    check_can_write(output, force=force)
    # the scan's projector and camera sizes are checked against the rig by reconstruct_scan
    # (a RigCalibration from load_rig stands for its Rig, and reconstruct_scan takes the
    # projector nonlinearity it learned)
    read = read_scan_with_progress if read is None else read
    data = read(scan_dir)
    data_2 = None if second is None else read(second)
    where = scan_dir if data_2 is None else f"{scan_dir} + {second}"

    def user_error(exc):
        msg = str(exc)
        for d in (data, data_2):
            if d is not None and msg.startswith(f"{d.source}: "):
                msg = msg[len(d.source) + 2:]
        return InputError(f"{where}: {msg}")

    with progress_bar("reconstructing", 1) as advance:
        # the height map is made while the point files are written (write_reconstruction)
        try:
            if data_2 is None:
                rec = reconstruct_scan(data, rig, max_residual=max_residual,
                                       with_height_map=False, **decode_options)
            else:
                rec = reconstruct_stereo_scans(data, data_2, rig, max_residual=max_residual,
                                               with_height_map=False, **decode_options)
        except (DecodeError, PhaseInputError, TriangulationError) as exc:
            raise user_error(exc) from None
        advance()
    if rec.cloud.count == 0:
        raise InputError(f"{scan_dir}: no valid point (is the object lit and in focus, and "
                         "does the rig belong to this scan?)")
    stereo_noise = None
    if data_2 is not None and getattr(rec, "match", None) is not None:
        # neighbouring matches share the second camera's pixels: their noise split, kept
        # in points.npz for the covariance of the fits ('measure')
        from telefringe.reconstruction.stereo import match_noise_maps

        try:
            stereo_noise = match_noise_maps(rig, rec.coords, rec.coords_2, rec.match)
        except TriangulationError as exc:
            info(f"[yellow]note:[/yellow] the matches' correlated noise is not kept ({exc}): "
                 "measurements will treat neighbouring points as independent")
    made = []

    def make_height_map():
        # as reconstruct_scan's with_height_map=True
        hm = height_map(rec.cloud, pixel_mm=pixel_mm) if rec.cloud.count >= 3 else None
        made.append(hm)
        return hm

    def summary(hm):
        out = {"scan": str(scan_dir), **cloud_summary(rec.cloud)}
        if getattr(rec.coords, "noise", None) is not None:
            out["noise_model"] = rec.coords.noise.summary()
        if second is not None:
            out["second_scan"] = str(second)
            out["stereo_noise"] = stereo_noise is not None
            if getattr(rec.coords_2, "noise", None) is not None:
                out["noise_model_second"] = rec.coords_2.noise.summary()
        if hm is not None:
            out["heightmap"] = {"pixel_mm": hm.pixel_mm, "shape": list(hm.z.shape)}
        return out

    with progress_bar("writing", 1) as advance, atomic_dir(output, force=force,
                                                               inputs=(scan_dir, second)) as tmp:
        try:
            write_reconstruction(tmp, rec.cloud, make_height_map, texture=rec.texture,
                                 radiance=rec.radiance, title=title or Path(scan_dir).name,
                                 ply=ply, summary=summary, stereo_noise=stereo_noise)
        except TriangulationError as exc:  # the height map's (e.g. pixel_mm too small)
            raise user_error(exc) from None
        advance()
    return dataclasses.replace(rec, height=made[0])


def _prefetch(*modules: str):
    """Import ``modules`` in a background thread and return it.

    The command spends its first second reading PNGs (decompression runs without the
    GIL) and loading compiled kernels; importing the writers' libraries (PLY, TIFF, PNG)
    meanwhile, on the other core, takes them off the critical path. A failed import is
    left for the real one to report.
    """
    import importlib
    import threading

    def run():
        for name in modules:
            try:
                importlib.import_module(name)
            except Exception:  # noqa: BLE001 - reported by the import that needs it
                pass

    t = threading.Thread(target=run, name="telefringe-prefetch", daemon=True)
    t.start()
    return t


def _load_numba_target() -> None:
    """Load numba's CPU target now, without importing scipy.linalg.

    The first compiled kernel a process runs (cached or not) loads numba's CPU target,
    which imports all of numba's implementations; ``numba.np.arraymath`` among them checks
    that BLAS is there by importing ``scipy.linalg.cython_blas``, i.e. all of
    scipy.linalg (with scipy's array-API layer, numpy.f2py, ...: ~0.15-0.3 s CPU of the
    command's cold start, for BLAS the reconstruction never calls). Here that check looks
    for the ``cython_blas`` extension module in scipy's folder instead, without importing
    it (numba's check of the LAPACK integer width still runs); numba's compiled BLAS
    calls import it at their first call, as they always do. A no-op where numba differs
    or once its target is loaded.
    """
    import os
    import sys

    if "numba.np.arraymath" in sys.modules or "scipy.linalg" in sys.modules:
        return
    try:
        import scipy
        from numba.core.registry import cpu_target
        from numba.np import linalg as np_linalg
    except ImportError:
        return
    original = getattr(np_linalg, "ensure_blas", None)
    check_width = getattr(np_linalg, "_check_lapack_int_width", None)
    target = getattr(cpu_target, "target_context", None)
    if None in (original, check_width, getattr(target, "refresh", None)):
        return

    def ensure_blas():
        import importlib.machinery

        where = [os.path.join(d, "linalg") for d in scipy.__path__]
        if importlib.machinery.PathFinder.find_spec("cython_blas", where) is None:
            raise ImportError("scipy 0.16+ is required for linear algebra")  # as numba
        check_width()

    np_linalg.ensure_blas = ensure_blas
    try:
        target.refresh()
    finally:
        np_linalg.ensure_blas = original
        arraymath = sys.modules.get("numba.np.arraymath")
        if getattr(arraymath, "ensure_blas", None) is ensure_blas:
            arraymath.ensure_blas = original


def _light_numba_cache_loads():
    """Until the returned ``restore()`` is called, numba loads its cached kernels without
    first loading all of its compiler (the implementations of every Python and numpy
    feature it compiles, and their typing: ~0.1 s CPU of the command's cold start, which
    runs cached kernels only).

    Before loading a cached kernel, numba refreshes its CPU target, i.e. loads those
    registries; a cached kernel's machine code needs none of them, only numba's runtime
    (NRT), which is initialised here instead. A kernel that is not in the cache is
    compiled as always (numba's compiler loads the registries first), and a cached one
    that fails to load this way is loaded again numba's way (after
    :func:`_load_numba_target`). The kernels' machine code is the same either way. A
    no-op where numba differs.
    """
    try:
        from numba.core import caching
        from numba.core.runtime import rtsys
    except ImportError:
        return lambda: None
    cache = getattr(caching, "Cache", None)
    original = getattr(cache, "load_overload", None)
    if None in (original, getattr(cache, "_load_overload", None),
                getattr(cache, "_guard_against_spurious_io_errors", None),
                getattr(rtsys, "initialize", None)) or getattr(original, "_telefringe",
                                                               False):
        return lambda: None

    def load_overload(self, sig, target_context):
        try:
            rtsys.initialize(target_context)
            with self._guard_against_spurious_io_errors():
                return self._load_overload(sig, target_context)
        except Exception:  # noqa: BLE001 - loaded numba's way, which reports its errors
            _load_numba_target()
            return original(self, sig, target_context)

    load_overload._telefringe = True
    cache.load_overload = load_overload

    def restore():
        cache.load_overload = original

    return restore


def _read_ahead(*folders):
    """Begin reading the scan ``folders`` on a background thread; return
    ``read(folder) -> Scan``, which waits for that folder and raises its reading error.

    The command then loads the rig (mostly numba's start-up, which holds the GIL) while
    the images are decoded (OpenCV and zlib release it): on two cores the reading costs
    about no time. ``read`` of a folder not given here reads it then.
    """
    import threading

    # telefringe's own modules imported here, on this thread: the background thread
    # imports only third-party leaves (OpenCV), nothing that the rig's loading imports
    import telefringe.io.scan_json  # noqa: F401

    results = {}

    def run():
        for folder in folders:
            try:
                results[folder] = (read_scan_with_progress(folder), None)
            except BaseException as exc:  # noqa: BLE001 - raised by read() on this thread
                results[folder] = (None, exc)

    thread = threading.Thread(target=run, name="telefringe-read", daemon=True)
    thread.start()

    def read(folder):
        if folder not in folders:
            return read_scan_with_progress(folder)
        thread.join()
        data, exc = results[folder]
        if exc is not None:
            raise exc
        return data

    read.wait = thread.join
    return read


def reconstruct_cmd(
    scan: Path = typer.Argument(..., help="Scan folder (with scan.json)."),
    rig: Path = typer.Option(..., "--rig", help="rig.json written by 'telefringe calibrate'."),
    output: Path = typer.Option(..., "-o", "--output", help="Output folder."),
    second: Path = typer.Option(None, "--second",
                                help="The second camera's scan folder of the same patterns "
                                     "(a two-camera rig.json): match the two cameras' "
                                     "phases; the cloud is on SCAN's (the first camera's) "
                                     "pixel grid."),
    search_mm: float = typer.Option(None, "--search-mm",
                                    help="With --second: half-length (mm) of each line "
                                         "searched for the match around where the cameras' "
                                         "axes meet (default: the first camera's field "
                                         "diagonal there)."),
    force: bool = typer.Option(False, "--force", help="Replace an existing output folder."),
    pixel_mm: float = typer.Option(None, "--pixel-mm",
                                   help="Height-map grid spacing in mm (default: the "
                                        "camera's footprint per pixel)."),
    max_residual: float = typer.Option(1.0, "--max-residual",
                                       help="With u and v fringes: drop points whose two "
                                            "projector coordinates disagree by more than "
                                            "this (projector px)."),
    ply: bool = typer.Option(True, "--ply/--no-ply", help="Also write cloud.ply."),
    gamma: bool = typer.Option(True, "--gamma-correction/--no-gamma-correction",
                               help="Remove the projector nonlinearity: with the rig's model "
                                    "(learned at calibration) where it has one for the "
                                    "scan's fringe groups, else learned from the scan's "
                                    "fringe ladder."),
    refit_gamma: bool = typer.Option(False, "--refit-gamma",
                                     help="Learn the nonlinearity from this scan even when "
                                          "the rig has a model (slower)."),
    method: str = typer.Option("auto", "--method",
                               help="Unwrapping: auto, hierarchical, heterodyne, "
                                    "number-theoretic or gray."),
    noise_model: str = typer.Option("auto", "--noise-model",
                                    help="Camera noise behind sigma: 'scan' measures it "
                                         "from the scan's own phase steps (needs >= 4 "
                                         "steps); 'calibrated' takes scan.json's "
                                         "meta.camera_noise; 'default' a typical 8-bit "
                                         "camera (often wrong by 2x); 'auto' (default): "
                                         "calibrated, else scan, else default with a "
                                         "warning."),
):
    """Reconstruct a scan into a 3D point cloud with per-point uncertainty.

    Writes OUTPUT/points.npz (xyz, mask, sigma_z, ... per camera pixel), cloud.ply,
    heightmap.tif (32-bit float, mm) with heightmap.json (pixel size, origin),
    heightmap.png and summary.json.

    Example: telefringe reconstruct scans/part --rig rig.json -o part_3d

    Two cameras: telefringe reconstruct scans/left --second scans/right --rig rig.json -o 3d
    """
    from telefringe.io.errors import InputError

    if pixel_mm is not None and not (pixel_mm > 0):
        raise InputError(f"--pixel-mm must be > 0, got {pixel_mm}")
    if not (max_residual > 0):
        raise InputError(f"--max-residual must be > 0, got {max_residual}")
    if search_mm is not None and not (search_mm > 0 and second is not None):
        raise InputError(f"--search-mm needs --second and a value > 0, got {search_mm}")
    from telefringe.fringes.noise import NOISE_SOURCES

    if noise_model not in NOISE_SOURCES:
        raise InputError(f"--noise-model must be one of {', '.join(NOISE_SOURCES)}, got "
                         f"{noise_model!r}")
    # third-party leaves only, which nothing else imports meanwhile (two threads importing
    # modules that import each other could see each other's half-initialised modules)
    _prefetch("plyfile", "tifffile", "PIL.Image", "PIL.ImageDraw", "x3pio")
    from telefringe.io.rig_json import load_rig

    read = _read_ahead(*((scan,) if second is None else (scan, second)))
    restore = _light_numba_cache_loads()
    try:  # the errors as before: the rig's, the output folder's, then the scan's
        rig_obj = load_rig(rig)
        n_cams = len(getattr(getattr(rig_obj, "rig", rig_obj), "cameras", ()))
        if second is not None and n_cams < 2:
            raise InputError(f"{rig}: --second needs a rig with two cameras (camera and "
                             "camera_2), this one has one")
        if second is None and getattr(getattr(rig_obj, "rig", rig_obj), "projector",
                                      1) is None:
            raise InputError(f"{rig}: the rig has no calibrated projector: give the second "
                             "camera's scan with --second")
        extra = {"phase_errors": None} if refit_gamma else {}
        rec = reconstruct_to_folder(scan, rig_obj, output, force=force, pixel_mm=pixel_mm,
                                    max_residual=max_residual, ply=ply,
                                    gamma_correction=gamma, method=method, second=second,
                                    noise=noise_model, read=read,
                                    **({"search_mm": search_mm} if search_mm else {}),
                                    **extra)
    finally:
        read.wait()  # no thread left reading, whatever happened
        restore()  # numba's own cache loads again
    c = rec.cloud
    for coords in (rec.coords, rec.coords_2):
        warn_nonlinearity_kept(getattr(coords, "axes", None), gamma)
    for name, ax in (getattr(rec.coords, "axes", None) or {}).items():
        fit = getattr(ax, "phase_errors", None)
        if gamma and fit is not None and any(m.harmonics for m in fit.models):
            src = "learned from the scan" if fit.n_samples else "the rig's model"
            detail(f"projector nonlinearity, axis {name}: {src}; peak error per group "
                   + ", ".join(f"{m.periods}: {m.peak:.4f} rad" for m in fit.models))
    for coords in (rec.coords, rec.coords_2):
        if getattr(coords, "noise", None) is not None:
            _report_noise(coords.noise)
    if state.quiet:  # nothing more to print: the figures are not computed
        return
    info(f"{c.count} points ({c.count / c.mask.size:.1%} of the pixels)")
    import json

    import numpy as np

    # the same figures as summary.json's (median and 95th percentile of sigma_z over the
    # valid points, where all are finite), read back rather than sorted again
    summary = json.loads((Path(output) / "summary.json").read_text())
    med, p95 = summary.get("sigma_z_median_mm"), summary.get("sigma_z_p95_mm")
    if med is not None and p95 is not None:
        info(f"sigma_z median {med * 1000:.2f} um, 95% below {p95 * 1000:.2f} um")
    if c.residual is not None and state.verbose:
        r = c.residual[c.mask]
        detail(f"u/v consistency residual median {np.nanmedian(r):.3f} projector px")
    info(f"wrote {output}")


def _report_noise(choice) -> None:
    """One line on the camera noise model behind sigma (a warning for the default)."""
    if state.quiet:  # (rich, for escape, not imported)
        return
    from rich.markup import escape

    m = choice.model
    if choice.source == "scan":
        e = choice.estimate
        lo, hi = e.intensity_range
        u = float(e.relative_uncertainty(0.5 * (lo + hi)))
        info(f"camera noise measured from the scan: sigma_I^2 = {e.a:.3g} + {e.b:.3g} I "
             f"DN^2 ({lo:.0f}-{hi:.0f} DN, sigma_I known to {u:.1%}; "
             f"{e.n_pixels} pixels)")
    elif choice.source == "calibrated":
        info(f"camera noise (calibrated, {escape(choice.note)}): read {m.read_noise:.3g} DN, "
             f"gain {m.gain:.3g} DN/DN")
    else:
        why = f" ({choice.note})" if choice.note else ""
        info(f"[yellow]warning:[/yellow] camera noise: the built-in typical camera"
             f"{escape(why)}; sigma may be off by 2x")


def register(app: typer.Typer) -> None:
    """Add ``reconstruct`` to the app."""
    app.command("reconstruct")(reconstruct_cmd)
