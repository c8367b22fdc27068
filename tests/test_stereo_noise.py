"""The stereo points' correlated noise (reconstruction/stereo.py, :func:`match_noise`):
neighbouring matches interpolate the same pixels of the second camera, so their errors
are correlated; the split into the first camera's own part and the second camera's
shared pixels gives each point's sigma exactly and the covariance of smooth sums of the
points against a Monte Carlo of the match (white noise maps), where treating the points
as independent understates it; and the sandwich covariance of a fit built from it
(metrology/spheres.py, :func:`_sandwich`) against the dense formula."""

from __future__ import annotations

import numpy as np
import pytest
from anyrig_rigs import Coords, stereo_rig_of, stereo_truth

from telefringe.metrology.spheres import _sandwich
from telefringe.reconstruction.cloud import TriangulationError
from telefringe.reconstruction.stereo import match_noise, match_stereo


def _dense(noise, sel):
    """The (n, n) covariance of the along-line errors at the pixels ``sel``."""
    W = noise.weights[sel]
    Q = noise.sources[sel]
    n = W.shape[0]
    src = np.unique(Q[Q >= 0])
    B = np.zeros((n, src.size))
    for q in range(Q.shape[1]):
        ok = Q[:, q] >= 0
        B[np.flatnonzero(ok), np.searchsorted(src, Q[ok, q])] += W[ok, q]
    return np.diag(noise.var_own[sel]) + B @ B.T


@pytest.mark.parametrize("kind", ["pp", "tt"])
def test_correlation_matches_monte_carlo(kind):
    """The variance of the mean error of all points (the kind of sum a fit's parameters
    are) from the split's covariance within 3 sigma of 200 Monte Carlo matches (a
    variance of 200 samples scatters by 10 %), where the independent points' sum of
    variances is off by far more; both axes, the second camera noisier than the first
    (its shared part then dominates)."""
    shape = (16, 24)
    rig = stereo_rig_of(kind, shape)
    _, (u1, v1), (u2, v2) = stereo_truth(rig, shape)
    s1, s2 = 0.02, 0.08

    def coords(u, v, s, rng=None):
        def noisy(a):
            return a if rng is None else a + rng.normal(0, s, shape)
        return Coords(noisy(u), noisy(v), None, np.full(shape, s), np.full(shape, s))

    c1, c2 = coords(u1, v1, s1), coords(u2, v2, s2)
    m0 = match_stereo(rig, c1, c2, max_residual=None)
    nz = match_noise(rig, c1, c2, m0)
    sel = m0.cloud.mask.copy()
    # the split gives the matcher's sigma exactly
    var = nz.var_own + np.sum(nz.weights ** 2, axis=-1)
    np.testing.assert_allclose(np.sqrt(var[sel]), m0.cloud.sigma_line[sel], rtol=1e-9)
    assert np.all(np.isnan(nz.var_own[~sel]))
    rng = np.random.default_rng(11)
    d0 = m0.cloud.directions
    runs = []
    for _ in range(200):
        cl = match_stereo(rig, coords(u1, v1, s1, rng), coords(u2, v2, s2, rng),
                          max_residual=None).cloud
        runs.append(np.sum((cl.xyz - m0.cloud.xyz)
                           * (d0 if d0.ndim == 3 else d0[None, None]), -1))
    runs = np.array(runs)
    sel &= np.all(np.isfinite(runs), axis=0)  # the points matched in every run
    assert sel.sum() > 0.6 * sel.size
    C = _dense(nz, sel)
    n = int(sel.sum())
    pred = float(C.sum()) / n ** 2
    indep = float(np.trace(C)) / n ** 2
    means = runs[:, sel].mean(axis=1)
    emp = float(np.var(means, ddof=1))
    tol = 3.0 * np.sqrt(2.0 / 199)
    print(kind, "var of the mean: MC", emp, "predicted", pred, "independent", indep)
    assert abs(emp / pred - 1.0) < tol, (emp, pred)
    assert abs(emp / indep - 1.0) > 2 * tol, (emp, indep)  # the correlation matters


def test_match_noise_needs_sigmas():
    rig = stereo_rig_of("pp")
    _, (u1, v1), (u2, v2) = stereo_truth(rig)
    c1, c2 = Coords(u1, v1), Coords(u2, v2)
    m = match_stereo(rig, c1, c2)
    with pytest.raises(TriangulationError, match="sigma_u_p"):
        match_noise(rig, c1, c2, m)


def test_sandwich_against_dense():
    """:func:`_sandwich` equals ``k Ninv J' C J Ninv`` with the dense C and
    ``k = f' f / tr((I - H) C)``; with independent equal noise, the usual
    ``f' f / dof Ninv``."""
    rng = np.random.default_rng(2)
    n, p, K, ns = 60, 4, 8, 40
    J = rng.normal(size=(n, p))
    a = rng.uniform(0.5, 1.0, n)
    f = rng.normal(size=n)
    var_own = rng.uniform(0.1, 1.0, n)
    W = rng.normal(size=(n, K))
    Q = np.array([rng.choice(ns, K, replace=False) for _ in range(n)])
    Q[rng.random((n, K)) < 0.2] = -1
    B = np.zeros((n, ns))
    for q in range(K):
        ok = Q[:, q] >= 0
        np.add.at(B, (np.flatnonzero(ok), Q[ok, q]), W[ok, q])
    C = np.diag(a) @ (np.diag(var_own) + B @ B.T) @ np.diag(a)
    Ninv = np.linalg.inv(J.T @ J)
    H = J @ Ninv @ J.T
    k = f @ f / np.trace((np.eye(n) - H) @ C)
    ref = k * Ninv @ J.T @ C @ J @ Ninv
    np.testing.assert_allclose(_sandwich(J, a, Ninv, f, var_own, W, Q), ref, rtol=1e-10)
    plain = _sandwich(J, np.ones(n), Ninv, f, np.full(n, 0.3), np.zeros((n, 1)),
                      np.full((n, 1), -1))
    np.testing.assert_allclose(plain, f @ f / (n - p) * Ninv, rtol=1e-12)
