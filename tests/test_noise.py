"""The camera's noise measured from a scan's own phase steps (telefringe.fringes.noise).

Tolerances:
- synthetic stacks with a known read + shot noise: a and b within 4 of their stated
  standard uncertainties, and the predicted sigma_I within 3 % where the pixels are;
- the virtual rig (every noise source of the renderer, gamma 2.2 projector, 8-bit
  projector levels, blur): the decoder's sigma of u_p from the scan's estimate against the
  scatter of u_p over 8 noise seeds, within 10 % (the issue's bound; measured 1.02 on the
  fast rig, 1.26 with the default model, which must stay outside);
- the subsample against every pixel: within 3 of the subsample's stated relative
  uncertainty.
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from telefringe.fringes.decode import decode
from telefringe.fringes.noise import (
    NoiseEstimateError,
    estimate_noise,
    resolve_noise,
    step_residuals,
)
from telefringe.fringes.phase import NoiseModel
from telefringe.fringes.scan import PhaseGroup, Scan, ScanManifest


def _synthetic(steps=(4,), *, a=0.5, b=0.03, gamma=2.2, shape=(200, 240), seed=0,
               offset=0.0, peak=230.0, integer=True):
    """A scan of a ramp of brightness with fringes (gamma-distorted) and noise a + b I."""
    rng = np.random.default_rng(seed)
    rows, cols = shape
    x = np.linspace(0, 1, cols)[None, :] * np.ones((rows, 1))
    alpha = 20 + (peak - 30) * np.linspace(0, 1, rows)[:, None] * np.ones((1, cols))
    groups, stacks = [], []
    for j, n in enumerate(steps):
        periods = 8 ** j  # a ladder: 1, 8, 64
        k = np.arange(n)[:, None, None]
        p = 0.5 + 0.5 * np.cos(2 * np.pi * periods * x[None] + offset + 2 * np.pi * k / n)
        clean = 3 + alpha[None] * (0.02 + 0.98 * p ** gamma)
        noisy = clean + rng.standard_normal(clean.shape) * np.sqrt(a + b * clean)
        if integer:
            noisy = np.clip(np.round(noisy), 0, 255).astype(np.uint8)
        groups.append(PhaseGroup(axis="u", periods=periods, steps=n, offset=offset))
        stacks.append(noisy)
    return Scan(ScanManifest(256, 64, tuple(groups)), tuple(stacks), max_value=255.0)


@pytest.mark.parametrize("steps", [(4, 4), (8,), (12,)])
def test_read_and_shot_noise_recovered(steps):
    a, b = 0.5, 0.03
    e = estimate_noise(_synthetic(steps, a=a + 1 / 12, b=b, integer=False), max_pixels=None)
    ua, ub = np.sqrt(np.diag(e.covariance))
    assert abs(e.a - (a + 1 / 12)) < 4 * ua + 1e-9, (e.a, ua)
    assert abs(e.b - b) < 4 * ub, (e.b, ub)
    for i in (30.0, 100.0, 200.0):
        assert abs(np.sqrt(e.variance(i) / (a + 1 / 12 + b * i)) - 1) < 0.03
    assert e.model.gain == pytest.approx(e.b)
    assert e.model.read_noise ** 2 + e.model.quantization ** 2 == pytest.approx(e.a)


def test_integer_images_and_the_harmonics():
    """8-bit rounding adds q^2 = 1/12; without removing the gamma harmonics the 4-step
    residual would be hundreds of times the noise."""
    scan = _synthetic((4,), a=0.3, b=0.02, seed=1)
    e = estimate_noise(scan, max_pixels=None)
    for i in (40.0, 150.0):
        assert abs(np.sqrt(e.variance(i) / (0.3 + 1 / 12 + 0.02 * i)) - 1) < 0.03
    flat = scan.stacks[0].reshape(4, -1)
    raw = step_residuals(flat, steps=4, harmonics=False).variance.mean()
    fit = step_residuals(flat, steps=4).variance.mean()
    assert raw > 50 * fit


def test_an_offset_group_is_read_with_its_offset():
    e = estimate_noise(_synthetic((6,), a=0.4, b=0.025, offset=-np.pi, seed=3,
                                  integer=False), max_pixels=None)
    assert abs(np.sqrt(e.variance(120.0) / (0.4 + 0.025 * 120)) - 1) < 0.03


def test_subsample_error_is_within_its_stated_uncertainty():
    scan = _synthetic((4, 4), a=0.3, b=0.02, shape=(300, 400), seed=4)
    full = estimate_noise(scan, max_pixels=None)
    sub = estimate_noise(scan)  # the default subsample
    assert sub.subsampled and not full.subsampled and sub.n_pixels < full.n_pixels / 2
    for i in (40.0, 120.0, 200.0):
        d = abs(np.sqrt(sub.variance(i) / full.variance(i)) - 1)
        assert d < 3 * float(sub.relative_uncertainty(i)), (i, d)


def test_when_the_noise_cannot_be_measured():
    three = _synthetic((3,))
    with pytest.raises(NoiseEstimateError, match="3 steps"):
        estimate_noise(three)
    choice = resolve_noise(three, "auto")
    assert choice.source == "default" and "3 steps" in choice.note
    assert choice.model == NoiseModel()
    with pytest.raises(NoiseEstimateError, match="3 steps"):
        resolve_noise(three, "scan")
    sat = _synthetic((4,), peak=2000.0)  # every lit pixel clips at 255
    sat = Scan(sat.manifest, (np.maximum(sat.stacks[0], 255 * (sat.stacks[0] > 60)),),
               max_value=255.0)
    with pytest.raises(NoiseEstimateError, match="saturated"):
        estimate_noise(sat)
    tiny = _synthetic((4,), shape=(8, 8))
    with pytest.raises(NoiseEstimateError, match="usable pixels"):
        estimate_noise(tiny)
    with pytest.raises(NoiseEstimateError, match="one of"):
        resolve_noise(tiny, "guess")


def test_resolve_and_decode_record_the_source():
    scan = _synthetic((4, 4), a=0.3, b=0.02, seed=5)
    pc = decode(scan, noise="scan", gamma_correction=False)
    assert pc.noise.source == "scan" and pc.noise.estimate is not None
    assert decode(scan).noise.source == "default"
    cal = Scan(scan.manifest, scan.stacks, max_value=255.0,
               meta={"camera_noise": {"read_noise_dn": 0.4, "gain_dn_per_dn": 0.02}})
    ch = resolve_noise(cal, "auto")
    assert ch.source == "calibrated" and ch.model == NoiseModel(0.4, 0.02)
    with pytest.raises(NoiseEstimateError, match="calibrated"):
        resolve_noise(scan, "calibrated")
    bad = Scan(scan.manifest, scan.stacks, meta={"camera_noise": {"read_noise_dn": "x"}})
    with pytest.raises(NoiseEstimateError, match="camera_noise"):
        resolve_noise(bad, "auto")
    summary = json.loads(json.dumps(pc.noise.summary()))
    assert summary["source"] == "scan" and summary["gain_dn_per_dn"] > 0


@pytest.mark.parametrize("preset", ["fast", "macro"])
def test_virtual_rig_sigma_matches_the_scatter_over_seeds(preset):
    from telefringe.simulate.presets import bin_camera_any, crop_camera, get_preset
    from telefringe.simulate.render import default_groups, render_scan, trace_geometry
    from telefringe.simulate.scenes import plate_at_z

    if preset == "fast":
        vr = crop_camera(get_preset("fast"), col0=60, row0=40, width=200, height=160)
    else:
        vr = bin_camera_any(get_preset("macro"), 8)
    scene = plate_at_z(0.0)
    geo = trace_geometry(vr, scene)
    groups = default_groups(vr, axes=("u",))
    us, sig, sig_default = [], [], []
    for seed in range(8):
        scan, truth = render_scan(vr, scene, groups, seed=seed, white=False, black=False,
                                  geometry=geo)
        pc = decode(scan, noise="scan", gamma_correction=False)
        assert pc.noise.source == "scan"
        us.append(pc.u_p)
        sig.append(pc.sigma_u_p)
        sig_default.append(decode(scan, gamma_correction=False).sigma_u_p)
    us = np.array(us)
    ok = np.all(np.isfinite(us), axis=0) & truth.lit
    assert ok.sum() > 5000
    observed = np.sqrt(np.mean(np.var(us[:, ok], axis=0, ddof=1)))
    ratio = np.sqrt(np.mean(np.array(sig)[:, ok] ** 2)) / observed
    ratio_default = np.sqrt(np.mean(np.array(sig_default)[:, ok] ** 2)) / observed
    print(f"{preset}: sigma / scatter {ratio:.3f} (default model {ratio_default:.3f})")
    assert 0.9 < ratio < 1.1, (ratio, ratio_default)
    assert not 0.9 < ratio_default < 1.1, ratio_default  # the test can tell


def test_a_12_bit_camera():
    from telefringe.simulate.presets import crop_camera, get_preset
    from telefringe.simulate.render import default_groups, render_scan
    from telefringe.simulate.scenes import plate_at_z

    vr = crop_camera(get_preset("fast"), col0=60, row0=40, width=200, height=160)
    vr = replace(vr, photometry=replace(vr.photometry, bit_depth=12))
    scan, _ = render_scan(vr, plate_at_z(0.0), default_groups(vr, axes=("u",)), seed=1,
                          white=False, black=False)
    e = estimate_noise(scan)
    true = vr.photometry.noise_model()
    lo, hi = e.intensity_range
    for i in (lo + 0.25 * (hi - lo), lo + 0.75 * (hi - lo)):
        # 12-bit steps of 16 stored DN: the true model's quantisation is 16^2 / 12
        tv = true.read_noise ** 2 + 16.0 ** 2 / 12 + true.gain * i
        assert abs(np.sqrt(e.variance(i) / tv) - 1) < 0.1, (i, e.variance(i), tv)


def test_reconstruct_records_the_noise_model(tmp_path, capsys):
    """`telefringe reconstruct` measures the noise from the scan by default and says so in
    summary.json; --noise-model default and calibrated (scan.json meta.camera_noise) as
    asked; a 3-step scan with --noise-model scan: one line, exit 2, nothing written."""
    from telefringe.cli import main
    from telefringe.fringes.decode import decode
    from telefringe.io.rig_json import bare_rig_json
    from telefringe.io.scan_json import write_scan
    from telefringe.simulate.presets import crop_camera, get_preset
    from telefringe.simulate.render import default_groups, render_scan
    from telefringe.simulate.scenes import plate_at_z

    vr = crop_camera(get_preset("fast"), col0=100, row0=80, width=120, height=100)
    scan, _ = render_scan(vr, plate_at_z(0.0), default_groups(vr), seed=3)
    # the projector's nonlinearity learned once and handed to the three reconstructions in
    # rig.json (as a calibration does) instead of each re-learning it from the same
    # stacks: ~2/3 of the test's CPU time went to those three identical fits
    steps = {(g.axis, int(g.periods)): int(g.steps) for g in scan.manifest.groups}
    learned = {(a, int(m.periods), steps[(a, int(m.periods))]): m
               for a, ax in decode(scan).axes.items() for m in ax.phase_errors.models}
    assert len(learned) == len(steps)
    rig = tmp_path / "rig.json"
    rig.write_text(json.dumps(bare_rig_json(vr.rig, reference_pose="truth",
                                            phase_errors=learned)))
    write_scan(tmp_path / "scan", scan)
    cal = Scan(scan.manifest, scan.stacks, scan.white, scan.black, scan.max_value,
               meta={"camera_noise": {"read_noise_dn": 0.2, "gain_dn_per_dn": 0.02}})
    write_scan(tmp_path / "cal", cal)
    three, _ = render_scan(vr, plate_at_z(0.0), default_groups(vr, steps=3), seed=3)
    write_scan(tmp_path / "three", three)
    sigma = {}
    for name, folder, opt in (("auto", "scan", "auto"), ("default", "scan", "default"),
                              ("cal", "cal", "auto")):
        out = tmp_path / f"out_{name}"
        assert main(["reconstruct", str(tmp_path / folder), "--rig", str(rig), "-o",
                     str(out), "--no-ply", "--noise-model", opt]) == 0
        summary = json.loads((out / "summary.json").read_text())
        sigma[name] = summary["sigma_z_median_mm"]
        sigma[name + "_source"] = summary["noise_model"]["source"]
    assert sigma["auto_source"] == "scan" and sigma["default_source"] == "default"
    assert sigma["cal_source"] == "calibrated"
    # the virtual camera's true noise is below the typical camera's (1.27x, see above)
    assert sigma["auto"] < sigma["default"] / 1.1
    assert "camera noise measured from the scan" in capsys.readouterr().out
    assert main(["reconstruct", str(tmp_path / "three"), "--rig", str(rig), "-o",
                 str(tmp_path / "o3"), "--noise-model", "scan", "--no-gamma-correction"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("error: ") and "3 steps" in err, err
    assert not (tmp_path / "o3").exists()
    assert main(["reconstruct", str(tmp_path / "three"), "--rig", str(rig), "-o",
                 str(tmp_path / "o4"), "--no-gamma-correction"]) == 0  # auto: default, warned
    assert "built-in typical camera" in capsys.readouterr().out
    summary = json.loads((tmp_path / "o4" / "summary.json").read_text())
    assert summary["noise_model"]["source"] == "default"
    assert "3 steps" in summary["noise_model"]["note"]
    assert main(["reconstruct", str(tmp_path / "scan"), "--rig", str(rig), "-o",
                 str(tmp_path / "o5"), "--noise-model", "guess"]) == 2
