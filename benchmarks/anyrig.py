"""Issue 11's done-means figures on the virtual mixes (mixed, macro, stereo).

Each rig is calibrated from rendered poses (12 by default) exactly as ``telefringe
calibrate`` does, then measures a held-out tilted plane (several scans with other
noise: Monte Carlo), the step gauge and the sphere. Printed per rig:

- plane: the mean signed distance from the true plane (the systematic height error),
  in um and as a fraction of the median per-pixel sigma along the normal (goal < 0.1),
  and as a z-score against its predicted uncertainty (noise from the repeated scans,
  calibration from rigs drawn from the adjustment's covariance; goal |z| <= 3);
- sigma ratio: Monte Carlo per-pixel std over the predicted sigma (goal within 10 %);
- step heights and sphere radius: error, predicted sigma, z-score, error / pixel sigma.

    .venv/bin/python benchmarks/anyrig.py [--rig mixed,macro,stereo] [--bin 2]
        [--poses 12] [--mc 8] [--seed 0]

``--bin 2`` (default) bins the cameras 2 x 2 (640 x 512 for these rigs) to keep the run
within minutes on a loaded machine; ``--bin 1`` renders at full resolution.
"""

from __future__ import annotations

import argparse
import time

from telefringe.simulate.anyrig import run_anyrig
from telefringe.simulate.presets import bin_camera_any, get_preset


def _row(f) -> str:
    um = 1000.0
    return (f"  {f.name:<14} error {f.error * um:+8.3f} um   sigma_pred {f.sigma_pred * um:7.3f} "
            f"um (noise {f.sigma_noise * um:.3f}, cal {f.sigma_cal * um:.3f})   z {f.z_score:+6.2f}"
            f"   |error| / pixel sigma {f.of_pixel_sigma:.3f} (pixel sigma "
            f"{f.sigma_pixel * um:.2f} um)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rig", default="mixed,macro,stereo")
    ap.add_argument("--bin", type=int, default=2)
    ap.add_argument("--poses", type=int, default=12)
    ap.add_argument("--mc", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    for name in args.rig.split(","):
        vrig = bin_camera_any(get_preset(name), args.bin)
        t0 = time.perf_counter()
        c0 = time.process_time()
        res = run_anyrig(vrig, n_poses=args.poses, seed=args.seed, n_mc=args.mc)
        wall = time.perf_counter() - t0
        cpu = time.process_time() - c0
        print(f"{vrig.name}: calibrated from {res.n_poses} rendered poses (mirror: "
              f"{res.mirror}); reprojection RMS "
              + ", ".join(f"{d} {v:.4f} px" for d, v in res.rms.items()))
        print(_row(res.plane_bias)
              + ("   OK" if res.plane_bias.of_pixel_sigma < 0.1
                 and abs(res.plane_bias.z_score) <= 3 else "   FAILS"))
        print(f"  sigma per point: Monte Carlo / predicted = {res.sigma_ratio:.3f} over "
              f"{res.n_mc} scans" + ("   OK" if abs(res.sigma_ratio - 1) <= 0.1 else
                                     "   FAILS"))
        ps = res.plane_fit_sigma
        print(f"  plane fit height sigma: predicted {ps[0] * 1000:.4f} um (as independent "
              f"points {ps[1] * 1000:.4f} um), spread over the {res.n_mc} scans "
              f"{ps[2] * 1000:.4f} um")
        for f in res.steps:
            print(_row(f) + ("   OK" if abs(f.z_score) <= 3 else "   FAILS"))
        for f in ([res.sphere] if res.sphere is not None else []) + list(res.sphere_centre):
            print(_row(f) + ("   OK" if abs(f.z_score) <= 3 else "   FAILS"))
        print(f"  ({wall:.0f} s wall, {cpu:.0f} s CPU of this process; the machine is "
              "shared, so wall time is disturbed)")


if __name__ == "__main__":
    main()
