"""Temporal unwrapping methods on synthetic phases (exact and seeded noise): correct
orders, unreliable pixels flagged rather than guessed, and ladders that cannot work."""

import numpy as np
import pytest

from telefringe.fringes.patterns import gray_code_bits
from telefringe.fringes.unwrap import (
    LadderError,
    absolute_unit_phase,
    decode_gray,
    heterodyne_plan,
    number_theoretic_candidates,
    unwrap_gray,
    unwrap_heterodyne,
    unwrap_hierarchical,
    unwrap_number_theoretic,
)

L = 800


def wrapped(x, p, sigma=0.0, rng=None):
    phi = 2 * np.pi * p * x / L
    if sigma:
        phi = phi + rng.normal(0, sigma, np.shape(x))
    return np.angle(np.exp(1j * phi))


X = np.linspace(-0.49, L - 0.51, 20001)  # the projector, clear of its wrap point
# with noise, pixels within a few standard deviations (of the coarsest phase, in pixels)
# of the projector's edges may wrap around to the other edge: the patterns are periodic
# over L, so all groups agree and nothing can tell. Keep noisy tests clear of the edges.
XN = np.linspace(0.1 * L, 0.9 * L, 20001)


@pytest.mark.parametrize("method, periods", [
    (unwrap_hierarchical, (1, 8, 64)),
    (unwrap_hierarchical, (64, 1, 8)),
    (unwrap_heterodyne, (70, 64, 59)),
    (unwrap_heterodyne, (64, 63)),
    (unwrap_number_theoretic, (13, 16)),
    (unwrap_number_theoretic, (11, 13, 16)),
])
def test_exact_phases_give_exact_orders_over_the_whole_projector(method, periods):
    res = method([wrapped(X, p) for p in periods], periods, length=L)
    assert res.reliable.all()
    for p, ab in zip(periods, res.phases, strict=True):
        assert np.max(np.abs(ab - 2 * np.pi * p * X / L)) < 1e-9


@pytest.mark.parametrize("method, periods, sigma", [
    (unwrap_hierarchical, (1, 8, 64), 0.02),
    (unwrap_heterodyne, (70, 64, 59), 0.01),
    (unwrap_number_theoretic, (11, 13, 16), 0.02),
])
def test_noise_small_enough_never_wrong(method, periods, sigma):
    rng = np.random.default_rng(0)
    res = method([wrapped(XN, p, sigma, rng) for p in periods], periods, length=L)
    fine = int(np.argmax(periods))
    err = res.phases[fine] - 2 * np.pi * periods[fine] * XN / L
    assert res.reliable.mean() > 0.999
    assert np.max(np.abs(err[res.reliable])) < 0.3


@pytest.mark.parametrize("method, periods, sigma", [
    (unwrap_hierarchical, (1, 8, 64), 0.12),
    (unwrap_heterodyne, (70, 64, 59), 0.08),
    (unwrap_number_theoretic, (11, 13, 16), 0.15),
])
def test_heavy_noise_is_flagged_not_guessed(method, periods, sigma):
    rng = np.random.default_rng(1)
    res = method([wrapped(XN, p, sigma, rng) for p in periods], periods, length=L)
    fine = int(np.argmax(periods))
    err = res.phases[fine] - 2 * np.pi * periods[fine] * XN / L
    wrong = np.abs(err) > np.pi
    assert wrong.any()  # this much noise does break orders...
    assert (~res.reliable).sum() > 5 * wrong.sum()  # ...far more are flagged
    # and most wrong ones among them: few slip through as "reliable"
    assert (wrong & res.reliable).sum() <= 0.25 * wrong.sum()
    assert np.all(res.residual[~res.reliable] > 1.0)


def test_ladders_that_cannot_work():
    ph = [wrapped(X, p) for p in (8, 64)]
    with pytest.raises(LadderError, match="one-period"):
        unwrap_hierarchical(ph, (8, 64), length=L)
    with pytest.raises(LadderError, match="no heterodyne beat"):
        unwrap_heterodyne(ph, (8, 64), length=L)
    with pytest.raises(LadderError, match="coprime"):
        unwrap_number_theoretic(ph, (8, 64), length=L)
    with pytest.raises(LadderError, match="differ"):
        unwrap_hierarchical([ph[0], ph[0]], (8, 8), length=L)
    with pytest.raises(ValueError, match="length"):
        unwrap_hierarchical(ph, (1, 8), length=0)
    nodes, steps = heterodyne_plan((70, 64, 59))
    assert sorted(n.periods for n in nodes) == [1, 5, 6, 59, 64, 70]
    assert steps[0][1] is None and nodes[steps[0][0]].periods == 1


def test_unit_phase_and_candidates():
    ph = np.array([0.0, -1e-3, np.pi, -np.pi / 2])
    a = absolute_unit_phase(ph, length=L)
    assert np.allclose(a, [0.0, -1e-3, np.pi, 1.5 * np.pi])
    c = number_theoretic_candidates((2, 3), length=12)
    assert c.shape[1] == 2 and len(np.unique(c, axis=0)) == len(c)
    assert not np.any(np.all(c == [2, 3], axis=1))


