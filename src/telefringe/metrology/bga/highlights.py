"""Ball centres from their specular highlights (Gaussian spot fits), and the centre's
depth along a highlight's camera line."""

from __future__ import annotations

import numpy as np

from telefringe.metrology._common import MetrologyError, _tangent_basis
from telefringe.reconstruction.cloud import PointCloud


def _gauss_spots(wins: np.ndarray, u0: float, v0: float, *, max_iter: int = 60):
    """Least-squares fits of a pixel-integrated 2D Gaussian + background to many windows.

    ``wins`` (n, n0, n1): each is fitted with a * ex(u) * ey(v) + b, ex the integral over
    the pixel of a unit Gaussian of centre x and sigma sg (error functions), by
    Levenberg-Marquardt, one window per thread (analytic Jacobian; bounds a >= 0,
    -1 <= x <= n1, -1 <= y <= n0, 0.2 <= sg <= 0.4 min(n0, n1) by projection;
    :func:`telefringe.metrology.bga._kernels.gauss_spots`). Returns a list of (x, y,
    cov_xy (2, 2), sg) in window pixel coordinates, or None where the fit failed or the
    spot is not clear (peak below 10 residual sigma, or within a pixel of the window's
    edge).
    """
    from telefringe.metrology.bga._kernels import gauss_spots

    W = np.ascontiguousarray(wins, dtype=np.float64)
    n, n0, n1 = W.shape
    lo = np.array([0.0, -1.0, -1.0, 0.2, -np.inf])
    hi = np.array([np.inf, n1, n0, 0.4 * min(n0, n1), np.inf])
    b0 = W.reshape(n, -1).min(axis=1)
    P0 = np.column_stack([(W.reshape(n, -1).max(axis=1) - b0) * 2 * np.pi * 0.7**2,
                          np.full(n, float(u0)), np.full(n, float(v0)), np.full(n, 0.7),
                          b0])
    P, cost = np.empty((n, 5)), np.empty(n)
    JtJ, ok = np.empty((n, 5, 5)), np.empty(n, dtype=bool)
    gauss_spots(W, np.ascontiguousarray(P0), lo, hi, int(max_iter), P, cost, JtJ, ok)
    out = []
    dof = max(n0 * n1 - 5, 1)
    for k in range(n):
        a, x, y, sg, b = P[k]
        s2r = float(cost[k]) / dof
        try:
            cov = s2r * np.linalg.inv(JtJ[k])
        except np.linalg.LinAlgError:
            out.append(None)
            continue
        peak = a / (2 * np.pi * sg * sg)
        if not (ok[k] and np.all(np.isfinite(P[k])) and peak > 10.0 * np.sqrt(s2r)
                and 1.0 <= x <= n1 - 2 and 1.0 <= y <= n0 - 2):
            out.append(None)
            continue
        out.append((x, y, cov[1:3, 1:3], sg))
    return out


