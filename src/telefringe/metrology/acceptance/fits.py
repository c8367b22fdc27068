"""Least-squares (Gaussian) sphere and plane fits of the acceptance test, with the 0.3 %
exclusion of VDI/VDE 2634 Part 2.

These fits minimise the sum of squared *orthogonal* distances (geometric least squares,
as ISO 10360-6 / PTB's TraCIM test data define the reference solutions), with equal
weights: the guideline's characteristics are properties of the point set, not of a
noise model. They are exact: on data whose least-squares solution is known they return
it to rounding (tests/test_acceptance_fits.py builds such data sets).

The sphere's covariance (the fit's own uncertainty, for PS and SD) is scaled by the
residuals. It treats the points as independent unless it is given their noise as
independent parts (:class:`PointNoise`): a two-camera match's points share the second
camera's pixels, so neighbouring points' errors are correlated and the independent
points' covariance understates the centre's and radius's variance (up to 1.8 times in
tests/test_stereo_noise_accept.py: centre x 1.78, diameter 1.16, a ball bar's distance
1.60); with it the covariance is the sandwich of the points' exact covariance, the fit
itself unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from telefringe.metrology._common import MetrologyError

__all__ = ["LSSphere", "LSPlane", "PointNoise", "correlated_covariance", "ls_sphere", "ls_plane",
           "n_excluded", "point_noise", "trimmed"]


@dataclass(frozen=True, eq=False)
class PointNoise:
    """The noise of n points split into independent parts: point i moves along its unit
    direction ``directions[i]`` by ``e_i + sum_q weights[i, q] z[sources[i, q]]``, with
    ``e_i`` its own error (variance ``var_own[i]``, independent of every other) and ``z``
    independent unit-variance sources shared between points (a two-camera match's: one
    per pixel and axis of the second camera, :class:`telefringe.reconstruction.stereo.
    StereoNoise`; :func:`point_noise` takes it at a region's pixels).

    Attributes
    ----------
    directions : (n, 3) unit, the line each point moves along (the first camera's).
    var_own : (n,) mm^2.   weights : (n, K) mm per unit source.
    sources : (n, K) int, the source of each weight, -1 where none (distinct within a row).
    """

    directions: np.ndarray
    var_own: np.ndarray
    weights: np.ndarray
    sources: np.ndarray

    def __post_init__(self):
        d = np.asarray(self.directions, dtype=np.float64)
        v = np.asarray(self.var_own, dtype=np.float64)
        w = np.asarray(self.weights, dtype=np.float64)
        s = np.asarray(self.sources)
        n = v.shape[0] if v.ndim == 1 else -1
        if (v.ndim != 1 or d.shape != (n, 3) or w.ndim != 2 or w.shape[0] != n
                or s.shape != w.shape or not np.issubdtype(s.dtype, np.integer)):
            raise MetrologyError(f"point noise of inconsistent shapes: directions {d.shape}, "
                                 f"var_own {v.shape}, weights {w.shape}, sources {s.shape} "
                                 "(integer)")
        if not (np.all(np.isfinite(v)) and np.all(v >= 0) and np.all(np.isfinite(w))
                and np.all(np.isfinite(d))):
            raise MetrologyError("point noise must be finite (var_own >= 0) at every point")
        for name, a in (("directions", d), ("var_own", v), ("weights", w), ("sources", s)):
            a = a.copy()
            a.setflags(write=False)
            object.__setattr__(self, name, a)

    def __len__(self) -> int:
        return int(self.var_own.shape[0])

    def take(self, index) -> PointNoise:
        """The noise of the points ``index`` selects ((n,) bool or integer indices)."""
        return PointNoise(self.directions[index], self.var_own[index], self.weights[index],
                          self.sources[index])


def point_noise(noise, directions, pixels) -> PointNoise:
    """A grid's noise split at some of its pixels.

    Parameters
    ----------
    noise : StereoNoise (:func:`telefringe.reconstruction.stereo.match_noise`): ``var_own``
        (rows, cols) mm^2, ``weights`` (rows, cols, K), ``sources`` (rows, cols, K).
    directions : (3,) or (rows, cols, 3) unit, the cloud's viewing directions.
    pixels : (k, 2) int, (row, col) of the points, in their order.

    Returns
    -------
    PointNoise of the k points.

    Raises
    ------
    MetrologyError
        Shapes that do not agree, or a pixel the noise does not cover (NaN var_own).
    """
    var = np.asarray(noise.var_own, dtype=np.float64)
    px = np.asarray(pixels, dtype=np.int64).reshape(-1, 2)
    d = np.asarray(directions, dtype=np.float64)
    if var.ndim != 2 or d.shape not in ((3,), var.shape + (3,)):
        raise MetrologyError(f"noise of shape {var.shape} and directions of shape {d.shape} "
                             "do not agree (directions (3,) or (rows, cols, 3))")
    r, c = px[:, 0], px[:, 1]
    v = var[r, c]
    if not np.all(np.isfinite(v)):
        raise MetrologyError(f"the noise does not cover {int(np.sum(~np.isfinite(v)))} of "
                             "the points (NaN var_own): not the cloud's match")
    dirs = np.broadcast_to(d, (px.shape[0], 3)) if d.ndim == 1 else d[r, c]
    return PointNoise(dirs, v, np.asarray(noise.weights)[r, c],
                      np.asarray(noise.sources)[r, c])


def correlated_covariance(J, a, f, noise: PointNoise):
    """Covariance of a least-squares fit's parameters whose residuals' noise is
    correlated, scaled by the residuals, and its part from the shared sources.

    The residual i moves by ``a_i delta_s_i`` when point i moves by ``delta_s_i`` along
    its line; ``delta_s = e + B z`` (``noise``), so the residuals' covariance is ``C =
    diag(a^2 var_own) + A B B' A``. The parameters' is the sandwich ``k N^-1 J' C J N^-1``
    (``N = J' J``), with ``k = f' f / tr((I - H) C)`` (``H = J N^-1 J'``; ``E[f' f] =
    tr((I - H) C)``): 1 when the noise model's size is right, what the residuals hold
    otherwise (with ``C`` a multiple of the identity the usual ``f' f / dof N^-1``).

    Parameters
    ----------
    J : (n, p) d residual / d parameters.   a : (n,) d residual / d point along its line.
    f : (n,) residuals.   noise : PointNoise of the n points.

    Returns
    -------
    (cov (p, p), sources (m,) int, gain (p, m)): the shared sources the fit sees and the
    parameters' change per unit of each (``sqrt(k) N^-1 J' A B``), from which the
    covariance with another fit of the same scan is ``gain_1[:, common] gain_2[:,
    common]'``.
    """
    J = np.asarray(J, dtype=np.float64)
    if len(noise) != J.shape[0]:
        raise MetrologyError(f"noise of {len(noise)} points for a fit of {J.shape[0]}")
    try:
        Ninv = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        raise MetrologyError("the fit is not determined by these points") from None
    Ja = J * a[:, None]
    own = (Ja * noise.var_own[:, None]).T @ Ja
    use = noise.sources >= 0
    src, inv = np.unique(noise.sources[use], return_inverse=True)
    rows = np.broadcast_to(np.arange(J.shape[0])[:, None], noise.sources.shape)[use]
    w = noise.weights[use]
    JB = np.stack([np.bincount(inv, weights=Ja[rows, c] * w, minlength=src.size)
                   for c in range(J.shape[1])]).reshape(J.shape[1], src.size)
    JCJ = own + JB @ JB.T
    tr_c = float(np.sum(a * a * (noise.var_own
                                 + np.sum(np.where(use, noise.weights, 0.0) ** 2, axis=1))))
    tr_hc = float(np.trace(Ninv @ JCJ))
    k = float(f @ f) / max(tr_c - tr_hc, 1e-300)
    return k * (Ninv @ JCJ @ Ninv), src, np.sqrt(k) * (Ninv @ JB)


@dataclass(frozen=True, eq=False)
class LSSphere:
    """A least-squares sphere with free radius.

    Attributes
    ----------
    centre : (3,) mm.   radius : float, mm.
    residuals : (n,) mm, ``|p - centre| - radius`` of the points fitted.
    covariance : (4, 4) mm^2, of (cx, cy, cz, r), from the residuals' scatter (the
        statistical uncertainty of the fit): of independent points, or with the points'
        correlated noise when the fit was given it (``noise=``).
    iterations : int, Gauss-Newton iterations taken.
    correlated : bool, the covariance holds the points' correlated noise.
    sources, source_gain : (m,) int and (4, m), with ``noise=``: the shared noise sources
        the fit sees and the change of (cx, cy, cz, r) per unit of each
        (:func:`correlated_covariance`), for the covariance with another sphere of the
        same scan; None otherwise.
    """

    centre: np.ndarray
    radius: float
    residuals: np.ndarray
    covariance: np.ndarray
    iterations: int
    correlated: bool = False
    sources: np.ndarray | None = None
    source_gain: np.ndarray | None = None

    @property
    def diameter(self) -> float:
        return 2.0 * self.radius


@dataclass(frozen=True, eq=False)
class LSPlane:
    """A least-squares (total least squares) plane ``normal . x = normal . centroid``.

    Attributes
    ----------
    normal : (3,) unit, with a non-negative z component.   centroid : (3,) mm.
    residuals : (n,) mm, signed distances of the points fitted.
    """

    normal: np.ndarray
    centroid: np.ndarray
    residuals: np.ndarray


def _points(points) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise MetrologyError(f"points must have shape (n, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise MetrologyError("points must be finite")
    return p


def ls_sphere(points, *, tol: float = 1e-13, max_iter: int = 200,
              noise: PointNoise | None = None) -> LSSphere:
    """Least-squares sphere with free radius: minimises ``sum (|p_i - c| - r)^2``.

    Start: the algebraic (Kasa) sphere; then Gauss-Newton on the orthogonal distances
    (with step halving when a step does not lower the sum), until the step is below
    ``tol`` relative to the size of the point set. Points are centred first, for
    conditioning.

    Parameters
    ----------
    points : (n, 3) array_like of float, mm, n >= 4, not coplanar.
    noise : PointNoise of the n points, optional: the covariance then holds their
        correlated noise (:func:`correlated_covariance`); the fit is the same.

    Returns
    -------
    LSSphere

    Raises
    ------
    MetrologyError
        Fewer than 4 points, coplanar points, or no convergence; noise of other points.
    """
    p = _points(points)
    n = p.shape[0]
    if n < 4:
        raise MetrologyError(f"a sphere needs at least 4 points, got {n}")
    m = p.mean(axis=0)
    q = p - m
    scale = float(np.sqrt(np.mean(np.sum(q * q, axis=1)))) or 1.0
    A = np.column_stack([2.0 * q, np.ones(n)])
    b = np.sum(q * q, axis=1)
    sol, _, rank, sv = np.linalg.lstsq(A, b, rcond=None)
    if rank < 4 or sv[-1] <= 1e-12 * sv[0]:
        raise MetrologyError("the points are coplanar (or fewer than 4 distinct): no sphere")
    c = sol[:3]
    r2 = sol[3] + c @ c
    if not r2 > 0:
        raise MetrologyError("no sphere fits these points (negative radius squared)")
    x = np.concatenate([c, [np.sqrt(r2)]])

    def resid(x):
        d = q - x[:3]
        dist = np.sqrt(np.sum(d * d, axis=1))
        return dist - x[3], d, dist

    f, d, dist = resid(x)
    cost = float(f @ f)
    floor = n * (1e-14 * scale) ** 2  # sums of squares below this are rounding
    prev = np.inf
    iterations = 0
    for _ in range(max_iter):
        iterations += 1
        J = np.column_stack([-d / dist[:, None], -np.ones(n)])
        step = np.linalg.lstsq(J, -f, rcond=None)[0]
        # step halving only where the sum of squares clearly rises (near the solution
        # its changes are at the rounding level and the full step is taken)
        t = 1.0
        while True:
            xn = x + t * step
            fn, dn, distn = resid(xn)
            cn = float(fn @ fn)
            # rounding moves each residual by ~1e-16 scale, the sum by ~2 |f| that much
            rounding = 1e-14 * scale * np.sqrt(n * max(cost, cn)) + floor
            if cn <= cost * (1.0 + 1e-9) + rounding or t < 1e-6:
                break
            t *= 0.5
        x, f, d, dist, cost = xn, fn, dn, distn, cn
        size = float(np.linalg.norm(step))
        # converged: a full step below tol, or steps at the rounding floor that no longer
        # shrink (Gauss-Newton's steps shrink geometrically until rounding stops them)
        if t == 1.0 and (size <= tol * scale or (size <= 1e-10 * scale and size > 0.5 * prev)):
            break
        prev = size
    else:
        raise MetrologyError("the sphere fit did not converge")
    J = np.column_stack([-d / dist[:, None], -np.ones(n)])
    if noise is not None:
        if len(noise) != n:
            raise MetrologyError(f"noise of {len(noise)} points for a sphere of {n}")
        # a point moved along its line by s moves its residual by (radial unit . line) s
        a = np.sum(d / dist[:, None] * noise.directions, axis=1)
        cov, src, gain = correlated_covariance(J, a, f, noise)
        return LSSphere(centre=x[:3] + m, radius=float(x[3]), residuals=f, covariance=cov,
                        iterations=iterations, correlated=True, sources=src,
                        source_gain=gain)
    dof = max(n - 4, 1)
    try:
        cov = float(f @ f) / dof * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        raise MetrologyError("the sphere is not determined by these points") from None
    return LSSphere(centre=x[:3] + m, radius=float(x[3]), residuals=f, covariance=cov,
                    iterations=iterations)


def ls_plane(points) -> LSPlane:
    """Least-squares (orthogonal distance) plane: the centroid and the eigenvector of the
    smallest eigenvalue of the points' scatter matrix (exact, no iteration).

    Parameters
    ----------
    points : (n, 3) array_like of float, mm, n >= 3, not collinear.

    Returns
    -------
    LSPlane

    Raises
    ------
    MetrologyError
        Fewer than 3 points, or collinear points.
    """
    p = _points(points)
    if p.shape[0] < 3:
        raise MetrologyError(f"a plane needs at least 3 points, got {p.shape[0]}")
    c = p.mean(axis=0)
    q = p - c
    # the SVD of the centred points (better conditioned than the scatter matrix)
    _, s, vt = np.linalg.svd(q, full_matrices=False)
    if s[1] <= 1e-12 * s[0]:
        raise MetrologyError("the points are collinear: no plane")
    nrm = vt[2]
    if nrm[2] < 0:
        nrm = -nrm
    return LSPlane(normal=nrm, centroid=c, residuals=q @ nrm)


def n_excluded(n: int, fraction: float) -> int:
    """How many of ``n`` points the exclusion of ``fraction`` (0.003) removes: the
    largest whole number not above ``fraction * n`` ("up to 0.3 %")."""
    if not 0 <= fraction < 0.5:
        raise MetrologyError(f"the excluded fraction must be in [0, 0.5), got {fraction}")
    return int(np.floor(fraction * n + 1e-9))


def trimmed(points, fit, fraction: float, *, noise: PointNoise | None = None):
    """Fit, drop the ``n_excluded`` points of largest |residual|, fit the rest again.

    Parameters
    ----------
    points : (n, 3) mm.   fit : :func:`ls_sphere` or :func:`ls_plane`.
    fraction : float, 0.003 for the guideline's 0.3 %.
    noise : PointNoise of the n points, optional, passed to ``fit`` (the kept points').

    Returns
    -------
    (fit result of the kept points, kept : (n,) bool)
    """
    p = _points(points)
    kw = {} if noise is None else {"noise": noise}
    first = fit(p, **kw)
    k = n_excluded(p.shape[0], fraction)
    keep = np.ones(p.shape[0], dtype=bool)
    if k == 0:
        return first, keep
    order = np.argsort(np.abs(first.residuals), kind="stable")
    keep[order[-k:]] = False
    return fit(p[keep], **({} if noise is None else {"noise": noise.take(keep)})), keep
