"""Decoding speed: 12 images of 1280 x 1024 uint8 (4 steps x 1/8/64 periods, one axis)
-> projector coordinate u_p + mask + modulation, in megapixels (camera pixels) per second.

Usage: python benchmarks/decode.py [--runs 7] [--threads N] [--peers /tmp/benchvenv] [--asm]

Prints, median (and best) of ``--runs`` runs after a warm-up call, with the load average
(the machine is shared: with a load above the core count every wall-clock figure here is
a fraction of what an idle machine gives; the single-thread CPU-time line is the most
load-independent one):

- telefringe ``decode_axis_fast``: the fused numba kernel (telefringe._kernels.fused_ladder,
  parallel over rows, vectorised: float32 polynomial arctangent <= 1e-6 rad, float32
  unwrapping, the result in float64; FMA contraction is the only fast-math flag), without
  and with a nonlinearity correction table (float32 linear interpolation, <= 1e-6 rad);
  and the same on one thread in CPU time (Mpx per CPU second);
- telefringe ``decode``: the full result (sigma_u_p, diagnostics, HDR choice) from the same
  fused kernel, with and without learning the nonlinearity from the data (the gamma fit,
  telefringe.fringes.nonlinearity, is most of that time); and ``decode(exact=True)``
  (float64 NumPy);
- a plain NumPy float32 reference (atan2, hierarchical unwrapping, mask);
- the peers ``fringes`` (GPL-3.0: benchmarked in its own throwaway venv, never imported
  here) and OpenCV contrib's ``structured_light`` (3-step PSP only), when that venv
  exists (``--peers``, default /tmp/benchvenv; create it with
  ``python -m venv /tmp/benchvenv && /tmp/benchvenv/bin/pip install fringes
  opencv-contrib-python-headless``);
- what bounds the speed: the rate of only reading the input once (12 bytes per pixel),
  and of the fused kernel, one thread in CPU time, on rows that stay in cache (arithmetic
  alone) against the full frame. The kernel does about 3 x (8 weighted sums, an atan2
  polynomial of degree 15 with one division, an unwrapping step) per pixel in 8-lane
  float32 and the finest level's phase and the result in 4-lane float64: it is
  arithmetic bound (both one-thread rates agree), far below the rate of reading the
  15.7 MB input;
- peak memory of a full-frame fast decode (tracemalloc in a fresh process, plus input).

``--asm`` compiles the kernel afresh (in a scratch cache) and counts its packed (ymm/zmm)
and scalar floating-point instructions: the check that the loops vectorise.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np

ROWS, COLS, WIDTH = 1024, 1280, 800
PERIODS = (1, 8, 64)
STEPS = 4


def make_images(seed: int = 0) -> list[np.ndarray]:
    """Three 4-step groups of a tilted plane (u from 20 to about 780), 8-bit, noisy."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:ROWS, 0:COLS].astype(np.float64)
    x = 20.0 + xx * 0.56 + 0.03 * yy
    out = []
    for p in PERIODS:
        k = np.arange(STEPS)[:, None, None]
        img = 60.0 + 80.0 * (1.0 + np.cos(2 * np.pi * p * x / WIDTH + 2 * np.pi * k / STEPS))
        img += rng.normal(0.0, 1.5, img.shape)
        out.append(np.clip(np.round(img), 0, 255).astype(np.uint8))
    return out


def timeit(fn, runs: int) -> tuple[float, float]:
    fn()  # warm-up (compilation / cache load)
    ts = []
    for _ in range(runs):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts), min(ts)


def numpy_reference(stacks, min_mod=5.1):
    """Plain NumPy float32: 4-step phase, hierarchical unwrapping, mask."""
    two_pi = np.float32(2 * np.pi)
    phi_abs = None
    ok = None
    for st, p, prev in zip(stacks, PERIODS, (None,) + PERIODS[:-1], strict=True):
        f = st.astype(np.float32)
        s = f[1] - f[3]
        c = f[0] - f[2]
        ph = np.arctan2(-s, c)
        mod = np.float32(0.5) * np.sqrt(s * s + c * c)
        good = (mod >= min_mod) & (st.max(axis=0) < 255)
        if phi_abs is None:
            phi_abs = np.mod(ph, two_pi)
            ok = good
        else:
            pred = phi_abs * np.float32(p / prev)
            phi_abs = ph + two_pi * np.round((pred - ph) / two_pi)
            ok &= good & (np.abs(pred - phi_abs) <= np.float32(np.pi / 2))
    u = phi_abs * np.float32(WIDTH / (2 * np.pi * PERIODS[-1]))
    u[~ok] = np.nan
    return u, ok, mod


