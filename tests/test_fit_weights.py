"""Fits of clouds weight every point by its own sigma: one point without a sigma is left
out, it does not switch the whole cloud to unweighted fitting (review 2.2, item 3)."""

from __future__ import annotations

import numpy as np

from telefringe.metrology.planes import fit_plane
from telefringe.reconstruction.cloud import PointCloud


def _cloud(sigma):
    v, u = np.mgrid[0:30, 0:40].astype(float)
    rng = np.random.default_rng(3)
    z = 0.2 + 0.01 * u * 0.05 + rng.normal(0.0, 1.0, u.shape) * sigma
    xyz = np.stack([0.05 * u, 0.05 * v, z], axis=-1)
    return PointCloud.from_xyz(xyz, sigma_z=sigma)


def test_sigma_weights_survive_one_missing_sigma():
    sigma = np.where(np.arange(40)[None, :] < 20, 0.001, 0.02) * np.ones((30, 40))
    full = fit_plane(_cloud(sigma))
    manual = fit_plane(_cloud(sigma).points(), weights=1.0 / sigma.ravel() ** 2)
    np.testing.assert_allclose(full.normal, manual.normal, rtol=0, atol=1e-12)
    holed = sigma.copy()
    holed[4, 7] = np.nan
    fit = fit_plane(_cloud(holed))
    assert fit.n_points == full.n_points - 1  # that point is left out, the rest weighted
    # unweighted, the noisy half would make the offset ~4x less certain
    assert fit.sigma_offset < 1.2 * full.sigma_offset
    flat = fit_plane(_cloud(holed).points())  # arrays: unit weights
    assert flat.sigma_offset > 2 * full.sigma_offset
