"""The stereo sphere's uncertainty over noise seeds, by how the projector's nonlinearity
(gamma) is corrected (issue 11).

Usage: python benchmarks/stereo_sphere_seeds.py [--bin 4] [--seeds 10] [--first 20]
    [--modes learned,shared,true,none] [--cache DIR] [--synthetic]

``--cache DIR`` keeps each seed's decoded maps and brightness images (and the noise-free
render's) as npz files and reuses them (a seed's render and decode is about 2-3 min of
CPU; a measurement a few seconds): then only the modes that take the learned decode.
``--synthetic`` renders nothing per seed: each draw is the noise-free render's maps plus
white noise of the decoded sigmas of the seed ``--first`` (as ``white``), and its
brightness images plus white noise of the camera's noise model over the scan's phase
images (what ``scan_radiance`` averages): every systematic effect of the render kept,
the noise exactly what the models say, a draw ~2.5 s of CPU.

The ``stereo`` preset's default sphere is rendered with ``--seeds`` noise seeds (from
``--first``) and measured with the TRUE rig (no calibration error) as ``measure sphere``
does with two cameras: matched (``match_stereo``), fitted through the point-spread model
with the match's correlated noise (``match_noise``). Each scan is decoded with the
camera's noise model and the gamma correction

- ``learned``: learned from each camera's own scan (the decoder's default without a
  calibration; the two cameras' estimates differ by their noise);
- ``shared``: learned from the first camera's scan and given to both (one estimate: a
  phase error common to both cameras at the same projector phase cancels in the match);
- ``true``: each camera's model learned from a noise-free render of the same scene
  (the population value, no estimation noise);
- ``none``: no correction.

Diagnostics (the gamma learned per scan, as ``learned``), to find what else the
predicted uncertainty misses:

- ``quiet-image``: the point-spread model's brightness images (``image``, ``image_2``)
  from a noise-free render (the points keep their noise);
- ``fixed-s2``: the spread variance given (the renderer's, ``psf_variance``) instead of
  estimated with the sphere;
- ``white``: each camera's decoded map of the noise-free render plus white Gaussian
  noise of this scan's decoded sigmas (every systematic effect kept, the noise exactly
  what the model says);
- ``white-1`` / ``white-2``: that for the first / second camera only;
- ``quiet``: both maps of the noise-free render (no noise at all; this scan's sigmas);
  ``quiet-fixed-s2``: and the spread variance given;
- ``shuffled``: the noise-free maps plus this scan's own decoding errors (decoded minus
  noise-free map, over sigma), shuffled among the pixels (the same values, their
  places random);
- ``no-reject``: the robust fit's rejection of points off (``reject_k`` 1e9);
- ``shared-s2`` / ``split-s2``: one spread variance for both cameras / one each
  (``psf_shared`` True / False; before 2026-12-02 the default chose by a pre-test, now
  it is one each, as ``learned``).

Printed per mode: each seed's errors (um), predicted sigmas and z-scores of the centre
(x, y, z) and the radius, the spread variance s^2 (px^2) and the sandwich's residual
scale k, then over the seeds the RMS of the z-scores (error / predicted sigma): ~1 when
the predicted uncertainty holds, the mean error (um) and its spread.

Measured (2026-12-02, load 10-18 on 2 cores; z RMS of centre x, y, z, radius):

- ``--seeds 10 --first 20``: learned 0.76 0.95 1.63 1.63, shared 0.77 0.95 1.64 1.64,
  true 0.75 0.93 1.64 1.64, none 0.70 0.94 1.61 1.60: the gamma correction is not the
  cause (learned minus true: 0.038 um RMS on the radius, whose sigma is 1.33 um).
  White noise 1.01 1.16 1.07 1.08; noise-free images 1.64 / 1.60; s^2 given 1.14 / 1.10.
- ``--seeds 30 --first 30 --modes learned,white,fixed-s2,shared-s2,split-s2``: learned
  1.17 0.97 1.25 1.29 (radius mean error +0.91 um, sd 1.51 um), white 1.07 1.02 1.17
  1.21 (sd 1.55 um), s^2 given 1.18 0.96 1.21 1.25 (mean +0.58, sd 1.03 um).
- ``--seeds 1 --first 20 --modes quiet,quiet-fixed-s2``: noise-free maps (with the
  scan's noisy images), s^2 estimated 0.251 px^2 (renderer 0.298): centre z -1.09 um,
  radius +0.96 um; s^2 given: +0.02 and +0.08 um. The systematic part is the s^2
  estimate's bias.
- ``--seeds 30 --first 30 --modes quiet-image``: 1.16 0.96 1.07 1.09 (radius mean
  error +0.41 um, s^2 0.304): most of that bias is the noise of the brightness images
  whose log-gradients the spread model takes (a noisy regressor shrinks s^2).

After the fit's correction for that noise (metrology/spheres.py, ``_eiv_correction``)
and one variance per camera by default (2026-12-02; the before figures from the same
cache with the previous commit's src; z RMS of centre x, y, z, radius; the sampling sd
of an RMS of n unit z-scores is about 1 / sqrt(2 n): 0.11 for 40, 0.16 for 20):

- ``--synthetic --seeds 40 --first 30 --modes learned,shared-s2 --cache DIR`` (96 s
  CPU after the noise-free render): learned (one variance per camera) 1.00 0.88 1.07
  1.09, mean error -0.13 um (centre z) and +0.17 um (radius), sd 1.89 / 1.57 um;
  shared-s2 0.96 0.89 1.08 1.10. Before: learned (the pre-test, which chose shared in
  all 40) 0.96 0.89 1.20 1.24, mean error -0.75 / +0.69 um; split-s2 1.07 0.88 1.19
  1.23.
- ``--seeds 40 --first 30 --modes learned,shared-s2 --cache DIR`` (the renders: about
  5 s of CPU each on an idle machine; 190 s CPU in all): learned 0.78 1.02 1.12 1.11,
  mean error +0.06 um (centre z) and +0.04 um (radius), sd 1.96 / 1.61 um; shared-s2
  1.11 1.01 1.12 1.11. Before (``--modes learned,shared-s2,split-s2``): learned (the
  pre-test chose shared in all 40) 1.12 1.01 1.20 1.22, mean error -0.58 / +0.58 um,
  sd 1.93 / 1.57 um; split-s2 0.84 1.02 1.20 1.23. The mean error is gone; what stays
  above 1 (1.12, one sampling sd) is the scatter, 1.12 times the predicted sigma.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np


def _models(coords) -> dict:
    """The models a decode learned, keyed as ``decode(phase_errors=...)`` takes them."""
    out = {}
    for axis, ax in coords.axes.items():
        fit = ax.phase_errors
        if fit is None:
            continue
        for m in fit.models:
            out[(axis, int(m.periods), 4)] = m
    return out


@dataclass(frozen=True)
class _Maps:
    u_p: np.ndarray
    v_p: np.ndarray
    mask: np.ndarray
    sigma_u_p: np.ndarray
    sigma_v_p: np.ndarray


def _white(quiet, noisy, rng) -> _Maps:
    """The noise-free decode ``quiet`` plus white noise of ``noisy``'s sigmas, valid
    where both are."""
    m = quiet.mask & noisy.mask
    u = np.where(m, quiet.u_p + noisy.sigma_u_p * rng.standard_normal(m.shape), np.nan)
    v = np.where(m, quiet.v_p + noisy.sigma_v_p * rng.standard_normal(m.shape), np.nan)
    return _Maps(u, v, m, np.where(m, noisy.sigma_u_p, np.nan),
                 np.where(m, noisy.sigma_v_p, np.nan))


def _shuffled(quiet, noisy, rng) -> _Maps:
    """The noise-free decode plus ``noisy``'s own normalised errors, permuted among the
    pixels valid in both, times each pixel's sigma."""
    m = quiet.mask & noisy.mask
    out = []
    for ax in ("u", "v"):
        q, x = getattr(quiet, ax + "_p"), getattr(noisy, ax + "_p")
        s = getattr(noisy, f"sigma_{ax}_p")
        z = ((x - q) / s)[m]
        full = np.full(m.shape, np.nan)
        full[m] = q[m] + s[m] * rng.permutation(z)
        out.append(full)
    return _Maps(out[0], out[1], m, np.where(m, noisy.sigma_u_p, np.nan),
                 np.where(m, noisy.sigma_v_p, np.nan))


