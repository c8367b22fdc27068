"""decode(scan) on analytic synthetic scans (seeded noise): ladders, methods, HDR, Gray
code, bit depths, and user errors."""

import numpy as np
import pytest

from telefringe.fringes.decode import DecodeError, decode
from telefringe.fringes.patterns import gray_code_bits
from telefringe.fringes.phase import NoiseModel
from telefringe.fringes.scan import GrayGroup, PhaseGroup, Scan, ScanManifest

W, H = 800, 600
ROWS, COLS = 96, 128


def truth_coords():
    yy, xx = np.mgrid[0:ROWS, 0:COLS].astype(float)
    u = 20.0 + xx * 5.7 + 0.3 * yy  # spans 20..772 (of 800)
    v = 40.0 + yy * 5.6 - 0.2 * xx  # spans 15..572 (of 600)
    return u, v


def phase_stack(x, length, periods, steps, *, rng, a=60.0, b=80.0, sigma=1.0, gamma=1.0,
                offset=0.0, exposure=1.0, top=255, dtype=np.uint8, scale=1.0):
    k = np.arange(steps)[:, None, None]
    pat = 0.5 + 0.5 * np.cos(2 * np.pi * periods * x / length + offset + 2 * np.pi * k / steps)
    img = (a + 2 * b * pat ** gamma) * exposure * scale
    img = img + rng.normal(0.0, sigma * scale, img.shape)
    return np.clip(np.round(img), 0, top).astype(dtype)


def make_scan(ladder=(1, 8, 64), steps=4, *, axes=("u",), seed=0, gamma=1.0, sigma=1.0,
              exposures=(1.0,), a=60.0, b=80.0, top=255, dtype=np.uint8, scale=1.0,
              gray=None, offset=0.0, white_black=False):
    rng = np.random.default_rng(seed)
    u, v = truth_coords()
    groups, stacks = [], []
    for ax in axes:
        x, length = (u, W) if ax == "u" else (v, H)
        for p in ladder:
            for e in exposures:
                groups.append(PhaseGroup(ax, p, steps, exposure=e, offset=offset))
                stacks.append(phase_stack(x, length, p, steps, rng=rng, gamma=gamma,
                                          sigma=sigma, exposure=e, a=a, b=b, top=top,
                                          dtype=dtype, scale=scale, offset=offset))
        if gray is not None:
            bits, comp = gray
            pat = gray_code_bits(np.arange(length), bits=bits, length=length,
                                 complementary=comp).astype(float)
            # projector pixels are squares; the optics blur them (Gaussian, 1 px)
            fine = np.arange(-0.5 + 1 / 32, length - 0.5, 1 / 16)
            prof = pat[:, np.clip(np.round(fine).astype(int), 0, length - 1)]
            ker = np.exp(-0.5 * (np.arange(-64, 65) / 16) ** 2)
            prof = np.stack([np.convolve(q, ker / ker.sum(), mode="same") for q in prof])
            seen = np.stack([np.interp(x, fine, q) for q in prof])
            img = a + 2 * b * seen + rng.normal(0, sigma, seen.shape)
            groups.append(GrayGroup(ax, bits, comp))
            stacks.append(np.clip(np.round(img), 0, top).astype(dtype))
    white = black = None
    if white_black:
        white = np.clip(np.round(np.full((ROWS, COLS), a + 2 * b)), 0, top).astype(dtype)
        black = np.clip(np.round(np.full((ROWS, COLS), a)), 0, top).astype(dtype)
    man = ScanManifest(W, H, tuple(groups))
    return Scan(man, tuple(stacks), white=white, black=black, max_value=float(top))


def noise(sigma=1.0):
    return NoiseModel(read_noise=sigma, gain=0.0)


def test_ladder_u_and_v_at_noise_floor():
    scan = make_scan(axes=("u", "v"))
    pc = decode(scan, noise=noise())
    u, v = truth_coords()
    assert pc.mask.all()
    for est, tru, sig in ((pc.u_p, u, pc.sigma_u_p), (pc.v_p, v, pc.sigma_v_p)):
        err = est - tru
        assert np.max(np.abs(err)) < 8 * np.nanmax(sig)  # no wrong order (a period is 12.5 px)
        rms, pred = np.sqrt(np.mean(err ** 2)), np.sqrt(np.mean(sig ** 2))
        # n = 12288 samples: relative standard error 0.6 %, 5 of them
        assert rms == pytest.approx(pred, rel=5 / np.sqrt(2 * err.size))
    assert pc.u_p.dtype == np.float64 and pc.mask.dtype == bool
    assert pc.modulation.shape == (ROWS, COLS)
    assert pc.axes["u"].method == "hierarchical"