_PEER = textwrap.dedent(r'''
    import json, statistics, sys, time
    import numpy as np
    runs = int(sys.argv[1])
    out = {}
    def timeit(fn):
        fn()
        ts = []
        for _ in range(runs):
            t = time.perf_counter(); fn(); ts.append(time.perf_counter() - t)
        return statistics.median(ts), min(ts)
    try:
        import fringes
        f = fringes.Fringes(X=1280, Y=1024, axes=(0,), K=3, N=(4, 4, 4), v=(1, 8, 64))
        I = f.encode()
        med, best = timeit(lambda: f.decode(I))
        out["fringes"] = {"median_s": med, "best_s": best, "version": fringes.__version__,
                          "what": "its own 12 frames (4 steps x 3 frequencies, one axis), "
                                  "temporal unwrapping"}
    except Exception as exc:  # noqa: BLE001
        out["fringes"] = {"error": repr(exc)}
    try:
        import cv2
        sl = cv2.structured_light
        params = sl.SinusoidalPattern.Params()
        params.width, params.height = 1280, 1024
        params.nbrOfPeriods = 64
        params.methodId = sl.PSP
        params.setMarkers = False
        pat = sl.SinusoidalPattern_create(params)
        ok, imgs = pat.generate()
        imgs = [np.ascontiguousarray(i) for i in imgs[:3]]
        def run():
            wrapped, shadow = pat.computePhaseMap(imgs)
            pat.unwrapPhaseMap(wrapped, (1280, 1024), shadowMask=shadow)
        med, best = timeit(run)
        out["opencv"] = {"median_s": med, "best_s": best, "version": cv2.__version__,
                         "what": "3 images (3-step PSP, one frequency) + spatial unwrapping"}
    except Exception as exc:  # noqa: BLE001
        out["opencv"] = {"error": repr(exc)}
    print(json.dumps(out))
''')

_MEMORY = textwrap.dedent(r'''
    import sys, tracemalloc
    import numpy as np
    from telefringe.fringes.fast import decode_axis_fast
    stacks = [np.load(p) for p in sys.argv[1:4]]
    decode_axis_fast([s[:, :16, :16].copy() for s in stacks], (1, 8, 64), 4,
                     length=800)  # load the cached kernel
    tracemalloc.start()
    r = decode_axis_fast(stacks, (1, 8, 64), 4, length=800)
    cur, peak = tracemalloc.get_traced_memory()
    print(peak / 2**20, sum(s.nbytes for s in stacks) / 2**20)
''')


