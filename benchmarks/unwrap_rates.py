"""Wrong fringe orders versus modulation / noise, for each unwrapping method.

Usage: python benchmarks/unwrap_rates.py [--pixels 200000] [--no-rig]

Synthetic part: 4-step images of random projector coordinates (x uniform over the middle
80 % of an 800-pixel projector, away from its wrap-around edges), background A = B + 20,
Gaussian noise sigma_I = 1 DN, modulation B = ratio * sigma_I. Each method decodes its
own usual period set:

- hierarchical 1 / 8 / 64;  heterodyne 70 / 64 / 59;  number-theoretic 11 / 13 / 16
  (all three: 12 images);
- Gray code, 6 bits + complementary, with 64 periods (4 + 7 = 11 images; bit contrast
  2 B, threshold the phase images' mean).

Printed per method and ratio B / sigma_I: the share of pixels flagged unreliable, the
share of pixels with a wrong order among those the method trusts, and the share that
would be wrong if the flags were ignored.

Virtual-rig part (fast preset, plate, default 4-step 1/8/64 ladder, gamma 2.2 corrected
from the data, no modulation threshold): the projector brightness is lowered step by
step; per step, over lit plate pixels away from the markers, the median B / sigma_I of
the finest group, the share flagged and the share wrong among the trusted ones.
"""

from __future__ import annotations

import argparse

import numpy as np

from telefringe.fringes.patterns import gray_code_bits
from telefringe.fringes.phase import wrapped_phase
from telefringe.fringes.unwrap import (
    unwrap_gray,
    unwrap_heterodyne,
    unwrap_hierarchical,
    unwrap_number_theoretic,
)

L = 800
RATIOS = (1.5, 2, 3, 4, 5, 7, 10, 15, 20, 30)


def _phases(x, periods, b, rng, steps=4):
    out, backs = [], []
    for p in periods:
        k = np.arange(steps)[:, None]
        img = (b + 20.0) + b * np.cos(2 * np.pi * p * x[None] / L + 2 * np.pi * k / steps)
        img = img + rng.normal(0.0, 1.0, img.shape)
        wp = wrapped_phase(img, steps=steps)
        out.append(wp.phase)
        backs.append(wp.background)
    return out, backs


def _rates(absolute, x, periods, reliable):
    fine = int(np.argmax(periods))
    err = absolute[fine] - 2 * np.pi * periods[fine] * x / L
    wrong = np.abs(err) > np.pi
    flagged = ~reliable
    trusted_wrong = (wrong & reliable).sum() / max(reliable.sum(), 1)
    return flagged.mean(), trusted_wrong, wrong.mean()


def synthetic(n: int, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.1 * L, 0.9 * L, n)
    print(f"synthetic: {n} pixels per cell, 4 steps, sigma_I = 1 DN; columns: flagged / "
          "wrong among trusted / wrong if flags ignored")
    header = f"{'B/sigma':>8s}" + "".join(f"{m:>34s}" for m in
                                         ("hierarchical 1/8/64", "heterodyne 70/64/59",
                                          "number-theoretic 11/13/16", "Gray 6+c / 64"))
    print(header)
    for ratio in RATIOS:
        cells = []
        for name, per in (("hier", (1, 8, 64)), ("het", (70, 64, 59)), ("nt", (11, 13, 16))):
            ph, _ = _phases(x, per, ratio, rng)
            fn = {"hier": unwrap_hierarchical, "het": unwrap_heterodyne,
                  "nt": unwrap_number_theoretic}[name]
            res = fn(ph, per, length=L)
            cells.append(_rates(res.phases, x, per, res.reliable))
        ph, backs = _phases(x, (64,), ratio, rng)
        bits = gray_code_bits(np.arange(L), bits=6, length=L, complementary=True)
        xi = np.clip(np.round(x).astype(int), 0, L - 1)
        gimg = (ratio + 20.0 - ratio) + 2 * ratio * bits[:, xi].astype(float)
        gimg = gimg + rng.normal(0.0, 1.0, gimg.shape)
        res = unwrap_gray(ph[0], gimg, backs[0], bits=6, complementary=True, length=L,
                          min_contrast=3.0)
        cells.append(_rates(res.phases, x, (64,), res.reliable))
        print(f"{ratio:8.1f}" + "".join(f"   {f:9.2e} {t:9.2e} {w:9.2e}   "
                                        for f, t, w in cells))


def rig() -> None:
    from telefringe.fringes.decode import decode
    from telefringe.fringes.phase import NoiseModel
    from telefringe.simulate.presets import get_preset
    from telefringe.simulate.render import default_groups, render_scan
    from telefringe.simulate.scenes import plate_at_z

    base = get_preset("fast")
    ph = base.photometry
    noise = NoiseModel(read_noise=ph.read_noise_e * 255 / ph.full_well_e,
                       gain=255 / ph.full_well_e)
    print("\nvirtual rig (fast preset, plate, 4-step 1/8/64, hierarchical): projector "
          "brightness lowered")
    print(f"{'DN/rad':>8s} {'median B/sigma_I':>17s} {'flagged':>10s} {'wrong|trusted':>14s}")
    for dn in (250.0, 60.0, 25.0, 12.0, 7.0):
        vr = base.with_photometry(dn_per_radiance=dn)
        scan, truth = render_scan(vr, plate_at_z(0.0), default_groups(vr, axes=("u",)),
                                  seed=7, white=False, black=False)
        pc = decode(scan, noise=noise, min_modulation=0.0)
        r = pc.axes["u"]
        # plate pixels 2 px or more from the markers (one albedo, one B / sigma level)
        from scipy.ndimage import binary_erosion

        lit = truth.lit & binary_erosion(truth.part == 0, iterations=2)
        sig_i = np.sqrt(noise.variance(r.background))
        ratio = float(np.median((r.modulation / sig_i)[lit]))
        err = np.abs(pc.u_p - truth.u_p)
        wrong_trusted = float(np.mean((err > 400 / 128)[lit & pc.mask])) if (
            lit & pc.mask).any() else float("nan")
        flagged = float(np.mean(~r.order_reliable[lit]))
        print(f"{dn:8.0f} {ratio:17.1f} {flagged:10.2e} {wrong_trusted:14.2e}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pixels", type=int, default=200_000)
    ap.add_argument("--no-rig", action="store_true")
    args = ap.parse_args()
    synthetic(args.pixels)
    if not args.no_rig:
        rig()


if __name__ == "__main__":
    main()
