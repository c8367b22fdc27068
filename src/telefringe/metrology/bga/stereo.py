"""The cap fits' covariance with a two-camera match's correlated noise.

A point matched by two cameras moves along its first camera's line by ``delta_s = e +
sum_q weights_q z_q``: its own part ``e`` and shares of the second camera's pixels' noise
``z`` (:class:`telefringe.reconstruction.stereo.StereoNoise`), which the matches of
neighbouring pixels share (their bilinear cells read the same pixels). A cap fit that
treats its points as independent understates its centre's and its apex's noise. Each
ball's fit is linearised at its solution on the points it kept, with the weights it used,
and its covariance is the sandwich of the points' exact covariance
(:func:`telefringe.metrology.spheres._sandwich`), scaled by the residuals as the
independent points' figure is; so is the point-spread model's common parameters' solve
(:func:`theta_sandwich`).

Monte Carlo (tests/test_stereo_noise_bga.py, 40 seeds, 15 balls, cap model "fixed"): the
apex heights' variance / predicted 1.02 with the noise, 2.84 without; the pitch 0.98 and
1.81. Cap model "psf" on the same scene (80 seeds; not a test: the heights share the common
parameters' part, so a ratio pooled over the balls needs many seeds): 0.96 with, 1.71
without, 1.35 with the caps' sandwich but the common parameters' independent figure.

Between balls: two balls' errors are correlated only through second-camera pixels read by
both balls' cap points (or by a cap's and the substrate's points), i.e. cap points of two
balls matched within two pixels of each other in the second camera. The caps of
neighbouring balls are at least the pitch less a diameter apart on the object, and the
substrate's points at least ``substrate_margin`` from every ball region: on a BGA resolved
well enough to fit its caps they share no pixel, and each ball's sandwich is then the whole
of its noise (the pitch's and the coplanarity's first-order figures, which combine the
balls' sigmas as independent, hold). :func:`shared_sources` counts such pixels; a
measurement where some exist warns (``StereoCorrelationWarning``) rather than report
figures that leave that correlation out.
"""

from __future__ import annotations

import numpy as np

from telefringe.metrology._common import MetrologyError


class StereoCorrelationWarning(RuntimeWarning):
    """Two balls' cap points (or a cap's and the substrate's) read the same pixel of the
    second camera: their errors are correlated, which the pitch's and the coplanarity's
    noise figures (the balls' sigmas combined as independent) leave out."""


def noise_at(cloud, noise, pixels: np.ndarray):
    """The StereoNoise ``noise``'s (var_own (m,), weights (m, K), sources (m, K)) and the
    line directions (m, 3) at the flat pixel indices ``pixels`` (m,) of ``cloud``."""
    if np.shape(noise.var_own) != tuple(cloud.shape):
        raise MetrologyError(f"noise has shape {np.shape(noise.var_own)}, the cloud "
                             f"{tuple(cloud.shape)}")
    K = np.shape(noise.weights)[-1]
    var_own = np.asarray(noise.var_own, dtype=np.float64).reshape(-1)[pixels]
    if not np.all(np.isfinite(var_own)):
        raise MetrologyError("noise does not cover every fitted point (NaN var_own)")
    weights = np.asarray(noise.weights, dtype=np.float64).reshape(-1, K)[pixels]
    sources = np.asarray(noise.sources).reshape(-1, K)[pixels]
    dirs = np.asarray(cloud.directions, dtype=np.float64)
    d = (np.broadcast_to(dirs, (pixels.size, 3)) if dirs.ndim == 1
         else dirs.reshape(-1, 3)[pixels])
    return var_own, weights, sources, d


def sphere_sandwich(pts, w, centre, radius: float, free_radius: bool, parts):
    """Covariance (4, 4) of (cx, cy, cz, r) (mm^2; the radius row and column 0 when it
    was fixed) of the weighted sphere fit of ``pts`` (m, 3) with weights ``w`` (m,) at its
    solution (``centre`` (3,), ``radius``), with the points' correlated noise ``parts``
    (:func:`noise_at` at their pixels)."""
    from telefringe.metrology.spheres import _sandwich

    var_own, weights, sources, d = parts
    sw = np.sqrt(np.asarray(w, dtype=np.float64))
    v = np.asarray(pts, dtype=np.float64) - centre
    dist = np.linalg.norm(v, axis=1)
    nn = v / dist[:, None]
    J = -nn if not free_radius else np.column_stack([-nn, -np.ones(len(dist))])
    J = J * sw[:, None]
    f = (dist - radius) * sw
    a = np.einsum("ij,ij->i", nn, d) * sw  # d residual / d the point along its line
    try:
        Ninv = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        raise MetrologyError("the sphere is not determined by these points") from None
    cov = np.zeros((4, 4))
    p = J.shape[1]
    cov[:p, :p] = _sandwich(J, a, Ninv, f, var_own, weights, sources)
    return cov