def test_sixteen_bit_and_float_scans():
    s16 = make_scan(top=65535, dtype=np.uint16, scale=257.0)
    pc = decode(s16, noise=noise().scaled(257.0))
    u, _ = truth_coords()
    assert pc.mask.all()
    assert np.sqrt(np.mean((pc.u_p - u) ** 2)) < 1.2 * np.sqrt(np.mean(pc.sigma_u_p ** 2))
    assert np.allclose(pc.modulation, 80 * 257, rtol=0.05)


@pytest.mark.parametrize("exact", [False, True], ids=["fused", "exact"])
def test_offset_0p7_gamma_and_shot_noise_at_noise_floor(exact):
    """Offset 0.7 rad (a sign error in the offset would shift u_p by 2 * 0.7 / (2 pi 64) *
    800 = 2.8 px; offset and 2 offset differ in the second-harmonic weights that give the
    quadrature level), gamma 2.2 and shot noise: the quadrature level, not A, sets the
    noise (sigma_I there is about 8 % below sigma_I(A) on these fringes)."""
    offset, a, b, gamma, read, gain = 0.7, 20.0, 95.0, 2.2, 0.5, 0.5
    rng = np.random.default_rng(7)
    u, _ = truth_coords()
    groups, stacks = [], []
    for p in (1, 8, 64):
        k = np.arange(4)[:, None, None]
        pat = 0.5 + 0.5 * np.cos(2 * np.pi * p * u / W + offset + 2 * np.pi * k / 4)
        img = a + 2 * b * pat ** gamma
        img = img + rng.normal(size=img.shape) * np.sqrt(read ** 2 + gain * img)
        groups.append(PhaseGroup("u", p, 4, offset=offset))
        stacks.append(np.clip(np.round(img), 0, 255).astype(np.uint8))
    scan = Scan(ScanManifest(W, H, tuple(groups)), tuple(stacks), max_value=255.0)
    pc = decode(scan, noise=NoiseModel(read_noise=read, gain=gain), exact=exact)
    # a few pixels (2 of 12288 here, a 4-sigma step 1 -> 8) are flagged, never wrong
    assert pc.mask.mean() > 0.999
    err, sig = (pc.u_p - u)[pc.mask], pc.sigma_u_p[pc.mask]
    assert np.max(np.abs(err / sig)) < 5.5  # no wrong order (P(|z| > 5.5) n = 5e-4)
    rms, pred = np.sqrt(np.mean(err ** 2)), np.sqrt(np.mean(sig ** 2))
    # measured rms / pred = 1.021, 1.011, 1.002 for seeds 7 (this one), 1, 2 (0.996-1.021
    # on both paths); n = 12286: relative standard error 1 / sqrt(2 n) = 0.64 %, 5 of them,
    # plus 1 % for the second-order terms at sigma_phi = 0.05 rad and the learned
    # correction's noise. Taking A for the quadrature level would give about 0.93.
    assert rms == pytest.approx(pred, rel=5 / np.sqrt(2 * err.size) + 0.01), (rms, pred)
    # no bias: the mean error is within 5 standard errors of zero
    assert abs(np.mean(err)) < 5 * pred / np.sqrt(err.size)


@pytest.mark.parametrize("method,ladder", [("heterodyne", (70, 64, 59)),
                                           ("heterodyne", (64, 63)),
                                           ("number-theoretic", (13, 16)),
                                           ("number-theoretic", (11, 13, 16)),
                                           ("hierarchical", (1, 6, 36))])
def test_methods_through_decode(method, ladder):
    scan = make_scan(ladder=ladder, sigma=0.5)
    pc = decode(scan, method=method, noise=noise(0.5))
    u, _ = truth_coords()
    assert pc.axes["u"].method == method
    assert pc.mask.mean() > 0.999
    assert np.nanmax(np.abs(pc.u_p - u)) < 8 * np.nanmax(pc.sigma_u_p)
    # "auto" picks a method that works, too
    auto = decode(scan, noise=noise(0.5))
    assert np.nanmax(np.abs(auto.u_p - u)) < 8 * np.nanmax(auto.sigma_u_p)


