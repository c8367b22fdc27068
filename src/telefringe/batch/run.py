"""measure_many: a batch of scans on Dask (a LocalCluster by default, any running cluster
by its address), or in this process."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import pickle
import shutil
import time
from pathlib import Path

from telefringe.batch.job import BatchOptions, ScanJob, install_rig, remove_rig, run_scan
from telefringe.batch.scans import expand_scans, scan_names
from telefringe.batch.table import Journal, to_frame, write_table
from telefringe.io.errors import InputError

__all__ = ["measure_many", "load_batch_rig", "cores"]


def cores() -> int:
    """CPU cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def load_batch_rig(rig):
    """(rig object, digest) of ``rig``: a rig.json path (loaded once, here; the digest is
    the file's bytes) or a Rig / RigCalibration (the digest of its devices and
    nonlinearity models)."""
    if isinstance(rig, (str, os.PathLike)):
        from telefringe.io.rig_json import load_rig

        path = Path(rig)
        obj = load_rig(path)
        return obj, hashlib.blake2b(path.read_bytes(), digest_size=16).hexdigest()
    inner = getattr(rig, "rig", rig)
    try:
        from telefringe.io.rig_json import bare_rig_json

        doc = bare_rig_json(inner, phase_errors=getattr(rig, "phase_errors", None))
        blob = json.dumps(doc, sort_keys=True, default=str).encode()
    except Exception:  # noqa: BLE001 - a device model the JSON writer does not know
        blob = pickle.dumps(rig)
    return rig, hashlib.blake2b(blob, digest_size=16).hexdigest()


@contextlib.contextmanager
def _lock(folder: Path):
    """Hold ``folder/.batch.lock`` (one batch writes to an output folder at a time)."""
    import fcntl

    f = open(folder / ".batch.lock", "a+")  # noqa: SIM115 - closed below
    try:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise InputError(f"{folder}: another batch is writing to this folder") from None
        yield
    finally:
        f.close()


