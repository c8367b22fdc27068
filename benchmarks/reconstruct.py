"""Reconstruction speed: scan folder (12 images 1280 x 1024) + rig -> points.

Usage: python benchmarks/reconstruct.py [--runs 5] [--scene tilted-plane] [--keep DIR]

Renders one scan of the paper rig (4 steps x 1/8/64 periods along u, no white/black: 12
images of 1280 x 1024, 8 bit), writes it as a scan folder with the TRUE rig's rig.json,
then prints, as the median of ``--runs`` runs after a warm-up:

- the time of each stage in-process: reading the 12 PNGs, decoding (with and without
  the data-driven gamma correction), triangulation (per-rig set-up cached, and the
  set-up itself), height map, writing the outputs;
- megapixels (camera pixels) per second for triangulation alone, decode + triangulate
  from images in memory, and read + decode + triangulate from the folder;
- the cold-start time of ``telefringe reconstruct`` for one scan (a new process, numba
  caches warm), and of ``python -c "import telefringe.cli"`` alone.
"""

from __future__ import annotations

import argparse
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


def _write_rig(path: Path, rig) -> bool:
    """A hand-made rig.json of the true rig (no calibration report); False when this
    telefringe has no rig.json reader."""
    import json

    try:
        from telefringe.io import rig as rig_io  # noqa: F401
    except ImportError:
        return False
    from telefringe.model import rotvec_from_rotation

    def dev(d):
        k = d.intrinsics
        return {"width": k.width, "height": k.height, "pixel_size_mm": [k.du, k.dv],
                "m": k.m, "principal_point_px": [k.u0, k.v0],
                "distortion": {"k1": k.k1, "s1": k.s1, "s2": k.s2},
                "rotation_vector": [float(v) for v in rotvec_from_rotation(d.R_dev_world)],
                "t_mm": [float(v) for v in d.t_dev]}

    path.write_text(json.dumps({"format": "telefringe-rig", "version": 1,
                                "world_frame": {"reference_pose": "truth"},
                                "camera": dev(rig.camera), "projector": dev(rig.projector)}))
    return True


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--scene", default="tilted-plane")
    ap.add_argument("--keep", type=Path, default=None, help="Keep the scan folder here.")
    args = ap.parse_args()

    import numba

    from telefringe.decode import decode
    from telefringe.io.export import write_reconstruction
    from telefringe.io.scan import read_scan, write_scan
    from telefringe.reconstruct import Triangulator, height_map, triangulate
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
    has_rig_json = _write_rig(root / "rig.json", vrig.rig)
    print(f"paper rig, scene {args.scene}: {n_img} images of {cols} x {rows} "
          f"({mpx:.2f} Mpx), {numba.get_num_threads()} threads, median of {args.runs} runs")

    # warm-up (numba caches load, per-rig set-up cached)
    data = read_scan(folder)
    coords = decode(data)
    cloud = triangulate(vrig.rig, coords)
    height_map(cloud)

    t_read, data = _median_time(lambda: read_scan(folder), args.runs)
    t_dec, coords = _median_time(lambda: decode(data), args.runs)
    t_dec_ng, coords_ng = _median_time(lambda: decode(data, gamma_correction=False),
                                       args.runs)
    t_setup, _ = _median_time(lambda: Triangulator.for_shape(vrig.rig, (rows, cols)),
                              args.runs)
    t_tri, cloud = _median_time(lambda: triangulate(vrig.rig, coords), args.runs)
    t_hm, hm = _median_time(lambda: height_map(cloud), args.runs)
    # CPU time on one thread: a figure that other jobs on the machine do not inflate
    n_thr = numba.get_num_threads()
    numba.set_num_threads(1)
    cpu = []
    for _ in range(max(args.runs, 5)):
        t0 = time.process_time()
        triangulate(vrig.rig, coords)
        cpu.append(time.process_time() - t0)
    numba.set_num_threads(n_thr)
    t_cpu = min(cpu)

    def write():
        with tempfile.TemporaryDirectory() as d:
            write_reconstruction(d, cloud, hm, texture=None)

    t_write, _ = _median_time(write, max(1, args.runs // 2))

    def line(name, t, n_mpx=mpx):
        print(f"  {name:<44s} {t * 1000:8.1f} ms  {n_mpx / t:8.1f} Mpx/s")

    print("stages:")
    line(f"read {n_img} PNG images", t_read)
    line("decode (gamma correction on, default)", t_dec)
    line("decode (gamma correction off)", t_dec_ng)
    line("per-rig set-up (Triangulator, once per rig)", t_setup)
    line("triangulate (set-up cached)", t_tri)
    line("triangulate, CPU time on 1 thread (best)", t_cpu)
    line("height map", t_hm)
    line("write points.npz, PLY, TIFF, PNG", t_write)
    print("end to end:")
    line("triangulate only", t_tri)
    line("decode + triangulate (images in memory)", t_dec + t_tri)
    line("decode (no gamma corr.) + triangulate", t_dec_ng + t_tri)
    line("read + decode + triangulate (from folder)", t_read + t_dec + t_tri)
    print(f"  valid points: {cloud.count} ({cloud.count / (rows * cols):.1%}), median sigma_z "
          f"{np.nanmedian(cloud.sigma_z) * 1000:.2f} um")

    imp = []
    for _ in range(3):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", "import telefringe.cli"], check=True)
        imp.append(time.perf_counter() - t0)
    print(f"cold start: python -c 'import telefringe.cli': {statistics.median(imp):.2f} s")
    if has_rig_json:
        exe = [sys.executable, "-m", "telefringe.cli"]
        cmd = exe + ["-q", "reconstruct", str(folder), "--rig", str(root / "rig.json"),
                     "-o", str(root / "out"), "--force"]
        ts = []
        for _ in range(3):
            t0 = time.perf_counter()
            subprocess.run(cmd, check=True)
            ts.append(time.perf_counter() - t0)
        cmd_ng = cmd + ["--no-gamma-correction", "--no-ply"]
        t0 = time.perf_counter()
        subprocess.run(cmd_ng, check=True)
        t_ng = time.perf_counter() - t0
        print(f"cold start: telefringe reconstruct (one scan, all outputs): "
              f"{statistics.median(ts):.2f} s (runs: {', '.join(f'{t:.2f}' for t in ts)})")
        print(f"cold start: ... --no-gamma-correction --no-ply: {t_ng:.2f} s")
    else:
        # no rig.json writer yet: the same work in a fresh process, the rig from the preset
        code = ("import sys; from telefringe.cli.reconstruct import reconstruct_to_folder; "
                "from telefringe.simulate.presets import get_preset; "
                "from telefringe.cli._common import state; state.quiet = True; "
                "reconstruct_to_folder(sys.argv[1], get_preset('paper').rig, sys.argv[2], "
                "force=True)")
        ts = []
        for _ in range(3):
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-c", code, str(folder), str(root / "out")],
                           check=True)
            ts.append(time.perf_counter() - t0)
        print("cold start: reconstruct_to_folder in a new process (what 'telefringe "
              "reconstruct' does; no rig.json writer in telefringe.io.rig yet): "
              f"{statistics.median(ts):.2f} s (runs: {', '.join(f'{t:.2f}' for t in ts)})")
    tmpdir.cleanup()


if __name__ == "__main__":
    main()
