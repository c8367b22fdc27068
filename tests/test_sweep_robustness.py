"""Unusual but legitimate inputs a user's rig or capture tool produces: each either works
or stops with a message naming the file / option and what is expected (never a silently
wrong result)."""

from __future__ import annotations

import numpy as np

from telefringe.fringes.decode import decode
from telefringe.fringes.scan import PhaseGroup, Scan, ScanManifest


def _fringe_scan(top: int, *, shape=(12, 20), clip: int | None = None) -> Scan:
    """A 4-step, one-period scan along u in 16-bit integers reaching about ``top`` (a
    camera's full scale), its brightest samples clipped at ``clip`` (a saturated pixel in
    the top-left corner)."""
    rows, cols = shape
    x = np.linspace(0.0, 2 * np.pi, cols, endpoint=False)[None, :] * np.ones((rows, 1))
    k = np.arange(4)[:, None, None]
    stack = top * (0.45 + 0.35 * np.cos(x[None] + 2 * np.pi * k / 4))
    stack[:, 0, 0] = 1.5 * top      # far above the full scale: clipped
    stack = np.round(np.minimum(stack, top if clip is None else clip)).astype(np.uint16)
    man = ScanManifest(projector_width=20, projector_height=10,
                       groups=(PhaseGroup(axis="u", periods=1, steps=4),))
    return Scan(manifest=man, stacks=(stack,), max_value=65535.0)


def test_lone_one_period_group_decodes_the_whole_projector():
    # a scan of one one-period group per axis (no ladder): the fused kernel returned NaN
    # for every pixel whose wrapped phase was negative (the projector's second half)
    sc = _fringe_scan(65535)
    for gamma in (True, False):
        fast = decode(sc, gamma_correction=gamma)
        exact = decode(sc, gamma_correction=gamma, exact=True)
        assert fast.mask.sum() == fast.mask.size - 1      # all but the clipped pixel
        np.testing.assert_array_equal(fast.mask, exact.mask)
        cols = np.arange(20.0) * np.ones((12, 1))
        # the true coordinate is the column (noise-free, rounded to integers: 0.003 px
        # measured)
        assert np.nanmax(np.abs(fast.u_p - cols)) < 0.01
        np.testing.assert_allclose(fast.u_p, exact.u_p, atol=1e-9)
