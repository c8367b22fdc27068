"""The VDI/VDE 2634-2 acceptance test on the virtual mixes (mixed, macro, stereo): for
each rig, ``telefringe simulate acceptance`` (23 positions; a stereo rig renders both
cameras) and ``telefringe accept`` with the true rig (no calibration error: what the
measurement itself makes of the artefacts), then the maxima of PF, PS, SD and F and the
range of PS over the spheres, and of the test spheres' size error through the cameras'
point-spread model with how many accept flags (docs/acceptance.md), in um.

    .venv/bin/python benchmarks/acceptance_anyrig.py [--rig mixed,macro,stereo] [--bin 4]
        [--seed 1] [--out DIR] [--gamma]

``--bin 4`` (default) bins the cameras 4 x 4 (320 x 256) to stay within minutes on a
loaded machine. ``--gamma`` learns the projector's nonlinearity from each scan (the
default measures without a correction; the virtual projector's 8-bit patterns carry
little). Reuses ``--out DIR/RIG/sim`` when it exists.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from telefringe.cli import main
from telefringe.io.rig_json import bare_rig_json
from telefringe.simulate import presets
from telefringe.simulate.presets import bin_camera_any


def run(name: str, factor: int, out: Path, seed: int, gamma: bool) -> dict:
    make = presets.PRESETS[name]
    presets.PRESETS[name] = lambda: bin_camera_any(make(), factor)
    try:
        out.mkdir(parents=True, exist_ok=True)
        if not (out / "sim").exists():
            assert main(["-q", "simulate", "acceptance", str(out / "sim"), "--rig", name,
                         "--seed", str(seed)]) == 0
        rig = presets.PRESETS[name]().rig
    finally:
        presets.PRESETS[name] = make
    (out / "rig.json").write_text(json.dumps(bare_rig_json(rig)))
    argv = ["-q", "accept", str(out / "sim" / "acceptance"), "--rig", str(out / "rig.json"),
            "--artefacts", str(out / "sim" / "artefacts.json"), "--json",
            str(out / "result.json"), "--force"]
    assert main(argv + ([] if gamma else ["--no-gamma-correction"])) == 0
    return json.loads((out / "result.json").read_text())


def main_(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rig", default="mixed,macro,stereo")
    ap.add_argument("--bin", type=int, default=4)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--gamma", action="store_true")
    a = ap.parse_args(argv)
    root = a.out or Path(tempfile.mkdtemp(prefix="acceptance_anyrig_"))
    print(f"true rig, seed {a.seed}, cameras binned {a.bin} x {a.bin}; um; outputs in {root}")
    print(f"{'rig':8} {'PF':>7} {'PS':>7} {'SD':>7} {'F':>7}   PS range over the spheres"
          "   through the point-spread model (flagged)   cap half-angle")
    for name in a.rig.split(","):
        t0 = time.perf_counter()
        res = run(name, a.bin, root / name, a.seed, a.gamma)
        ps = [p["value"] * 1e3 for p in res["PS"]["positions"]]
        caps = [p["cap_half_angle_deg"] for p in res["PS"]["positions"]]
        sp = [p["spread_model"] for p in res["PS"]["positions"] if "spread_model" in p]
        model = (f"{min(m['value'] for m in sp) * 1e3:+.1f} .. "
                 f"{max(m['value'] for m in sp) * 1e3:+.1f} "
                 f"({sum(m['differs_from_PS'] for m in sp)} of {len(sp)})" if sp else "-")
        print(f"{name:8} " + " ".join(f"{res[q]['max'] * 1e3:+7.1f}" for q in
                                      ("PF", "PS", "SD", "F"))
              + f"   {min(ps):+.1f} .. {max(ps):+.1f}   {model}"
              + f"   {min(caps):.0f}-{max(caps):.0f} deg"
              + f"   ({time.perf_counter() - t0:.0f} s wall, machine shared)")


if __name__ == "__main__":
    main_()
