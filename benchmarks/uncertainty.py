"""Monte Carlo check of the calibration uncertainty propagated into measurements.

The ``fast`` virtual rig's calibration set (fixed poses) is rendered with N different
noise seeds and calibrated N times (each calibration is cached as rig.json in
``--cache``, default ``$TMPDIR/telefringe-uncertainty``: a rerun only calibrates the seeds
it lacks). Held-out scenes (a tilted circle plate, a step gauge, a sphere on a plane, a
BGA read at full resolution through a window) are rendered and decoded once (the plate
in ``--plate-draws`` noise draws, see PLATE_SEEDS); each of the N rigs triangulates and
measures them. Per quantity the table gives the calibration
uncertainty u_cal predicted from each rig's covariance (median over the rigs), the
spread observed over the N rigs (their standard deviation: the scenes' noise is the same
for every rig, so the spread is the calibration's alone), their ratio, and the coverage:
the share of (rig, quantity) cases where |measured - true| <= U = 2 u (u with the noise
part). Goals (issue 13): ratio within 1 +- 0.25, coverage >= 90 %.

    .venv/bin/python benchmarks/uncertainty.py [--seeds 40] [--poses 6] [--cache DIR]
        [--only plate,steps,sphere,bga] [--plate-draws 4]
        [--plate-edge-supersample 21]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

DECODE = {"gamma_correction": True}  # as benchmarks/centre_bias.py's calibrations


def calibrate_seeds(cache: Path, seeds, n_poses: int, *, log=print, available=False):
    """Calibrate the ``fast`` rig once per seed (random poses and noise). The observations
    (detected centres, projector read there: the call calibrate_from_scans makes) are
    cached in ``cache`` under the digest of the code making them
    (benchmarks/centre_bias.py), the calibrations under the digest of the calibration
    too: a changed calibration only calibrates again."""
    from centre_bias import code_digest, observations

    from telefringe.calibration.rig import calibrate_devices
    from telefringe.io.rig_json import load_rig, save_rig
    from telefringe.simulate.presets import get_preset

    vrig = get_preset("fast")
    cache.mkdir(parents=True, exist_ok=True)
    digest = code_digest(("geometry", "devices", "fringes", "targets", "simulate",
                          "calibration"))
    rigs = []
    for s in seeds:
        tag = "g" if DECODE["gamma_correction"] else "ng"
        path = cache / f"rig_fast_p{n_poses}_poses_and_noise_s{s:03d}_{tag}_{digest}.json"
        if available and not path.exists():
            continue
        if not path.exists():
            # poses drawn anew with the noise: a fixed pose set would keep the same
            # systematic part of the observations' errors (which the covariance, scaled by
            # the residuals, holds) in every calibration, out of the spread
            t0 = time.process_time()
            args, kwargs = observations(vrig, "fast", s, n_poses, cache)
            cal = calibrate_devices(*args, **kwargs)
            save_rig(path, cal, force=True)
            log(f"calibrated seed {s}: rms {cal.rms_camera:.4f} / {cal.rms_projector:.4f} px, "
                f"{time.process_time() - t0:.0f} s CPU")
        rigs.append(load_rig(path))
    return vrig, rigs


#: Noise seeds of the held-out plate's renders. A plate's mean spacing is, per row, its
#: end markers' difference: their detection error, fixed for one image, is half of the
#: spacing's u (0.03 um of u_noise, twice u_cal), so one render is one draw of it and its
#: coverage over the rigs the luck of that draw (with the true rig and 7 edge sub-samples,
#: seeds 501, 502, 503 of that scene: X +0.056, +0.005, +0.010 um, u_noise 0.030). With
#: 21 sub-samples these four draw X +0.030, +0.002, -0.013, -0.026 um and Y +0.028,
#: -0.021, -0.050, -0.017 um, u_noise 0.029 and 0.035. Coverage and spread are pooled over
#: the rigs and these draws (the spread over the rigs for each draw: the calibration's).
PLATE_SEEDS = (501, 601, 701, 801)
#: Sub-samples per side of the plate's edge pixels (the preset's 7 elsewhere). The
#: renderer's midpoint rule over an edge pixel errs by a few per cent of its contrast;
#: with 7 x 7 it moves each marker's detected centre by 0.0034 px RMS, fixed per marker
#: (benchmarks/detector_bias.py), an error of the simulated image that a camera's exact
#: pixel integration does not have and that no uncertainty of the measurement can hold:
#: on the held-out pose noise-free, the spacing X from the detected centres is off by
#: +0.043 um with 7 (0.0026 px in the first column's mean), +0.009 um with 21.
PLATE_EDGE_SUPERSAMPLE = 21

BGA_WINDOW = 360  # full-resolution camera pixels (the fast rig's camera is binned 4 x 4)


def _bga_calibration(cal, col0, row0):
    """``cal`` with its camera read at full resolution in a window: the rig unbinned and
    the covariance carried through (u0, v0 scale by the binning factor)."""
    from dataclasses import replace

    from telefringe.simulate.experiments import unbin_rig

    rig = unbin_rig(cal.rig, 4, col0=col0, row0=row0, width=BGA_WINDOW, height=BGA_WINDOW)
    D = np.ones(len(cal.parameter_names))
    for name in ("camera.u0", "camera.v0"):
        D[cal.parameter_names.index(name)] = 4.0
    cov = cal.covariance * np.outer(D, D)
    return replace(cal, rig=rig, covariance=cov, std=np.sqrt(np.diag(cov)))


def held_out_scenes(vrig, only=None, *, plate_seed: int = PLATE_SEEDS[0],
                    plate_edge_supersample: int = PLATE_EDGE_SUPERSAMPLE):
    """Render and decode the held-out scenes named in ``only`` (default: all of
    :data:`SCENES`) once: name -> dict (coords, texture, truth). The plate is rendered
    with the noise seed ``plate_seed`` and ``plate_edge_supersample`` sub-samples per side
    of its edge pixels (see :data:`PLATE_EDGE_SUPERSAMPLE`)."""
    from dataclasses import replace

    from telefringe.fringes.decode import decode
    from telefringe.fringes.images import fringe_free_image, scan_radiance
    from telefringe.geometry.so3 import rotation_from_rotvec
    from telefringe.simulate.experiments import bga_window, unbin_rig
    from telefringe.simulate.presets import HDR_EXPOSURES
    from telefringe.simulate.render import default_groups, render_scan
    from telefringe.simulate.scenes import default_bga, default_steps, plate_from_target

    only = SCENES if only is None else only
    groups = default_groups(vrig)
    out = {}
    T = vrig.target
    c_t = np.array([(T.cols - 1) * T.pitch_mm / 2, (T.rows - 1) * T.pitch_mm / 2, 0.0])
    R = rotation_from_rotvec(np.radians([6.0, -4.0, 3.0]))
    t = c_t + np.array([0.5, -0.3, 0.8]) - R @ c_t
    if "plate" in only:
        vplate = vrig.with_photometry(edge_supersample=int(plate_edge_supersample))
        scan, _ = render_scan(vplate, plate_from_target(T, R, t), groups, seed=plate_seed)
        out["plate"] = dict(coords=decode(scan, **DECODE), texture=fringe_free_image(scan),
                            normal=R[:, 2], point=t)
    if "steps" in only:
        steps = default_steps()
        scan, _ = render_scan(vrig, steps, groups, seed=502)
        out["steps"] = dict(coords=decode(scan, **DECODE),
                            heights=np.concatenate([[0.0], np.asarray(steps.blocks)[:, 5]]))
    if "sphere" in only:
        out["sphere"] = sphere_scene(vrig)
    if "bga" not in only:
        return out
    bga = default_bga(0, rows=10, cols=10, n_missing=2)
    fine = replace(vrig, rig=unbin_rig(vrig.rig, 4))
    col0, row0 = bga_window(fine, size=BGA_WINDOW)
    vwin = replace(vrig, rig=unbin_rig(vrig.rig, 4, col0=col0, row0=row0, width=BGA_WINDOW,
                                       height=BGA_WINDOW))
    scan, _ = render_scan(vwin, bga, groups, exposures=HDR_EXPOSURES, seed=504)
    out["bga"] = dict(coords=decode(scan, **DECODE), radiance=scan_radiance(scan), bga=bga,
                      window=(col0, row0))
    return out


def sphere_scene(vrig):
    """The held-out sphere: decoded coordinates, the brightness (the fringes' mean level)
    and the finest fringe periods, which the sphere's point-spread model needs."""
    from telefringe.fringes.decode import decode
    from telefringe.fringes.images import scan_radiance
    from telefringe.metrology.spheres import finest_fringe_periods
    from telefringe.simulate.render import default_groups, render_scan
    from telefringe.simulate.scenes import Sphere

    sph = Sphere(center=np.array([15.0, 12.0, -1.0]), radius=2.5)
    scan, _ = render_scan(vrig, sph, default_groups(vrig), seed=503)
    return dict(coords=decode(scan, **DECODE), centre=np.asarray(sph.center),
                radius=sph.radius, radiance=scan_radiance(scan),
                periods=finest_fringe_periods(scan.manifest))


SCENES = ("plate", "steps", "sphere", "bga")


def measure_all(cal, scenes, only=SCENES):
    """Measure the held-out scenes named in ``only`` with one calibration: list of
    (quantity, value, truth, u_noise, u_cal) rows (arrays flattened)."""
    from telefringe.metrology import (
        BGANominal,
        BGAOptions,
        Plane,
        measure_bga,
        measure_plate,
        measure_sphere,
        measure_steps,
        seating_plane_coplanarity,
    )
    from telefringe.metrology.uncertainty import (
        bga_uncertainty,
        plate_uncertainty,
        sphere_uncertainty,
        steps_uncertainty,
    )
    from telefringe.reconstruction.telecentric import triangulate
    from telefringe.targets.circle_grid import detect_circle_grid

    rows = []

    def add(name, unc, truth):
        v = np.ravel(unc.value)
        rows.append((name, v, np.broadcast_to(np.ravel(truth), v.shape),
                     np.broadcast_to(np.ravel(unc.u_noise), v.shape),
                     np.broadcast_to(np.ravel(unc.u_calibration), v.shape)))

    if "plate" in only:
        got = {}
        for s in scenes["plate"]:  # one dict per noise draw (PLATE_SEEDS)
            cloud = triangulate(cal.rig, s["coords"])
            if "det" not in s:
                s["det"] = detect_circle_grid(s["texture"], rows=9, cols=11)
            # the detected centres corrected through the rig's camera (markers 1.5 mm
            # across), with their uncertainties from the detector's fits
            m = plate_uncertainty(measure_plate(cloud, s["det"].centers, rows=9, cols=11,
                                                pitch_mm=3.0, camera=cal.rig.camera,
                                                marker_diameter_mm=1.5,
                                                centres_sigma_px=s["det"].center_sigma),
                                  cloud, cal)
            n_t = s["normal"] * np.sign(s["normal"][2])
            pa = np.asarray(m.z.at)
            z_true = (n_t @ s["point"] - n_t[0] * pa[0] - n_t[1] * pa[1]) / n_t[2]
            for name, key, truth in (("plate Z", "z", z_true),
                                     ("plate tilt (deg)", "tilt_deg",
                                      np.degrees(np.arccos(n_t[2]))),
                                     ("marker spacing X", "spacing_x", 3.0),
                                     ("marker spacing Y", "spacing_y", 3.0)):
                got.setdefault(name, []).append((m.uncertainty[key], truth))
        for name, draws in got.items():
            add(name, _cat(*(u for u, _ in draws)), np.array([t for _, t in draws]))

    if "steps" in only:
        s = scenes["steps"]
        cloud = triangulate(cal.rig, s["coords"])
        m = steps_uncertainty(measure_steps(cloud), cloud, cal)
        if m.heights.size == s["heights"].size:
            add("step heights", m.uncertainty["step_heights"], np.diff(s["heights"]))
            add("level heights (above base)", _skip0(m.uncertainty["heights"]),
                s["heights"][1:])

    if "sphere" in only:
        s = scenes["sphere"]
        cloud = triangulate(cal.rig, s["coords"])
        m = sphere_uncertainty(measure_sphere(cloud, rig=cal.rig, image=s["radiance"],
                                              fringe_periods=s["periods"]), cloud, cal)
        add("sphere radius", m.uncertainty["radius"], s["radius"])
        add("sphere centre", m.uncertainty["centre"], s["centre"])

    if "bga" not in only:
        return rows
    s = scenes["bga"]
    bga = s["bga"]
    cal_w = _bga_calibration(cal, *s["window"])
    cloud = triangulate(cal_w.rig, s["coords"])
    nominal = BGANominal(rows=bga.rows, cols=bga.cols, pitch_mm=bga.pitch,
                         ball_diameter_mm=bga.ball_diameter)
    m = bga_uncertainty(measure_bga(cloud, nominal, image=s["radiance"],
                                    options=BGAOptions(seed=0)), cloud, cal_w)
    idx = np.asarray(m.index)
    true_h = (bga.ball_height + np.asarray(bga.height_offsets))[idx[:, 0], idx[:, 1]]
    add("BGA apex heights", m.uncertainty["height"], true_h)
    grid = np.stack([idx[:, 1], idx[:, 0]], axis=1) * bga.pitch
    add("BGA positions", m.uncertainty["position"], grid)
    add("BGA pitch", _cat(m.uncertainty["pitch_x"], m.uncertainty["pitch_y"]), bga.pitch)
    present = bga.present()
    cog = np.array([bga.origin[0] + (bga.cols - 1) * bga.pitch / 2,
                    bga.origin[1] + (bga.rows - 1) * bga.pitch / 2])
    cop_t = seating_plane_coplanarity(bga.apexes_world()[present], cog,
                                      reference=Plane.horizontal(0.0)).value
    add("BGA coplanarity", m.uncertainty["coplanarity"], cop_t)
    return rows


def _skip0(unc):
    from telefringe.metrology.uncertainty import Uncertainty

    return Uncertainty(np.ravel(unc.value)[1:], np.ravel(unc.u_noise)[1:],
                       np.ravel(unc.u_calibration)[1:])


def _cat(*parts):
    """The values of several Uncertainty objects in one (non-finite values dropped)."""
    from telefringe.metrology.uncertainty import Uncertainty

    def cat(field):
        return np.concatenate([np.broadcast_to(np.ravel(getattr(p, field)),
                                               np.ravel(p.value).shape) for p in parts])

    v = cat("value")
    ok = np.isfinite(v)
    return Uncertainty(v[ok], cat("u_noise")[ok], cat("u_calibration")[ok])


def table(per_rig, reference):
    """Per quantity: (name, n values, predicted u_cal, RMS deviation from the true rig's
    measurement, spread (std over the rigs), ratio, calibration coverage, coverage
    against the truth, median u_noise, mean error against the truth).

    ``per_rig``: the rows of :func:`measure_all` for each calibration; ``reference``:
    the rows measured with the true rig (the same decoded scenes), whose error is the
    scenes' own (noise and the measurement's bias) without any calibration error.
    """
    out = []
    for q, ref in enumerate(reference):
        name = ref[0]
        vals = np.array([rig[q][1] for rig in per_rig])  # (N, m)
        truth = np.array([rig[q][2] for rig in per_rig])
        un = np.array([rig[q][3] for rig in per_rig])
        uc = np.array([rig[q][4] for rig in per_rig])
        pred = float(np.sqrt(np.mean(np.median(uc, axis=0) ** 2)))
        dev = vals - ref[1][None, :]
        rms_dev = float(np.sqrt(np.mean(dev ** 2)))
        spread = float(np.sqrt(np.mean(np.var(vals, axis=0, ddof=1))))
        cal_cover = float(np.mean(np.abs(dev) <= 2.0 * uc))
        U = 2.0 * np.hypot(np.nan_to_num(un), uc)
        cover = float(np.mean(np.abs(vals - truth) <= U))
        out.append((name, vals.shape[1], pred, rms_dev, spread, rms_dev / pred, cal_cover,
                    cover, float(np.median(un)), float(np.mean(vals - truth))))
    return out


def _true_calibration(cal, vrig):
    """``cal`` holding the true rig (its covariance is not used)."""
    from dataclasses import replace

    return replace(cal, rig=vrig.rig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=40)
    ap.add_argument("--poses", type=int, default=6)
    ap.add_argument("--cache", type=Path,
                    default=Path(tempfile.gettempdir()) / "telefringe-uncertainty")
    ap.add_argument("--first-seed", type=int, default=0,
                    help="seeds first-seed .. first-seed + seeds - 1 (to calibrate in parts)")
    ap.add_argument("--calibrate-only", action="store_true")
    ap.add_argument("--available", action="store_true",
                    help="use only the seeds whose calibration is already in the cache")
    ap.add_argument("--plate-draws", type=int, default=len(PLATE_SEEDS),
                    help=f"noise draws of the held-out plate (1-{len(PLATE_SEEDS)})")
    ap.add_argument("--plate-edge-supersample", type=int, default=PLATE_EDGE_SUPERSAMPLE,
                    help="sub-samples per side of the plate's edge pixels (the preset: 7)")
    ap.add_argument("--only", default=",".join(SCENES),
                    help="comma-separated held-out scenes to measure (default: all of "
                    f"{', '.join(SCENES)})")
    args = ap.parse_args(argv)
    only = tuple(x.strip() for x in args.only.split(",") if x.strip())
    if not only or any(x not in SCENES for x in only):
        ap.error(f"--only takes a comma-separated subset of {', '.join(SCENES)}")
    vrig, rigs = calibrate_seeds(args.cache, range(args.first_seed, args.first_seed + args.seeds),
                                 args.poses, available=args.available)
    if args.calibrate_only:
        return 0
    t0 = time.process_time()
    import pickle

    from centre_bias import code_digest

    tag = "g" if DECODE["gamma_correction"] else "ng"
    scenes = {}

    def cached(label, make):  # each scene (plate draw) cached on its own
        f = args.cache / f"held_out_{label}_{tag}_{code_digest()}.pickle"
        if f.exists():
            return pickle.loads(f.read_bytes())
        out = make()
        f.write_bytes(pickle.dumps(out))
        return out

    for name in only:
        if name == "plate":
            es = args.plate_edge_supersample
            scenes[name] = [cached(f"plate_s{k}_e{es}",
                                   lambda k=k, es=es: held_out_scenes(
                                       vrig, ("plate",), plate_seed=k,
                                       plate_edge_supersample=es)["plate"])
                            for k in PLATE_SEEDS[:args.plate_draws]]
        else:
            scenes[name] = cached(name, lambda name=name: held_out_scenes(vrig, (name,))[name])
    print(f"held-out scenes rendered and decoded: {time.process_time() - t0:.0f} s CPU",
          flush=True)
    per_rig = []
    t0 = time.process_time()
    for k, cal in enumerate(rigs):
        per_rig.append(measure_all(cal, scenes, only))
        print(f"rig {k + 1}/{len(rigs)} measured", file=sys.stderr, flush=True)
    print(f"measured with {len(rigs)} rigs: {time.process_time() - t0:.0f} s CPU")
    reference = measure_all(_true_calibration(rigs[0], vrig), scenes, only)
    rows = table(per_rig, reference)
    print(f"\nfast rig, {args.poses} calibration poses, N = {len(rigs)} calibrations "
          f"(each its own random poses and noise); um unless noted\n")
    print("| quantity | values | predicted u_cal | observed spread | ratio | common offset "
          "of the rigs | coverage abs(err) <= U | median u_noise | mean error vs truth |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    ok = True
    for name, m, pred, rms_dev, spread, _, _, cover, un, bias in rows:
        f = 1.0 if "deg" in name else 1000.0
        unit = " deg" if "deg" in name else ""
        offset = np.sqrt(max(rms_dev ** 2 - spread ** 2 * (len(rigs) - 1) / len(rigs), 0.0))
        ratio = spread / pred
        print(f"| {name} | {m} | {pred * f:.3g}{unit} | {spread * f:.3g}{unit} | "
              f"{ratio:.2f} | {offset * f:.3g}{unit} | {cover:.0%} | {un * f:.3g}{unit} | "
              f"{bias * f:+.3g}{unit} |")
        ok &= bool(0.75 <= ratio <= 1.25 and cover >= 0.9)
    print("\nobserved spread: standard deviation over the rigs (RMS over a quantity's values); "
          "ratio = spread / predicted u_cal;\ncommon offset: RMS of the mean deviation of the "
          "rigs' measurements from the true rig's (a bias shared by the calibrations, which "
          "no covariance holds);\ncoverage: share of (rig, value) with abs(measured - true) "
          "<= U = 2 u, u = sqrt(u_noise^2 + u_cal^2)")
    print(f"\nsampling error of a spread from N = {len(rigs)}: "
          f"{1 / np.sqrt(2 * (len(rigs) - 1)):.1%} (one sigma)")
    print("all within goals (ratio 0.75-1.25, coverage >= 90 %)" if ok else
          "NOT all within goals")
    return 0


if __name__ == "__main__":
    os.environ.setdefault("PYTHONHASHSEED", "0")
    sys.exit(main())