def _refine_by_highlights(cloud: PointCloud, image: np.ndarray, regions, centre, sig_c,
                          nrm, radius, sig_surface):
    """Ball centres on the substrate plane from their specular highlights.

    Under telecentric camera and projector every ball is seen and lit the same way, so
    its highlight sits at the same offset from its centre on every ball: the highlight
    (a small bright spot, located to ~0.01 px by a Gaussian fit) gives each ball's
    position relative to the others far better than the noisy cap fit; the common offset
    is the median of (highlight - cap centre) over the balls.

    The highlight's 3-D point is where its camera line meets the ball's fitted sphere.
    The line is exact (the points of neighbouring pixels lie on their own lines whatever
    their depth error: only their components across the viewing direction are used);
    the depth along it comes from the sphere fit of the whole cap, not from the few
    points at the highlight (whose depth noise, ~ sigma_line / 5, would move the centre
    on the substrate by the viewing direction's tilt times that).

    ``radius`` (n,) are the fitted radii, ``sig_surface`` (n,) the standard uncertainty
    of the fitted surface along the viewing direction near the top (mm).

    Returns (centre, sigma_centre, refined, lines (n, 3): a point of each highlight's
    camera line or NaN, median offset (3,) of highlight from centre or None).
    """
    if image.shape != cloud.shape:
        raise MetrologyError(f"image has shape {image.shape}, the cloud {cloud.shape}")
    rows, cols = cloud.shape
    d = np.asarray(cloud.direction, dtype=np.float64)
    h = 3
    hl = np.full(centre.shape, np.nan)
    hl_cov = np.full((centre.shape[0], 3, 3), np.nan)
    lines = np.full(centre.shape, np.nan)  # a point of each highlight's camera line
    found = []
    for k, (sl, reg) in enumerate(regions):
        sub = np.where(reg, image[sl], -np.inf)
        if not np.any(np.isfinite(sub)):
            continue
        # (no NaN left: argmax gives nanargmax's first largest)
        pi, pj = np.unravel_index(int(np.argmax(np.nan_to_num(sub, nan=-np.inf))),
                                  sub.shape)
        pv, pu = sl[0].start + pi, sl[1].start + pj
        if not (h <= pv < rows - h and h <= pu < cols - h):
            continue
        win = image[pv - h:pv + h + 1, pu - h:pu + h + 1]
        if not np.all(np.isfinite(win)):
            continue
        found.append((k, pv, pu, win))
    spots = (_gauss_spots(np.stack([f[3] for f in found]), float(h), float(h))
             if found else [])
    fitted = [(f, g) for f, g in zip(found, spots, strict=True) if g is not None]
    if fitted:
        # (compiled, one ball per thread: the NumPy steps are in its docstring)
        from telefringe.metrology.bga._kernels import highlight_lines

        ks = np.array([f[0] for f, _ in fitted], dtype=np.int64)
        P = np.ascontiguousarray(np.stack([
            cloud.xyz[pv - h:pv + h + 1, pu - h:pu + h + 1] for (_, pv, pu, _), _ in fitted]),
            dtype=np.float64)
        n_f = ks.size
        out_l, out_h = np.full((n_f, 3), np.nan), np.full((n_f, 3), np.nan)
        out_c = np.full((n_f, 3, 3), np.nan)
        highlight_lines(P, np.array([g[0] for _, g in fitted], dtype=np.float64),
                        np.array([g[1] for _, g in fitted], dtype=np.float64),
                        np.ascontiguousarray(d), np.ascontiguousarray(centre[ks],
                                                                      dtype=np.float64),
                        np.ascontiguousarray(radius[ks], dtype=np.float64),
                        np.ascontiguousarray(np.stack([g[2] for _, g in fitted]),
                                             dtype=np.float64),
                        np.ascontiguousarray(np.asarray(sig_surface)[ks], dtype=np.float64),
                        out_l, out_h, out_c)
        lines[ks], hl[ks], hl_cov[ks] = out_l, out_h, out_c
    good = np.all(np.isfinite(hl), axis=1)
    if np.count_nonzero(good) < 3:
        return centre, sig_c, np.zeros(centre.shape[0], dtype=bool), lines, None
    off = hl[good] - centre[good]
    T = _tangent_basis(nrm)
    trend = _offset_trend(off, centre[good] @ T.T)
    if trend is None:
        med = np.median(off, axis=0)
        # the median's uncertainty (common to all balls): 1.25 std / sqrt(n)
        s_med = 1.2533 * off.std(axis=0, ddof=1) / np.sqrt(off.shape[0])
        med_good, var_med = med, (T**2) @ (s_med**2)
    else:
        # the offset drifts over the part (a projector or camera that is not
        # telecentric lights or sees each ball from another direction): each ball's
        # offset from the fitted trend, with that prediction's uncertainty
        med_good, s_pred = trend
        med = np.full(centre.shape, np.nan)
        med[good] = med_good
        var_med = (s_pred**2) @ (T**2).T  # (m, 2)
    new_c = centre.copy()
    new_s = sig_c.copy()
    delta = hl[good] - med_good - centre[good]
    delta -= (delta @ nrm)[:, None] * nrm  # move on the substrate plane only
    new_c[good] = centre[good] + delta
    # in-plane uncertainty from the highlight fit and the offset; along the normal the
    # cap fit's
    var_t = np.einsum("ij,kjl,il->ki", T, hl_cov[good], T)  # (m, 2), tangent basis
    var_t = var_t + var_med
    var_n = (sig_c[good] ** 2) @ (nrm**2)  # (m,)
    new_s[good] = np.sqrt(var_t @ (T**2) + var_n[:, None] * nrm**2)
    return new_c, new_s, good, lines, med


