"""N-step wrapped phase, masks, HDR fusion and the phase noise model."""

import numpy as np
import pytest

from telefringe.fringes.phase import (
    NoiseModel,
    PhaseInputError,
    WrappedPhase,
    fuse_hdr,
    low_modulation_mask,
    phase_shift_coefficients,
    phase_sigma,
    saturation_mask,
    shadow_mask,
    wrap,
    wrapped_phase,
)


def fringes(phi, steps, a=100.0, b=60.0, offset=0.0):
    k = np.arange(steps).reshape((-1,) + (1,) * np.ndim(phi))
    return a + b * np.cos(phi + offset + 2 * np.pi * k / steps)


def test_four_step_is_the_papers_formula_exactly():
    rng = np.random.default_rng(1)
    imgs = rng.integers(0, 256, size=(4, 64, 80), dtype=np.uint8)
    wp = wrapped_phase(imgs, steps=4)
    i = imgs.astype(float)
    ref = np.arctan2(i[3] - i[1], i[0] - i[2])
    ref[ref == -np.pi] = np.pi
    assert np.array_equal(wp.phase, ref)
    assert np.all(wp.phase > -np.pi) and np.all(wp.phase <= np.pi)
    assert np.array_equal(wp.background, i.mean(0))
    assert np.allclose(wp.modulation, 0.5 * np.hypot(i[3] - i[1], i[0] - i[2]), rtol=1e-15)


def test_minus_pi_maps_to_plus_pi():
    # I3 - I1 = 0 and I0 - I2 < 0: the phase is pi, not -pi
    imgs = np.array([10, 50, 90, 50], dtype=np.uint8).reshape(4, 1, 1)
    assert wrapped_phase(imgs, steps=4).phase[0, 0] == np.pi


@pytest.mark.parametrize("steps", [3, 4, 5, 6, 8, 12])
@pytest.mark.parametrize("offset", [0.0, -np.pi, 0.7])
def test_any_step_count_recovers_phase_modulation_background(steps, offset):
    phi = np.linspace(-np.pi, np.pi, 1001)[1:]
    imgs = fringes(phi, steps, offset=offset)
    wp = wrapped_phase(imgs, steps=steps, offset=offset)
    assert np.max(np.abs(wrap(wp.phase - phi))) < 1e-12
    assert np.allclose(wp.modulation, 60.0, atol=1e-11)
    assert np.allclose(wp.background, 100.0, atol=1e-12)


@pytest.mark.parametrize("steps", [3, 4, 5, 8])
def test_quadrature_is_its_definition_on_gamma_distorted_fringes(steps):
    """quadrature = (2/N) sum_k I_k sin^2(phi + offset + 2 pi k / N) (WrappedPhase), written
    out here sample by sample, at offset 0.7 (not 0 or -pi, where offset and 2 offset, or
    +offset and -offset, give the same weights) on fringes with gamma 2.2."""
    offset, a, b = 0.7, 20.0, 190.0
    phi = np.linspace(-np.pi, np.pi, 721)[1:]
    k = np.arange(steps)[:, None]
    imgs = a + b * (0.5 + 0.5 * np.cos(phi + offset + 2 * np.pi * k / steps)) ** 2.2
    wp = wrapped_phase(imgs, steps=steps, offset=offset)
    theta = wp.phase + offset + 2 * np.pi * k / steps
    ref = 2 / steps * np.sum(imgs * np.sin(theta) ** 2, axis=0)
    assert np.max(np.abs(wp.quadrature - ref)) < 1e-12 * np.max(ref)
    # the peaky fringe is darker where its phase is read: the level differs from A
    # (by 5-20 % of it here, so a test taking one for the other would see it)
    assert np.max(np.abs(wp.quadrature - wp.background) / wp.background) > 0.05
    # for a pure sinusoid A + B cos(theta_k) it is A when N >= 4; with 3 steps the sum of
    # cos(theta_k) sin^2(theta_k) leaves -(B/2) cos(3 (phi + offset))
    pure = wrapped_phase(fringes(phi, steps, offset=offset), steps=steps, offset=offset)
    expect = 100.0 - (30.0 * np.cos(3 * (phi + offset)) if steps == 3 else 0.0)
    assert np.allclose(pure.quadrature, expect, rtol=1e-12)


def test_dtypes_and_leading_shape_and_no_mutation():
    phi = np.linspace(-3, 3, 60).reshape(6, 10)
    f = fringes(phi, 4)
    for arr in (np.round(f).astype(np.uint8), np.round(f * 200).astype(np.uint16),
                f.astype(np.float32), f):
        before = arr.copy()
        wp = wrapped_phase(arr, steps=4)
        assert wp.phase.shape == (6, 10) and wp.phase.dtype == np.float64
        assert np.array_equal(arr, before)
        assert np.max(np.abs(wrap(wp.phase - phi))) < 0.02


def test_coefficients_are_exact_for_quarter_steps():
    c, s = phase_shift_coefficients(4, -np.pi)
    assert set(np.abs(c)) <= {0.0, 1.0} and set(np.abs(s)) <= {0.0, 1.0}


@pytest.mark.parametrize("bad", [2, 0, 3.0, True])
def test_bad_steps(bad):
    with pytest.raises(PhaseInputError):
        wrapped_phase(np.zeros((4, 2, 2)), steps=bad)


