"""Decoding accuracy figures on the virtual rig and the real capture (what the tests in
tests/test_decode_rig.py and tests/test_gamma.py assert, printed).

Usage: python benchmarks/decode_accuracy.py [--skip-bga]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--skip-bga", action="store_true")
    args = ap.parse_args()
    from scipy.ndimage import binary_erosion

    from telefringe.fringes.decode import decode
    from telefringe.fringes.nonlinearity import periodic_error
    from telefringe.fringes.phase import NoiseModel, wrapped_phase
    from telefringe.fringes.scan import Scan, ScanManifest
    from telefringe.simulate.presets import get_preset
    from telefringe.simulate.render import default_groups, render_scan
    from telefringe.simulate.scenes import default_bga, plate_at_z

    def noise_of(vrig):
        ph = vrig.photometry
        return NoiseModel(read_noise=ph.read_noise_e * 255 / ph.full_well_e,
                          gain=255 / ph.full_well_e)

    paper = get_preset("paper")
    scan, truth = render_scan(paper, plate_at_z(0.0), default_groups(paper, axes=("u",)),
                              seed=11, white=False, black=False)
    lit = truth.lit & np.isin(truth.part, (0, 1))
    for gc in (True, False):
        pc = decode(scan, noise=noise_of(paper), gamma_correction=gc)
        err = (pc.u_p - truth.u_p)[lit]
        ok = np.isfinite(err)
        rms = np.sqrt(np.mean(err[ok] ** 2))
        pred = np.sqrt(np.mean(pc.sigma_u_p[lit][ok] ** 2))
        print(f"paper plate, 4-step 1/8/64, gamma correction {gc}: {lit.sum()} lit plate px, "
              f"valid {ok.mean():.4%}, u_p RMS {rms:.5f} px, noise model {pred:.5f} px, "
              f"ratio {rms / pred:.3f}, max |err| {np.max(np.abs(err[ok])):.3f} px "
              "(a period is 12.5 px)")

    fast = get_preset("fast")
    for steps in (3, 4):
        scan, truth = render_scan(fast, plate_at_z(0.0),
                                  default_groups(fast, axes=("u",), steps=steps), seed=steps,
                                  white=False, black=False)
        lit = truth.lit & np.isin(truth.part, (0, 1))
        core = truth.lit & binary_erosion(truth.part == 0, iterations=2)
        pc = decode(scan, noise=noise_of(fast))
        raw = decode(scan, noise=noise_of(fast), gamma_correction=False)
        fine = wrapped_phase(scan.stacks[2], steps=steps).phase
        true = 2 * np.pi * 64 * truth.u_p / fast.projector.intrinsics.width
        before = periodic_error(fine[lit], true[lit], harmonics=range(1, 25)).peak
        after = periodic_error(pc.axes["u"].phase_errors.models[2].correct(fine)[lit],
                               true[lit], harmonics=range(1, 25)).peak
        e = (pc.u_p - truth.u_p)[core]
        rms, pred = np.sqrt(np.mean(e ** 2)), np.sqrt(np.mean(pc.sigma_u_p[core] ** 2))
        print(f"fast rig, {steps}-step gamma 2.2: finest periodic error peak {before:.4f} -> "
              f"{after:.4f} rad ({before / after:.0f}x); valid lit {pc.mask[lit].mean():.4%} "
              f"(without correction {raw.mask[lit].mean():.2%}); max |err| "
              f"{np.nanmax(np.abs(pc.u_p - truth.u_p)[lit]):.3f} px; interior RMS {rms:.5f} "
              f"vs model {pred:.5f} px ({rms / pred:.3f})")

    if not args.skip_bga:
        exposures = (4.0, 0.6, 0.1)
        scan, truth = render_scan(paper, default_bga(0), default_groups(paper, axes=("u",)),
                                  exposures=exposures, seed=5, white=False, black=False)
        balls = truth.lit & (truth.part == 2)
        pc = decode(scan, noise=noise_of(paper))
        line = [f"BGA, paper rig: {balls.sum()} lit ball px; HDR {exposures}: valid "
                f"{pc.mask[balls].mean():.3%}"]
        for e in exposures:
            keep = [i for i, g in enumerate(scan.manifest.groups) if g.exposure == e]
            man = ScanManifest(scan.manifest.projector_width, scan.manifest.projector_height,
                               tuple(scan.manifest.groups[i] for i in keep))
            one = Scan(man, tuple(scan.stacks[i] for i in keep), max_value=scan.max_value)
            valid = decode(one, noise=noise_of(paper)).mask[balls].mean()
            line.append(f"exposure {e} alone {valid:.2%}")
        print("; ".join(line))

    shared = Path(__file__).resolve().parents[2] / "shared" / "realdata"
    if shared.is_dir():
        from telefringe.io.scan_json import read_scan

        scan = read_scan(shared / "slmaster_mono_relief")
        pc = decode(scan)
        r = pc.axes["u"]
        obj = ~r.low_modulation & ~r.saturated
        jumps = sum(int(np.sum(np.abs(d[np.isfinite(d)]) > 30))
                    for d in (np.diff(pc.u_p, axis=1), np.diff(pc.u_p, axis=0)))
        print(f"real 12-step + complementary Gray capture: {obj.sum()} object px, valid "
              f"{pc.mask[obj].mean():.3%}, neighbour jumps > 30 px: {jumps}, u_p 1..99 % "
              f"{np.nanpercentile(pc.u_p, 1):.0f}..{np.nanpercentile(pc.u_p, 99):.0f}")


if __name__ == "__main__":
    main()