def line_sandwich(pts, w, centre, radius: float, direction, parts) -> float:
    """Standard uncertainty (mm) of the depth t of a sphere's centre fitted on the line
    ``a + t direction`` (:func:`telefringe.metrology.bga.highlights._fit_along_line`,
    solution ``centre``, radius ``radius``) to ``pts`` (m, 3) with weights ``w``, with
    their correlated noise ``parts``; NaN when the line does not determine it."""
    from telefringe.metrology.spheres import _sandwich

    var_own, weights, sources, d = parts
    sw = np.sqrt(np.asarray(w, dtype=np.float64))
    v = np.asarray(pts, dtype=np.float64) - centre
    dist = np.linalg.norm(v, axis=1)
    nn = v / dist[:, None]
    J = (-(nn @ np.asarray(direction, dtype=np.float64)) * sw)[:, None]
    den = float(J[:, 0] @ J[:, 0])
    if not den > 0:
        return np.nan
    f = (dist - radius) * sw
    a = np.einsum("ij,ij->i", nn, d) * sw
    return float(np.sqrt(max(_sandwich(J, a, np.array([[1.0 / den]]), f, var_own,
                                       weights, sources)[0, 0], 0.0)))


def shared_sources(groups) -> tuple[int, int]:
    """(sources read by more than one of ``groups[:-1]`` (the balls), sources of the last
    (the substrate) read by a ball too): each group an (m, K) int array of sources (< 0:
    none)."""
    balls = [np.unique(g[g >= 0]) for g in groups[:-1]]
    if balls:
        allb = np.concatenate(balls)
        u, counts = np.unique(allb, return_counts=True)
        between = int(np.count_nonzero(counts > 1))
    else:
        u, between = np.zeros(0, dtype=np.int64), 0
    sub = groups[-1]
    with_sub = int(np.intersect1d(u, np.unique(sub[sub >= 0])).size)
    return between, with_sub


def theta_sandwich(caps, parts, radius: float) -> np.ndarray:
    """Covariance (p, p) of the point-spread fits' common parameters theta (cap model
    "psf", :func:`telefringe.metrology.bga.psf._fit_caps_smoothed`) with the points'
    correlated noise: the sandwich of the Schur-reduced Gauss-Newton system at its
    solution, scaled by the residuals.

    Per ball k of the solve (``caps``: its CapFits, with ``regressors`` and ``views``;
    ``parts``: :func:`noise_at` at its points), in sqrt(w)-scaled rows: J the residuals'
    Jacobian in the centre, K in theta, P = I - J (J'J)^-1 J' (the centre eliminated),
    a their response to a point moving along its line. theta moves by -A^-1 sum_k K_k'
    P_k (a_k delta_s_k), A = sum_k K_k' P_k K_k, so its covariance is A^-1 (sum_k M_k
    C_k M_k') A^-1 with M_k = K_k' P_k diag(a_k) and C_k the points' covariance (the
    balls share no pixel, see the module), scaled by sum f'f / sum tr(P C) (the
    independent points' figure when C is the weights' identity).
    """
    A = S = None
    chi2 = tr = 0.0
    for c, (var_own, weights, sources, d) in zip(caps, parts, strict=True):
        sw = np.sqrt(np.asarray(c.weights, dtype=np.float64))
        v = np.asarray(c.points, dtype=np.float64) - c.fit.centre
        dist = np.linalg.norm(v, axis=1)
        nn = v / dist[:, None]
        J = -nn * sw[:, None]
        K = (np.einsum("ij,ij->i", nn, c.views) * sw)[:, None] * c.regressors
        a = np.einsum("ij,ij->i", nn, d) * sw
        f = (dist - radius) * sw
        P = np.eye(len(sw)) - J @ np.linalg.solve(J.T @ J, J.T)
        M = K.T @ P
        use = sources >= 0
        src, inv = np.unique(sources[use], return_inverse=True)
        B = np.zeros((len(sw), src.size))
        rows = np.broadcast_to(np.arange(len(sw))[:, None], sources.shape)[use]
        np.add.at(B, (rows, inv), weights[use])
        aB = a[:, None] * B
        Ma = M * a[None, :]
        Sk = (Ma * var_own[None, :]) @ Ma.T + (M @ aB) @ (M @ aB).T
        A = M @ K if A is None else A + M @ K
        S = Sk if S is None else S + Sk
        chi2 += float(f @ f)
        tr += float(np.sum(np.diag(P) * a * a * var_own) + np.sum(aB * (P @ aB)))
    Ai = np.linalg.inv(A)
    return chi2 / max(tr, 1e-300) * (Ai @ S @ Ai)
