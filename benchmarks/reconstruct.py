"""Reconstruction speed: scan folder (12 images 1280 x 1024) + rig -> points.

Usage: python benchmarks/reconstruct.py [--runs 5] [--scene tilted-plane] [--keep DIR]
                                        [--no-cold-start] [--no-bytecode-cache]

Renders one scan of the paper rig (4 steps x 1/8/64 periods along u, no white/black: 12
images of 1280 x 1024, 8 bit), writes it as a scan folder with the TRUE rig's rig.json,
then prints the load average (the machine is shared: figures move with it) and, as the
median of ``--runs`` runs after a warm-up:

- the time of each stage in-process: reading the 12 PNGs, decoding (with and without the
  data-driven gamma correction), the per-rig set-up (once per rig and image size),
  triangulation, height map, writing the outputs;
- megapixels (camera pixels) per second for triangulation alone and for decode +
  triangulate from images in memory: gamma correction learned from the scan, off, and
  with the rig's model (learned once, as a calibration does; here from another scan);
- where the CPU time of decode + triangulate goes, on one thread: the fused kernel alone
  (u_p and mask) without and with the rig's gamma model, the full ``decode()`` without
  correction, with the model as a Fourier series (the default) and from its tables, and
  triangulation;
- the cold start of ``telefringe reconstruct`` for one scan (a new process, numba caches
  warm): gamma learned from the scan, off, and from a rig.json that carries the model
  (wall, CPU of the process, and wall less the main thread's wait for a CPU, which on a
  shared machine approximates an idle one); and its split by stage, one after the other
  (the command overlaps some: it reads the images while the rig and numba load, and
  makes the height map and writes the X3P and PNG while it writes points.npz and the
  PLY).

What bounds each figure:

- triangulation: its arithmetic (two divisions, ~150 flops per pixel, vectorised). Per
  pixel the u-only kernel reads the line offsets a, b, u_p, sigma_u_p and the mask
  (33 B) and writes x, y, z, sigma and the flags and mask bytes (34 B): ~88 MB per
  1.3 Mpx scan, but a slice that stays in cache takes the same CPU time per pixel as the
  whole frame (benchmarks/triangulate_identity.py). The "memory floor" line copies the
  same number of bytes (a (n, 4) float64 array into another) for scale. The per-rig
  set-up (undistorting every camera pixel) is paid once per rig and shape.
- decode + triangulate: decoding (telefringe.fringes.decode: wrapped phase, unwrapping and, by
  default, fitting and removing the projector's gamma from the fringes; with the rig's
  model, its Fourier series, cut per tile of pixels to what the result needs); writing
  the decoder's output planes (u_p, sigma, modulation, background: 8 bytes each per
  pixel, and the flags) costs about 2 ms CPU per plane per 1.3 Mpx.
- cold start: Python + numpy + typer imports (rich only when it prints: not with -q),
  importing numba (~0.25 s CPU; the command loads the cached kernels without numba's
  registries of implementations, which would import scipy.linalg: -0.1 to -0.3 s), the
  ~7 kernels on the path (~0.02-0.05 s each), decoding, the noise estimate (its chi^2
  tails from a table, not scipy.special), triangulating, the outputs, and the process's
  end (the command freezes the garbage collector at its end: the shutdown's collections
  walked numba's objects for ~0.4 s CPU); see the split. The cold runs use bytecode caches
  (as an installed package has them) unless --no-bytecode-cache: without them (e.g.
  PYTHONDONTWRITEBYTECODE set) every run compiles telefringe's ~60 modules again.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _median_time(fn, runs):
    ts = []
    out = None
    for _ in range(runs):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts), out


def _load() -> str:
    return "load average " + ", ".join(f"{v:.2f}" for v in os.getloadavg())


def _write_rig(path: Path, rig, phase_errors=None) -> None:
    """A rig.json of the true rig (no calibration report), with the projector's
    nonlinearity models when given."""
    import json

    from telefringe.io.rig_json import bare_rig_json

    path.write_text(json.dumps(bare_rig_json(rig, reference_pose="truth",
                                             phase_errors=phase_errors)))


# The cold start split: what 'telefringe reconstruct' does, stage by stage, in a new process
_SPLIT = r"""
import sys, time
t0 = time.perf_counter()
c0 = time.process_time()
marks = []
def mark(name):
    marks.append((name, time.perf_counter(), time.process_time()))
