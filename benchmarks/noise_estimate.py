"""What measuring the camera noise from the scan costs and how close it comes.

Usage: python benchmarks/noise_estimate.py [--rig paper] [--repeat 5] [--seeds 8]

1. Speed: on a full-resolution virtual scan (u and v ladders 1/8/64, 4 steps, plate),
   the CPU time of ``estimate_noise`` (the default subsample of 24 000 pixels) against
   ``decode`` on the fast path, minimum over ``--repeat`` runs (``time.process_time``:
   the machine may be shared).
2. Accuracy: the decoder's predicted sigma of u_p (noise measured from each scan) against
   the scatter of u_p over ``--seeds`` noise seeds (the issue's bound: within 10 %), and
   the same with the decoder's default (typical-camera) model and with the renderer's
   true noise model.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rig", default="paper")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--seeds", type=int, default=8)
    args = ap.parse_args(argv)

    from telefringe.fringes.decode import decode
    from telefringe.fringes.noise import estimate_noise
    from telefringe.simulate.presets import get_preset
    from telefringe.simulate.render import default_groups, render_scan, trace_geometry
    from telefringe.simulate.scenes import plate_at_z

    vr = get_preset(args.rig)
    scene = plate_at_z(0.0)
    geo = trace_geometry(vr, scene)
    scan, truth = render_scan(vr, scene, default_groups(vr), seed=0, white=False,
                              black=False, geometry=geo)
    npx = int(np.prod(scan.shape))
    decode(scan, noise="scan", gamma_correction=False)  # compile and import once
    t_est, t_dec = [], []
    for _ in range(args.repeat):
        c = time.process_time()
        estimate_noise(scan)
        t_est.append(time.process_time() - c)
        c = time.process_time()
        decode(scan, gamma_correction=False)
        t_dec.append(time.process_time() - c)
    print(f"{args.rig} rig, {scan.shape[1]} x {scan.shape[0]} px, "
          f"{sum(s.shape[0] for s in scan.stacks)} images")
    print(f"estimate_noise: {min(t_est) * 1e3:.1f} ms CPU (min of {args.repeat}); "
          f"decode (fused fast path, no nonlinearity learning): {min(t_dec) * 1e3:.1f} ms CPU "
          f"({npx / min(t_dec) / 1e6:.1f} Mpx per CPU-s); the estimate adds "
          f"{min(t_est) / min(t_dec):.0%}")

    us, pred = [], {"scan": [], "default": [], "true model": []}
    true = vr.photometry.noise_model()
    groups = default_groups(vr, axes=("u",))
    for seed in range(args.seeds):
        s, truth = render_scan(vr, scene, groups, seed=seed, white=False, black=False,
                               geometry=geo)
        pc = decode(s, noise="scan", gamma_correction=False)
        us.append(pc.u_p)
        pred["scan"].append(pc.sigma_u_p)
        pred["default"].append(decode(s, gamma_correction=False).sigma_u_p)
        pred["true model"].append(decode(s, noise=true, gamma_correction=False).sigma_u_p)
        if seed == 0:
            e = pc.noise.estimate
            print(f"estimate (seed 0): a = {e.a:.4f} +- {np.sqrt(e.covariance[0, 0]):.4f} "
                  f"DN^2, b = {e.b:.5f} +- {np.sqrt(e.covariance[1, 1]):.5f}; true "
                  f"a = {true.read_noise ** 2 + true.quantization ** 2:.4f}, "
                  f"b = {true.gain:.5f}; groups excluded: {list(e.excluded)}")
    us = np.array(us)
    ok = np.all(np.isfinite(us), axis=0) & truth.lit
    observed = np.sqrt(np.mean(np.var(us[:, ok], axis=0, ddof=1)))
    print(f"u_p scatter over {args.seeds} seeds: {observed:.5f} px RMS ({ok.sum()} pixels)")
    for name, v in pred.items():
        r = np.sqrt(np.mean(np.array(v)[:, ok] ** 2)) / observed
        print(f"  predicted sigma / scatter, {name:10s}: {r:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