def test_wrong_count_and_nan():
    with pytest.raises(PhaseInputError, match="holds 3 images but steps = 4"):
        wrapped_phase(np.zeros((3, 2, 2)), steps=4)
    bad = np.zeros((4, 2, 2))
    bad[1, 0, 0] = np.nan
    with pytest.raises(PhaseInputError, match="NaN"):
        wrapped_phase(bad, steps=4)
    assert issubclass(PhaseInputError, ValueError)


@pytest.mark.parametrize("steps", [3, 4, 7])
def test_phase_noise_matches_model_monte_carlo(steps):
    rng = np.random.default_rng(steps)
    n = 40000
    phi = rng.uniform(-np.pi, np.pi, n)
    a, b, sigma_i = 90.0, 25.0, 2.0
    imgs = fringes(phi, steps, a=a, b=b) + rng.normal(0, sigma_i, (steps, n))
    wp = wrapped_phase(imgs, steps=steps)
    err = wrap(wp.phase - phi)
    pred = float(phase_sigma(b, a, steps=steps, noise=NoiseModel(sigma_i, 0.0, 0.0)))
    assert pred == pytest.approx(np.sqrt(2 / steps) * sigma_i / b)
    # sample std of n draws: relative standard error 1/sqrt(2n) = 0.35 %; allow 5 of them
    # plus the second-order term of the atan (sigma_I/B)^2 ~ 0.6 %
    assert np.std(err) == pytest.approx(pred, rel=5 / np.sqrt(2 * n) + 2 * (sigma_i / b) ** 2)


def test_noise_model_variance_and_scaling():
    nm = NoiseModel(read_noise=1.0, gain=0.5, quantization=0.0)
    assert nm.variance(10.0) == pytest.approx(6.0)
    assert nm.variance(-5.0) == pytest.approx(1.0)
    s = nm.scaled(257.0)
    assert s.read_noise == 257.0 and s.gain == 0.5 * 257
    with pytest.raises(ValueError):
        NoiseModel(read_noise=-1.0)


def test_masks():
    imgs = np.full((4, 2, 3), 100, dtype=np.uint8)
    imgs[2, 1, 1] = 255
    sat = saturation_mask(imgs, max_value=255)
    assert sat.sum() == 1 and sat[1, 1]
    low = low_modulation_mask(np.array([[1.0, 5.0, np.nan]]), min_modulation=5.0)
    assert low.tolist() == [[True, False, True]]
    sh = shadow_mask(white=np.array([[200, 20]]), black=np.array([[10, 10]]), min_contrast=20)
    assert sh.tolist() == [[False, True]]
    sh2 = shadow_mask(background=np.array([[3.0, 50.0]]), min_contrast=10)
    assert sh2.tolist() == [[True, False]]
    with pytest.raises(PhaseInputError):
        shadow_mask(min_contrast=1.0)


def test_hdr_fusion_takes_longest_unsaturated_exposure():
    shape = (1, 3)
    wps = [WrappedPhase(np.full(shape, v), np.full(shape, 10 * v), np.full(shape, 20 * v))
           for v in (1.0, 2.0, 3.0)]
    exposures = [0.25, 1.0, 4.0]
    sats = [np.array([[False, False, False]]), np.array([[False, True, True]]),
            np.array([[False, True, True]])]
    sats[2] = np.array([[False, True, True]])
    sats[0] = np.array([[False, False, True]])
    fused = fuse_hdr(wps, sats, exposures)
    assert fused.exposure_index.tolist() == [[2, 0, 2]]
    assert fused.wrapped.phase.tolist() == [[3.0, 1.0, 3.0]]
    assert fused.exposure.tolist() == [[4.0, 0.25, 4.0]]
    assert fused.saturated.tolist() == [[False, False, True]]
    with pytest.raises(PhaseInputError):
        fuse_hdr(wps, sats, [1.0, 1.0, 2.0])


@pytest.mark.parametrize("dtype, steps, offset", [
    (np.uint8, 12, -np.pi), (np.uint16, 4, 0.0), (np.float64, 3, 0.7), (np.uint8, 5, 0.3)])
def test_compiled_sums_are_bit_identical_to_numpy(monkeypatch, dtype, steps, offset):
    """wrapped_phase's compiled sums (large images) against its NumPy loop: every output
    bit-identical (the same float64 products and additions in the same order)."""
    from telefringe.fringes import phase as P

    rng = np.random.default_rng(steps)
    shape = (steps, 260, 300)
    x = rng.uniform(0, 2 * np.pi, shape[1:])
    top = 255 if dtype == np.uint8 else 4000
    imgs = np.stack([0.45 * top + 0.4 * top * np.cos(x + offset + 2 * np.pi * k / steps)
                     for k in range(steps)]) + rng.normal(0, 2.0, shape)
    imgs = np.clip(imgs, 0, top)
    imgs = imgs if dtype == np.float64 else np.round(imgs).astype(dtype)
    assert imgs[0].size >= P._COMPILED_MIN_PIXELS and imgs.dtype in P._COMPILED_DTYPES
    for arr in (imgs, imgs[:, ::-1, :], imgs.reshape(steps, -1)):  # strided, 1-D trailing
        got = wrapped_phase(arr, steps=steps, offset=offset)
        monkeypatch.setattr(P, "_COMPILED_MIN_PIXELS", 10 ** 12)
        ref = wrapped_phase(arr, steps=steps, offset=offset)
        monkeypatch.undo()
        for f in ("phase", "modulation", "background", "quadrature"):
            assert np.array_equal(getattr(got, f), getattr(ref, f)), f
