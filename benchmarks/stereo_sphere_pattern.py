"""Where the stereo sphere's size bias comes from: for test spheres of the ``stereo``
preset (true rig), the points' radial errors against the rendered sphere by their
distance (px) to the second camera's silhouette, PS as ``accept`` measures it, PS with
the points matched near the second camera's silhouette left out, and PS with the second
camera's bilinear interpolation corrected from its map's second differences (the
interpolation's error ``-(fx (1 - fx) M_xx + fy (1 - fy) M_yy) / 2`` moved along the
line by the phase's slope), in um.

    .venv/bin/python benchmarks/stereo_sphere_pattern.py [--bin 8] [--spheres 0,3]

The figures in docs/acceptance.md ("How the cause was found") are of ``--bin 8
--spheres 0,3``: a smooth pattern over the cap (about +4 um near the silhouettes, -4
um at the top, mean about zero), no edge outliers, interpolation not the main part.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy import ndimage

from telefringe.geometry.interpolation import bilinear
from telefringe.metrology.acceptance import Artefacts, evaluate_position
from telefringe.metrology.acceptance.fits import ls_sphere
from telefringe.reconstruction.pipeline import reconstruct_stereo_scans
from telefringe.simulate.acceptance import acceptance_positions, iter_acceptance_scans
from telefringe.simulate.presets import bin_camera_any, get_preset


def _second_difference(M, axis: int):
    out = np.full(M.shape, np.nan)
    if axis == 1:
        out[:, 1:-1] = M[:, :-2] - 2 * M[:, 1:-1] + M[:, 2:]
    else:
        out[1:-1] = M[:-2] - 2 * M[1:-1] + M[2:]
    return out


def _interpolation_shift(cam2, coords_2, X, d):
    """(n,) mm along the first camera's lines: where the points move when the second
    camera's maps are read with the bilinear interpolation's error removed (the two axes
    combined with equal weights)."""
    num = np.zeros(len(X))
    den = np.zeros(len(X))
    valid = np.asarray(coords_2.mask, dtype=bool)
    for M in (coords_2.u_p, coords_2.v_p):
        M = np.where(valid, np.asarray(M, dtype=float), np.nan)
        u2, v2 = cam2.project(X)
        _, _, _, (_, _, fx, fy) = bilinear(M, u2, v2)
        h = 1e-4
        g = (bilinear(M, *cam2.project(X + h * d))[0]
             - bilinear(M, *cam2.project(X - h * d))[0]) / (2 * h)
        c = -0.5 * (fx * (1 - fx) * bilinear(_second_difference(M, 1), u2, v2)[0]
                    + fy * (1 - fy) * bilinear(_second_difference(M, 0), u2, v2)[0])
        c = np.where(np.isfinite(c), c, 0.0)
        num += g * c
        den += g * g
    return -num / den


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bin", type=int, default=8)
    ap.add_argument("--spheres", default="0,3")
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args(argv)
    vrig = bin_camera_any(get_preset("stereo"), a.bin)
    art, pos = acceptance_positions(vrig)
    chosen = [pos[int(k)] for k in a.spheres.split(",")]
    cams = vrig.camera_names
    cam2 = vrig.rig.cameras[cams[1]]
    D = art.sphere_diameter
    cert = Artefacts(D, 1e-4, 0.0, 1e-4, 1.0, 1e-4, (D, D), 0.0, 1e-4)
    first = iter_acceptance_scans(vrig, chosen, seed=a.seed, camera=cams[0])
    second = iter_acceptance_scans(vrig, chosen, seed=a.seed, camera=cams[1])
    for (p, s1, _), (_, s2, _) in zip(first, second, strict=True):
        rec = reconstruct_stereo_scans(s1, s2, vrig.rig, with_height_map=False,
                                       gamma_correction=False)
        cl = rec.cloud
        c0, r0 = p.scene.centres[0], p.scene.radii[0]
        t = evaluate_position(p.name, "sphere", cl.xyz, cl.mask, cert).test
        px = evaluate_position(p.name, "sphere", cl.xyz, cl.mask, cert).pixels[0][t.kept]
        X = cl.xyz[px[:, 0], px[:, 1]]
        d = np.broadcast_to(np.asarray(cl.directions) if np.ndim(cl.directions) == 1
                            else cl.directions[px[:, 0], px[:, 1]], X.shape)
        err = np.linalg.norm(X - c0, axis=1) - r0
        u2, v2 = rec.match.u2[px[:, 0], px[:, 1]], rec.match.v2[px[:, 0], px[:, 1]]
        lab, _ = ndimage.label(np.asarray(rec.coords_2.mask, dtype=bool))
        main_label = np.bincount(lab[np.round(v2).astype(int), np.round(u2).astype(int)]
                                 ).argmax()
        edge2 = ndimage.map_coordinates(ndimage.distance_transform_edt(lab == main_label),
                                        [v2, u2], order=1)
        print(f"{p.name}: sphere {2 * r0:.4f} mm (nominal {D:.4f}); PS {t.PS * 1e3:+.1f} um, "
              f"{len(X)} points, radial error against the rendered sphere "
              f"{err.mean() * 1e3:+.2f} um mean")
        for lo, hi in ((0, 3), (3, 4), (4, 5), (5, 6), (6, 8), (8, 99)):
            s = (edge2 >= lo) & (edge2 < hi)
            if s.any():
                print(f"   {lo}-{hi} px from the second camera's silhouette: {s.sum():4d} "
                      f"points, radial error {err[s].mean() * 1e3:+6.2f} um "
                      f"(sd {err[s].std() * 1e3:.2f})")
        for thr in (2, 3, 4):
            k = edge2 > thr + 0.5
            print(f"   without the points within {thr} px of it: PS "
                  f"{(ls_sphere(X[k]).diameter - D) * 1e3:+.1f} um ({k.sum()} points)")
        Xc = X + _interpolation_shift(cam2, rec.coords_2, X, d)[:, None] * d
        print(f"   interpolation corrected: PS {(ls_sphere(Xc).diameter - D) * 1e3:+.1f} um",
              flush=True)


if __name__ == "__main__":
    main()
