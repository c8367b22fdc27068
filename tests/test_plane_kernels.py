"""The compiled kernels of the robust plane fit (telefringe.metrology._plane_kernels) and
of the BGA segmentation (telefringe.metrology.bga._kernels) against independent NumPy
and SciPy references: the pruned least median of squares against every trial's median,
the whole robust fit against the NumPy form it replaced, the dilation against
scipy.ndimage."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from telefringe.metrology._common import _MAD, _TUKEY_C, _tangent_basis
from telefringe.metrology._plane_kernels import lmeds_best
from telefringe.metrology.bga._kernels import heights, row_steps, within_taxicab
from telefringe.metrology.planes import _lmeds_plane, fit_plane


def _plane_points(rng, n=3000, outliers=0.3):
    """A tilted plane with noise, a fraction of outliers above it (balls), mm."""
    xy = rng.uniform(-10, 10, (n, 2))
    z = 0.3 + 0.01 * xy[:, 0] - 0.02 * xy[:, 1] + rng.normal(0, 0.002, n)
    out = rng.random(n) < outliers
    z[out] += rng.uniform(0.05, 0.4, np.count_nonzero(out))
    return np.column_stack([xy, z])


def _lmeds_reference(sub, triples):
    """Every trial's median, the first smallest (np.argmin), as the kernel did before."""
    meds = np.full(len(triples), np.inf)
    planes = []
    for t, (i, j, k) in enumerate(triples):
        a, b, c = sub[i], sub[j], sub[k]
        nn = np.cross(b - a, c - a)
        big = max(1.0, np.max(np.abs([a, b, c])))
        if np.linalg.norm(nn) < 1e-12 * big * big:
            planes.append(None)
            continue
        nn = nn / np.linalg.norm(nn)
        planes.append((nn, nn @ a))
        meds[t] = np.median((sub @ nn - nn @ a) ** 2)
    t = int(np.argmin(meds))
    return t, planes[t], meds[t]


@pytest.mark.parametrize("seed", range(6))
def test_pruned_lmeds_picks_the_same_trial_as_every_median(seed):
    rng = np.random.default_rng(seed)
    m = 400 + seed  # even and odd point counts
    sub = _plane_points(rng, m, outliers=0.4)
    triples = np.array([rng.choice(m, 3, replace=False) for _ in range(120)])
    triples[3] = [5, 5, 9]  # degenerate (two equal points)
    triples[50] = triples[7]  # a repeated trial: the first one must win a tie
    t, n, d, med = lmeds_best(sub, triples)
    t_ref, (n_ref, d_ref), med_ref = _lmeds_reference(sub, triples)
    assert t == t_ref
    np.testing.assert_allclose(n, n_ref, atol=1e-15)
    assert abs(d - d_ref) < 1e-14 and abs(med - med_ref) <= 1e-12 * med_ref
    # every trial collinear: no plane
    line = np.column_stack([np.arange(10.0), 2 * np.arange(10.0), np.zeros(10)])
    assert lmeds_best(line, np.array([[0, 1, 2], [3, 4, 5]]))[0] == -1