#: modes that need the noise-free render, and the scans themselves (not cacheable)
_NEEDS_QUIET = {"true", "quiet-image", "white", "white-1", "white-2", "quiet",
                "quiet-fixed-s2", "shuffled"}
_NEEDS_SCANS = {"shared", "true", "none"}
_CACHEABLE = {"learned", "fixed-s2", "shared-s2", "split-s2", "no-reject", "quiet-image",
              "white", "white-1", "white-2", "quiet", "quiet-fixed-s2", "shuffled"}


#: the scale factor k of the last sandwich covariance (see ``_record_scale``)
_SCALE: list = []


def _record_scale():
    """Wrap ``spheres._sandwich`` to record its scale ``k = f'f / tr((I - H) C)`` (the
    residuals over what the noise model predicts for them) in ``_SCALE``."""
    from telefringe.metrology import spheres

    orig = spheres._sandwich

    def wrapped(J, a, Ninv, f, var_own, weights, sources):
        # with f'f = 1 the result is Ninv J'CJ Ninv / d, d = tr(C) - tr(H C) = tr(C) -
        # d tr(N unit) (N = inv(Ninv)): d = tr(C) / (1 + tr(N unit)), k = f'f / d
        unit = orig(J, a, Ninv, np.ones(1), var_own, weights, sources)
        use = sources >= 0
        tr_c = float(np.sum(a * a * (var_own + np.sum(np.where(use, weights, 0.0) ** 2,
                                                        axis=1))))
        d = tr_c / (1.0 + float(np.trace(np.linalg.inv(Ninv) @ unit)))
        _SCALE.append(float(f @ f) / d)
        return orig(J, a, Ninv, f, var_own, weights, sources)

    spheres._sandwich = wrapped


