"""The compiled complementary Gray-code unwrapping (telefringe.fringes._gray_kernels)
against the float64 NumPy reference (unwrap._unwrap_gray_numpy): the absolute phase, the
reliability mask and the residual must be bit-identical (same float64 operations in the
same order; no tolerance), on synthetic codes with noise, blur-like weak bits, order
errors and values on the rounding boundaries, and on the real capture when present."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from telefringe.fringes import unwrap as U
from telefringe.fringes.patterns import gray_code_bits

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT / ".." / "shared" / "realdata" / "slmaster_mono_relief"


def _same(a, b):
    assert np.array_equal(a.phases[0], b.phases[0])
    assert np.array_equal(a.reliable, b.reliable)
    assert np.array_equal(a.residual, b.residual)


def _synthetic(bits, length, dtype, rng, rows=37, cols=211):
    """Gray-code images of random projector columns: bits with random contrast (some
    below any threshold), noise, and a noisy wrapped phase (some order errors)."""
    x = rng.uniform(-0.5, length - 0.5, (rows, cols))
    xr = np.clip(np.round(x), 0, length - 1)
    code = gray_code_bits(xr, bits=bits, length=length, complementary=True).astype(float)
    amp = rng.uniform(0.0, 80.0, code.shape)
    thr = rng.uniform(40.0, 120.0, (rows, cols))
    imgs = thr + amp * (2 * code - 1) + rng.normal(0, 3.0, code.shape)
    if dtype.kind in "ui":
        imgs = np.clip(np.round(imgs), 0, np.iinfo(dtype).max)
    imgs = imgs.astype(dtype)
    p = 2 ** bits
    phase = np.angle(np.exp(1j * (2 * np.pi * p * x / length
                                  + rng.normal(0, 0.6, x.shape))))
    # values on the decision boundaries: |phase| = pi / 2, phase = pi, 0
    flat = phase.ravel()
    flat[::17] = np.pi / 2
    flat[5::17] = -np.pi / 2
    flat[9::23] = np.pi
    flat[11::29] = 0.0
    return phase, imgs, thr


@pytest.mark.parametrize("bits, length, dtype", [
    (5, 1920, np.uint8), (4, 1000, np.uint16), (3, 97, np.float64), (7, 1280, np.uint8),
    (1, 64, np.float64)])
def test_compiled_complementary_gray_matches_numpy(bits, length, dtype):
    rng = np.random.default_rng(bits * 1000 + length)
    phase, imgs, thr = _synthetic(bits, length, np.dtype(dtype), rng)
    for mc in (3.0, rng.uniform(0.0, 30.0, thr.shape)):
        ref = U._unwrap_gray_numpy(phase, imgs, thr, bits=bits, complementary=True,
                                   length=length, min_contrast=mc)
        # the test is not vacuous: some pixels are flagged, most are not
        assert 0.02 < np.mean(~ref.reliable) < 0.9
        got = U._unwrap_gray_compiled(phase, imgs, thr, bits=bits, length=length,
                                      min_contrast=mc)
        _same(got, ref)
        _same(U.unwrap_gray(phase, imgs, thr, bits=bits, complementary=True, length=length,
                            min_contrast=mc), ref)


def test_non_finite_inputs_keep_the_numpy_path():
    rng = np.random.default_rng(1)
    phase, imgs, thr = _synthetic(4, 800, np.dtype(np.uint8), rng, rows=5, cols=40)
    thr[2, 3] = np.nan
    assert not U._compiled_ok(phase, imgs, thr, 3.0, 5)
    ref = U._unwrap_gray_numpy(phase, imgs, thr, bits=4, complementary=True, length=800,
                               min_contrast=3.0)
    _same(U.unwrap_gray(phase, imgs, thr, bits=4, complementary=True, length=800,
                        min_contrast=3.0), ref)


@pytest.mark.skipif(not (REAL / "scan.json").is_file(), reason=f"{REAL} is not present")
def test_compiled_gray_matches_numpy_on_the_real_scan():
    from telefringe.fringes.phase import NoiseModel, wrapped_phase
    from telefringe.io.scan_json import read_scan

    scan = read_scan(REAL)
    g = scan.manifest.groups
    wp = wrapped_phase(scan.stacks[0], steps=g[0].steps, offset=g[0].offset)
    thr = wp.background
    mc = 3.0 * np.sqrt(NoiseModel().variance(thr))
    ref = U._unwrap_gray_numpy(wp.phase, scan.stacks[1], thr, bits=g[1].bits,
                               complementary=True, length=1920, min_contrast=mc)
    got = U.unwrap_gray(wp.phase, scan.stacks[1], thr, bits=g[1].bits, complementary=True,
                        length=1920, min_contrast=mc)
    _same(got, ref)
    assert 0.9 < ref.reliable.mean() < 1.0


def test_compiled_gray_matches_numpy_on_a_virtual_scan():
    """A Gray-code scan rendered by the virtual rig (sphere, 4 steps x 16 periods, 4 bits
    + complementary): the compiled path equals the NumPy one, with the white/black
    threshold decode() uses."""
    from telefringe.fringes.patterns import pattern_groups
    from telefringe.fringes.phase import NoiseModel, wrapped_phase
    from telefringe.simulate.presets import get_preset
    from telefringe.simulate.render import render_scan
    from telefringe.simulate.scenes import make_scene

    vr = get_preset("fast")
    groups = pattern_groups(steps=4, periods=(16,), axes=("u",), gray_bits=4)
    scan, _ = render_scan(vr, make_scene("sphere"), groups, seed=2)
    wp = wrapped_phase(scan.stacks[0], steps=4)
    thr = 0.5 * (scan.white.astype(np.float64) + scan.black.astype(np.float64))
    mc = 3.0 * np.sqrt(NoiseModel().variance(thr))
    length = scan.manifest.projector_width
    ref = U._unwrap_gray_numpy(wp.phase, scan.stacks[1], thr, bits=4, complementary=True,
                               length=length, min_contrast=mc)
    _same(U.unwrap_gray(wp.phase, scan.stacks[1], thr, bits=4, complementary=True,
                        length=length, min_contrast=mc), ref)
    assert 0.2 < ref.reliable.mean() < 1.0  # the sphere, and the unlit background flagged
