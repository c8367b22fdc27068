"""Batch throughput: scans per minute on a Dask LocalCluster with 1 and 2 workers against
the plain loop in one process, and Dask's overhead per scan.

Usage: python benchmarks/batch.py [--scans 16] [--measure sphere] [--keep DIR]

One scan of the fast virtual rig (26 images of 320 x 256, 8 bit: u and v fringes, white,
black; a sphere on a plane) is rendered once and copied into ``--scans`` scan folders;
the rig.json carries the projector's nonlinearity model (learned once, as a calibration
does). Each configuration runs the whole batch (decode -> reconstruct -> measure, every
output written: points.npz, height map, measurement.json, the table) after a warm-up
batch of as many scans as workers (compiled kernels loaded in every process), with
``force`` (nothing reused):

- plain loop: ``measure_many(..., workers=0)``, one scan after another in this process,
  numba on every core;
- LocalCluster, 1 worker process (numba on every core) and 2 worker processes (numba on
  cores / 2 threads each): ``measure_many(..., client=...)``.

Printed per configuration: wall time of the batch (minimum of --runs), scans per minute,
and CPU time (of this process, which also runs the local scheduler, and of the
workers). Dask's overhead per scan is the 1-worker
wall time minus the plain loop's, per scan, relative to the plain loop's time per scan
(goal: at most 5 %). The cluster's start-up (once per batch) is printed apart. The
machine may be shared: compare minima.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
import warnings
from pathlib import Path


def _make(root: Path, n: int) -> list[str]:
    from telefringe.fringes.decode import decode
    from telefringe.io.rig_json import bare_rig_json
    from telefringe.io.scan_json import write_scan
    from telefringe.simulate.presets import get_preset
    from telefringe.simulate.render import default_groups, render_scan
    from telefringe.simulate.scenes import make_scene

    vrig = get_preset("fast")
    scan, _ = render_scan(vrig, make_scene("sphere"), default_groups(vrig), seed=0)
    coords = decode(scan)
    models = {(ax, m.periods, 4): m for ax, a in coords.axes.items()
              for m in a.phase_errors.models}
    (root / "rig.json").write_text(json.dumps(bare_rig_json(vrig.rig, phase_errors=models)))
    (root / "scan_0").mkdir()
    write_scan(root / "scan_0" / "scan", scan)
    for k in range(1, n):
        shutil.copytree(root / "scan_0", root / f"scan_{k}")
    return [str(root / f"scan_{k}" / "scan") for k in range(n)]


def _cpu(client) -> float:
    return sum(client.run(time.process_time).values()) if client is not None else 0.0


def _run(scans, rig, out, measure, runs, *, client=None, threads=None):
    from telefringe.batch import measure_many

    kw = {"measure": measure, "force": True}
    out.mkdir(parents=True, exist_ok=True)
    n_warm = 1 if client is None else len(client.scheduler_info()["workers"])
    measure_many(scans[:n_warm], rig, output=out / "warm", client=client,
                 workers=0 if client is None else None, threads=threads, **kw)
    best = None
    for _ in range(runs):
        c0, w0 = time.process_time(), _cpu(client)
        t0 = time.perf_counter()
        frame = measure_many(scans, rig, output=out / "run", client=client,
                             workers=0 if client is None else None, threads=threads, **kw)
        t = time.perf_counter() - t0
        cpu = (time.process_time() - c0, _cpu(client) - w0)
        assert (frame["status"] == "ok").all(), frame["error"].tolist()
        if best is None or t < best[0]:
            best = (t, cpu, frame)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=int, default=16)
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--measure", default="sphere")
    ap.add_argument("--keep", type=Path, default=None)
    args = ap.parse_args()

    import numba
    from distributed import Client, LocalCluster

    from telefringe.batch.run import cores

    tmp = tempfile.TemporaryDirectory()
    root = args.keep if args.keep is not None else Path(tmp.name)
    root.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    scans = _make(root, args.scans)
    rig = root / "rig.json"
    n_cores = cores()
    print(f"batch throughput: {args.scans} scans (fast rig, 26 images of 320 x 256), measure "
          f"{args.measure}, {n_cores} cores, load average {os.getloadavg()[0]:.2f} (the "
          f"machine may be shared: minima of {args.runs} runs); scans made in "
          f"{time.perf_counter() - t0:.0f} s")
    results = {}
    t, cpu, frame = _run(scans, rig, root / "loop", args.measure, args.runs,
                         threads=numba.config.NUMBA_NUM_THREADS)
    results["plain loop (1 process)"] = (t, cpu)
    per_stage = frame[["t_read_s", "t_reconstruct_s", "t_measure_s", "t_write_s"]].median()
    for n_workers in (1, 2):
        per = max(1, n_cores // n_workers)
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                                   host="127.0.0.1", dashboard_address=None, silence_logs=50,
                                   env={"NUMBA_NUM_THREADS": str(per),
                                        "OMP_NUM_THREADS": "1"})
            client = Client(cluster)
        start = time.perf_counter() - t0
        try:
            t, cpu, _ = _run(scans, rig, root / f"dask{n_workers}", args.measure, args.runs,
                             client=client)
        finally:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                client.close()
                cluster.close()
        results[f"LocalCluster, {n_workers} worker(s) x {per} numba threads"] = (t, cpu)
        print(f"  (cluster start-up, {n_workers} worker(s): {start:.1f} s, once per batch)")
    print(f"  {'configuration':<44s} {'wall':>8s} {'scans/min':>10s} {'CPU here':>9s} "
          f"{'workers':>8s}")
    for name, (t, cpu) in results.items():
        print(f"  {name:<44s} {t:7.2f}s {60 * args.scans / t:10.1f} {cpu[0]:8.2f}s "
              f"{cpu[1]:7.2f}s")
    print("  (CPU here: this process, with the local scheduler and the client; workers: "
          "the worker processes)")
    loop = results["plain loop (1 process)"][0]
    one = [v for k, v in results.items() if "1 worker" in k][0][0]
    print(f"  Dask's overhead per scan (1 worker vs the plain loop): "
          f"{(one - loop) / args.scans * 1000:+.1f} ms = {(one - loop) / loop:+.1%} "
          f"(goal <= 5 %)")
    print("  per scan in the plain loop (median): "
          + ", ".join(f"{k[2:-2]} {v * 1000:.0f} ms" for k, v in per_stage.items()))
    tmp.cleanup()


if __name__ == "__main__":
    main()