@contextlib.contextmanager
def _client(client, scheduler, workers: int | None, n_scans: int, threads: int | None):
    """(client, numba threads per task): the given client, one connected to
    ``scheduler``, or a new LocalCluster of ``workers`` processes on loopback."""
    if client is not None:
        yield client, threads
        return
    from distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            c = Client(scheduler, timeout="10s")
        except OSError as exc:
            raise InputError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None
        with c:
            yield c, threads
        return
    n_cores = cores()
    n = workers if workers is not None else max(1, min(n_cores, n_scans))
    per = threads if threads is not None else max(1, n_cores // n)
    # one task per worker process at a time, its compiled kernels on `per` threads:
    # workers x threads = cores; BLAS single-threaded
    env = {"NUMBA_NUM_THREADS": str(per), "OMP_NUM_THREADS": "1",
           "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                           host="127.0.0.1", dashboard_address=None, env=env,
                           silence_logs=50)
    try:
        with Client(cluster) as c:
            yield c, per
    finally:
        cluster.close()


def measure_many(scans, rig, *, measure: str = "none", output=None, force: bool = False,
                 client=None, scheduler: str | None = None, workers: int | None = None,
                 threads: int | None = None, progress=None, options: BatchOptions | None = None,
                 **option_values):
    """Decode, reconstruct and measure many scans, on Dask or in this process.

    Parameters
    ----------
    scans : str, path-like or a sequence of them
        Scan folders, glob patterns or list files (see
        :func:`telefringe.batch.scans.expand_scans`).
    rig : path-like (rig.json) or Rig / RigCalibration
        Loaded once and sent once to each worker.
    measure : {"none", "bga", "plate", "sphere", "steps"}
    output : path-like or None
        Folder for the table (``results.parquet``, ``results.csv``) and each scan's
        outputs (``scans/<name>/``: points.npz, height map, measurement.json, bga.csv,
        row.json); created if absent (its parent must exist). None: nothing is written,
        the table is only returned (and nothing can be resumed).
    force : bool
        Redo scans whose outputs are complete and current (by default they are reused:
        same images, rig and options).
    client : distributed.Client, optional
        Run on this client's cluster.
    scheduler : str, optional
        Address of a running Dask scheduler (``tcp://host:8786``).
    workers : int, optional
        Worker processes of the LocalCluster started otherwise (default: the cores, at
        most one per scan). ``0``: no Dask, every scan in this process, one after another.
    threads : int, optional
        Compiled-kernel (numba) threads per task (default: cores / workers for a
        LocalCluster; the workers' own setting on another cluster).
    progress : callable, optional
        ``progress(done, total, row)`` after each scan.
    options : BatchOptions, optional; or its fields as keywords (``rows=24``, ...).
        A two-camera rig's scans: ``second="../camera_2"`` (each scan's second camera's
        folder, relative to it), matched as ``telefringe reconstruct --second`` does.

    Returns
    -------
    pandas.DataFrame
        A row per scan, in the order given: ``scan``, ``path``, ``status`` ("ok" or
        "failed"), ``error`` (one line), ``reused``, ``measure``, ``points``, timings
        (``t_*_s``), ... and the measurement's figures with their uncertainties as
        ``<measure>.<field>`` (see :data:`telefringe.batch.table.FIXED_TYPES`).

    Raises
    ------
    InputError
        Bad scans argument, rig, options or output folder (nothing is run). A scan that
        fails does not raise: its row says why.
    """
    if options is None:
        options = BatchOptions(measure=measure, **option_values)
    elif option_values or measure != "none":
        raise InputError("give either options or option keywords, not both")
    if workers is not None and workers < 0:
        raise InputError(f"workers must be >= 0, got {workers}")
    if threads is not None and threads < 1:
        raise InputError(f"threads must be >= 1, got {threads}")
    if isinstance(scans, (str, os.PathLike)):
        scans = [scans]
    paths = expand_scans(scans)
    names = scan_names(paths)
    rig_obj, digest = load_batch_rig(rig)
    n_cams = len(getattr(getattr(rig_obj, "rig", rig_obj), "cameras", ()))
    if options.second is not None and n_cams < 2:
        raise InputError(f"second ({options.second}) needs a rig with two cameras (camera "
                         f"and camera_2), this one has {n_cams}")
    out = None
    if output is not None:
        out = Path(output)
        if out.exists() and not out.is_dir():
            raise InputError(f"{out}: is a file, expected an output folder")
        if not out.parent.is_dir():
            raise InputError(f"{out}: the folder {out.parent} does not exist")
        out.mkdir(exist_ok=True)
    jobs = [ScanJob(path=str(p), name=n,
                    output=None if out is None else str(out / "scans" / n), force=force,
                    rig_digest=digest) for p, n in zip(paths, names, strict=True)]
    if out is None:
        return _run_all(jobs, options, rig_obj, digest, None, client, scheduler, workers,
                        threads, progress)
    (out / "scans").mkdir(exist_ok=True)
    with _lock(out):
        return _run_all(jobs, options, rig_obj, digest, out, client, scheduler, workers,
                        threads, progress)


def _run_all(jobs, options, rig_obj, digest, out, client, scheduler, workers, threads,
             progress):
    rows: list[dict | None] = [None] * len(jobs)
    journal = None if out is None else Journal(out)
    done = 0
    finished = False

    def finish(i, row):
        nonlocal done
        rows[i] = row
        done += 1
        if journal is not None:
            journal.append(row)
        if progress is not None:
            progress(done, len(jobs), row)

    try:
        if workers == 0 and client is None and scheduler is None:
            install_rig(digest, rig_obj)
            try:
                opts = options if threads is None else _with_threads(options, threads)
                for i, job in enumerate(jobs):
                    finish(i, run_scan(job, opts))
            finally:
                remove_rig(digest)
        else:
            with _client(client, scheduler, workers, len(jobs), threads) as (c, per):
                _on_dask(c, jobs, _with_threads(options, per), rig_obj, digest, finish)
        frame = to_frame(rows)
        if out is not None:
            write_table(out, frame)
            _remove_leftovers(out / "scans")
        finished = True
        return frame
    finally:
        if journal is not None:
            journal.close(remove=finished)


def _with_threads(options: BatchOptions, n: int | None) -> BatchOptions:
    from dataclasses import replace

    return options if n is None else replace(options, numba_threads=int(n))


def _on_dask(c, jobs, options, rig_obj, digest, finish) -> None:
    from distributed import as_completed

    from telefringe.batch._dask import RigPlugin

    plugin = RigPlugin(digest, rig_obj)
    c.register_plugin(plugin, name=plugin.name)
    try:
        token = f"{time.time_ns():x}"
        futures = {}
        for i, job in enumerate(jobs):
            f = c.submit(run_scan, job, options, key=f"telefringe-scan-{token}-{i}",
                         pure=False)
            futures[f.key] = (i, f)
        for f in as_completed([f for _, f in futures.values()]):
            i, _ = futures.pop(f.key)
            try:
                row = f.result()
            except Exception as exc:  # noqa: BLE001 - e.g. KilledWorker: the scan's row
                from telefringe.batch.job import _one_line, _row

                row = _row(jobs[i], options, status="failed", output="",
                           error=f"the worker running this scan died ({_one_line(exc)})")
                row["worker"] = ""
            f.release()
            finish(i, row)
    finally:
        with contextlib.suppress(Exception):
            c.unregister_worker_plugin(plugin.name)


def _remove_leftovers(folder: Path) -> None:
    """Remove the hidden ``.*.part`` folders a killed worker left (no task is running)."""
    for p in folder.glob(".*.part"):
        shutil.rmtree(p, ignore_errors=True)
