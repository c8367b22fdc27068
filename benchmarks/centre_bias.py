"""The circle-centre bias of rendered calibrations, with and without its correction.

For each seed the ``fast`` rig's calibration set (random poses and noise, as
benchmarks/uncertainty.py draws them) is rendered once and its observations (the detected
circle centres and the projector coordinates read there) are cached as a pickle in
``--cache`` (default ``$TMPDIR/telefringe-centre-bias``). Each set is then calibrated twice:
without the centre correction (``marker_radius=None``) and with it (the target's radius:
the centres corrected with the current estimate through each device's full model, the
adjustment repeated). Printed per seed and as a mean: the camera magnification's error
against the true rig in units of its predicted standard deviation, and the reprojection
RMS of camera and projector.

    .venv/bin/python benchmarks/centre_bias.py [--seeds 4] [--poses 6] [--preset fast|paper-quick]
"""

from __future__ import annotations

import argparse
import itertools
import os
import pickle
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: decoding as ``telefringe calibrate`` and ``reconstruct`` do by default: the projector's
#: nonlinearity learned and removed. Without it the decoded projector coordinate carries a
#: fixed error along each projector axis (0.0024 / 0.0030 px RMS on the fast rig, a
#: function of the projector coordinate: the fused coarser groups bring their nonlinearity
#: errors at periods the surround of a marker does not average out) that every calibration
#: absorbs alike into the projector's intrinsics (m +0.8, u0 -0.9, v0 -1.0, k1 +1.0 of
#: their standard deviations; with the correction within 0.2, s2 -0.4).
DECODE = {"gamma_correction": True}


def learned_phase_errors(scan) -> dict:
    """The projector nonlinearity learned from one scan, ``(axis, periods, steps) ->
    PhaseErrorModel`` (the models calibrate_from_scans collects from each pose)."""
    from telefringe.calibration.from_scans import _learned_models
    from telefringe.fringes.decode import decode

    return _learned_models(scan, decode(scan, **DECODE))


class _Captured(Exception):
    pass


#: what the observations depend on (a change makes new ones): every package they pass
#: through, and the module that reads them and calls the calibration
OBSERVATION_SOURCES = ("geometry", "devices", "fringes", "targets", "simulate",
                       "calibration/from_scans.py")


def code_digest(sources=OBSERVATION_SOURCES) -> str:
    """A short digest of telefringe's sources under ``sources`` (sub-packages or files
    relative to the package): cached results made by other code are never reused."""
    import hashlib

    import telefringe

    root = Path(telefringe.__file__).parent
    h = hashlib.sha256()
    for sub in sources:
        p = root / sub
        for f in (sorted(p.rglob("*.py")) if p.is_dir() else [p]):
            h.update(f.relative_to(root).as_posix().encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:10]


def observations(vrig, preset: str, seed: int, n_poses: int, cache: Path):
    """(args, kwargs) of the calibrate_devices call calibrate_from_scans makes, cached
    (under the digest of the code that makes them)."""
    tag = "g" if DECODE["gamma_correction"] else "ng"
    path = cache / f"obs_{preset}_p{n_poses}_s{seed:03d}_{tag}_{code_digest()}.pkl"
    if path.exists():
        return pickle.loads(path.read_bytes())
    import telefringe.calibration.from_scans as fs
    from telefringe.simulate.calibration import (
        calibration_manifest,
        iter_calibration_set,
        simulate_calibration_poses,
    )

    poses = simulate_calibration_poses(vrig, n_poses=n_poses, seed=seed)
    man = calibration_manifest(vrig, poses)
    got = {}

    def capture(*args, **kwargs):
        got["call"] = (args, kwargs)
        raise _Captured

    orig = fs.calibrate_devices
    fs.calibrate_devices = capture
    options = dict(DECODE)
    try:
        rendered = iter_calibration_set(vrig, poses, seed=1000 + seed)
        first = next(rendered)
        if DECODE["gamma_correction"]:
            # learned once, from the reference pose, and given to every pose's decoding:
            # the same correction as learning it from each (a property of the projector,
            # 5 s CPU per pose to learn), at a sixth of the time
            options["phase_errors"] = learned_phase_errors(first[1])
        scans = ((name, scan) for name, scan, _, _ in itertools.chain([first], rendered))
        fs.calibrate_from_scans(scans, man.target, man.camera_pixel_size,
                                man.projector_pixel_size, man.reference_pose,
                                projector_side=man.projector_side, decode_options=options)
    except _Captured:
        pass
    finally:
        fs.calibrate_devices = orig
    cache.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_bytes(pickle.dumps(got["call"]))
    tmp.replace(path)
    return got["call"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--poses", type=int, default=6)
    ap.add_argument("--preset", default="fast", help="a preset, or paper-quick (the paper "
                    "rig binned 2 x 2)")
    ap.add_argument("--cache", type=Path, default=Path(
        os.environ.get("TMPDIR", tempfile.gettempdir())) / "telefringe-centre-bias")
    ap.add_argument("--render-only", action="store_true")
    a = ap.parse_args(argv)
    from telefringe.calibration.rig import calibrate_devices
    from telefringe.simulate.presets import get_preset

    if a.preset == "paper-quick":  # the paper rig as `telefringe paper --quick` has it
        from telefringe.simulate.experiments import paper_rig

        vrig = paper_rig(quick=True)
    else:
        vrig = get_preset(a.preset)
    m_true = vrig.rig.camera.intrinsics.m
    rows = {False: [], True: []}
    for s in range(a.first_seed, a.first_seed + a.seeds):
        t0 = time.process_time()
        args, kwargs = observations(vrig, a.preset, s, a.poses, a.cache)
        print(f"seed {s}: observations ({time.process_time() - t0:.0f} s CPU)", flush=True)
        if a.render_only:
            continue
        for corr in (False, True):
            kw = dict(kwargs)
            if corr:
                kw["centre_bias"] = "full"
            else:
                kw["marker_radius"] = None
            t0 = time.process_time()
            cal = calibrate_devices(*args, **kw)
            z = (cal.camera.intrinsics.m - m_true) / cal.std_of("camera.m")
            rows[corr].append((z, (cal.camera.intrinsics.m / m_true - 1),
                               cal.rms_camera, cal.rms_projector))
            print(f"  {'corrected  ' if corr else 'uncorrected'}: m error {z:+.2f} sigma "
                  f"({rows[corr][-1][1]:+.2e} rel), rms {cal.rms_camera:.4f} / "
                  f"{cal.rms_projector:.4f} px ({time.process_time() - t0:.0f} s CPU)",
                  flush=True)
    for corr in (False, True):
        if rows[corr]:
            r = np.array(rows[corr])
            sd = r[:, 0].std(ddof=1) if len(r) > 1 else 0.0
            print(f"{'corrected  ' if corr else 'uncorrected'} over {len(r)} seeds: m error "
                  f"mean {r[:, 0].mean():+.2f} sigma (sd {sd:.2f}),"
                  f" mean {r[:, 1].mean():+.2e} rel; rms camera {r[:, 2].mean():.4f} px, "
                  f"projector {r[:, 3].mean():.4f} px")
    return 0


if __name__ == "__main__":
    sys.exit(main())