def gray_images(x, bits, comp, rng, blur=1.0, a=60.0, b=80.0, sigma=1.0):
    pat = gray_code_bits(np.arange(L), bits=bits, length=L, complementary=comp).astype(float)
    fine = np.arange(-0.5 + 1 / 32, L - 0.5, 1 / 16)
    prof = pat[:, np.clip(np.round(fine).astype(int), 0, L - 1)]
    ker = np.exp(-0.5 * (np.arange(-96, 97) / (16 * blur)) ** 2)
    prof = np.stack([np.convolve(q, ker / ker.sum(), mode="same") for q in prof])
    seen = np.stack([np.interp(x, fine, q) for q in prof])
    return a + 2 * b * seen + rng.normal(0, sigma, seen.shape), np.full(x.shape, a + b)


@pytest.mark.parametrize("comp", [False, True])
def test_gray_code_orders_at_every_block_edge(comp):
    rng = np.random.default_rng(3)
    x = np.linspace(0, L - 1, 40001)
    imgs, thr = gray_images(x, 5, comp, rng)
    phase = wrapped(x, 32, 0.01, rng)
    res = unwrap_gray(phase[None], imgs[:, None], thr[None], bits=5, complementary=comp,
                      length=L, min_contrast=3.0)
    err = res.phases[0][0] - 2 * np.pi * 32 * x / L
    ok = res.reliable[0]
    assert ok.mean() > 0.99
    assert np.max(np.abs(err[ok])) < 0.1  # no wrong order among trusted pixels


def test_plain_gray_code_naive_rule_fails_where_ours_does_not():
    """The rule `block + (phase < 0)` puts the order change at the phase zero crossing,
    half a projector pixel from the code's edge (pixel boundaries): a band of pixels at
    every block edge gets the wrong order. The in-block rule does not."""
    rng = np.random.default_rng(4)
    x = np.linspace(0, L - 1, 40001)
    imgs, thr = gray_images(x, 5, False, rng, sigma=0.2)
    phase = wrapped(x, 32)
    block = decode_gray(imgs, thr).index
    naive = phase + 2 * np.pi * (block + (phase < 0))
    assert np.sum(np.abs(naive - 2 * np.pi * 32 * x / L) > 1) > 100
    res = unwrap_gray(phase[None], imgs[:, None], thr[None], bits=5, complementary=False,
                      length=L, min_contrast=1.0)
    assert np.max(np.abs(res.phases[0][0] - 2 * np.pi * 32 * x / L)) < 1e-9


# DESIGN.md: image j < n shows bit j (most significant first) of the Gray code of block
# floor(x 2^n / L); with `complementary` one more image shows the least significant bit of
# the Gray code of the half-blocks floor(x 2^(n+1) / L). Written out by hand (3-bit Gray
# codes of blocks 0..7: 000 001 011 010 110 111 101 100; the LSB of the Gray code of the
# half-block h is bit0(h) xor bit1(h): 0 1 1 0 0 1 1 0 ...):
_GRAY_BY_HAND = [  # L = 800, 3 bits: blocks of 100 px, half-blocks of 50 px
    # x,  bits MSB first, complementary bit
    (0, (0, 0, 0), 0), (49, (0, 0, 0), 0), (50, (0, 0, 0), 1), (99, (0, 0, 0), 1),
    (100, (0, 0, 1), 1), (150, (0, 0, 1), 0), (250, (0, 1, 1), 1), (399, (0, 1, 0), 0),
    (400, (1, 1, 0), 0), (650, (1, 0, 1), 1), (799, (1, 0, 0), 0),
]


def test_gray_code_bits_follow_the_design_definition():
    x = np.array([r[0] for r in _GRAY_BY_HAND])
    bits = np.array([r[1] for r in _GRAY_BY_HAND]).T
    comp = np.array([r[2] for r in _GRAY_BY_HAND])
    got = gray_code_bits(x, bits=3, length=800, complementary=True)
    assert got.shape == (4, x.size) and got.dtype == np.uint8
    assert np.array_equal(got[:3], bits) and np.array_equal(got[3], comp)
    assert np.array_equal(gray_code_bits(x, bits=3, length=800, complementary=False), bits)
    # a length that is not a multiple of 2^bits: L = 600, 2 bits, blocks 0..3 = 00 01 11 10
    # from x = 0, 150, 300, 450 (149 * 4 / 600 = 0.993 is still block 0)
    got = gray_code_bits(np.array([0, 149, 150, 299, 300, 449, 450, 599]), bits=2,
                         length=600, complementary=False)
    assert np.array_equal(got.T, [[0, 0], [0, 0], [0, 1], [0, 1], [1, 1], [1, 1], [1, 0],
                                  [1, 0]])


def test_decode_gray_reads_the_block_index():
    x = np.arange(L)
    for comp in (False, True):
        ref = gray_code_bits(x, bits=4, length=L, complementary=comp).astype(bool)
        imgs = np.where(ref, 200.0, 20.0)
        code = decode_gray(imgs, np.full(L, 110.0))
        expect = (x * 2 ** (4 + comp) // L)
        assert np.array_equal(code.index, expect)
