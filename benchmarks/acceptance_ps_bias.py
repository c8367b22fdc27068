"""Why the stereo rig's PS is biased: per test sphere of a ``simulate acceptance`` set
(true rig), the guideline's PS (free-radius least-squares fit of the points, as
``telefringe accept``) with its U (k = 2, the points taken as independent), and the
size error of the same eroded points fitted through the cameras' point-spread model
(:func:`telefringe.metrology.acceptance.spread_probing_size`, each camera's spread
variance estimated with the sphere) with 2 x its fit's sigma, in um.

    .venv/bin/python benchmarks/acceptance_ps_bias.py DIR [--rig stereo] [--bin 4]

DIR is the ``--out`` of ``benchmarks/acceptance_anyrig.py`` (``DIR/RIG/sim`` and
``DIR/RIG/rig.json`` are reused; run that first).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from telefringe.io.acceptance_json import load_acceptance_set, load_artefacts
from telefringe.io.rig_json import load_rig
from telefringe.io.scan_json import read_scan
from telefringe.metrology.acceptance import evaluate_position, spread_probing_size
from telefringe.metrology.spheres import sphere_spread_options
from telefringe.reconstruction._rig import as_rig
from telefringe.reconstruction.pipeline import reconstruct_scan, reconstruct_stereo_scans


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dir", type=Path)
    ap.add_argument("--rig", default="stereo")
    a = ap.parse_args(argv)
    root = a.dir / a.rig
    folder = root / "sim" / "acceptance"
    rig = as_rig(load_rig(root / "rig.json"))
    cert = load_artefacts(root / "sim" / "artefacts.json")
    print(f"{a.rig}: sphere {cert.sphere_diameter:.4f} mm; um")
    print(f"{'position':10} {'n':>5} {'PS':>7} {'U':>5} {'PS/U':>5}   {'spread PS':>9} "
          f"{'2u':>5}  s^2 per camera (px^2)")
    for e in load_acceptance_set(folder):
        if e.artefact != "sphere":
            continue
        scan = read_scan(folder / e.scan)
        scan_2 = None if e.second is None else read_scan(folder / e.second)
        if scan_2 is None:
            rec = reconstruct_scan(scan, rig, with_height_map=False, gamma_correction=False)
        else:
            rec = reconstruct_stereo_scans(scan, scan_2, rig, with_height_map=False,
                                           gamma_correction=False)
        cl = rec.cloud
        pos = evaluate_position(e.name, "sphere", cl.xyz, cl.mask, cert)
        t = pos.test
        U = 2.0 * np.hypot(cert.u_of("PS"), t.u_fit_diameter)
        opts = sphere_spread_options(rig, rec.radiance, cl.shape, scan.manifest, scan_2)
        opts.pop("rig")
        sp = spread_probing_size(pos, cl, cert, rig, opts.pop("image"), **opts).spread
        print(f"{e.name:10} {t.n_points:5d} {t.PS * 1e3:+7.1f} {U * 1e3:5.1f} "
              f"{t.PS / U:+5.1f}   {sp.PS * 1e3:+9.1f} {2 * sp.u_fit_diameter * 1e3:5.1f}  "
              + " ".join(f"{v:.3f}" for v in sp.variances_px2)
              + f"  ({sp.n_points} points)", flush=True)


if __name__ == "__main__":
    main()