#: A trend of the highlight offsets over the part is used when one of its slopes is
#: beyond this many standard errors (6 slopes tested: a false trend once in ~3000 parts
#: whose offset is truly common).
TREND_K = 4.0


def _offset_trend(off: np.ndarray, xy: np.ndarray):
    """An affine trend of the balls' highlight offsets ``off`` (m, 3) over their
    in-plane positions ``xy`` (m, 2) (mm), fitted robustly (least squares, then without
    residuals beyond 4 MAD, repeated until the kept balls repeat, at most 5 times).

    With a telecentric camera and projector the offset is the same for every ball and
    the trend's slopes are noise; with a pinhole projector (or camera) the light (or the
    view) comes from another direction at every ball and the offset drifts over the part
    (about r times half the angle the part subtends). Returns (prediction (m, 3), its
    standard uncertainty (m, 3)) when a slope is beyond :data:`TREND_K` of its standard
    error, else None (the median offset is used).
    """
    m = off.shape[0]
    if m < 12:
        return None
    A = np.column_stack([np.ones(m), xy - xy.mean(axis=0)])
    keep = np.ones(m, dtype=bool)
    for _ in range(5):
        coef, *_ = np.linalg.lstsq(A[keep], off[keep], rcond=None)
        res = off - A @ coef
        scale = 1.4826 * np.median(np.abs(res[keep]), axis=0)
        new = np.all(np.abs(res) <= 4.0 * np.maximum(scale, 1e-15), axis=1)
        if np.array_equal(new, keep) or np.count_nonzero(new) < 12:
            break
        keep = new
    coef, *_ = np.linalg.lstsq(A[keep], off[keep], rcond=None)
    res = off[keep] - A[keep] @ coef
    s2 = np.sum(res**2, axis=0) / max(int(keep.sum()) - 3, 1)  # (3,)
    try:
        C = np.linalg.inv(A[keep].T @ A[keep])
    except np.linalg.LinAlgError:
        return None
    t = np.abs(coef[1:]) / np.sqrt(np.outer(np.diag(C)[1:], s2) + 1e-300)  # (2, 3)
    if not np.any(t > TREND_K):
        return None
    var = np.einsum("ij,jk,ik->i", A, C, A)[:, None] * s2[None, :]
    return A @ coef, np.sqrt(var)


def _fit_along_line(q: np.ndarray, w: np.ndarray, a: np.ndarray, d: np.ndarray, r: float,
                    c0: np.ndarray):
    """Sphere of radius r with its centre on the line a + t d, fitted to points q (m, 3)
    with weights w: Gauss-Newton on t. Returns (centre (3,), sigma_t (mm)) or None."""
    t = float((c0 - a) @ d)
    for _ in range(20):
        v = q - (a + t * d)
        dist = np.linalg.norm(v, axis=1)
        f = dist - r
        j = -(v @ d) / dist  # d f / d t
        den = float(j @ (w * j))
        if not den > 0:
            return None
        step = -float(j @ (w * f)) / den
        t += step
        if abs(step) < 1e-9:
            break
    v = q - (a + t * d)
    f = np.linalg.norm(v, axis=1) - r
    dof = max(q.shape[0] - 1, 1)
    s_t = float(np.sqrt(float(f @ (w * f)) / dof / den))
    if not np.isfinite(t):
        return None
    return a + t * d, s_t
