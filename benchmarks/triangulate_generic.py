"""Speed of the generic camera + projector triangulation on a 1.3 Mpx frame.

Usage: python benchmarks/triangulate_generic.py [--runs 7] [--reference]

A pinhole camera of 1280 x 1024 px (about 40 x 32 mm at 200 mm, with distortion) and a
pinhole projector of 1280 x 800 px (with distortion) look at a surface of random heights
within +-2 mm of z = 0; the projector coordinates of each pixel come from the projector
model (render-free) with 0.05 px of noise. Prints, for u fringes only and for u + v
(the maximum-likelihood solve with its residual):

- megapixels per second of ``telefringe.reconstruction.generic.triangulate`` (the rig's
  per-pixel lines cached, as for every scan after the first), from the fastest of
  ``--runs`` runs by the wall clock, and the CPU time per run (process time: all
  threads; load-independent, but counts the threads' spinning);
- the one-time set-up per rig and image size (the camera's lines);
- the same for the telecentric camera + pinhole projector and pinhole camera +
  telecentric projector mixes (two telecentric devices take the fast path of
  ``benchmarks/reconstruct.py``);
- with ``--reference``: the NumPy reference path once (slow).

The machine may be shared: the load average is printed; wall-clock figures move with it.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


@dataclass(frozen=True)
class Coords:
    u_p: np.ndarray | None
    v_p: np.ndarray | None = None
    mask: np.ndarray | None = None
    sigma_u_p: np.ndarray | None = None
    sigma_v_p: np.ndarray | None = None


def _rigs(shape):
    from anyrig_rigs import pinhole, telecentric_camera, telecentric_projector

    from telefringe.devices.rig import Rig

    rows, cols = shape
    cam = pinhole((0.0, 0.0, 200.0), f=cols * 200.0 / 40.0, size=(cols, rows),
                  dist=(-0.12, 0.3, 4e-4, -3e-4, 0.0), pp=(3.0, -2.0))
    prj = pinhole((80.0, 5.0, 190.0), f=1280 * 215.0 / 50.0, size=(1280, 800),
                  dist=(0.08, -0.2, -5e-4, 2e-4, 0.0), pp=(3.0, 40.0), roll=-0.03)
    tcam = telecentric_camera(shape)
    return {"pinhole camera + pinhole projector": Rig(cam, prj),
            "telecentric camera + pinhole projector": Rig(tcam, prj),
            "pinhole camera + telecentric projector": Rig(cam, telecentric_projector())}


def _coords(rig, shape, seed=0):
    cam = rig.camera
    rows, cols = shape
    v, u = np.mgrid[0:rows, 0:cols].astype(float)
    o, d = cam.backproject(u, v)
    o = np.broadcast_to(o, shape + (3,))
    d = np.broadcast_to(d, shape + (3,))
    rng = np.random.default_rng(seed)
    z = rng.uniform(-2.0, 2.0, size=shape)
    s = (z - o[..., 2]) / d[..., 2]
    X = o + s[..., None] * d
    up, vp = rig.projector.project(X)
    up = up + rng.normal(0.0, 0.05, shape)
    vp = vp + rng.normal(0.0, 0.05, shape)
    sig = np.full(shape, 0.05)
    return up, vp, sig


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--reference", action="store_true",
                    help="also time the NumPy reference path once")
    args = ap.parse_args(argv)
    from telefringe.reconstruction import generic

    shape = (1024, 1280)
    mpx = shape[0] * shape[1] / 1e6
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cpus; numba threads "
          f"{os.environ.get('NUMBA_NUM_THREADS', 'default')}")
    for name, rig in _rigs(shape).items():
        up, vp, sig = _coords(rig, shape)
        t0 = time.perf_counter()
        generic._CACHE.clear()
        tri = generic.GenericTriangulator.for_shape(rig, shape)
        setup = time.perf_counter() - t0
        print(f"{name}: {mpx:.2f} Mpx; set-up (camera lines, once per rig and size) "
              f"{setup:.2f} s")
        for label, c in (("u only", Coords(up, None, None, sig)),
                         ("u + v", Coords(up, vp, None, sig, sig))):
            tri.triangulate(c)  # compile / warm
            walls, cpus = [], []
            for _ in range(args.runs):
                w0, c0 = time.perf_counter(), time.process_time()
                cloud = tri.triangulate(c)
                walls.append(time.perf_counter() - w0)
                cpus.append(time.process_time() - c0)
            best = min(walls)
            print(f"  {label:7s}: {mpx / best:6.1f} Mpx/s (best of {args.runs}: "
                  f"{best * 1e3:.1f} ms; median {np.median(walls) * 1e3:.1f} ms; CPU "
                  f"{min(cpus) * 1e3:.1f} ms/run = {mpx / min(cpus):.1f} Mpx per CPU-s); "
                  f"{cloud.count / cloud.mask.size:.1%} valid")
            if args.reference:
                w0 = time.perf_counter()
                tri.triangulate(c, compiled=False)
                ref = time.perf_counter() - w0
                print(f"           NumPy reference: {mpx / ref:.2f} Mpx/s ({ref:.1f} s)")


if __name__ == "__main__":
    main()
