"""fringe_free_image averages a phase group in float64 without copying the stack to
float64 first: bit for bit the mean of the float64 copy, for every image type a scan
holds."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from telefringe.fringes.images import fringe_free_image


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32, np.float64])
@pytest.mark.parametrize("steps", [3, 4, 5, 8, 12])
def test_mean_of_the_group_bit_for_bit(dtype, steps):
    rng = np.random.default_rng(steps)
    top = {np.uint8: 255, np.uint16: 65535}.get(dtype, 1.0)
    stack = (rng.uniform(0, top, (steps, 97, 131))).astype(dtype)
    group = SimpleNamespace(steps=steps, periods=8, exposure=1.0)
    scan = SimpleNamespace(white=None, manifest=SimpleNamespace(groups=[group]),
                           stacks=[stack], source="test")
    got = fringe_free_image(scan)
    want = np.asarray(stack, dtype=np.float64).mean(axis=0)
    assert got.dtype == np.float64 and got.shape == (97, 131)
    assert np.array_equal(got, want)
