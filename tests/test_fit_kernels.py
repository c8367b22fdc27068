"""The compiled fit kernels (telefringe.metrology._fit_kernels) against independent
references: the sphere fit's Levenberg-Marquardt against scipy's least squares, the
hand-written order statistics and small solves the kernels use against NumPy's (the
plane's kernels: tests/test_plane_kernels.py)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from telefringe.metrology._fit_kernels import _inv, _median, _percentile, _solve
from telefringe.metrology.spheres import _sphere_geometric


def _cap(rng, n=60, r=0.225, noise=1e-3):
    """Points of a sphere cap (the top 60 deg, as a BGA ball's) with radial noise."""
    th = rng.uniform(0, np.radians(60), n)
    ph = rng.uniform(0, 2 * np.pi, n)
    c = np.array([15.0, 12.0, 0.1])
    d = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=1)
    return c + (r + rng.normal(0, noise, n))[:, None] * d, c


def test_sphere_lm_kernel_matches_scipy_least_squares():
    rng = np.random.default_rng(1)
    worst = 0.0
    for k in range(20):
        p, c = _cap(rng)
        w = rng.uniform(0.5, 2.0, p.shape[0])
        fixed = k % 2 == 0
        start = c + rng.normal(0, 0.01, 3)
        cc, r, f, J = _sphere_geometric(p, w, start, 0.225, fixed_radius=fixed)

        def res(x, p=p, w=w, fixed=fixed):
            rad = 0.225 if fixed else x[3]
            return np.sqrt(w) * (np.linalg.norm(p - x[:3], axis=1) - rad)

        x0 = start if fixed else np.r_[start, 0.225]
        ref = least_squares(res, x0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
        worst = max(worst, float(np.max(np.abs(cc - ref.x[:3]))))
        if not fixed:
            worst = max(worst, abs(r - ref.x[3]))
        # the returned residuals and weighted Jacobian belong to the solution
        np.testing.assert_allclose(f, np.linalg.norm(p - cc, axis=1) - r, atol=1e-15)
        assert J.shape == (p.shape[0], 3 if fixed else 4)
        np.testing.assert_allclose(J[:, :3], -np.sqrt(w)[:, None] * (p - cc)
                                   / np.linalg.norm(p - cc, axis=1)[:, None], atol=1e-14)
    assert worst < 1e-9  # mm (the noise is 1e-3 mm)


def test_order_statistics_equal_numpys():
    """_percentile and _median on sizes 1..40 with ties, sorted and reversed runs: the
    median bit for bit NumPy's; the percentile bit for bit numba's np.percentile (the
    closest ranks of the sorted values, lower (1 - m) + upper m with rank 1 + (n - 1) q /
    100 = f + m) and NumPy's within 2 eps of the values' range (NumPy writes the same
    interpolation another way); NaN with a NaN, as both."""
    rng = np.random.default_rng(3)
    eps = np.finfo(float).eps
    for n in range(1, 41):
        for a in (rng.normal(size=n), np.round(rng.normal(size=n), 1),
                  np.sort(rng.normal(size=n)), -np.sort(rng.normal(size=n)), np.ones(n)):
            before = a.copy()
            srt = np.sort(a)
            for q in (75.0, 0.5, 33.3, 99.9):
                rank = 1 + (n - 1) * (q / 100.0)
                f = int(np.floor(rank))
                m = rank - f
                want = srt[0] if n == 1 else srt[f - 1] * (1 - m) + srt[f] * m
                got = _percentile(a, q)
                assert got == want, (n, q)
                assert abs(got - np.percentile(a, q)) <= 2 * eps * np.ptp(a), (n, q)
            assert _median(a) == np.median(a), n
            np.testing.assert_array_equal(a, before)  # the input is not reordered
    a = rng.normal(size=9)
    a[4] = np.nan
    assert np.isnan(_percentile(a, 75.0)) and np.isnan(_median(a))


def test_small_solves_equal_lapack_to_rounding():
    """_solve and _inv (LU with partial pivoting) against LAPACK's (np.linalg) on 3 x 3
    and 4 x 4 systems, well and badly conditioned: within 4 eps times the condition
    number times the largest entry (twice the worst measured, 1.97 for the inverse and
    1.12 for the solve); LinAlgError for a singular or non-finite A."""
    rng = np.random.default_rng(4)
    eps = np.finfo(float).eps
    for n in (3, 4):
        for k in range(200):
            U, _ = np.linalg.qr(rng.normal(size=(n, n)))
            V, _ = np.linalg.qr(rng.normal(size=(n, n)))
            A = U @ np.diag(np.logspace(0, -(k % 10), n)) @ V.T  # cond up to 1e9
            B = rng.normal(size=(n, 2))
            cond = np.linalg.cond(A)
            X = np.linalg.solve(A, B)
            assert np.max(np.abs(_solve(A, B) - X)) <= 4 * eps * cond * np.max(np.abs(X))
            Ai = np.linalg.inv(A)
            assert np.max(np.abs(_inv(A) - Ai)) <= 4 * eps * cond * np.max(np.abs(Ai))
    A = np.ones((3, 3))
    with pytest.raises(np.linalg.LinAlgError):
        _solve(A, np.ones((3, 1)))
    A = np.eye(3)
    A[1, 2] = np.inf
    with pytest.raises(np.linalg.LinAlgError):
        _inv(A)