def _robust_plane_numpy(p, w, max_iter=50, seed=0):
    """The robust fit as NumPy code (the form the kernels replaced): normal, offset,
    inliers, sigma_offset, tilt covariance."""
    wf = w / w.mean()
    P = p.T.copy()

    def tls(P, w):
        c = (P @ w) / w.sum()
        Q = P - c[:, None]
        evals, evecs = np.linalg.eigh((Q * w) @ Q.T)
        n = evecs[:, 0]
        return (-n if n[2] < 0 else n), c

    n, d, _ = _lmeds_plane(p, np.random.default_rng(seed))
    r = n @ P - d
    scale = max(_MAD * np.median(np.abs(r)), 1e-12)
    extent = float(np.max(np.ptp(P, axis=1))) + 1e-12
    for _ in range(max_iter):
        u = r / (_TUKEY_C * scale)
        wt = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
        n_new, c = tls(P, wf * wt)
        d_new = float(n_new @ c)
        r = n_new @ P - d_new
        inl = wt > 0
        new_scale = max(_MAD * np.median(np.abs(r[inl])), 1e-12)
        tol = 1e-3 * new_scale / np.sqrt(max(int(np.count_nonzero(inl)), 1))
        done = (abs(d_new - d) < tol and np.linalg.norm(n_new - n) * extent < tol
                and abs(new_scale - scale) < 1e-3 * scale)
        n, d, scale = n_new, d_new, new_scale
        if done:
            break
    keep = np.abs(r) < _TUKEY_C * scale
    Pk, wk = P[:, keep], wf[keep]
    n, c = tls(Pk, wk)
    d = float(n @ c)
    rk = n @ Pk - d
    wk_n = wk / wk.mean()
    s2 = float(np.sum(wk_n * rk * rk) / (keep.sum() - 3))
    q = _tangent_basis(n) @ (Pk - c[:, None])
    return n, d, keep, np.sqrt(s2 / wk_n.sum()), s2 * np.linalg.inv((q * wk_n) @ q.T)


@pytest.mark.parametrize("seed", range(3))
def test_robust_plane_fit_matches_its_numpy_form(seed):
    rng = np.random.default_rng(10 + seed)
    p = _plane_points(rng)
    w = rng.uniform(0.5, 2.0, p.shape[0])
    f = fit_plane(p, weights=w, robust=True)
    n, d, keep, s_off, tilt_cov = _robust_plane_numpy(p, w)
    np.testing.assert_array_equal(f.inliers, keep)
    np.testing.assert_allclose(f.normal, n, atol=1e-13)
    assert abs(f.offset - d) < 1e-13
    assert abs(f.sigma_offset - s_off) < 1e-12 * s_off
    np.testing.assert_allclose(f.tilt_covariance, tilt_cov, rtol=1e-10)


def test_segmentation_kernels_match_numpy_and_scipy():
    rng = np.random.default_rng(3)
    xyz = rng.normal(size=(40, 50, 3))
    mask = rng.random((40, 50)) < 0.8
    xyz[~mask] = np.nan
    normal = np.array([0.1, -0.2, 1.0]) / np.linalg.norm([0.1, -0.2, 1.0])
    h = np.empty((40, 50))
    heights(xyz, mask, normal, 0.25, h)
    ref = np.where(mask, xyz @ normal - 0.25, np.nan)
    np.testing.assert_array_equal(np.isnan(h), np.isnan(ref))
    np.testing.assert_allclose(h[mask], ref[mask], atol=1e-15)
    steps = np.linalg.norm(np.diff(xyz[:, :, :2], axis=1), axis=2)
    np.testing.assert_array_equal(row_steps(xyz), steps[np.isfinite(steps)])
    for k in (1, 3, 7):
        above = rng.random((60, 70)) < 0.01
        above[0, 5] = above[59, 69] = True  # at the borders
        np.testing.assert_array_equal(within_taxicab(above, k),
                                      ndimage.binary_dilation(above, iterations=k))


def test_log_and_depth_match_numpy():
    from telefringe.metrology.bga._kernels import log_and_depth

    rng = np.random.default_rng(4)
    xyz = rng.normal(size=(20, 30, 3))
    mask = rng.random((20, 30)) < 0.8
    image = rng.uniform(-0.2, 2.0, (20, 30))
    image[3, 4] = np.nan
    d = np.array([0.05, -0.02, 1.0]) / np.linalg.norm([0.05, -0.02, 1.0])
    dirs = rng.normal(size=(20, 30, 3))
    for directions in (np.broadcast_to(d, (20, 30, 3)), dirs):
        ln_i, t = np.empty((20, 30)), np.empty((20, 30))
        log_and_depth(image, xyz, mask, directions, ln_i, t)
        with np.errstate(invalid="ignore"):
            ref_ln = np.log(np.where(image > 0, image, np.nan))
        np.testing.assert_array_equal(np.isnan(ln_i), np.isnan(ref_ln))
        np.testing.assert_allclose(ln_i, ref_ln, rtol=4.5e-16)  # (1 ulp: another log)
        ref_t = np.where(mask, np.sum(xyz * directions, axis=2), np.nan)
        np.testing.assert_allclose(t, ref_t, rtol=0, atol=1e-15)
        np.testing.assert_array_equal(np.isnan(t), ~mask)