import telefringe.cli
from telefringe.io.rig_json import load_rig
from telefringe.io.scan_json import read_scan
from telefringe.fringes.decode import decode
from telefringe.reconstruction.telecentric import triangulate
from telefringe.reconstruction.heightmap import height_map
from telefringe.io.figures.heightmap_png import write_height_png
from telefringe.io.ply import write_ply
from telefringe.io.points_npz import write_points
from telefringe.io.tiff import write_height_tiff
from telefringe.io.x3p import write_height_x3p
mark("imports (cli, rig.json reader, decode, reconstruct)")
from telefringe.cli.reconstruct import _light_numba_cache_loads
_light_numba_cache_loads()  # as the command: cached kernels without numba's registries
from telefringe.geometry._distortion_kernels import undistort_point
undistort_point(0.0, 0.0, 0.0, 0.0, 0.0)
mark("numba start-up (one cached function)")
calib = load_rig(sys.argv[1])
rig = calib.rig
data = read_scan(sys.argv[2])
mark("read rig.json + 12 PNGs")
mode = sys.argv[4]
coords = decode(data, gamma_correction=mode != "off",
                phase_errors=calib.phase_errors if mode == "rig" else None)
mark({"off": "decode, no gamma correction", "fit": "decode, gamma learned from the scan",
      "rig": "decode, the rig's gamma model"}[mode])
cloud = triangulate(rig, coords)
mark("triangulate (incl. per-rig set-up)")
hm = height_map(cloud)
mark("height map")
from telefringe.io.reconstruction_folder import preview_map as _preview
out = sys.argv[3]
write_points(out + "/points.npz", cloud)
mark("write points.npz")
write_ply(out + "/cloud.ply", cloud)
mark("write cloud.ply")
write_height_tiff(out + "/heightmap.tif", hm)
mark("write heightmap.tif")
write_height_x3p(out + "/heightmap.x3p", hm)
mark("write heightmap.x3p")
import PIL.Image, PIL.ImageDraw
mark("import Pillow")
write_height_png(out + "/heightmap.png", _preview(hm))
mark("draw + write heightmap.png")
prev, cprev = t0, c0
print(f"    {'':<44s}   wall    CPU")
for name, t, c in marks:
    print(f"    {name:<44s} {t - prev:6.2f} {c - cprev:6.2f} s")
    prev, cprev = t, c
print(f"    {'total (after the interpreter started)':<44s} {prev - t0:6.2f} {cprev - c0:6.2f} s")
"""


# 'telefringe reconstruct' in a new process as the command line runs it, which then writes
# to argv[1] its CPU time and its main thread's time spent waiting for a CPU (Linux)
_COLD = r"""
import sys, time
from telefringe.cli import main
stats = sys.argv[1]
sys.argv = ["telefringe", *sys.argv[2:]]
rc = main()  # as the command runs it (no argv: the process ends after it)
try:
    with open("/proc/thread-self/schedstat") as f:
        wait = int(f.read().split()[1]) / 1e9
except OSError:
    wait = float("nan")
with open(stats, "w") as f:
    f.write(f"{time.process_time()} {wait}")