_ASM = textwrap.dedent(r'''
    import re
    import numpy as np
    from telefringe import _kernels as _k
    from telefringe.fringes.fast import decode_axis_fast
    st = [np.zeros((4, 8, 8), np.uint8) for _ in range(3)]
    decode_axis_fast(st, (1, 8, 64), 4, length=800)
    asm = "\n".join(_k.fused_ladder.inspect_asm().values())
    ops = re.findall(r"\b(v[a-z0-9]+?)(ps|pd|ss|sd)\s[^\n]*%([xyz])mm", asm)
    arith = {"add", "sub", "mul", "div", "fmadd213", "fmadd231", "fmadd132", "fnmadd213",
             "fnmadd231", "fnmadd132", "fmsub213", "fmsub231", "fmsub132", "sqrt", "max",
             "min", "round", "cmp"}
    packed = sum(1 for o, t, r in ops if t in ("ps", "pd") and r in "yz"
                 and o[1:] in arith)
    scalar = sum(1 for o, t, r in ops if t in ("ss", "sd") and o[1:] in arith)
    print(f"asm of fused_ladder: {packed} packed (ymm/zmm) and {scalar} scalar float "
          "arithmetic instructions (scalar: loop remainders, the table gather, HDR merges)")
''')


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--threads", type=int, default=None, help="numba threads (default all)")
    ap.add_argument("--peers", default="/tmp/benchvenv", help="venv with fringes and OpenCV")
    ap.add_argument("--asm", action="store_true", help="count packed vs scalar float ops")
    args = ap.parse_args()

    import numba

    from telefringe.fringes import _kernels as _k
    from telefringe.fringes.decode import decode
    from telefringe.fringes.fast import decode_axis_fast
    from telefringe.fringes.nonlinearity import PhaseErrorModel
    from telefringe.fringes.scan import PhaseGroup, Scan, ScanManifest

    if args.threads:
        numba.set_num_threads(args.threads)
    mpx = ROWS * COLS / 1e6
    stacks = make_images()
    print(f"workload: {len(PERIODS) * STEPS} images {COLS} x {ROWS} uint8 "
          f"({sum(s.nbytes for s in stacks) / 1e6:.1f} MB), periods {PERIODS}, {STEPS} steps;"
          f" numba threads {numba.get_num_threads()}, cores {os.cpu_count()}, load average "
          f"{os.getloadavg()[0]:.2f}")
    rows = []

    def report(name, med, best, note=""):
        rows.append((name, mpx / med, mpx / best, note))
        print(f"  {name:<44s} {mpx / med:8.1f} Mpx/s (best {mpx / best:7.1f})  {note}",
              flush=True)

    scan = Scan(ScanManifest(WIDTH, 600, tuple(PhaseGroup("u", p, STEPS) for p in PERIODS)),
                tuple(stacks))
    t0 = time.perf_counter()
    decode_axis_fast([s[:, :8, :8].copy() for s in stacks], PERIODS, STEPS, length=WIDTH)
    print(f"cold start (load the cached kernel): {time.perf_counter() - t0:.2f} s")
    med, best = timeit(lambda: decode_axis_fast(stacks, PERIODS, STEPS, length=WIDTH),
                       args.runs)
    report("telefringe decode_axis_fast", med, best, "u_p float64 + mask + modulation")
    med, best = timeit(lambda: decode_axis_fast(stacks, PERIODS, STEPS, length=WIDTH,
                                                dtype=np.float32), args.runs)
    report("telefringe decode_axis_fast (float32 u_p)", med, best)
    models = [PhaseErrorModel(p, (4, 8), np.array([0.0, 0.0]), np.array([-0.011, -0.001]))
              for p in PERIODS]
    med, best = timeit(lambda: decode_axis_fast(stacks, PERIODS, STEPS, length=WIDTH,
                                                phase_errors=models), args.runs)
    report("telefringe decode_axis_fast + gamma table", med, best,
           "(correction learned once per rig)")
    numba.set_num_threads(1)
    ts = []
    for _ in range(args.runs):
        t = time.process_time()
        decode_axis_fast(stacks, PERIODS, STEPS, length=WIDTH)
        ts.append(time.process_time() - t)
    numba.set_num_threads(args.threads or numba.config.NUMBA_NUM_THREADS)
    report("decode_axis_fast, 1 thread, per CPU second", statistics.median(ts), min(ts),
           "(Mpx per CPU s: less sensitive to the load)")
    med, best = timeit(lambda: decode(scan, gamma_correction=False), args.runs)
    report("telefringe decode (full, no gamma fit)", med, best,
           "sigma_u_p, diagnostics (fused kernel)")
    med, best = timeit(lambda: decode(scan), max(1, args.runs // 3))
    report("telefringe decode (full, gamma fit)", med, best, "(the fit is most of it)")
    med, best = timeit(lambda: decode(scan, gamma_correction=False, exact=True),
                       max(1, args.runs // 3))
    report("telefringe decode(exact=True), no gamma fit", med, best, "float64 NumPy")
    med, best = timeit(lambda: numpy_reference(stacks), args.runs)
    report("plain NumPy float32 reference", med, best)

    # what bounds it
    big = np.concatenate(stacks)
    med, best = timeit(lambda: _read_only(big), args.runs)
    report("floor: read the input once (numba sum)", med, best)
    # arithmetic alone: the same kernel, one thread, on 16 rows repeated (the inputs stay
    # in cache); 64 calls make up a full frame; CPU time, the per-call overhead (timed on
    # a tiny image) removed
    small = [np.ascontiguousarray(s[:, :16, :]) for s in stacks]
    tiny = [np.ascontiguousarray(s[:, :1, :8]) for s in stacks]
    reps = ROWS // 16
    numba.set_num_threads(1)
    ts, over = [], []
    for _ in range(args.runs):
        for arr, out in ((small, ts), (tiny, over)):
            t = time.process_time()
            for _ in range(reps):
                decode_axis_fast(arr, PERIODS, STEPS, length=WIDTH)
            out.append(time.process_time() - t)
    numba.set_num_threads(args.threads or numba.config.NUMBA_NUM_THREADS)
    d = [max(a - b, 1e-9) for a, b in zip(ts, over, strict=True)]
    report("same, cache-resident rows, 1 thread, CPU s", statistics.median(d), min(d),
           "(arithmetic alone)")

    peers = Path(args.peers) / "bin" / "python"
    if peers.exists():
        with tempfile.TemporaryDirectory() as tmp:
            script = Path(tmp) / "peer.py"
            script.write_text(_PEER)
            res = subprocess.run([str(peers), str(script), str(max(3, args.runs // 2))],
                                 capture_output=True, text=True, timeout=3600)
        try:
            out = json.loads(res.stdout.strip().splitlines()[-1])
        except (IndexError, json.JSONDecodeError):
            out = {}
            print(f"  peers: failed ({res.stderr.strip()[-300:]})")
        for name, r in out.items():
            if "error" in r:
                print(f"  {name}: cannot run ({r['error']})")
            else:
                report(f"{name} {r['version']}", r["median_s"], r["best_s"], r["what"])
    else:
        print(f"  peers: no venv at {args.peers} (see the module docstring)")

    with tempfile.TemporaryDirectory() as tmp:
        script = Path(tmp) / "mem.py"
        script.write_text(_MEMORY)
        names = []
        for i, st in enumerate(stacks):
            names.append(str(Path(tmp) / f"s{i}.npy"))
            np.save(names[-1], st)
        res = subprocess.run([sys.executable, str(script), *names], capture_output=True,
                             text=True, timeout=600)
    try:
        peak, inp = (float(x) for x in res.stdout.split())
        print(f"peak memory of a full-frame fast decode: {peak:.1f} MB allocated by the decode "
              f"(outputs; numba scratch: about 170 kB per parallel task) + {inp:.1f} MB "
              f"input = {peak + inp:.1f} MB")
    except ValueError:
        print(f"memory measurement failed: {res.stderr.strip()[-300:]}")
    one = [r for r in rows if r[0].startswith("decode_axis_fast, 1 thread")][0][1]
    floor = [r for r in rows if r[0].startswith("floor")][0][1]
    arith = [r for r in rows if r[0].startswith("same, cache-resident")][0][1]
    bound = ("arithmetic (per pixel, 3 x: 8 weighted sums, an atan2 polynomial with a "
             "division, an unwrapping step; the result in float64)" if one > 0.7 * arith
             else "memory traffic as much as arithmetic")
    print(f"bound: {bound}: one thread decodes {one:.0f} Mpx per CPU second on the full "
          f"frame, {arith:.0f} on rows that stay in cache; reading the input alone "
          f"runs at {floor:.0f} Mpx/s; {numba.get_num_threads()} threads can at best give "
          f"{numba.get_num_threads() * one:.0f} Mpx/s on idle cores "
          f"(load average now {os.getloadavg()[0]:.2f})")
    if args.asm:
        res = subprocess.run([sys.executable, "-c", _ASM], capture_output=True, text=True,
                             timeout=1200, env={**os.environ,
                                                "NUMBA_CACHE_DIR": tempfile.mkdtemp()})
        print(res.stdout.strip() or f"asm check failed: {res.stderr.strip()[-300:]}")
    del _k


def _read_only(big):
    from telefringe.fringes import _kernels as _k

    return _k.read_floor(big)


if __name__ == "__main__":
    main()
