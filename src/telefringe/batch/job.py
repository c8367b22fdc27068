"""One scan of a batch: decode -> reconstruct -> measure, its outputs written atomically,
and its row of the results table. Runs on a Dask worker (or in the calling process)."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import socket
import threading
import time
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["MEASURES", "BatchOptions", "ScanJob", "run_scan", "ROW_FILE", "FIXED_COLUMNS"]

MEASURES = ("none", "bga", "plate", "sphere", "steps")
#: in each scan's output folder: its row of the table, with the key of its inputs
ROW_FILE = "row.json"
#: bumped when the outputs of a scan change meaning (old outputs are then redone)
OUTPUT_VERSION = 3

#: the columns every row has, in order (the measurement's own follow, named
#: ``<measure>.<field>``); their types are in :data:`telefringe.batch.table.FIXED_TYPES`
FIXED_COLUMNS = ("scan", "path", "status", "error", "reused", "measure", "points",
                 "valid_fraction", "sigma_z_median_mm", "warnings", "t_read_s",
                 "t_reconstruct_s", "t_measure_s", "t_write_s", "t_total_s", "worker",
                 "output", "key")


@dataclass(frozen=True)
class BatchOptions:
    """What is done to every scan of a batch (part of the key of its outputs).

    Attributes
    ----------
    measure : {"none", "bga", "plate", "sphere", "steps"}
    rows, cols : int or None, the nominal grid (bga: balls, default the span found;
        plate: markers, default 9 x 11).
    pitch : float or None, mm (bga default 0.8, plate 3.0).
    diameter : float, mm, the nominal ball diameter (bga).
    dark : bool, dark markers on a light plate (plate).
    min_height : float or None, mm (sphere: points above the base plane).
    min_step : float, mm (steps).
    free_radius : bool, bga: fit each ball's radius (see ``telefringe measure bga``).
    gamma_correction, refit_gamma : bool, the projector nonlinearity (as ``telefringe
        reconstruct``: the rig's model where it has one, else learned from the scan;
        ``refit_gamma`` learns it from every scan).
    method : str, the unwrapping method.
    max_residual : float, projector px (u/v consistency).
    pixel_mm : float or None, height-map spacing.
    write_points, ply : bool, write points.npz (and the height map) / cloud.ply per scan.
    numba_threads : int or None, compiled-kernel threads per task (None: the worker's).
    second : str or None, a two-camera rig: the second camera's scan folder of each scan,
        relative to the scan's folder (e.g. ``"../camera_2"``); the two scans are matched
        as ``telefringe reconstruct SCAN --second SECOND`` does, points.npz keeps the
        matches' noise split and the plate, sphere, steps and BGA fits take it (neighbouring
        matches share the second camera's pixels), as ``telefringe measure`` does. None:
        the first camera and the projector.
    """

    measure: str = "none"
    rows: int | None = None
    cols: int | None = None
    pitch: float | None = None
    diameter: float = 0.45
    dark: bool = True
    min_height: float | None = None
    min_step: float = 0.05
    free_radius: bool = False
    gamma_correction: bool = True
    refit_gamma: bool = False
    method: str = "auto"
    max_residual: float = 1.0
    pixel_mm: float | None = None
    write_points: bool = True
    ply: bool = False
    numba_threads: int | None = None
    second: str | None = None

    def __post_init__(self):
        from telefringe.io.errors import InputError

        if self.measure not in MEASURES:
            raise InputError(f"measure must be one of {', '.join(MEASURES)}, got "
                             f"{self.measure!r}")
        for name in ("rows", "cols", "numba_threads"):
            v = getattr(self, name)
            if v is not None and not (isinstance(v, int) and v >= 1):
                raise InputError(f"{name} must be an integer >= 1, got {v!r}")
        for name in ("pitch", "diameter", "min_step", "max_residual", "pixel_mm"):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and v > 0):
                raise InputError(f"{name} must be > 0, got {v!r}")
        if self.min_height is not None and not (np.isfinite(self.min_height)
                                                and self.min_height >= 0):
            raise InputError(f"min_height must be >= 0, got {self.min_height!r}")
        if self.second is not None and not (isinstance(self.second, str) and self.second
                                            and not os.path.isabs(self.second)):
            raise InputError("second must be a folder relative to each scan's folder "
                             f"(e.g. '../camera_2'), got {self.second!r}")

    def key_dict(self) -> dict:
        """The options that change a scan's outputs (not the thread count)."""
        d = asdict(self)
        d.pop("numba_threads")
        if d["second"] is None:  # the key of a one-camera batch as before the option
            d.pop("second")
        return d


@dataclass(frozen=True)
class ScanJob:
    """One scan of a batch: its folder, its name, and where its outputs go (None: nothing
    is written)."""

    path: str
    name: str
    output: str | None
    force: bool = False
    rig_digest: str = ""
    extra: dict = field(default_factory=dict)


def job_key(scan_digest: str, rig_digest: str, options: BatchOptions) -> str:
    """The key of a scan's outputs: a hash of its inputs' hash, the rig's, the options and
    the output format version."""
    from telefringe import __version__

    doc = {"scan": scan_digest, "rig": rig_digest, "options": options.key_dict(),
           "version": OUTPUT_VERSION, "telefringe": __version__}
    return hashlib.blake2b(json.dumps(doc, sort_keys=True).encode(),
                           digest_size=16).hexdigest()


def read_row(folder) -> dict | None:
    """The row stored in a scan's output folder (None when absent or unreadable)."""
    try:
        return json.loads((Path(folder) / ROW_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def _one_line(exc: BaseException) -> str:
    msg = " ".join(str(exc).split()) or type(exc).__name__
    from telefringe.io.errors import InputError
    from telefringe.metrology import MetrologyError

    if isinstance(exc, (InputError, MetrologyError, ValueError)):
        return msg
    return f"{type(exc).__name__}: {msg}"


_THREADS_LOCK = threading.Lock()


@contextlib.contextmanager
def _numba_threads(n: int | None):
    """Run the compiled kernels on ``n`` threads in this thread (numba's setting is per
    calling thread)."""
    if n is None:
        yield
        return
    import numba

    old = numba.get_num_threads()
    numba.set_num_threads(max(1, min(int(n), numba.config.NUMBA_NUM_THREADS)))
    try:
        yield
    finally:
        numba.set_num_threads(old)


# ----------------------------------------------------------------------------- measure
def _measure(rec, options: BatchOptions, rig=None, noise=None, scan=None, scan_2=None):
    """(measurement, summary dict) of a reconstruction; (None, {}) for 'none', as
    ``telefringe measure <kind> [--rig]`` gives them for its folder. ``rig`` (the rig
    that made it): its camera corrects the plate's detected marker centres; a
    RigCalibration with a parameter covariance (a calibrated rig.json) adds the
    calibration's part to each figure's uncertainty (a two-camera cloud's through both
    cameras, :func:`~telefringe.metrology.uncertainty.for_stereo_scan`) and fits the
    sphere through the cameras' point-spread model. ``noise``: a two-camera match's
    StereoNoise, which the plate's, the steps', the BGA's and (through the point-spread
    model) the sphere's fits take; ``scan``, ``scan_2``: the cameras' scans (the sphere's
    point-spread model)."""
    cal = _calibration_of(rig)
    measurement, summary = _measure_only(rec, options, rig, noise, cal, scan, scan_2)
    if measurement is None or cal is None:
        return measurement, summary
    from telefringe.io import reports
    from telefringe.metrology import uncertainty as mu

    fn = {"plate": mu.plate_uncertainty, "sphere": mu.sphere_uncertainty,
          "steps": mu.steps_uncertainty, "bga": mu.bga_uncertainty}[options.measure]
    if options.measure == "sphere" and scan_2 is not None:
        cal = mu.for_stereo_scan(cal, scan_2)  # as 'measure sphere --rig' (two cameras)
    measurement = fn(measurement, rec.cloud, cal)
    if options.measure == "sphere":
        summary = reports.sphere_summary(measurement.sphere, measurement.base,
                                         region=measurement.region,
                                         uncertainty=measurement.uncertainty,
                                         spread=measurement.spread)
    else:
        summary = getattr(reports, f"{options.measure}_summary")(measurement)
    return measurement, summary


def _calibration_of(rig):
    """``rig`` where it carries a finite parameter covariance (a RigCalibration from a
    calibrated rig.json), else None (a bare rig: the figures' u then hold the noise)."""
    import numpy as np

    cov = getattr(rig, "covariance", None)
    if cov is None or not hasattr(rig, "parameter_names"):
        return None
    cov = np.asarray(cov, dtype=np.float64)
    if cov.size == 0 or not np.all(np.isfinite(cov)):
        return None
    return rig


def _measure_only(rec, options: BatchOptions, rig=None, noise=None, cal=None, scan=None,
                  scan_2=None):
    """(measurement, summary dict) with the noise's uncertainty alone."""
    from telefringe.io import reports

    m = options.measure
    cloud = rec.cloud
    if m == "none":
        return None, {}
    if m == "sphere":
        from telefringe.metrology import measure_sphere
        from telefringe.metrology.spheres import sphere_spread_options

        spread = {} if cal is None else sphere_spread_options(
            cal.rig, rec.radiance, cloud.shape, None if scan is None else scan.manifest,
            scan_2)
        if noise is not None and spread.get("image_2") is not None:
            spread["noise"] = noise
        elif noise is not None:
            warnings.warn("u of radius and centre treats neighbouring points as "
                          "independent, which understates it for two cameras: the matches' "
                          "correlated noise enters the fit through the cameras' point-spread "
                          "model, which needs a calibrated two-camera rig.json with a "
                          "projector", stacklevel=2)
        sm = measure_sphere(cloud, min_height=options.min_height, **spread)
        return sm, reports.sphere_summary(sm.sphere, sm.base, region=sm.region,
                                          spread=sm.spread)
    if m == "steps":
        from telefringe.metrology import measure_steps

        st = measure_steps(cloud, min_step=options.min_step, noise=noise)
        return st, reports.steps_summary(st)
    if m == "plate":
        from telefringe.io.errors import InputError
        from telefringe.metrology import measure_plate
        from telefringe.targets.circle_grid import detect_circle_grid

        rows = 9 if options.rows is None else options.rows
        cols = 11 if options.cols is None else options.cols
        det = detect_circle_grid(rec.texture, rows=rows, cols=cols, dark=options.dark)
        if not det:
            raise InputError(f"the {rows} x {cols} circle grid was not found: {det.reason}")
        pitch = 3.0 if options.pitch is None else options.pitch
        # markers half the pitch across (the plate telefringe simulates, as the paper's)
        pm = measure_plate(cloud, det.centers, rows=rows, cols=cols, pitch_mm=pitch,
                           camera=None if rig is None else rig.camera,
                           marker_diameter_mm=0.5 * pitch, noise=noise,
                           centres_sigma_px=det.center_sigma)
        return pm, reports.plate_summary(pm)
    from telefringe.metrology import BGANominal, BGAOptions, measure_bga

    nominal = BGANominal(rows=options.rows, cols=options.cols,
                         pitch_mm=0.8 if options.pitch is None else options.pitch,
                         ball_diameter_mm=options.diameter)
    bm = measure_bga(cloud, nominal, image=rec.radiance,
                     options=BGAOptions(cap_model="free" if options.free_radius else "psf"),
                     noise=noise)
    return bm, reports.bga_summary(bm)


def flatten_summary(summary: dict, prefix: str) -> dict:
    """The scalar figures of a measurement's summary as columns ``prefix.key.sub``:
    numbers, booleans, strings and None as they are; 3-vectors of numbers as ``.x``,
    ``.y``, ``.z``; lists of lists (missing balls, ...) by their ``.count``; other lists
    (per-ball arrays) are left to the scan's own files.

    >>> flatten_summary({"r": 1.0, "c": [1, 2, 3], "b": {"n": 2}, "m": [[0, 1]]}, "s")
    {'s.r': 1.0, 's.c.x': 1, 's.c.y': 2, 's.c.z': 3, 's.b.n': 2, 's.m.count': 1}
    """
    out: dict = {}

    def walk(v, key):
        if isinstance(v, dict):
            for k, x in v.items():
                walk(x, f"{key}.{k}")
        elif isinstance(v, list):
            if len(v) == 3 and all(isinstance(x, (int, float)) or x is None for x in v):
                for axis, x in zip("xyz", v, strict=True):
                    out[f"{key}.{axis}"] = x
            elif v and all(isinstance(x, list) for x in v) or (not v and key.endswith(
                    ("missing", "unexpected"))):
                out[f"{key}.count"] = len(v)
        elif v is None or isinstance(v, (bool, int, float, str)):
            out[key] = v

    for k, v in summary.items():
        walk(v, f"{prefix}.{k}")
    return out


# ----------------------------------------------------------------------------- the task
_RIGS: dict[str, object] = {}
_RIGS_LOCK = threading.Lock()


def install_rig(digest: str, rig) -> None:
    """Keep ``rig`` in this process for the tasks that name it by ``digest``."""
    with _RIGS_LOCK:
        _RIGS[digest] = rig


def remove_rig(digest: str) -> None:
    with _RIGS_LOCK:
        _RIGS.pop(digest, None)


def _rig(digest: str):
    with _RIGS_LOCK:
        rig = _RIGS.get(digest)
    if rig is None:
        raise RuntimeError(f"the rig {digest[:12]} was not sent to this worker")
    return rig


def _worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def _row(job: ScanJob, options: BatchOptions, **values) -> dict:
    row = {c: None for c in FIXED_COLUMNS}
    row.update(scan=job.name, path=job.path, status="ok", error="", reused=False,
               measure=options.measure, warnings="", worker=_worker_name(),
               output="" if job.output is None else job.output, key="")
    row.update(values)
    return row


def run_scan(job: ScanJob, options: BatchOptions) -> dict:
    """Decode, reconstruct and measure one scan; write its outputs; return its row.

    Never raises for a problem of the scan: the row's ``status`` is ``"failed"`` and its
    ``error`` says why in one line. With an output folder whose ``row.json`` carries the
    same key (same images, rig and options), the scan is not redone (``reused``) unless
    ``job.force``. The output folder appears complete or not at all.
    """
    t0 = time.perf_counter()
    key = ""
    try:
        from telefringe.batch.scans import scan_digest

        digest = scan_digest(job.path)
        second = _second_folder(job, options)
        if second is not None:  # a two-camera scan: both cameras' images
            digest = f"{digest}+{scan_digest(second)}"
        key = job_key(digest, job.rig_digest, options)
        if job.output is not None and not job.force:
            old = read_row(job.output)
            if old is not None and old.get("key") == key and old.get("status") == "ok":
                old.update(reused=True, path=job.path, scan=job.name, output=job.output)
                return old
        with _numba_threads(options.numba_threads):
            return _run(job, options, key, t0)
    except Exception as exc:  # noqa: BLE001 - every problem of a scan goes in its row
        return _row(job, options, status="failed", error=_one_line(exc), key=key,
                    output="", t_total_s=time.perf_counter() - t0)


def _second_folder(job: ScanJob, options: BatchOptions) -> Path | None:
    """The second camera's scan folder of ``job`` (None: one camera)."""
    if options.second is None:
        return None
    return Path(os.path.normpath(Path(job.path) / options.second))


def _run(job: ScanJob, options: BatchOptions, key: str, t0: float) -> dict:
    from telefringe.fringes.decode import DecodeError
    from telefringe.fringes.phase import PhaseInputError
    from telefringe.io.errors import InputError
    from telefringe.io.scan_json import read_scan
    from telefringe.reconstruction.cloud import TriangulationError
    from telefringe.reconstruction.pipeline import reconstruct_scan, reconstruct_stereo_scans

    rig = _rig(job.rig_digest)
    scan = read_scan(job.path)
    second = _second_folder(job, options)
    scan_2 = None if second is None else read_scan(second)
    t1 = time.perf_counter()
    extra = {"phase_errors": None} if options.refit_gamma else {}
    kw = dict(max_residual=options.max_residual, pixel_mm=options.pixel_mm,
              with_height_map=options.write_points and job.output is not None,
              gamma_correction=options.gamma_correction, method=options.method, **extra)
    try:
        if scan_2 is None:
            rec = reconstruct_scan(scan, rig, **kw)
        else:  # two cameras: as 'telefringe reconstruct SCAN --second SECOND'
            rec = reconstruct_stereo_scans(scan, scan_2, rig, **kw)
    except (DecodeError, PhaseInputError, TriangulationError) as exc:
        msg = str(exc)
        for s in (scan, scan_2):
            if s is not None and msg.startswith(f"{s.source}: "):
                msg = msg[len(s.source) + 2:]
        raise InputError(msg) from None
    if rec.cloud.count == 0:
        raise InputError("no valid point (is the object lit and in focus, and does the rig "
                         "belong to this scan?)")
    t2 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        maps = _match_noise_maps(rec, rig) if scan_2 is not None else None
        measurement, summary = _measure(rec, options, rig,
                                        None if maps is None else maps.expand(), scan, scan_2)
    t3 = time.perf_counter()
    from telefringe.fringes.decode import nonlinearity_kept
    from telefringe.io.reports import cloud_summary

    cs = cloud_summary(rec.cloud)
    kept = [f"camera {i + 1} {m}" if scan_2 is not None else m
            for i, c in enumerate((rec.coords, getattr(rec, "coords_2", None)))
            for m in nonlinearity_kept(getattr(c, "axes", None), options.gamma_correction)]
    row = _row(job, options, key=key, points=int(rec.cloud.count),
               valid_fraction=cs["valid_fraction"], sigma_z_median_mm=cs["sigma_z_median_mm"],
               warnings="; ".join(dict.fromkeys(
                   [*kept, *(" ".join(str(w.message).split()) for w in caught)])),
               t_read_s=t1 - t0, t_reconstruct_s=t2 - t1, t_measure_s=t3 - t2)
    row.update(flatten_summary(summary, options.measure))
    if job.output is not None:
        _write(job, options, rec, measurement, summary, cs, row, second, maps)
    row["t_write_s"] = time.perf_counter() - t3
    row["t_total_s"] = time.perf_counter() - t0
    if job.output is not None:  # the timings, written last (the folder is complete)
        from telefringe.io.jsonable import write_json

        write_json(Path(job.output) / ROW_FILE, row, force=True)
    return row


def _match_noise_maps(rec, rig):
    """A two-camera reconstruction's matches' noise split (StereoNoiseMaps, as
    ``telefringe reconstruct --second`` keeps in points.npz), or None with a warning
    (the row's) where it cannot be split: the fits then treat the points as
    independent."""
    from telefringe.reconstruction.cloud import TriangulationError
    from telefringe.reconstruction.stereo import match_noise_maps

    try:
        return match_noise_maps(rig, rec.coords, rec.coords_2, rec.match)
    except TriangulationError as exc:
        warnings.warn(f"the matches' correlated noise is not split ({exc}): u treats "
                      "neighbouring points as independent, which understates it for two "
                      "cameras", stacklevel=2)
        return None


def _write(job, options, rec, measurement, summary, cs, row, second=None,
           maps=None) -> None:
    from telefringe.io.atomic import atomic_dir
    from telefringe.io.jsonable import write_json

    inputs = (job.path, _second_folder(job, options))
    with atomic_dir(job.output, force=True, inputs=inputs) as tmp:
        if options.write_points:
            from telefringe.io.reconstruction_folder import write_reconstruction

            info = {"scan": job.path, **cs}
            if second is not None:  # as 'telefringe reconstruct --second' writes it
                info.update(second_scan=str(second), stereo_noise=maps is not None)
            write_reconstruction(tmp, rec.cloud, rec.height, texture=rec.texture,
                                 radiance=rec.radiance, title=job.name, ply=options.ply,
                                 summary=info, stereo_noise=maps)
        if measurement is not None:
            write_json(tmp / "measurement.json", summary)
            if options.measure == "bga":
                from telefringe.io.bga_csv import write_bga_csv

                write_bga_csv(tmp / "bga.csv", measurement)
        write_json(tmp / ROW_FILE, {**row, "t_write_s": None, "t_total_s": None})