def test_heterodyne_combines_all_groups():
    scan = make_scan(ladder=(70, 64, 59), sigma=1.0)
    pc = decode(scan, noise=noise())
    u, _ = truth_coords()
    err = pc.u_p - u
    rms, pred = np.sqrt(np.nanmean(err ** 2)), np.sqrt(np.nanmean(pc.sigma_u_p ** 2))
    # inverse-variance combination: sigma_x of group p is L sigma_phi / (2 pi p), so the
    # three together give L sigma_phi / (2 pi sqrt(70^2 + 64^2 + 59^2))
    sigma_phi = np.sqrt(2 / 4) * np.sqrt(1 + 1 / 12) / 80
    expect = 800 * sigma_phi / (2 * np.pi * np.sqrt(70 ** 2 + 64 ** 2 + 59 ** 2))
    assert pred == pytest.approx(expect, rel=1e-3)
    assert rms == pytest.approx(pred, rel=5 / np.sqrt(2 * err.size))


@pytest.mark.parametrize("complementary", [False, True])
def test_gray_code(complementary):
    scan = make_scan(ladder=(16,), gray=(4, complementary), sigma=1.0)
    pc = decode(scan, noise=noise())
    u, _ = truth_coords()
    assert pc.axes["u"].method == "gray"
    ok = pc.mask
    assert ok.mean() > 0.95
    assert np.max(np.abs(pc.u_p[ok] - u[ok])) < 8 * np.nanmax(pc.sigma_u_p)


def test_hdr_recovers_saturated_pixels():
    # reflectance rising left to right: exposure 1 saturates the right part, 0.4 does not
    refl = np.linspace(0.3, 1.6, COLS)[None, :]
    scan1 = make_scan(a=60.0 * refl, b=80.0 * refl, exposures=(1.0,))
    scan2 = make_scan(a=60.0 * refl, b=80.0 * refl, exposures=(0.4, 1.0))
    single = decode(scan1, noise=noise())
    hdr = decode(scan2, noise=noise())
    u, _ = truth_coords()
    sat = single.saturated
    assert 0.2 < sat.mean() < 0.6
    assert np.array_equal(single.mask, ~sat)
    assert hdr.mask.all() and not hdr.saturated.any()
    assert np.max(np.abs(hdr.u_p - u)) < 8 * np.nanmax(hdr.sigma_u_p)
    used = hdr.axes["u"].exposure
    # the brightest sample of 4 steps is at least a + b (1 + cos(pi / 4)) = 196.6 refl
    assert np.all(used[:, refl[0] < 1.0] == 1.0) and np.all(used[:, refl[0] > 1.3] == 0.4)


def test_ladder_that_cannot_unwrap():
    with pytest.raises(DecodeError, match="cannot unwrap"):
        decode(make_scan(ladder=(8, 64)))
    with pytest.raises(DecodeError, match="hierarchical"):
        decode(make_scan(ladder=(13, 16)), method="hierarchical")


def test_all_saturated():
    with pytest.raises(DecodeError, match="saturated"):
        decode(make_scan(a=300.0))


def test_low_modulation_and_shadow_are_invalid():
    scan = make_scan(b=1.0, white_black=True)
    pc = decode(scan, noise=noise())
    assert not pc.mask.any()
    assert np.all(np.isnan(pc.u_p)) and np.all(np.isnan(pc.sigma_u_p))


@pytest.mark.parametrize("exposures", [(1.0,), (1.0, 0.3)], ids=["single", "hdr"])
def test_nonlinearity_learned_from_sampled_pixels_equals_the_full_image_fit(monkeypatch,
                                                                           exposures):
    """The fused path computes the wrapped phases only at the pixels the fit uses; the
    models and coordinates must be exactly those of computing them over the whole image."""
    import telefringe.fringes.decode as dec
    from telefringe.simulate.presets import get_preset
    from telefringe.simulate.render import default_groups, render_scan
    from telefringe.simulate.scenes import plate_at_z

    vrig = get_preset("fast")
    scan, _ = render_scan(vrig, plate_at_z(0.2), default_groups(vrig, steps=3),
                          exposures=exposures, seed=11)
    monkeypatch.setattr(dec, "_FIT_SAMPLES", 20_000)  # fewer than the good pixels
    sampled = decode(scan)
    monkeypatch.setattr(dec, "_fit_from_samples", lambda *a, **k: None)
    full = decode(scan)
    for ax in ("u", "v"):
        a, b = sampled.axes[ax], full.axes[ax]
        assert any(m.harmonics for m in a.phase_errors.models)  # 3 steps at gamma 2.2
        for ma, mb in zip(a.phase_errors.models, b.phase_errors.models, strict=True):
            assert ma.harmonics == mb.harmonics
            assert np.array_equal(ma.cos_coef, mb.cos_coef)
            assert np.array_equal(ma.sin_coef, mb.sin_coef)
        assert np.array_equal(a.valid, b.valid)
        assert np.array_equal(a.coordinate, b.coordinate, equal_nan=True)
