"""Speed of the default reconstruct's decode: the projector's gamma LEARNED from the scan.

Usage: python benchmarks/learn_gamma.py [--scan DIR] [--preset paper] [--scene tilted-plane]
                                        [--runs 3] [--axes u,v]

Without ``--scan`` renders one scan of the virtual rig ``--preset`` (4 steps x 1/8/64
periods along u, 1/8/48 along v, as ``telefringe simulate scan``) and keeps its truth;
with ``--scan`` reads a scan folder (e.g. one written by ``telefringe simulate scan``; its
truth from ``DIR/../truth/scan.npz`` when there). Then, as the median (wall) and the
minimum (CPU: ``time.process_time``, all threads) of ``--runs`` runs after a warm-up,
decodes it three ways:

- ``learned``: the default (no gamma model in the rig), the projector's phase-error model
  learned from the scan's own fringes (telefringe.fringes.nonlinearity);
- ``rig's model``: the same models given (as a rig.json carrying them gives them);
- ``off``: no gamma correction;

and prints Mpx/s (wall; the machine may be shared: see the load printed) and CPU seconds
per Mpx. The learning's own cost is ``learned`` less ``rig's model``. With a truth, also
the decoded projector coordinates' RMS error against it (valid pixels, in units of the
median predicted sigma): the learned model must not make it grow.
Run it on two versions (PYTHONPATH) for a before/after.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import time
from pathlib import Path

import numpy as np


def _load() -> str:
    try:
        up = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    except OSError:
        up = "load average " + ", ".join(f"{v:.2f}" for v in os.getloadavg())
    return up


def _timed(fn, runs):
    walls, cpus, out = [], [], None
    for _ in range(runs):
        c0, t0 = time.process_time(), time.perf_counter()
        out = fn()
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    return statistics.median(walls), min(cpus), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scan", type=Path, default=None)
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--scene", default="tilted-plane")
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()

    import numba

    import telefringe
    from telefringe.fringes.decode import decode

    truth = None
    if args.scan is None:
        from telefringe.simulate.presets import get_preset
        from telefringe.simulate.render import default_groups, render_scan
        from telefringe.simulate.scenes import make_scene

        vrig = get_preset(args.preset)
        scan, tr = render_scan(vrig, make_scene(args.scene), default_groups(vrig),
                               white=False, black=False, seed=0)
        truth = {"u": tr.u_p, "v": tr.v_p}
        what = f"{args.preset} rig, scene {args.scene} (rendered)"
    else:
        from telefringe.io.scan_json import read_scan

        scan = read_scan(args.scan)
        npz = args.scan.parent / "truth" / "scan.npz"
        if npz.exists():
            with np.load(npz) as d:
                truth = {"u": d["u_p"], "v": d["v_p"]}
        what = str(args.scan)
    rows, cols = scan.stacks[0].shape[1:]
    mpx = rows * cols / 1e6
    print(f"telefringe from {Path(telefringe.__file__).parent}")
    print(f"{what}: {sum(s.shape[0] for s in scan.stacks)} images of {cols} x {rows} "
          f"({mpx:.2f} Mpx), {numba.get_num_threads()} threads, {os.cpu_count()} CPUs")
    print(f"  {_load()}")

    learned = decode(scan)  # warm-up (numba caches load)
    steps = {(g.axis, int(g.periods)): int(g.steps) for g in scan.manifest.groups
             if hasattr(g, "steps")}
    models = {(ax, m.periods, steps[(ax, m.periods)]): m
              for ax, co in learned.axes.items() if co.phase_errors is not None
              for m in co.phase_errors.models}
    decode(scan, phase_errors=models)
    decode(scan, gamma_correction=False)
    res = {}
    for name, kw in (("learned (default)", {}), ("rig's model", {"phase_errors": models}),
                     ("off", {"gamma_correction": False})):
        res[name] = _timed(lambda kw=kw: decode(scan, **kw), args.runs)
    print(f"decode, median wall / min CPU of {args.runs} runs:")
    for name, (wall, cpu, _) in res.items():
        print(f"  {name:<20s} wall {wall:7.3f} s {mpx / wall:7.2f} Mpx/s   "
              f"CPU {cpu:7.3f} s {cpu / mpx:7.3f} CPU s/Mpx")
    wl, cl, _ = res["learned (default)"]
    wr, cr, _ = res["rig's model"]
    print(f"  learning the model alone: wall {wl - wr:.3f} s, CPU {cl - cr:.3f} s "
          f"({(cl - cr) / mpx:.3f} CPU s/Mpx)")
    for ax, co in learned.axes.items():
        fit = co.phase_errors
        if fit is None:
            continue
        print(f"  axis {ax}: learned {[m.harmonics for m in fit.models]}, model RMS "
              f"{[round(m.rms, 5) for m in fit.models]} rad, pair residual RMS "
              f"{fit.residual_rms:.5f} rad, {fit.n_samples} samples")
    if truth is not None:
        print("against the truth (valid pixels; RMS error / median predicted sigma):")
        for name in ("learned (default)", "off"):
            out = res[name][2]
            for ax, co in out.axes.items():
                ok = co.valid & np.isfinite(truth[ax])
                err = (co.coordinate - truth[ax])[ok]
                sig = float(np.median(co.sigma[ok]))
                rms = float(np.sqrt(np.mean(err ** 2)))
                print(f"  {name:<20s} {ax}: {ok.mean():6.1%} valid, RMS error {rms:.6f} px "
                      f"= {rms / sig:.4f} sigma, median |error| "
                      f"{np.median(np.abs(err)):.6f} px")
    print(f"  {_load()}")


if __name__ == "__main__":
    main()
