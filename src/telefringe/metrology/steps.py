"""Step gauges: parallel flat levels fitted jointly (one common normal)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from telefringe.metrology._common import _MAD, MetrologyError, _freeze, _tangent_basis
from telefringe.reconstruction.cloud import PointCloud


@dataclass(frozen=True, eq=False)
class StepMeasurement:
    """Parallel flat levels of a step gauge.

    Attributes
    ----------
    normal : (3,) common unit normal of the levels (toward the camera).
    offsets : (k,) mm, ``normal . x = offset`` of each level, ascending.
    heights : (k,) mm, each level's height above the lowest (``offsets - offsets[0]``).
    sigma_heights : (k,) mm, standard uncertainty of ``heights`` from the residuals (0 for
        the lowest): the larger of the noise model's figure (independent points, or a
        two-camera match's correlated noise when given, ``correlated``) and the one from
        the residuals' spatial autocovariance (a phase ripple a level spans only a few
        periods of).
    step_heights : (k - 1,) mm, height of each level above the one below.
    sigma_steps : (k - 1,) mm, the same for ``step_heights``.
    rms : (k,) mm, RMS residual of each level.   n_points : (k,) int.
    centroids : (k, 3) mm.
    labels : (rows, cols) int, level of each pixel (-1: unused).
    edge_px : float, pixels: the margin kept from walls and other levels (see
        :func:`measure_steps`).
    correlated : bool, the noise model's figure holds a two-camera match's correlated
        noise (``measure_steps(..., noise=)``).
    uncertainty : dict of str -> Uncertainty, or None: ``"heights"``, ``"step_heights"``
        with the noise and calibration parts (set by
        :func:`telefringe.metrology.uncertainty.steps_uncertainty`; None until then).
    """

    normal: np.ndarray
    offsets: np.ndarray
    heights: np.ndarray
    sigma_heights: np.ndarray
    step_heights: np.ndarray
    sigma_steps: np.ndarray
    rms: np.ndarray
    n_points: np.ndarray
    centroids: np.ndarray
    labels: np.ndarray
    uncertainty: dict | None = None
    edge_px: float = float("nan")
    correlated: bool = False

    def __post_init__(self):
        _freeze(self, "normal", "offsets", "heights", "sigma_heights", "step_heights",
                "sigma_steps", "rms", "n_points", "centroids", "labels")


def _level_peaks(h: np.ndarray, *, min_step: float, min_points: int, bin_mm: float):
    lo, hi = float(h.min()), float(h.max())
    nb = max(int(np.ceil((hi - lo) / bin_mm)) + 1, 1)
    if nb > 2_000_000:
        raise MetrologyError("height range too large for the bin size")
    hist, edges = np.histogram(h, bins=nb, range=(lo, lo + nb * bin_mm))
    centres = 0.5 * (edges[:-1] + edges[1:])
    # counts within +- min_step / 3 of each bin (the band a level's points are taken from)
    half = max(int(round(min_step / 3.0 / bin_mm)), 0)
    counts = np.convolve(hist, np.ones(2 * half + 1, dtype=np.int64), mode="same")
    # tallest first; a peak must be min_step away from every taller one
    order = np.argsort(-counts, kind="stable")
    peaks = []
    for b in order:
        if counts[b] < min_points:
            break
        if all(abs(centres[b] - p) >= min_step for p in peaks):
            peaks.append(float(centres[b]))
    return sorted(peaks)


def _parallel_planes_normal_equations(pts_list, n: np.ndarray):
    """Gauss-Newton normal equations of parallel planes about the common normal ``n``.

    Parameters: the normal tilted to n + t0 T0 + t1 T1 (T = tangent basis of n) and the
    offsets d_k; residual of point p of level k: n . p + t . (T p) - d_k (linear in
    (t, d), the first order of the tilted normal). Returns (M (2 + K, 2 + K) = J^T J,
    b (2 + K,) = -J^T r0 with r0 = n . p (the residuals at t = 0, d = 0), T (2, 3)).
    """
    T = _tangent_basis(n)
    K = len(pts_list)
    M = np.zeros((2 + K, 2 + K))
    b = np.zeros(2 + K)
    for k, p in enumerate(pts_list):
        q = p @ T.T  # (m, 2)
        r = p @ n
        M[:2, :2] += q.T @ q
        sq = q.sum(axis=0)
        M[:2, 2 + k] -= sq
        M[2 + k, :2] -= sq
        M[2 + k, 2 + k] += p.shape[0]
        b[:2] -= q.T @ r
        b[2 + k] += r.sum()
    return M, b, T


def _joint_parallel_planes(pts_list, n0: np.ndarray):
    """Common normal and offsets of parallel planes, Gauss-Newton on (tilts, offsets)."""
    n = n0.copy()
    K = len(pts_list)
    for _ in range(5):
        Ms, bs, T = _parallel_planes_normal_equations(pts_list, n)
        try:
            x = np.linalg.solve(Ms, bs)
        except np.linalg.LinAlgError:
            raise MetrologyError("the levels do not determine a plane orientation") from None
        n_new = n + x[0] * T[0] + x[1] * T[1]
        n_new /= np.linalg.norm(n_new)
        if n_new[2] < 0:
            n_new = -n_new
        moved = np.linalg.norm(n_new - n)
        n = n_new
        if moved < 1e-13:
            break
    # final offsets, residuals and covariance at the solution
    offsets = np.array([float(np.mean(p @ n)) for p in pts_list])
    res = [p @ n - d for p, d in zip(pts_list, offsets, strict=True)]
    N = sum(p.shape[0] for p in pts_list)
    s2 = sum(float(np.sum(r * r)) for r in res) / max(N - 2 - K, 1)
    M, _, _ = _parallel_planes_normal_equations(pts_list, n)
    cov = s2 * np.linalg.inv(M)
    return n, offsets, res, cov


#: A lag of the residuals' autocovariance is used where at least this share of the kept
#: points has a partner at that lag (see :func:`_correlated_covariance`).
MIN_PAIR_SHARE = 0.25


def _correlated_covariance(xyz, labels, n, offsets):
    """Covariance (2 + K, 2 + K) of the joint fit's (tilts, offsets) when the residuals
    are spatially correlated (a ripple of the phase, form), from their own
    autocovariance.

    The residual field is taken as stationary over the image: its autocovariance C(lag)
    is estimated from the residuals of every kept pixel (all levels together, the large
    base included, by FFT): the sum of the products of the pairs at each pixel lag divided
    by the number of those pairs (the unbiased estimate), at every lag that at least
    :data:`MIN_PAIR_SHARE` of the points have a partner at (0 beyond: lags so long that
    few pairs estimate them). The fit's sandwich ``M^-1 (A^T C A) M^-1`` (A the design
    matrix, M = A^T A) gives the parameters' covariance: the expected covariance of the
    fit's errors over placements of the gauge relative to a ripple of that
    autocovariance. With uncorrelated residuals it scatters about the usual ``s^2 M^-1``
    (below); a level's mean error from a structure wider than a pixel (a level a few fringe
    periods wide, or less than one period of a ripple that repeats every few fringes) is
    what it adds.

    Not tapered: a taper (Bartlett's, out to the narrowest level's width, before) cuts
    the covariance between points farther apart than its reach, along a level's length
    and between neighbouring levels, where a ripple whose period is comparable to a
    level's width is still correlated; on the ``fast`` virtual rig's step gauge (an 8-bit
    projector's quantisation ripple, 4 fringe periods long) the steps' errors over 12
    placements were 1.44 times that figure (RMS), 1.02 times this one (noise-free; 1.14
    and 0.96 with the camera's noise).
    The price is the estimate's own scatter (the long lags are estimated from fewer
    pairs): on white noise it scatters about the white figure, 0.41-1.24 of it (mean 0.82:
    each level's residuals have their own mean removed) over 16 synthetic clouds of five
    strip levels without a base plate (the tapered one: 0.88-1.01); on the virtual rig's
    gauge (a large base) it varies by 8-10 % over the placements. The sandwich need not
    be positive semi-definite with this estimate: the caller takes the larger of it and
    the white-noise figure.
    ``labels`` (rows, cols) int, -1 unused; ``xyz`` (rows, cols, 3) mm.
    """
    from scipy import fft as sfft

    sel = labels >= 0
    rows_any = np.flatnonzero(sel.any(axis=1))
    cols_any = np.flatnonzero(sel.any(axis=0))
    box = (slice(rows_any[0], rows_any[-1] + 1), slice(cols_any[0], cols_any[-1] + 1))
    sel = sel[box]
    lab = labels[box]
    p = np.where(sel[..., None], xyz[box], 0.0)
    K = offsets.size
    T = _tangent_basis(n)
    q = p @ T.T
    q = np.where(sel[..., None], q - q[sel].mean(axis=0), 0.0)  # centred: better conditioned
    r = np.where(sel, p @ n - offsets[np.maximum(lab, 0)], 0.0)
    shape = tuple(sfft.next_fast_len(2 * m, real=True) for m in sel.shape)
    Fr = sfft.rfft2(r, shape)
    num = sfft.irfft2(Fr * np.conj(Fr), shape)
    Fs = sfft.rfft2(sel.astype(np.float64), shape)
    pairs = np.rint(sfft.irfft2(Fs * np.conj(Fs), shape))  # kept pairs at each lag
    N = float(np.count_nonzero(sel))
    C = np.where(pairs >= MIN_PAIR_SHARE * N, num / np.maximum(pairs, 1.0), 0.0)
    FC = sfft.rfft2(C)
    cols = [q[..., 0], q[..., 1]] + [-(lab == k).astype(np.float64) for k in range(K)]
    A = np.stack([c[sel] for c in cols], axis=1)
    M = A.T @ A
    B = np.zeros((2 + K, 2 + K))
    for j, c in enumerate(cols):
        conv = sfft.irfft2(sfft.rfft2(c, shape) * FC, shape)[:sel.shape[0], :sel.shape[1]]
        B[:, j] = A.T @ conv[sel]
    B = 0.5 * (B + B.T)
    Mi = np.linalg.inv(M)
    return Mi @ B @ Mi


def _noise_covariance(cloud: PointCloud, noise, labels, n, offsets):
    """Covariance (2 + K, 2 + K) of the joint fit's (tilts, offsets) with the points'
    correlated noise (a two-camera match's ``StereoNoise``), scaled by the residuals.

    A point moved by ``delta_s`` along its line ``d`` moves its residual ``n . p - d_k``
    by ``(n . d) delta_s``; the fit is linear in (tilts, offsets) about ``n`` (design
    ``[T p, -1 of its level]``, :func:`_parallel_planes_normal_equations`), so the
    parameters' covariance is the sandwich of the points' exact covariance from the
    noise split (:func:`telefringe.metrology.spheres._sandwich`: ``k M^-1 A' C A M^-1``,
    ``k = r' r / tr((I - H) C)``), which with independent points of equal sigma is the
    usual ``s^2 M^-1``. The tangent coordinates are centred on the kept points (the
    offsets' differences, the heights, do not depend on where they are taken).
    ``labels`` (rows, cols) int, -1 unused."""
    from telefringe.metrology.spheres import _sandwich

    if np.shape(noise.var_own) != cloud.shape:
        raise MetrologyError(f"noise has shape {np.shape(noise.var_own)}, the cloud "
                             f"{cloud.shape}")
    sel = labels >= 0
    var_own = np.asarray(noise.var_own, dtype=np.float64)[sel]
    if not np.all(np.isfinite(var_own)):
        raise MetrologyError("noise does not cover every fitted point (NaN var_own): not "
                             "the cloud's match")
    p = cloud.xyz[sel]
    lev = labels[sel]
    K = offsets.size
    T = _tangent_basis(n)
    q = p @ T.T
    q -= q.mean(axis=0)
    J = np.column_stack([q, -(lev[:, None] == np.arange(K)[None, :]).astype(np.float64)])
    f = p @ n - offsets[lev]
    dirs = np.asarray(cloud.directions, dtype=np.float64)
    d = np.broadcast_to(dirs, p.shape) if dirs.ndim == 1 else dirs[sel]
    Ninv = np.linalg.inv(J.T @ J)
    return _sandwich(J, d @ n, Ninv, f, var_own, np.asarray(noise.weights)[sel],
                     np.asarray(noise.sources)[sel])


def _dominant_normal(cloud: PointCloud) -> np.ndarray:
    """Median of the normals of the cloud's pixel quads: the orientation shared by most
    of the surface (the levels of a step gauge; a plane fit would tilt along the
    staircase)."""
    xyz = cloud.xyz
    a = xyz[:-1, 1:] - xyz[:-1, :-1]
    b = xyz[1:, :-1] - xyz[:-1, :-1]
    nq = np.cross(a, b).reshape(-1, 3)
    nq = nq[np.all(np.isfinite(nq), axis=1)]
    if nq.shape[0] < 3:
        raise MetrologyError("too few neighbouring valid points to find the orientation")
    nq /= np.linalg.norm(nq, axis=1, keepdims=True)
    nq[nq[:, 2] < 0] *= -1
    n = np.median(nq, axis=0)
    return n / np.linalg.norm(n)


#: Largest bias of a kept point from light of a neighbouring level, as a share of its own
#: noise sigma (sets the margin kept from every wall; see :func:`measure_steps`).
EDGE_BIAS_SHARE = 0.1


def _footprint_tail(x, psf_px: float) -> np.ndarray:
    """Share of a pixel's footprint (its unit square blurred by a Gaussian of ``psf_px``
    pixels sigma) beyond a straight edge ``x`` pixels from its centre: (n,) for (n,) x."""
    from scipy.special import ndtr

    x = np.atleast_1d(np.asarray(x, dtype=np.float64))
    if psf_px <= 0:
        return np.clip(0.5 - x, 0.0, 1.0)
    t = (np.arange(64) + 0.5) / 64 - 0.5  # midpoint rule across the pixel
    return np.mean(ndtr(-(x[:, None] + t[None, :]) / psf_px), axis=1)


def edge_margin_px(step_mm: float, sigma_mm: float, psf_px: float) -> float:
    """Smallest distance (pixels, between pixel centres) from the nearest pixel of another
    level at which a pixel's bias from that level's light is at most
    :data:`EDGE_BIAS_SHARE` of its noise.

    A pixel ``D`` pixels from a foreign one is at least ``D - 1`` pixels from the wall
    between them (the foreign pixel may hold just over half of the other level's light);
    the share of its footprint beyond the wall, times the height difference ``step_mm``,
    bounds its bias (a mixed pixel's height lies between the levels' for a small share).

    >>> round(edge_margin_px(2.0, 0.008, 0.5), 2)  # 2 mm steps, 8 um noise, focused camera
    2.9
    """
    if not (step_mm > 0 and sigma_mm > 0):
        return 1.0
    limit = EDGE_BIAS_SHARE * sigma_mm / step_mm
    d = np.arange(1.0, 1.0 + 12.0 * psf_px + 2.0, 0.01)  # the tail is below 1e-30 at the end
    ok = _footprint_tail(d - 1.0, psf_px) <= limit
    return float(d[np.argmax(ok)]) if ok.any() else float(d[-1])


def _assign(h_img, mask, offsets, s_img, k_band, floor):
    """Nearest level of every valid pixel and whether its height lies within ``k_band``
    of its own noise scale of that level's plane.

    Returns (nearest (rows, cols) int, -1 invalid; r (rows, cols) residual to the nearest
    plane, mm; in_band (rows, cols) bool; scale (k,) the factor on ``s_img`` per level:
    the robust spread of the residuals in units of ``s_img``, at least ``floor``).
    """
    hv = np.where(mask, h_img, 0.0)
    dist = np.abs(hv[..., None] - offsets[None, None, :])
    nearest = np.where(mask, np.argmin(dist, axis=-1), -1)
    r = np.where(mask, hv - offsets[np.maximum(nearest, 0)], np.nan)
    K = offsets.size
    scale = np.ones(K)
    # per level: the noise model scaled up where the residuals say it is too optimistic
    for k in range(K):
        z = np.abs(r[nearest == k] / s_img[nearest == k])
        z = z[np.isfinite(z)]
        if z.size:
            scale[k] = max(floor, _MAD * float(np.median(z)), 1e-12)
    band = k_band * s_img * scale[np.maximum(nearest, 0)]
    in_band = mask & (np.abs(r) <= band)
    return nearest, r, in_band, scale


def _structure(nearest, in_band, mask):
    """Level of each pixel for the wall geometry: its nearest level where it lies within
    its band, or where it is a lone outlier among 8 in-band neighbours of its own level
    (noise, not a wall: it must not carve a hole); -1 elsewhere (walls, mixed pixels,
    invalid pixels)."""
    out = np.where(in_band, nearest, -1)
    lone = mask & ~in_band
    if lone.any():
        pad = np.pad(out, 1, constant_values=-1)
        same = np.zeros(out.shape, dtype=np.int64)
        rows, cols = out.shape
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                if dr or dc:
                    same += pad[1 + dr:1 + dr + rows, 1 + dc:1 + dc + cols] == nearest
        lone &= same == 8
        out = np.where(lone, nearest, out)
    return out


def measure_steps(cloud: PointCloud, *, min_step: float = 0.05, min_points: int = 200,
                  psf_px: float = 0.5, edge_px: float | None = None,
                  k_band: float = 4.0, noise=None) -> StepMeasurement:
    """Heights of the flat levels of a step gauge (parallel planes fitted jointly).

    The median normal of the surface gives a first orientation; heights along it are
    histogrammed and every peak holding at least ``min_points`` points, ``min_step``
    (mm) or more from a taller one, starts a level. Then, until the points stop
    changing: every valid pixel goes to its nearest level's plane; it is kept if its
    distance to it is within ``k_band`` of its own noise along the normal (the cloud's
    ``sigma_line`` times the cosine of its line with the normal; scaled up per level where
    the residuals' robust spread says the noise model is optimistic) and if it lies at
    least ``edge_px`` pixels (Euclidean, between centres) from every pixel that is not
    of its level (walls, mixed pixels, other levels, invalid pixels, the image border); all
    levels are fitted as parallel planes with one common normal (Gauss-Newton). The
    points are thus chosen by their distance to fitted planes, never to a histogram's
    bins: a small change of the calibration moves them smoothly.

    ``sigma_heights`` and ``sigma_steps`` come from the residuals: the fit's covariance
    with their spatial autocovariance (:func:`_correlated_covariance`), never less than
    the noise model's (uncorrelated residuals, or with ``noise`` the two-camera match's
    correlated noise, :func:`_noise_covariance`; both scaled by the residuals). A phase
    ripple is correlated over its period, and a level a few periods wide does not average
    it away: an uncorrected projector nonlinearity's ripple repeats every fringe period,
    and an 8-bit projector's quantisation ripple every
    ``W / gcd(W, p)`` projector pixels (W the panel's pixels along the fringe axis, p the
    finest group's periods: 25 pixels, 4 fringe periods, with 64 periods on 400). Its
    bias on a level is fixed for a given placement of the gauge; the figure is its spread
    over placements.

    ``edge_px`` None: the margin at which a pixel's bias from the light of another level
    (its footprint, the pixel blurred by a Gaussian of ``psf_px`` pixels, beyond the
    wall, times the largest height difference of the levels) is at most a tenth of its
    noise (:func:`edge_margin_px`); 0.5 px is a focused camera.

    A cloud matched by two cameras has correlated noise: neighbouring matches interpolate
    the same pixels of the second camera, so the independent points' figure understates
    the levels' errors. Its noise split (``noise``) gives the noise model's figure the
    sandwich of the points' exact covariance. The autocovariance figure sees that
    correlation too (it is short-range), but estimated from the residuals alone it
    scatters (0.4-1.2 times the white figure on white noise): the noise model is the
    reliable floor, the autocovariance what a ripple adds beyond it; the larger of the two
    is taken (tests/test_stereo_noise_steps.py).

    Parameters
    ----------
    cloud : PointCloud, any camera (per-pixel viewing directions are used).
    min_step : float, mm, the smallest step to find.
    min_points : int, fewest points of a level.
    psf_px, edge_px, k_band : see above.
    noise : StereoNoise, optional, a cloud matched by two cameras: the matches' noise
        split (:func:`telefringe.reconstruction.stereo.match_noise`, on the cloud's grid).
        The levels found and fitted are the same.

    Returns
    -------
    StepMeasurement (``edge_px`` the margin used; ``correlated`` with ``noise``).

    Raises
    ------
    MetrologyError
        No step found; ``noise`` of another shape or not covering a fitted point.
    """
    from scipy import ndimage

    if not (np.isfinite(min_step) and min_step > 0):
        raise MetrologyError("min_step must be > 0")
    if not (np.isfinite(psf_px) and psf_px >= 0):
        raise MetrologyError("psf_px must be >= 0")
    if edge_px is not None and not (np.isfinite(edge_px) and edge_px >= 0):
        raise MetrologyError("edge_px must be >= 0")
    if not (np.isfinite(k_band) and k_band > 0):
        raise MetrologyError("k_band must be > 0")
    pts = cloud.points()
    if pts.shape[0] < 2 * min_points:
        raise MetrologyError(f"the cloud has {pts.shape[0]} valid points: too few for steps")
    xyz = cloud.xyz
    mask = cloud.mask
    # the start: levels as peaks of the heights' histogram along the surface's median
    # normal (which the walls tilt a little), the normal refined once by a joint fit of
    # the points near the peaks, the peaks found again along it
    n = _dominant_normal(cloud)
    for rough in (True, False):
        h = xyz[mask] @ n
        peaks = np.asarray(_level_peaks(h, min_step=min_step, min_points=min_points,
                                        bin_mm=min_step / 10.0))
        if peaks.size < 2:
            raise MetrologyError(
                f"found {peaks.size} level(s) of at least {min_points} points: no step")
        if rough:
            near = [xyz[mask][np.abs(h - pk) < min_step / 3] for pk in peaks]
            n = _joint_parallel_planes([p for p in near if p.shape[0] >= 3], n)[0]
    offsets = peaks.astype(np.float64)
    sig_line = np.asarray(cloud.sigma_line, dtype=np.float64)
    has_sigma = bool(np.any(np.isfinite(sig_line[mask]) & (sig_line[mask] > 0)))
    prev = None
    margin = np.nan
    merged = False
    for _ in range(12 + offsets.size):  # each merge of two starts takes one pass
        h_img = np.where(mask, xyz @ n, np.nan)
        if has_sigma:
            cosine = np.abs(np.asarray(cloud.directions) @ n)
            s_img = sig_line * np.broadcast_to(cosine, mask.shape)
            s_img = np.where(np.isfinite(s_img) & (s_img > 0), s_img,
                             np.nanmedian(s_img[mask]))
        else:
            s_img = np.ones(mask.shape)  # the per-level robust scale replaces it
        nearest, r, in_band, scale = _assign(h_img, mask, offsets, s_img, k_band,
                                             1.0 if has_sigma else 0.0)
        struct = _structure(nearest, in_band, mask)
        if edge_px is None:
            sig = float(np.median((s_img * scale[np.maximum(nearest, 0)])[in_band]))
            margin = edge_margin_px(float(np.ptp(offsets)), sig, psf_px)
        else:
            margin = float(edge_px)
        labels = np.full(mask.shape, -1, dtype=np.int64)
        pts_list = []
        keep = []
        for k in range(offsets.size):
            own = struct == k
            sel = own & in_band & (nearest == k)
            if margin > 1.0 and own.any():
                # the distance to the nearest pixel not of this level, within the level's
                # bounding box (grown by one pixel, which is not of it)
                rr = np.flatnonzero(own.any(axis=1))
                cc = np.flatnonzero(own.any(axis=0))
                box = (slice(rr[0], rr[-1] + 1), slice(cc[0], cc[-1] + 1))
                dist = ndimage.distance_transform_edt(np.pad(own[box], 1))[1:-1, 1:-1]
                sel[box] &= dist >= margin
            if np.count_nonzero(sel) < min_points:
                continue
            labels[sel] = len(pts_list)
            pts_list.append(xyz[sel])
            keep.append(k)
        if len(pts_list) < 2:
            raise MetrologyError("fewer than 2 levels left after edge removal: no step")
        n, fitted, res, cov = _joint_parallel_planes(pts_list, n)
        offsets = fitted
        if np.min(np.diff(np.sort(offsets))) < min_step:
            # two starts on one level: keep the fuller one, assign again
            counts = np.array([p.shape[0] for p in pts_list])
            keep_o = []
            for b in np.argsort(offsets):
                if keep_o and offsets[b] - offsets[keep_o[-1]] < min_step:
                    if counts[b] > counts[keep_o[-1]]:
                        keep_o[-1] = b
                else:
                    keep_o.append(b)
            offsets = offsets[np.sort(keep_o)]
            prev = None
            merged = True
            continue
        merged = False
        if prev is not None and prev.shape == labels.shape and np.array_equal(prev, labels):
            break
        prev = labels
    if merged:
        raise MetrologyError("the levels did not settle (their starts kept merging)")
    cov_c = _correlated_covariance(xyz, labels, n, offsets)
    if noise is not None:
        # the noise model's figure with the matches' correlation, in place of the
        # independent points' (the same fit, the same residuals)
        cov = _noise_covariance(cloud, noise, labels, n, offsets)
    order = np.argsort(offsets)
    offsets = offsets[order]
    K = len(offsets)
    cov_d = cov[2:, 2:][np.ix_(order, order)]
    cov_dc = cov_c[2:, 2:][np.ix_(order, order)]
    relabel = np.full(K + 1, -1, dtype=np.int64)
    relabel[order] = np.arange(K)
    labels = np.where(labels >= 0, relabel[labels], -1)
    heights = offsets - offsets[0]

    def var_diff(c, a, b):
        return max(c[a, a] + c[b, b] - 2 * c[a, b], 0.0)

    # the larger of the noise model's (white, or the stereo noise) and the
    # correlated-residual figures
    sig_h = np.sqrt([max(var_diff(cov_d, k, 0), var_diff(cov_dc, k, 0)) for k in range(K)])
    steps = np.diff(offsets)
    sig_s = np.sqrt([max(var_diff(cov_d, k + 1, k), var_diff(cov_dc, k + 1, k))
                     for k in range(K - 1)])
    rms = np.array([float(np.sqrt(np.mean(res[k] ** 2))) for k in order])
    npts = np.array([pts_list[k].shape[0] for k in order], dtype=np.int64)
    cents = np.array([pts_list[k].mean(axis=0) for k in order])
    return StepMeasurement(n, offsets, heights, sig_h, steps, sig_s, rms, npts, cents, labels,
                           edge_px=float(margin), correlated=noise is not None)
