"""Speed of the two-camera stereo matcher on the ``stereo`` preset's full frames.

Usage: python benchmarks/stereo.py [--runs 5] [--bin 1] [--reference] [--threads N]

The ``stereo`` virtual rig (two pinhole cameras of 1280 x 1024 px with distortion, 30 deg
apart, a pinhole projector between them) looks at the held-out plane of
``benchmarks/anyrig.py`` (tilted 7 deg); each camera's projector coordinates (u_p, v_p)
come from the projector model (render-free: each pixel's line meets the plane, the point
is projected) with 0.03 px of noise. Prints, for u fringes only and for u + v (the
maximum-likelihood match with its residual):

- megapixels (of the first camera) per second of ``match_stereo`` by the wall clock (the
  fastest of ``--runs`` runs, on all numba threads: ``--threads``, default all cores);
- megapixels per CPU-second (process time of that run: all threads; load-independent,
  but counts the threads' spinning);
- with ``--reference``: the NumPy reference path once (slow: about 15-20 CPU-s per
  frame).

The machine may be shared: the load average is printed; wall-clock figures move with it.
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Coords:
    u_p: np.ndarray | None
    v_p: np.ndarray | None = None
    mask: np.ndarray | None = None
    sigma_u_p: np.ndarray | None = None
    sigma_v_p: np.ndarray | None = None


def _plane_coords(cam, projector, plane, noise, rng):
    w, h = cam.image_size
    v, u = np.mgrid[0:h, 0:w].astype(float)
    o, d = cam.backproject(u, v)
    o = np.broadcast_to(o, d.shape)
    s = ((plane.point - o) @ plane.normal) / (d @ plane.normal)
    X = o + s[..., None] * d
    up, vp = projector.project(X)
    pw, ph = projector.image_size
    lit = (up >= 0) & (up <= pw - 1) & (vp >= 0) & (vp <= ph - 1)
    up = np.where(lit, up + rng.normal(0, noise, up.shape), np.nan)
    vp = np.where(lit, vp + rng.normal(0, noise, vp.shape), np.nan)
    sig = np.full(up.shape, noise)
    return up, vp, sig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--bin", type=int, default=1)
    ap.add_argument("--reference", action="store_true")
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args()
    import numba

    from telefringe.reconstruction.stereo import match_stereo
    from telefringe.simulate.anyrig import held_out_plane
    from telefringe.simulate.presets import bin_camera_any, get_preset

    if args.threads:
        numba.set_num_threads(args.threads)
    vrig = bin_camera_any(get_preset("stereo"), args.bin)
    rig = vrig.rig
    plane = held_out_plane(vrig)
    rng = np.random.default_rng(0)
    maps = [_plane_coords(rig.cameras[c], rig.projector, plane, 0.03, rng)
            for c in rig.camera_names]
    w, h = rig.cameras[rig.camera_names[0]].image_size
    mpx = w * h / 1e6
    print(f"stereo preset{'' if args.bin == 1 else f' binned {args.bin}'}: {w} x {h} px "
          f"({mpx:.2f} Mpx), numba threads {numba.get_num_threads()}, load average "
          f"{os.getloadavg()[0]:.1f} (wall figures are disturbed on a shared machine)")
    for axes in ("u", "u+v"):
        cs = [Coords(m[0], m[1] if axes == "u+v" else None, None, m[2], m[2]) for m in maps]
        match_stereo(rig, *cs, engine="compiled")  # compile / warm up
        best_wall, cpu_at_best = np.inf, np.nan
        for _ in range(args.runs):
            t0, c0 = time.perf_counter(), time.process_time()
            m = match_stereo(rig, *cs, engine="compiled")
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            if wall < best_wall:
                best_wall, cpu_at_best = wall, cpu
        print(f"  {axes:<4} compiled: {mpx / best_wall:6.2f} Mpx/s wall (best of {args.runs}: "
              f"{best_wall:.3f} s), {mpx / cpu_at_best:6.2f} Mpx per CPU-second "
              f"({cpu_at_best:.3f} CPU-s); {m.cloud.count} points")
        if args.reference:
            t0, c0 = time.perf_counter(), time.process_time()
            r = match_stereo(rig, *cs, engine="numpy")
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            same = np.array_equal(r.cloud.flags, m.cloud.flags)
            dx = float(np.nanmax(np.abs(r.cloud.xyz - m.cloud.xyz)))
            print(f"  {axes:<4} NumPy reference: {mpx / wall:6.2f} Mpx/s wall ({wall:.1f} s), "
                  f"{mpx / cpu:6.3f} Mpx per CPU-second ({cpu:.1f} CPU-s); flags equal: "
                  f"{same}, max |xyz difference| {dx:.1e} mm")


if __name__ == "__main__":
    main()