sys.exit(rc)
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--scene", default="tilted-plane")
    ap.add_argument("--keep", type=Path, default=None, help="Keep the scan folder here.")
    ap.add_argument("--no-cold-start", action="store_true",
                    help="Skip the cold-start runs (new processes).")
    ap.add_argument("--no-bytecode-cache", action="store_true",
                    help="Cold starts as the environment says (with PYTHONDONTWRITEBYTECODE "
                         "set, every run compiles telefringe's modules from source) instead "
                         "of with bytecode caches, as an installed package has them.")
    args = ap.parse_args()

    import numba

    from telefringe.fringes.decode import decode
    from telefringe.io.figures.heightmap_png import write_height_png
    from telefringe.io.ply import write_ply
    from telefringe.io.points_npz import write_points
    from telefringe.io.reconstruction_folder import preview_map as _preview
    from telefringe.io.scan_json import read_scan, write_scan
    from telefringe.io.tiff import write_height_tiff
    from telefringe.reconstruction.heightmap import height_map
    from telefringe.reconstruction.telecentric import Triangulator, triangulate
    from telefringe.simulate.presets import get_preset
    from telefringe.simulate.render import default_groups, render_scan
    from telefringe.simulate.scenes import make_scene

    vrig = get_preset("paper")
    groups = default_groups(vrig, axes=("u",))
    scan, _ = render_scan(vrig, make_scene(args.scene), groups, white=False, black=False,
                          seed=0)
    n_img = sum(s.shape[0] for s in scan.stacks)
    rows, cols = scan.stacks[0].shape[1:]
    mpx = rows * cols / 1e6
    tmpdir = tempfile.TemporaryDirectory()
    root = args.keep if args.keep is not None else Path(tmpdir.name)
    root.mkdir(parents=True, exist_ok=True)
    folder = root / "scan"
    write_scan(folder, scan, force=True)
    _write_rig(root / "rig.json", vrig.rig)
    # the nonlinearity learned once (as a calibration does), here from another scan
    other, _ = render_scan(vrig, make_scene(args.scene), groups, white=False, black=False,
                           seed=1)
    learned = {("u", m.periods, 4): m for m in decode(other).axes["u"].phase_errors.models}
    _write_rig(root / "rig_gamma.json", vrig.rig, learned)
    print(f"paper rig, scene {args.scene}: {n_img} images of {cols} x {rows} "
          f"({mpx:.2f} Mpx), {numba.get_num_threads()} threads, median of {args.runs} runs, "
          f"{os.cpu_count()} CPUs, {_load()}")

    # warm-up (numba caches load, per-rig set-up cached)
    data = read_scan(folder)
    coords = decode(data)
    cloud = triangulate(vrig.rig, coords)
    height_map(cloud)

    t_read, data = _median_time(lambda: read_scan(folder), args.runs)
    t_dec, coords = _median_time(lambda: decode(data), args.runs)
    t_dec_ng, coords_ng = _median_time(lambda: decode(data, gamma_correction=False),
                                       args.runs)
    t_dec_rig, _ = _median_time(lambda: decode(data, phase_errors=learned), args.runs)
    t_setup, _ = _median_time(lambda: Triangulator.for_shape(vrig.rig, (rows, cols)),
                              args.runs)
    runs_tri = max(args.runs, 9)
    t_tri, cloud = _median_time(lambda: triangulate(vrig.rig, coords), runs_tri)
    # the same bytes as the kernel moves, copied: (n, 4) float64 in and out
    src_dst = (np.ones((rows * cols, 4)), np.empty((rows * cols, 4)))
    t_floor, _ = _median_time(lambda: np.copyto(src_dst[1], src_dst[0]), runs_tri)
    # CPU time on one thread: a figure that other jobs on the machine inflate less
    n_thr = numba.get_num_threads()
    numba.set_num_threads(1)
    cpu = []
    for _ in range(runs_tri):
        t0 = time.process_time()
        triangulate(vrig.rig, coords)
        cpu.append(time.process_time() - t0)
    numba.set_num_threads(n_thr)
    t_cpu = statistics.median(cpu)
    # decode (the rig's gamma model) + triangulate, CPU time of both threads, minimum of
    # the runs: the work done, what other jobs on a shared machine inflate least
    cpu_dt = []
    for _ in range(runs_tri):
        t0 = time.process_time()
        triangulate(vrig.rig, decode(data, phase_errors=learned))
        cpu_dt.append(time.process_time() - t0)
    t_cpu_dt = min(cpu_dt)
    t_hm, hm = _median_time(lambda: height_map(cloud), args.runs)
    # where the CPU time goes: one thread, CPU time, minimum of the runs
    from telefringe.fringes import fast as _fast
    from telefringe.fringes.fast import decode_axis_fast

    per = [int(g.periods) for g in data.manifest.groups]
    rig_models = [learned[("u", p, 4)] for p in per]
    length = data.manifest.axis_length("u")

    def with_tables():
        old = _fast.TABLE_MIN_TERMS
        _fast.TABLE_MIN_TERMS = 0
        try:
            return decode(data, phase_errors=learned)
        finally:
            _fast.TABLE_MIN_TERMS = old

    split = (
        ("fused kernel, u_p + mask only, no correction",
         lambda: decode_axis_fast(data.stacks, per, 4, length=length)),
        ("fused kernel, u_p + mask only, rig's gamma",
         lambda: decode_axis_fast(data.stacks, per, 4, length=length,
                                  phase_errors=rig_models)),
        ("decode(), gamma correction off", lambda: decode(data, gamma_correction=False)),
        ("decode(), rig's gamma (series, the default)",
         lambda: decode(data, phase_errors=learned)),
        ("decode(), rig's gamma from the tables", with_tables),
        ("triangulate", lambda: triangulate(vrig.rig, coords)),
    )
    numba.set_num_threads(1)
    cpu_split = []
    for name, fn in split:
        fn()
        ts = []
        for _ in range(runs_tri):
            t0 = time.process_time()
            fn()
            ts.append(time.process_time() - t0)
        cpu_split.append((name, min(ts)))
    numba.set_num_threads(n_thr)

    def write():
        with tempfile.TemporaryDirectory() as d:
            d = Path(d)
            write_points(d / "points.npz", cloud)
            write_ply(d / "cloud.ply", cloud)
            write_height_tiff(d / "heightmap.tif", hm)
            write_height_png(d / "heightmap.png", _preview(hm))

    t_write, _ = _median_time(write, max(1, args.runs // 2))

    def line(name, t, n_mpx=mpx):
        print(f"  {name:<48s} {t * 1000:8.1f} ms  {n_mpx / t:8.1f} Mpx/s")

    print("stages:")
    line(f"read {n_img} PNG images", t_read)
    line("decode (gamma correction on, default)", t_dec)
    line("decode (gamma correction off)", t_dec_ng)
    line("decode (the rig's gamma model, learned once)", t_dec_rig)
    line("per-rig set-up (Triangulator, once per rig)", t_setup)
    line("triangulate (set-up cached)", t_tri)
    line("triangulate, CPU time on 1 thread", t_cpu)
    line("memory floor: copy the kernel's bytes", t_floor)
    line("height map", t_hm)
    line("write points.npz, PLY, TIFF, PNG", t_write)
    print(f"end to end ({_load()}):")
    line("triangulation alone", t_tri)
    line("decode + triangulate (gamma correction on)", t_dec + t_tri)
    line("decode + triangulate (gamma correction off)", t_dec_ng + t_tri)
    line("decode + triangulate (the rig's gamma model)", t_dec_rig + t_tri)
    line("read + decode + triangulate (gamma on)", t_read + t_dec + t_tri)
    line("decode + triangulate (rig's gamma), CPU s (min)", t_cpu_dt)
    print(f"    (per CPU-second: on {n_thr} idle cores at most {n_thr * mpx / t_cpu_dt:.0f} "
          "Mpx/s)")
    print(f"where the CPU time goes (1 thread, CPU time, min of {runs_tri}; {_load()}):")
    for name, t in cpu_split:
        print(f"  {name:<48s} {t * 1000:8.1f} ms  {mpx / t:8.1f} Mpx/CPU-s")
    print(f"  valid points: {cloud.count} ({cloud.count / (rows * cols):.1%}), median sigma_z "
          f"{np.nanmedian(cloud.sigma_z) * 1000:.2f} um")

    if not args.no_cold_start:
        # bytecode caches as an installed package has them (pip compiles the modules; an
        # editable install writes them at the first import), unless the environment
        # forbids writing them (PYTHONDONTWRITEBYTECODE): then in a folder of their own,
        # written by a first run that is not timed
        env = dict(os.environ)
        caches = "as the environment has them"
        if not args.no_bytecode_cache and env.pop("PYTHONDONTWRITEBYTECODE", None):
            env["PYTHONPYCACHEPREFIX"] = str(root / "pycache")
            caches = "on (PYTHONDONTWRITEBYTECODE set here: in a temporary folder)"
        subprocess.run([sys.executable, "-c", _COLD, str(root / "cold_stats.txt"), "-q",
                        "reconstruct", str(folder), "--rig", str(root / "rig_gamma.json"),
                        "-o", str(root / "out"), "--force"], check=True, env=env)
        imp = []
        for _ in range(3):
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-c", "import telefringe.cli"], check=True,
                           env=env)
            imp.append(time.perf_counter() - t0)
        print(f"cold start ({_load()}), median of 3, bytecode caches {caches}:")
        print(f"  python -c 'import telefringe.cli': {statistics.median(imp):.2f} s")
        stats = root / "cold_stats.txt"
        exe = [sys.executable, "-c", _COLD, str(stats)]
        cmd = exe + ["-q", "reconstruct", str(folder), "--rig", str(root / "rig.json"),
                     "-o", str(root / "out"), "--force"]
        rig_gamma = [cmd[:cmd.index("--rig") + 1] + [str(root / "rig_gamma.json")]
                     + cmd[cmd.index("--rig") + 2:]]
        for label, full in (("", cmd), (" --no-gamma-correction",
                                        cmd + ["--no-gamma-correction"]),
                            (" (rig.json with the gamma model)", rig_gamma[0])):
            ts, cs, qs = [], [], []
            for _ in range(3):
                r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
                t0 = time.perf_counter()
                subprocess.run(full, check=True, env=env)
                ts.append(time.perf_counter() - t0)
                r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
                cs.append(r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime)
                qs.append(ts[-1] - float(stats.read_text().split()[1]))
            # CPU time of the process (all its threads): what other jobs inflate least;
            # wall minus the time the main thread waited for a CPU: roughly what an idle
            # machine would take (the other threads' waits still count)
            print(f"  telefringe reconstruct{label} (all outputs): "
                  f"{statistics.median(ts):.2f} s (runs: {', '.join(f'{t:.2f}' for t in ts)})"
                  f"; CPU {min(cs):.2f} s (min); wall - main thread's run-queue wait "
                  f"{min(qs):.2f} s (min)")
        for mode, rig_json in (("off", "rig.json"), ("fit", "rig.json"),
                               ("rig", "rig_gamma.json")):
            print(f"  split (gamma: {mode}, one run, {_load()}):")
            with tempfile.TemporaryDirectory() as d:
                subprocess.run([sys.executable, "-c", _SPLIT, str(root / rig_json),
                                str(folder), d, mode], check=True, env=env)
    tmpdir.cleanup()


if __name__ == "__main__":
    main()