def test_erosion_kernel_matches_scipy():
    from telefringe.metrology.bga._kernels import eroded_taxicab

    rng = np.random.default_rng(6)
    for k in (1, 2, 3):
        for shape in ((1, 1), (3, 7), (15, 12)):
            m = ndimage.binary_dilation(rng.random(shape) < 0.3)
            np.testing.assert_array_equal(eroded_taxicab(m, k),
                                          ndimage.binary_erosion(m, iterations=k))
        full = np.ones((6, 5), dtype=bool)  # the border counts as outside
        np.testing.assert_array_equal(eroded_taxicab(full, k),
                                      ndimage.binary_erosion(full, iterations=k))


def test_highlight_lines_match_their_numpy_form():
    from telefringe.metrology._common import _poly_design
    from telefringe.metrology.bga._kernels import highlight_lines

    rng = np.random.default_rng(8)
    d = np.array([0.1, -0.05, -1.0]) / np.linalg.norm([0.1, -0.05, -1.0])
    n, h = 5, 3
    vv, uu = np.mgrid[-h:h + 1, -h:h + 1].astype(float)
    # points on each pixel's line: a smooth map of the pixel plus any depth along d
    P = np.empty((n, 7, 7, 3))
    for k in range(n):
        base = np.array([k * 0.8, 0.2, 0.0]) + 0.033 * (uu[..., None] * [1, 0.01, 0]
                                                      + vv[..., None] * [0.02, 1, 0])
        P[k] = base + 0.001 * (uu**2)[..., None] * [1, 0, 0] + rng.normal(
            0, 0.01, (7, 7, 1)) * d
    P[1, 2, 3] = np.nan
    P[4, :6] = np.nan  # too few points
    xs, ys = rng.uniform(2.5, 3.5, n), rng.uniform(2.5, 3.5, n)
    centres = np.array([[k * 0.8, 0.2, -0.1] for k in range(n)])
    radii = np.full(n, 0.225)
    radii[2] = 0.01  # the line misses this sphere
    cov = np.tile(np.diag([1e-4, 2e-4]), (n, 1, 1))
    sig = np.full(n, 1e-3)
    lines, hl, hl_cov = (np.full((n, 3), np.nan), np.full((n, 3), np.nan),
                         np.full((n, 3, 3), np.nan))
    highlight_lines(P, xs, ys, d, centres, radii, cov, sig, lines, hl, hl_cov)
    for k in range(n):
        p = P[k].reshape(-1, 3)
        ok = np.all(np.isfinite(p), axis=1)
        if ok.sum() < 12:
            assert np.all(np.isnan(hl[k]))
            continue
        Q = p[ok] - np.outer(p[ok] @ d, d)
        A = _poly_design((uu - (xs[k] - h)).ravel()[ok], (vv - (ys[k] - h)).ravel()[ok], 2)
        coef = np.linalg.lstsq(A, Q, rcond=None)[0]
        q, J = coef[0], coef[1:3].T
        w = q - centres[k]
        b = w @ d
        disc = b * b - (w @ w - radii[k] ** 2)
        if not disc >= 0:
            assert k == 2 and np.all(np.isnan(hl[k]))
            continue
        np.testing.assert_allclose(lines[k], q, rtol=0, atol=1e-13)
        np.testing.assert_allclose(hl[k], q + (-b - np.sqrt(disc)) * d, rtol=0, atol=1e-12)
        np.testing.assert_allclose(hl_cov[k], J @ cov[k] @ J.T + 1e-6 * np.outer(d, d),
                                   rtol=1e-10, atol=1e-20)
