"""The BGA measurement's compiled kernels against the NumPy forms they replace."""

import numpy as np

from telefringe.metrology.bga._kernels import footprint_counts
from telefringe.metrology.bga.grid import _grid_local


def _reference_counts(xyz, mask, T, theta, origin, pitch, rows, cols, radius):
    f = _grid_local(xyz[mask] @ T.T, theta, origin) / pitch
    k = np.round(f).astype(np.int64)
    near = np.all((k >= 0) & (k < (cols, rows)), axis=1) & (
        np.hypot(*(f - k).T) * pitch < radius)
    return np.bincount(k[near, 1] * cols + k[near, 0],
                       minlength=rows * cols).reshape(rows, cols)


def test_footprint_counts_match_the_numpy_form():
    rng = np.random.default_rng(3)
    h, w = 120, 150
    xyz = np.empty((h, w, 3))
    xyz[..., 0], xyz[..., 1] = np.meshgrid(np.linspace(-1, 9, w), np.linspace(-1, 7, h))
    xyz[..., 2] = 0.02 * xyz[..., 0] - 0.01 * xyz[..., 1] + rng.normal(0, 0.01, (h, w))
    mask = rng.random((h, w)) > 0.2
    xyz[~mask] = np.nan
    n = np.array([-0.02, 0.01, 1.0])
    n /= np.linalg.norm(n)
    e1 = np.cross([0.0, 1.0, 0.0], n)
    e1 /= np.linalg.norm(e1)
    T = np.array([e1, np.cross(n, e1)])
    theta, origin, pitch = 0.013, np.array([0.11, -0.07]), 0.8
    rows, cols, radius = 9, 13, 0.3  # (columns 11, 12 off the cloud)
    got = footprint_counts(xyz, mask, T, np.cos(theta), np.sin(theta), origin, pitch,
                           rows, cols, radius)
    ref = _reference_counts(xyz, mask, T, theta, origin, pitch, rows, cols, radius)
    assert ref.sum() > 1000 and (ref == 0).any()  # positions off the cloud count 0
    np.testing.assert_array_equal(got, ref)


def test_gradient_terms_match_numpy_gradient():
    from telefringe.metrology.bga._kernels import gradient_terms

    rng = np.random.default_rng(4)
    for shape in ((2, 2), (5, 3), (40, 57)):
        ln_i = rng.normal(size=shape)
        t = rng.normal(size=shape)
        ln_i[rng.random(shape) < 0.1] = np.nan
        out = np.zeros(shape + (3,))
        gradient_terms(ln_i, t, 0.37, out)
        gi_v, gi_u = np.gradient(ln_i)
        gt_v, gt_u = np.gradient(t)
        ref = np.stack([(gi_u * gt_u + gi_v * gt_v) / 0.37, gi_u, gi_v], axis=-1)
        np.testing.assert_array_equal(out, ref)  # bit for bit (NaN where NaN)
