"""BGA cycle time: one HDR BGA scan, images in memory, measured to its ball table in a
warm process.

Usage: python benchmarks/inspect_bga.py [--runs 5] [--cache DIR] [--baseline SRC]
       [--table OUT.npz] [--compare REF.npz]

(Issue 14 calls it ``benchmarks/inspect.py``: a script of that name in this folder would
shadow the standard library's ``inspect`` for every benchmark run from here.)

The scan: the paper rig (1280 x 1024 camera, 1.3 Mpx), the default BGA (24 x 24 balls at
0.8 mm pitch, 4 missing: 572 balls), u fringes 1/8/64 periods x 4 steps = 12 images at 3
exposures (HDR, 36 images, 8 bit), no white/black. The rig's projector nonlinearity
model is learned once (as a calibration does) and given to the decoder.

Per run (after a warm-up run): decode (the rig's gamma model), triangulate (per-rig
set-up cached), the radiance image (for the highlights) and the fringe-free texture,
measure_bga (default options: the point-spread cap model, highlights), i.e. what
``reconstruct_scan`` + ``measure_bga`` do. Printed: each stage's wall time (minimum and
median of --runs) and process (CPU) time, and the total. The machine may be shared:
the minimum wall time is the figure least disturbed by other jobs, the process time
shows the work done (on 2 threads, up to 2x the wall time).

``--baseline SRC``: also run the same timing with the telefringe source tree at SRC
(e.g. an export of the commit this work started from, ``git archive a1becc3 | tar -x
-C /tmp/tf_start``) in a new process, and print the ratios (wall and CPU). Without it,
the ratio is of CPU time to the figures measured at the start (START_CPU).

``--table OUT.npz`` saves the ball table (every per-ball array of the BGAMeasurement and
its scalars); ``--compare REF.npz`` prints the largest difference of each against a
table saved earlier (e.g. by the commit before a speed change).

The rendered scan is cached in --cache (default: a temporary folder) as scan.npz; the
first run renders it (about a minute).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: measured with this script (--baseline) on commit a1becc3, the start of issue 14: 2
#: threads, a shared machine at load average 16 on 2 cores, so the wall times are
#: inflated; process (CPU) time, median of 3 runs, seconds. Without --baseline the ratio
#: is taken on CPU time against these.
START_CPU = {"decode": 0.118, "triangulate": 0.028, "radiance": 0.131, "measure": 4.310,
             "total": 4.616}

STAGES = ("decode", "triangulate", "radiance", "measure")


def _render(path: Path) -> None:

    from telefringe.fringes.decode import decode
    from telefringe.simulate.presets import HDR_EXPOSURES, get_preset
    from telefringe.simulate.render import default_groups, render_scan
    from telefringe.simulate.scenes import default_bga

    vrig = get_preset("paper")
    bga = default_bga(0)
    scan, _ = render_scan(vrig, bga, default_groups(vrig, axes=("u",)),
                          exposures=HDR_EXPOSURES, white=False, black=False, seed=0)
    fit = decode(scan).axes["u"].phase_errors
    arrays = {f"stack_{i}": s for i, s in enumerate(scan.stacks)}
    groups = [{"axis": g.axis, "periods": int(g.periods), "steps": int(g.steps),
               "exposure": float(g.exposure)} for g in scan.manifest.groups]
    models = [{"periods": int(m.periods), "harmonics": [int(h) for h in m.harmonics],
               "cos": [float(c) for c in m.cos_coef], "sin": [float(s) for s in m.sin_coef]}
              for m in fit.models]
    meta = {"groups": groups, "models": models,
            "projector": [scan.manifest.projector_width, scan.manifest.projector_height],
            "bga": {"rows": bga.rows, "cols": bga.cols, "pitch": bga.pitch,
                    "diameter": bga.ball_diameter}}
    np.savez(path, meta=json.dumps(meta), **arrays)


#: the BGAMeasurement's per-ball arrays compared by --compare
TABLE = ("index", "centre", "sigma_centre", "refined", "apex", "height", "sigma_height",
         "sigma_height_noise", "diameter", "position", "rms", "n_points", "found",
         "pitch_x", "pitch_y")


def _table(m) -> dict:
    t = {k: np.asarray(getattr(m, k)) for k in TABLE}
    t["scalars"] = np.array([m.coplanarity.value, m.psf_variance, m.sigma_psf_variance,
                             m.pitch_error_max, m.grid_angle_deg, m.substrate.offset,
                             *m.substrate.normal, m.substrate.sigma_offset])
    t["not_measured"] = np.array(repr(m.not_measured))
    t["missing"] = np.array(repr(m.missing))
    return t


def _compare(t: dict, ref_path: Path) -> None:
    ref = np.load(ref_path)
    worst = 0.0
    print(f"ball table against {ref_path}:")
    for k in ref.files:
        a, b = ref[k], t[k]
        if a.shape != b.shape:
            print(f"  {k}: shape {b.shape} against {a.shape}")
            worst = np.inf
        elif a.dtype.kind == "f":
            same_nan = np.array_equal(np.isnan(a), np.isnan(b))
            fin = np.isfinite(a) & np.isfinite(b)
            d = float(np.max(np.abs(a[fin] - b[fin]))) if fin.any() else 0.0
            worst = max(worst, d if same_nan else np.inf)
            print(f"  {k:<20s} largest difference {d:.2e}"
                  + ("" if same_nan else "  (NaN at other places)"))
        elif not np.array_equal(a, b):
            print(f"  {k}: differs")
            worst = np.inf
    print(f"  largest difference of any value: {worst:.2e} (mm, mm^2 or deg)")


def _time(path: str, runs: int, table: str | None = None) -> dict:
    """The timing, in this process (with whatever telefringe is importable)."""

    from telefringe.fringes.decode import decode
    from telefringe.fringes.images import fringe_free_image, scan_radiance
    from telefringe.fringes.nonlinearity import PhaseErrorModel
    from telefringe.fringes.scan import PhaseGroup, Scan, ScanManifest
    from telefringe.metrology import BGANominal, measure_bga
    from telefringe.reconstruction.telecentric import triangulate
    from telefringe.simulate.presets import get_preset

    data = np.load(path)
    meta = json.loads(str(data["meta"]))
    groups = tuple(PhaseGroup(**g) for g in meta["groups"])
    stacks = tuple(data[f"stack_{i}"] for i in range(len(groups)))
    man = ScanManifest(meta["projector"][0], meta["projector"][1], groups)
    scan = Scan(man, stacks, max_value=255.0, source="bench")
    phase_errors = {("u", m["periods"], 4): PhaseErrorModel(
        m["periods"], tuple(m["harmonics"]), np.asarray(m["cos"]), np.asarray(m["sin"]))
        for m in meta["models"]}
    rig = get_preset("paper").rig
    b = meta["bga"]
    nominal = BGANominal(rows=b["rows"], cols=b["cols"], pitch_mm=b["pitch"],
                         ball_diameter_mm=b["diameter"])

    def cycle():
        t = {}
        c = {}
        t0, c0 = time.perf_counter(), time.process_time()
        coords = decode(scan, phase_errors=phase_errors)
        t1, c1 = time.perf_counter(), time.process_time()
        cloud = triangulate(rig, coords)
        t2, c2 = time.perf_counter(), time.process_time()
        radiance = scan_radiance(scan)
        fringe_free_image(scan)
        t3, c3 = time.perf_counter(), time.process_time()
        m = measure_bga(cloud, nominal, image=radiance)
        t4, c4 = time.perf_counter(), time.process_time()
        for k, (a, z, ca, cz) in zip(STAGES, ((t0, t1, c0, c1), (t1, t2, c1, c2),
                                               (t2, t3, c2, c3), (t3, t4, c3, c4)),
                                     strict=True):
            t[k], c[k] = z - a, cz - ca
        t["total"], c["total"] = t4 - t0, c4 - c0
        return t, c, m

    cycle()  # warm-up: compiled kernels loaded, per-rig set-up cached
    walls, cpus = [], []
    m = None
    for _ in range(runs):
        t, c, m = cycle()
        walls.append(t)
        cpus.append(c)
    import numba

    if table is not None:
        np.savez(table, **_table(m))
    return {"wall_min": {k: min(w[k] for w in walls) for k in walls[0]},
            "wall_median": {k: statistics.median(w[k] for w in walls) for k in walls[0]},
            "cpu_median": {k: statistics.median(c[k] for c in cpus) for k in cpus[0]},
            "balls": int(m.n_balls), "coplanarity_mm": float(m.coplanarity.value),
            "threads": numba.get_num_threads()}


def _run_timing(path: Path, runs: int, src: str | None, table: Path | None = None) -> dict:
    env = dict(os.environ)
    if src is not None:
        env["PYTHONPATH"] = str(Path(src) / "src")
    extra = [] if table is None else ["--save-table", str(table)]
    out = subprocess.run([sys.executable, __file__, "--time", str(path), "--runs", str(runs),
                          *extra], check=True, capture_output=True, text=True, env=env)
    return json.loads(out.stdout.strip().splitlines()[-1])


def _print(label: str, r: dict) -> None:
    print(f"{label}: {r['balls']} balls, coplanarity {r['coplanarity_mm'] * 1000:.2f} um, "
          f"{r['threads']} threads")
    print(f"  {'stage':<34s} {'wall min':>9s} {'wall med':>9s} {'CPU med':>9s}")
    for k in (*STAGES, "total"):
        name = {"decode": "decode (the rig's gamma model)",
                "triangulate": "triangulate (set-up cached)",
                "radiance": "radiance + texture images",
                "measure": "measure_bga (ball table)", "total": "total"}[k]
        print(f"  {name:<34s} {r['wall_min'][k]:8.3f}s {r['wall_median'][k]:8.3f}s "
              f"{r['cpu_median'][k]:8.3f}s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--cache", type=Path, default=None)
    ap.add_argument("--baseline", default=None, help="A telefringe source tree to compare.")
    ap.add_argument("--table", type=Path, default=None,
                    help="Save this tree's ball table here (.npz).")
    ap.add_argument("--compare", type=Path, default=None,
                    help="Compare this tree's ball table with one saved by --table.")
    ap.add_argument("--time", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--save-table", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.time is not None:
        print(json.dumps(_time(args.time, args.runs, args.save_table)))
        return
    tmp = tempfile.TemporaryDirectory()
    folder = args.cache if args.cache is not None else Path(tmp.name)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "scan.npz"
    if not path.exists():
        t0 = time.perf_counter()
        _render(path)
        print(f"rendered the scan in {time.perf_counter() - t0:.0f} s ({path})")
    print(f"BGA cycle time, one HDR scan (36 images of 1280 x 1024, 8 bit) in memory, "
          f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f} (the machine may "
          f"be shared: compare minima)")
    table = args.table
    if table is None and args.compare is not None:
        table = Path(tmp.name) / "table.npz"
    now = _run_timing(path, args.runs, None, table)
    _print("this tree", now)
    if args.compare is not None:
        _compare(dict(np.load(table)), args.compare)
    if args.baseline is not None:
        base = _run_timing(path, args.runs, args.baseline)
        _print(f"baseline ({args.baseline})", base)
        print("ratio to the baseline (time before / time now): minimum wall "
              + ", ".join(f"{k} {base['wall_min'][k] / now['wall_min'][k]:.1f}x"
                          for k in (*STAGES, "total"))
              + "; median CPU "
              + ", ".join(f"{k} {base['cpu_median'][k] / now['cpu_median'][k]:.1f}x"
                          for k in (*STAGES, "total")))
    else:
        print("ratio to the start of issue 14 (a1becc3, CPU time measured earlier, see "
              "START_CPU): "
              + ", ".join(f"{k} {START_CPU[k] / now['cpu_median'][k]:.1f}x"
                          for k in (*STAGES, "total")))
    goal = now["wall_min"]["total"]
    print(f"target <= 1 s wall on 2 cores: {'met' if goal <= 1.0 else 'NOT met'} "
          f"({goal:.2f} s)")
    tmp.cleanup()


if __name__ == "__main__":
    main()