def _s2_true(vrig) -> float:
    """The renderer's point-spread variance (camera px^2): the pixel's box and the
    defocus kernel."""
    from telefringe.simulate.render import _blur_kernel

    k = _blur_kernel(vrig.photometry.camera_blur_px)
    x = np.arange(k.size) - k.size // 2
    return 1.0 / 12.0 + float(np.sum(k * x * x))


def _load_or_decode(args, vrig, sph, seed: int, geoms: dict):
    """(the learned decode of each camera, measure_sphere's image options, the scans or
    None) of the noise seed ``seed``: from ``args.cache`` when there (no scans), else
    rendered (and cached)."""
    from telefringe.fringes.decode import decode
    from telefringe.fringes.images import scan_radiance
    from telefringe.metrology.spheres import finest_fringe_periods
    from telefringe.simulate.anyrig import scan_scene

    names = vrig.rig.camera_names
    path = (None if args.cache is None
            else args.cache / f"stereo_b{args.bin}_s{seed:03d}.npz")
    if path is not None and path.exists():
        z = np.load(path)
        learned = {c: _Maps(*(z[f"{c}_{a}"] for a in _Maps.__dataclass_fields__))
                   for c in names}
        return learned, {"rig": vrig.rig, "image": z[f"{names[0]}_image"],
                         "image_2": z[f"{names[1]}_image"],
                         "fringe_periods": tuple(float(v) for v in z["periods"])}, None
    scans, _ = scan_scene(vrig, sph, seed=seed, geometries=geoms)
    kw = {"rig": vrig.rig, "image": scan_radiance(scans[names[0]]),
          "image_2": scan_radiance(scans[names[1]]),
          "fringe_periods": finest_fringe_periods(scans[names[0]].manifest)}
    noise = vrig.photometry.noise_model()
    learned = {c: decode(s, noise=noise) for c, s in scans.items()}
    if path is not None:
        arrays = {f"{c}_{a}": np.asarray(getattr(learned[c], a))
                  for c in names for a in _Maps.__dataclass_fields__}
        np.savez_compressed(path, **arrays, periods=np.asarray(kw["fringe_periods"]),
                            **{f"{names[0]}_image": kw["image"],
                               f"{names[1]}_image": kw["image_2"]})
        learned = {c: _Maps(*(arrays[f"{c}_{a}"] for a in _Maps.__dataclass_fields__))
                   for c in names}  # as a later run reads them
    return learned, kw, scans


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bin", type=int, default=4)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--first", type=int, default=20)
    ap.add_argument("--modes", default="learned,shared,true,none")
    ap.add_argument("--cache", type=Path, default=None,
                    help="keep each seed's decoded maps and images here (npz) and reuse "
                         "them: only the modes that take the learned decode then")
    ap.add_argument("--synthetic", action="store_true",
                    help="no render per seed: the noise-free render's maps plus white "
                         "noise of the decoded sigmas of the seed --first, and its "
                         "brightness images plus white noise of the camera's noise model "
                         "(over the scan's images)")
    args = ap.parse_args()
    import functools

    from telefringe.fringes.decode import decode
    from telefringe.fringes.images import scan_radiance
    from telefringe.metrology import spheres
    from telefringe.metrology.spheres import measure_sphere
    from telefringe.reconstruction.stereo import match_noise, match_stereo
    from telefringe.simulate.anyrig import scan_scene
    from telefringe.simulate.presets import bin_camera_any, get_preset
    from telefringe.simulate.scenes import default_sphere

    modes = args.modes.split(",")
    _record_scale()
    vrig = bin_camera_any(get_preset("stereo"), args.bin)
    names = vrig.rig.camera_names
    noise = vrig.photometry.noise_model()
    sph = default_sphere()
    truth = np.r_[sph.center, sph.radius]
    geoms: dict = {}
    if args.cache is not None:
        if set(modes) & _NEEDS_SCANS:
            raise SystemExit(f"--cache: only the modes {sorted(_CACHEABLE)}")
        args.cache.mkdir(parents=True, exist_ok=True)
    quiet_path = None if args.cache is None else args.cache / f"stereo_b{args.bin}_quiet.npz"
    if quiet_path is not None and quiet_path.exists() and "true" not in modes:
        z = np.load(quiet_path)
        decoded0 = {c: _Maps(*(z[f"{c}_{a}"] for a in _Maps.__dataclass_fields__))
                    for c in names}
        images0 = {c: z[f"{c}_image"] for c in names}
        n_images = int(z["n_images"])
    elif set(modes) & _NEEDS_QUIET or args.synthetic:
        quiet = vrig.with_photometry(full_well_e=1e12, read_noise_e=0.0, bit_depth=16)
        scans0, _ = scan_scene(quiet, sph, seed=0)
        decoded0 = {c: decode(s, noise=noise) for c, s in scans0.items()}
        true_models = {c: _models(d) for c, d in decoded0.items()}
        # on the noisy scans' scale (8-bit DN per unit exposure)
        images0 = {c: scan_radiance(s) * (vrig.photometry.max_value
                                          / quiet.photometry.max_value)
                   for c, s in scans0.items()}
        n_images = sum(st.shape[0] for st in scans0[names[0]].stacks)
        if quiet_path is not None:
            np.savez_compressed(quiet_path, n_images=n_images, **{
                f"{c}_{a}": np.asarray(getattr(decoded0[c], a))
                for c in names for a in _Maps.__dataclass_fields__},
                **{f"{c}_image": images0[c] for c in names})
    if args.synthetic:  # the reference scan's decoded sigmas
        ref = _load_or_decode(args, vrig, sph, args.first, geoms)[0]
    z_all = {m: [] for m in modes}
    e_all = {m: [] for m in modes}
    t0, c0 = time.perf_counter(), time.process_time()
    for k in range(args.seeds):
        seed = args.first + k
        if args.synthetic:
            rng = np.random.default_rng(3000 + seed)
            learned = {c: _white(decoded0[c], ref[c], rng) for c in names}
            img = {c: images0[c] + np.sqrt(noise.variance(images0[c]) / n_images)
                   * rng.standard_normal(images0[c].shape) for c in names}
            kw = {"rig": vrig.rig, "image": img[names[0]], "image_2": img[names[1]],
                  "fringe_periods": _load_or_decode(args, vrig, sph, args.first,
                                                    geoms)[1]["fringe_periods"]}
        else:
            learned, kw, scans = _load_or_decode(args, vrig, sph, seed, geoms)
        for mode in modes:
            if mode == "learned":
                coords = learned
            elif mode == "shared":
                pe = _models(learned[names[0]])
                coords = {names[0]: learned[names[0]],
                          names[1]: decode(scans[names[1]], noise=noise, phase_errors=pe)}
            elif mode == "true":
                coords = {c: decode(s, noise=noise, phase_errors=true_models[c])
                          for c, s in scans.items()}
            elif mode == "none":
                coords = {c: decode(s, noise=noise, gamma_correction=False)
                          for c, s in scans.items()}
            elif mode in ("quiet-image", "fixed-s2", "shared-s2", "split-s2", "no-reject"):
                coords = learned
            elif mode.startswith("white"):
                rng = np.random.default_rng(1000 + seed)
                which = {"white": names, "white-1": names[:1], "white-2": names[1:]}[mode]
                coords = {c: _white(decoded0[c], learned[c], rng) if c in which
                          else learned[c] for c in names}
            elif mode in ("quiet", "quiet-fixed-s2"):
                coords = {c: _Maps(decoded0[c].u_p, decoded0[c].v_p,
                                   decoded0[c].mask & learned[c].mask, learned[c].sigma_u_p,
                                   learned[c].sigma_v_p) for c in names}
            elif mode == "shuffled":
                rng = np.random.default_rng(2000 + seed)
                coords = {c: _shuffled(decoded0[c], learned[c], rng) for c in names}
            else:
                raise SystemExit(f"unknown mode {mode}")
            opts = dict(kw)
            if mode == "quiet-image":
                opts["image"], opts["image_2"] = images0[names[0]], images0[names[1]]
            if mode in ("fixed-s2", "quiet-fixed-s2"):
                opts["psf_variance"] = _s2_true(vrig)
            if mode in ("shared-s2", "split-s2"):
                opts["psf_shared"] = mode == "shared-s2"
            c1, c2 = coords[names[0]], coords[names[1]]
            m = match_stereo(vrig.rig, c1, c2)
            spread = spheres._measure_with_spread
            if mode == "no-reject":
                spheres._measure_with_spread = functools.partial(spread, reject_k=1e9)
            try:
                meas = measure_sphere(m.cloud, noise=match_noise(vrig.rig, c1, c2, m),
                                      **opts)
            finally:
                spheres._measure_with_spread = spread
            fit, sp = meas.sphere, meas.spread
            est = np.r_[fit.centre, fit.radius]
            sig = np.r_[fit.sigma_centre, fit.sigma_radius]
            e_all[mode].append(est - truth)
            z_all[mode].append((est - truth) / sig)
            print(f"seed {seed} {mode:<8} error (x, y, z, r) "
                  + " ".join(f"{v * 1e3:+7.3f}" for v in est - truth)
                  + " um  sigma " + " ".join(f"{v * 1e3:.3f}" for v in sig)
                  + "  z " + " ".join(f"{v:+6.2f}" for v in (est - truth) / sig)
                  + f"  s2 {sp.variance_px2:.3f} +- {sp.sigma_variance_px2:.3f}"
                  + ("" if sp.shared else f", {sp.variance_2_px2:.3f} +- "
                     f"{sp.sigma_variance_2_px2:.3f}")
                  + f"  ({fit.n_inliers} of {fit.n_points} points, k {_SCALE[-1]:.2f})",
                  flush=True)
    print(f"({time.perf_counter() - t0:.0f} s wall, {time.process_time() - c0:.0f} s CPU)")
    print(f"over {args.seeds} seeds ({args.first}..{args.first + args.seeds - 1}), true rig, "
          f"stereo preset binned {args.bin}:")
    for mode in modes:
        z = np.array(z_all[mode])
        e = np.array(e_all[mode]) * 1e3
        print(f"  {mode:<8} z RMS (x, y, z, r) "
              + " ".join(f"{v:.2f}" for v in np.sqrt(np.mean(z ** 2, axis=0)))
              + "   mean error " + " ".join(f"{v:+.2f}" for v in e.mean(axis=0))
              + " um   sd " + " ".join(f"{v:.2f}" for v in e.std(axis=0, ddof=1)) + " um")


if __name__ == "__main__":
    main()
