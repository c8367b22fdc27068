"""Bit-for-bit check of the triangulators against another revision of the code.

Usage: python benchmarks/triangulate_identity.py [--ref main] [--scan] [--runs 9]

Loads ``reconstruction/telecentric.py``, ``generic.py`` and ``_generic_kernels.py`` as
they are at git revision ``--ref`` (as private modules, next to the working tree's
package) and triangulates the same coordinates with both, on:

- the paper rig (telecentric camera and projector, 1280 x 1024) with projector coordinates
  from its model (render-free: a tilted, wavy surface, 0.05 px of noise, a mask with
  holes, NaN coordinates, pixels outside the projector): u only, u + v, v only, u + v
  with ``use_v_p=False``, no sigmas, ``max_sigma_z`` set; with ``--scan``, also the
  decoded coordinates of a rendered scan (slow: rendering and decoding);
- the mixed and pinhole rigs of ``benchmarks/triangulate_generic.py`` (1280 x 1024) by the
  generic triangulator, u only and u + v.

Every field of every cloud must be equal (``np.array_equal``, NaNs equal; the same dtype
and shape). Then prints the CPU time on one thread (minimum of ``--runs``) and the wall
time on all threads (minimum) of both, interleaved run by run (the machine may be
shared), and what bounds the telecentric u-only kernel: its CPU time on one thread over
the full frame against the same work on a 4096-pixel slice solved again and again (its
inputs and outputs in the core's L2 cache: the arithmetic alone). Exits with status 1
when a cloud differs.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "tests"))


@dataclass(frozen=True)
class Coords:
    u_p: np.ndarray | None
    v_p: np.ndarray | None = None
    mask: np.ndarray | None = None
    sigma_u_p: np.ndarray | None = None
    sigma_v_p: np.ndarray | None = None


def _old_modules(ref: str, tmp: Path):
    """telecentric, generic of revision ref as private modules (generic's kernels too)."""
    def show(path):
        return subprocess.run(["git", "-C", str(ROOT), "show", f"{ref}:{path}"], check=True,
                              capture_output=True, text=True).stdout

    base = "src/telefringe/reconstruction/"
    mods = {}
    for name, src in (("_old_generic_kernels", show(base + "_generic_kernels.py")),
                      ("_old_telecentric", show(base + "telecentric.py")),
                      ("_old_generic", show(base + "generic.py").replace(
                          "from telefringe.reconstruction import _generic_kernels as _gk",
                          "import _old_generic_kernels as _gk"))):
        path = tmp / f"{name}.py"
        path.write_text(src)
        spec = importlib.util.spec_from_file_location(name, path)
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod
        spec.loader.exec_module(mod)
        mods[name] = mod
    return mods["_old_telecentric"], mods["_old_generic"]


def _same(a, b) -> list[str]:
    """Names of the PointCloud fields that differ (values, dtype or shape)."""
    diff = []
    for f in ("xyz", "mask", "sigma_line", "residual", "flags", "directions"):
        x, y = getattr(a, f), getattr(b, f)
        if x is None or y is None:
            if (x is None) != (y is None):
                diff.append(f)
            continue
        nan = x.dtype.kind == "f"
        if (x.dtype != y.dtype or x.shape != y.shape
                or not np.array_equal(x, y, equal_nan=nan)):
            diff.append(f)
    return diff


def _paper_coords(rig, shape, seed=0):
    """Projector coordinates of a tilted, wavy surface seen by the paper rig, with noise,
    a mask with holes, NaNs and (where the surface leaves the projector) outside pixels."""
    from telefringe.reconstruction.telecentric import Triangulator

    tri = Triangulator.for_shape(rig, shape)
    rows, cols = shape
    v, u = np.mgrid[0:rows, 0:cols].astype(float)
    # line points at s = 0, then moved along the line to the surface z = f(x, y)
    X0 = tri.line_points(np.zeros(shape))
    d = tri.direction
    zs = 0.02 * X0[..., 0] - 0.015 * X0[..., 1] + 0.4 * np.sin(X0[..., 0] / 3.0)
    s = (zs - X0[..., 2]) / d[2]
    X = X0 + s[..., None] * d
    up, vp = rig.projector.project(X)
    rng = np.random.default_rng(seed)
    up = up + rng.normal(0.0, 0.05, shape)
    vp = vp + rng.normal(0.0, 0.05, shape)
    su = np.full(shape, 0.05) * (1.0 + rng.uniform(0.0, 1.0, shape))
    sv = 1.5 * su
    mask = rng.uniform(size=shape) > 0.02
    mask[100:140, 200:260] = False
    up[300:310, :] = np.nan
    vp[:, 500:505] = np.nan
    # a band far off the projector's image: outside pixels
    up[600:620, :] += 5000.0
    return up, vp, su, sv, mask


def _cases_paper(rig, shape, scan):
    from telefringe.reconstruction.telecentric import triangulate

    up, vp, su, sv, mask = _paper_coords(rig, shape)
    # a sigma_z bound that flags about half the points
    max_sz = float(np.nanmedian(triangulate(rig, Coords(up, None, mask, su)).sigma_z))
    cases = [
        ("u only", Coords(up, None, mask, su), {}),
        ("u only, no mask, no sigma", Coords(up), {}),
        ("u only, max_sigma_z", Coords(up, None, mask, su), {"max_sigma_z": max_sz}),
        ("u + v", Coords(up, vp, mask, su, sv), {}),
        ("u + v, use_v_p=False", Coords(up, vp, mask, su, sv), {"use_v_p": False}),
        ("u + v, no sigmas, no bounds", Coords(up, vp, mask), {"check_bounds": False}),
        ("v only", Coords(None, vp, mask, None, sv), {}),
        ("u only, float32 inputs", Coords(up.astype(np.float32), None, mask,
                                          su.astype(np.float32)), {}),
    ]
    if scan:
        from telefringe.fringes.decode import decode
        from telefringe.simulate.presets import get_preset
        from telefringe.simulate.render import default_groups, render_scan
        from telefringe.simulate.scenes import make_scene

        vrig = get_preset("paper")
        for axes in (("u",), ("u", "v")):
            data, _ = render_scan(vrig, make_scene("tilted-plane"),
                                  default_groups(vrig, axes=axes), white=False, black=False,
                                  seed=0)
            c = decode(data)
            cases.append((f"rendered scan {'+'.join(axes)}, decoded", c, {}))
    return cases


def _time(fns, runs):
    """CPU time on one thread (min) and wall on all threads (min), interleaved.

    The one-thread runs come first, after a pause: the worker threads of a parallel
    region spin for a while after it (OpenMP's wait policy), and that CPU time would
    count in the next run's process time."""
    import numba

    n_thr = numba.get_num_threads()
    cpu = {k: [] for k in fns}
    wall = {k: [] for k in fns}
    numba.set_num_threads(1)
    try:
        time.sleep(0.5)
        for _ in range(runs):
            for k, f in fns.items():
                t0 = time.process_time()
                f()
                cpu[k].append(time.process_time() - t0)
    finally:
        numba.set_num_threads(n_thr)
    for _ in range(runs):
        for k, f in fns.items():
            t0 = time.perf_counter()
            f()
            wall[k].append(time.perf_counter() - t0)
    return {k: (min(cpu[k]), min(wall[k])) for k in fns}, n_thr


def _kernel_bound(rig, shape, runs):
    """CPU time (1 thread, min of runs) of the u-only kernel on the full frame and of the
    same number of pixels solved on a 4096-pixel slice (in cache), interleaved."""
    import numba

    from telefringe.reconstruction import telecentric

    up, _, su, _, mask = _paper_coords(rig, shape)
    seen = {}
    kernel = telecentric._solve_u_fast

    def spy(*a):
        seen["args"] = a
        return kernel(*a)

    telecentric._solve_u_fast = spy
    try:
        telecentric.triangulate(rig, Coords(up, None, mask, su))
    finally:
        telecentric._solve_u_fast = kernel
    full = seen["args"]
    block = telecentric._solve_u_block

    @numba.njit(nogil=True)
    def again(reps, *a):
        n = 0
        for _ in range(reps):
            n += block(*a)
        return n

    m, lo = 4096, full[0].shape[0] // 2
    small = tuple(x[lo:lo + m].copy() if isinstance(x, np.ndarray) and x.shape[0] > m
                  else x for x in full)
    n = full[0].shape[0]
    reps = n // m
    t, _ = _time({"full": lambda: block(*full), "in cache": lambda: again(reps, *small)},
                 runs)
    print(f"  telecentric u-only kernel, CPU 1 thread: full frame {t['full'][0] * 1e3:.2f} ms;"
          f" the same pixel count on a {m}-pixel slice in cache (arithmetic alone) "
          f"{t['in cache'][0] * 1e3 * n / (m * reps):.2f} ms")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ref", default="main", help="git revision to compare with")
    ap.add_argument("--scan", action="store_true",
                    help="also a rendered and decoded scan of the paper rig (slow)")
    ap.add_argument("--runs", type=int, default=9, help="timing runs (0: no timing)")
    args = ap.parse_args(argv)

    from triangulate_generic import _coords, _rigs

    from telefringe.reconstruction import generic, telecentric
    from telefringe.simulate.presets import get_preset

    tmp = tempfile.TemporaryDirectory()
    old_tele, old_gen = _old_modules(args.ref, Path(tmp.name))
    print(f"working tree vs {args.ref}; load average {os.getloadavg()[0]:.2f}")
    bad = 0
    shape = (1024, 1280)
    mpx = shape[0] * shape[1] / 1e6
    rig = get_preset("paper").rig
    timed = {}
    for name, c, kw in _cases_paper(rig, shape, args.scan):
        new = telecentric.triangulate(rig, c, **kw)
        old = old_tele.triangulate(rig, c, **kw)
        diff = _same(new, old)
        bad += bool(diff)
        print(f"  paper rig (telecentric), {name}: "
              f"{'identical' if not diff else 'DIFFERS in ' + ', '.join(diff)} "
              f"({new.count} valid)")
        if name in ("u only", "u + v"):
            timed[f"telecentric {name}"] = (
                lambda c=c, kw=kw: old_tele.triangulate(rig, c, **kw),
                lambda c=c, kw=kw: telecentric.triangulate(rig, c, **kw))
    for rname, grig in _rigs(shape).items():
        up, vp, sig = _coords(grig, shape)
        mask = np.ones(shape, dtype=bool)
        mask[50:90, 100:400] = False
        for label, c in (("u only", Coords(up, None, mask, sig)),
                         ("u + v", Coords(up, vp, mask, sig, 1.2 * sig)),
                         ("u + v, no sigmas", Coords(up, vp)),
                         ("v only", Coords(None, vp, mask, None, sig))):
            new = generic.triangulate(grig, c)
            old = old_gen.triangulate(grig, c)
            diff = _same(new, old)
            bad += bool(diff)
            print(f"  {rname}, {label}: "
                  f"{'identical' if not diff else 'DIFFERS in ' + ', '.join(diff)} "
                  f"({new.count} valid)")
            if rname.startswith("pinhole camera + pinhole") and label != "u + v, no sigmas":
                timed[f"generic pinhole {label}"] = (
                    lambda c=c, g=grig: old_gen.triangulate(g, c),
                    lambda c=c, g=grig: generic.triangulate(g, c))
    print("identical" if not bad else f"{bad} clouds DIFFER")
    if args.runs > 0:
        print(f"times ({mpx:.2f} Mpx; min of {args.runs}, old and new interleaved; "
              f"load average {os.getloadavg()[0]:.2f}):")
        for name, (f_old, f_new) in timed.items():
            f_old(), f_new()
            t, n_thr = _time({"old": f_old, "new": f_new}, args.runs)
            print(f"  {name:26s} CPU 1 thread: {args.ref} {t['old'][0] * 1e3:6.2f} ms, new "
                  f"{t['new'][0] * 1e3:6.2f} ms; wall {n_thr} threads: {args.ref} "
                  f"{t['old'][1] * 1e3:6.2f} ms, new {t['new'][1] * 1e3:6.2f} ms "
                  f"({mpx / t['new'][1]:.0f} Mpx/s)")
        _kernel_bound(rig, shape, args.runs)
        print(f"  (load average {os.getloadavg()[0]:.2f})")
    tmp.cleanup()
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
