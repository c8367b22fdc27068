"""Gray-code decode speed on the real capture ``../shared/realdata/slmaster_mono_relief``.

Usage: python benchmarks/decode_gray.py [--data DIR] [--repeat 3] [--profile]

One phase group (12 steps, 32 periods) unwrapped by a complementary 5-bit Gray code,
1280 x 1024 camera pixels. Prints the CPU time (``time.process_time``, all threads) and
wall time of :func:`telefringe.fringes.decode.decode` (the default noise model, so that
the noise estimate is not timed), best of ``--repeat``, and Mpx/s from the CPU time.
``--profile`` prints the cProfile of one decode (top 20 by cumulative time).
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time
from pathlib import Path

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "realdata" / \
    "slmaster_mono_relief"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--profile", action="store_true")
    args = ap.parse_args(argv)
    from telefringe.fringes.decode import decode
    from telefringe.io.scan_json import read_scan

    scan = read_scan(args.data)
    mpx = scan.stacks[0].shape[1] * scan.stacks[0].shape[2] / 1e6
    decode(scan, noise="default")  # warm-up (compiled kernels, caches)
    cpu, wall = [], []
    for _ in range(args.repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        pc = decode(scan, noise="default")
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    print(f"scan: {mpx:.2f} Mpx, method {pc.axes['u'].method}, "
          f"{int(pc.mask.sum())} valid pixels")
    print(f"decode: {min(cpu):.3f} s CPU ({mpx / min(cpu):.1f} Mpx/s CPU), "
          f"{min(wall):.3f} s wall (best of {args.repeat}; shared machine: wall varies)")
    if args.profile:
        prof = cProfile.Profile()
        prof.enable()
        decode(scan, noise="default")
        prof.disable()
        pstats.Stats(prof).sort_stats("cumulative").print_stats(20)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
