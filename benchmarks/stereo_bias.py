"""Where the stereo bias comes from: matching or calibration (issue 11).

Usage: python benchmarks/stereo_bias.py [--bin 4] [--poses 12] [--seed 0]
    [--calibration default,noiseless,noiseless-sharp]

On the ``stereo`` preset the held-out plate (``benchmarks/anyrig.py``) and the sphere are
rendered once and measured four ways: from the true phase maps (the renderer's exact u_p,
v_p at each pixel centre) or from the decoded scans, each with the true rig or with a rig
calibrated from ``--poses`` rendered poses. Printed: the plate's mean signed distance
from the truth (um, and over the median per-pixel sigma along the normal) and the RMS of
the distances; the sphere's fitted radius error (um).

- true maps + true rig: the matching alone (sub-pixel interpolation of the second
  camera's phase along the epipolar line);
- decoded + true rig: adds the decoding (noise, blur, pixel integration);
- true maps + calibrated rig: the calibration alone.

``--calibration`` also calibrates from noise-free renders (``noiseless``: no shot or read
noise, 16 bit; ``noiseless-sharp``: and no camera blur): what the calibration does with
no noise at all is its systematic part. Takes minutes per calibration.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class _Coords:
    u_p: np.ndarray
    v_p: np.ndarray
    mask: np.ndarray
    sigma_u_p: np.ndarray
    sigma_v_p: np.ndarray


def _true_maps(truths):
    return {c: _Coords(t.u_p, t.v_p, np.isfinite(t.u_p) & np.isfinite(t.v_p),
                       np.full(t.u_p.shape, 0.03), np.full(t.u_p.shape, 0.03))
            for c, t in truths.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bin", type=int, default=4)
    ap.add_argument("--poses", type=int, default=12)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--calibration", default="default")
    args = ap.parse_args()
    from telefringe.metrology.spheres import measure_sphere
    from telefringe.reconstruction.stereo import triangulate_stereo
    from telefringe.simulate.anyrig import (
        _decode_all,
        _plane_errors,
        calibrate_virtual,
        held_out_plane,
        scan_scene,
    )
    from telefringe.simulate.presets import bin_camera_any, get_preset
    from telefringe.simulate.scenes import default_sphere

    vrig = bin_camera_any(get_preset("stereo"), args.bin)
    names = vrig.rig.camera_names
    noise = vrig.photometry.noise_model()
    plane, sph = held_out_plane(vrig), default_sphere()
    rendered = {"plane": scan_scene(vrig, plane, seed=args.seed + 101),
                "sphere": scan_scene(vrig, sph, seed=args.seed + 401)}
    variants = {"default": vrig,
                "noiseless": vrig.with_photometry(full_well_e=1e12, read_noise_e=0.0,
                                                  bit_depth=16),
                "noiseless-sharp": vrig.with_photometry(full_well_e=1e12, read_noise_e=0.0,
                                                        bit_depth=16, camera_blur_px=0.0)}
    rigs = [("true rig", vrig.rig, None)]
    for v in args.calibration.split(","):
        cal = calibrate_virtual(variants[v], n_poses=args.poses, seed=args.seed)
        rigs.append((f"rig calibrated ({v})", cal.rig, cal))
    for label, rig, cal in rigs:
        print(label + ("" if cal is None else ": reprojection RMS " + ", ".join(
            f"{d} {float(r.rms):.4f} px" for d, r in cal.devices.items())))
        for data in ("true maps", "decoded"):
            out = []
            for scene, (scans, truths) in rendered.items():
                coords = (_true_maps(truths) if data == "true maps"
                          else _decode_all(scans, cal, noise) if cal is not None
                          else _decode_all(scans, None, noise))
                cloud = triangulate_stereo(rig, coords[names[0]], coords[names[1]])
                if scene == "plane":
                    e, s, _ = _plane_errors(cloud, plane)
                    out.append(f"plate {np.mean(e) * 1e3:+.3f} um "
                               f"({np.mean(e) / np.median(s):+.3f} pixel sigma), RMS "
                               f"{np.std(e) * 1e3:.3f} um")
                else:
                    fit = measure_sphere(cloud).sphere
                    out.append(f"sphere radius {(fit.radius - sph.radius) * 1e3:+.3f} um "
                               f"(sd {np.sqrt(fit.covariance[3, 3]) * 1e3:.3f})")
            print(f"  {data:<9}: " + "; ".join(out), flush=True)


if __name__ == "__main__":
    main()
