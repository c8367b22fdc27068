"""Finite-difference checks of the hand-written Jacobians and normal equations of the cap
fits through the point-spread model (Schur complement) and of the joint parallel planes."""

from __future__ import annotations

import numpy as np

from telefringe.metrology.bga.psf import _cap_residuals, _schur_normal_equations
from telefringe.metrology.steps import _parallel_planes_normal_equations


def _cap(rng, m=60, r=0.225, npar=3):
    c = np.array([0.1, -0.2, 0.13])
    view = np.array([0.05, -0.03, 1.0])
    view /= np.linalg.norm(view)
    u = rng.normal(size=(m, 3))
    u[:, 2] = np.abs(u[:, 2]) + 1.0
    u /= np.linalg.norm(u, axis=1)[:, None]
    pts = c + r * u + rng.normal(0, 1e-3, (m, 3))
    R = rng.normal(0, 1.0, (m, npar)) * [50.0, 1.0, 1.0][:npar]
    return pts, R, c, view, r


def _num_jac(f, x, h):
    cols = []
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = h
        cols.append((f(x + e) - f(x - e)) / (2 * h))
    return np.stack(cols, axis=1)


def test_cap_residual_jacobians_match_finite_differences():
    rng = np.random.default_rng(0)
    pts, R, c, view, r = _cap(rng)
    theta = np.array([3e-4, 2e-3, -1e-3])
    res, J, K = _cap_residuals(pts, R, c + 0.002, theta, r, view)
    Jn = _num_jac(lambda x: _cap_residuals(pts, R, x, theta, r, view)[0], c + 0.002, 1e-6)
    Kn = _num_jac(lambda t: _cap_residuals(pts, R, c + 0.002, t, r, view)[0], theta, 1e-7)
    # central differences: truncation ~h^2 |f'''| and rounding ~eps |f| / h, both < 1e-8
    assert np.max(np.abs(J - Jn)) < 1e-8
    assert np.max(np.abs(K - Kn)) < 1e-8 * np.max(np.abs(K))


def test_schur_complement_equals_the_full_gauss_newton_step():
    """The reduced normal equations of theta give the same step as the full system in
    (every ball's centre, theta), and the reduced matrix inverts to the theta block of
    the full inverse (the covariance)."""
    rng = np.random.default_rng(1)
    npar = 3
    terms = []
    for _ in range(4):
        pts, R, c, view, r = _cap(rng, npar=npar)
        res, J, K = _cap_residuals(pts, R, c + rng.normal(0, 1e-3, 3), np.zeros(npar), r,
                                   view)
        w = rng.uniform(0.5, 2.0, res.size)
        terms.append((res, J, K, w))
    A, b, chi2, dof = _schur_normal_equations(terms, npar)
    nb = len(terms)
    n = 3 * nb + npar
    H = np.zeros((n, n))
    g = np.zeros(n)
    for k, (res, J, K, w) in enumerate(terms):
        Jf = np.zeros((res.size, n))
        Jf[:, 3 * k:3 * k + 3] = J
        Jf[:, 3 * nb:] = K
        H += Jf.T @ (w[:, None] * Jf)
        g += Jf.T @ (w * res)
    full = -np.linalg.solve(H, g)
    step = -np.linalg.solve(A, b)
    assert np.allclose(step, full[3 * nb:], rtol=1e-9, atol=1e-12 * np.max(np.abs(full)))
    assert np.allclose(np.linalg.inv(A), np.linalg.inv(H)[3 * nb:, 3 * nb:], rtol=1e-8)
    assert chi2 == sum(float(res @ (w * res)) for res, _, _, w in terms)
    assert dof == sum(res.size - 3 for res, *_ in terms)


def test_parallel_planes_normal_equations_match_finite_differences():
    rng = np.random.default_rng(2)
    n0 = np.array([0.01, -0.02, 1.0])
    n0 /= np.linalg.norm(n0)
    pts_list = [rng.uniform(-5, 5, (m, 3)) * [1, 1, 0] + [0, 0, z] + rng.normal(0, 1e-3, (m, 3))
                for m, z in ((200, 0.0), (150, 1.0), (100, 2.5))]
    M, b, T = _parallel_planes_normal_equations(pts_list, n0)
    K = len(pts_list)

    def resid(x):
        n = n0 + x[0] * T[0] + x[1] * T[1]
        n = n / np.linalg.norm(n)
        return np.concatenate([p @ n - x[2 + k] for k, p in enumerate(pts_list)])

    x0 = np.zeros(2 + K)
    Jn = _num_jac(resid, x0, 1e-6)
    # the model is the first order of the renormalised normal: equal Jacobians at t = 0
    assert np.allclose(M, Jn.T @ Jn, rtol=1e-7, atol=1e-7 * np.max(np.abs(M)))
    assert np.allclose(b, -Jn.T @ resid(x0), rtol=1e-7, atol=1e-7 * np.max(np.abs(b)))
