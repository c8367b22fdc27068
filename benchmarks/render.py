"""How long the virtual rig takes to render one full-resolution scan on the paper rig.

Usage: python benchmarks/render.py [--scene plate|steps|sphere|bga|tilted-plane] [--runs 3]

Prints, per run, the time to trace the geometry (once per scan) and the total time of
``render_scan`` for the default 24 fringe images (4 steps x 1/8/64 periods along u,
1/8/48 along v) plus white and black frames, then the median, and the peak memory.
The first call compiles/loads the numba kernels and is not counted.
"""

from __future__ import annotations

import argparse
import resource
import statistics
import time

from telefringe.simulate.presets import get_preset
from telefringe.simulate.render import default_groups, render_scan, trace_geometry
from telefringe.simulate.scenes import SCENE_NAMES, make_scene


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="plate", choices=SCENE_NAMES)
    ap.add_argument("--rig", default="paper")
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    vrig = get_preset(args.rig)
    scene = make_scene(args.scene)
    groups = default_groups(vrig)
    # warm-up: load the compiled kernels (small window of the camera)
    from telefringe.simulate.presets import crop_camera

    render_scan(crop_camera(vrig, col0=0, row0=0, width=32, height=32), scene, groups[:1])
    n_images = sum(g.count for g in groups) + 2
    rows, cols = vrig.camera.intrinsics.shape
    print(f"rig {vrig.name}: camera {cols} x {rows}, scene {args.scene}, {n_images} images")
    totals = []
    for run in range(args.runs):
        t0 = time.perf_counter()
        geom = trace_geometry(vrig, scene)
        n_edge = geom.edge_pixels.size
        del geom
        t1 = time.perf_counter()
        scan, _ = render_scan(vrig, scene, groups, seed=run)
        t2 = time.perf_counter()
        totals.append(t2 - t1)
        del scan
        print(f"run {run}: geometry {t1 - t0:.2f} s ({n_edge} edge pixels "
              f"traced at {vrig.photometry.edge_supersample}^2), render_scan {t2 - t1:.2f} s "
              f"({(t2 - t1) / n_images * 1000:.0f} ms per image all included)")
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"median render_scan: {statistics.median(totals):.2f} s for {n_images} images "
          f"({rows * cols * n_images / statistics.median(totals) / 1e6:.1f} Mpx/s); "
          f"peak RSS {peak_mb:.0f} MB")


if __name__ == "__main__":
    main()
