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
    sigma_heights : (k,) mm, standard uncertainty of ``heights`` (0 for the lowest).
    step_heights : (k - 1,) mm, height of each level above the one below.
    sigma_steps : (k - 1,) mm.
    rms : (k,) mm, RMS residual of each level.   n_points : (k,) int.
    centroids : (k, 3) mm.
    labels : (rows, cols) int, level of each pixel (-1: unused).
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


def measure_steps(cloud: PointCloud, *, min_step: float = 0.05, min_points: int = 200,
                  edge_px: int = 2) -> StepMeasurement:
    """Heights of the flat levels of a step gauge (parallel planes fitted jointly).

    The median normal of the surface gives a first orientation; heights along it are
    histogrammed and
    every peak holding at least ``min_points`` points, ``min_step`` (mm) or more from a
    taller one, is a level. Pixels within ``min_step / 3`` of a level, with their region
    shrunk by ``edge_px`` pixels (edges mix levels), are fitted as parallel planes with
    one common normal (Gauss-Newton, twice with re-assignment, 4-sigma rejection).

    Returns
    -------
    StepMeasurement
    """
    from scipy import ndimage

    if not (np.isfinite(min_step) and min_step > 0):
        raise MetrologyError("min_step must be > 0")
    pts = cloud.points()
    if pts.shape[0] < 2 * min_points:
        raise MetrologyError(f"the cloud has {pts.shape[0]} valid points: too few for steps")
    n = _dominant_normal(cloud)
    labels = np.full(cloud.shape, -1, dtype=np.int64)
    xyz = cloud.xyz
    mask = cloud.mask
    for _ in range(2):
        h_img = np.where(mask, xyz @ n, np.nan)
        hv = h_img[mask]
        bin_mm = min_step / 10.0
        peaks = _level_peaks(hv, min_step=min_step, min_points=min_points, bin_mm=bin_mm)
        if len(peaks) < 2:
            raise MetrologyError(
                f"found {len(peaks)} level(s) of at least {min_points} points: no step")
        labels[:] = -1
        pts_list = []
        keep_peaks = []
        for pk in peaks:
            sel = mask & (np.abs(np.nan_to_num(h_img, nan=np.inf) - pk) < min_step / 3)
            if edge_px > 0:
                sel = ndimage.binary_erosion(sel, iterations=int(edge_px))
            if np.count_nonzero(sel) < min_points:
                continue
            p = xyz[sel]
            # refine the level robustly: 4-sigma rejection around its median height
            r = p @ n
            med = np.median(r)
            scale = _MAD * np.median(np.abs(r - med)) + 1e-12
            good = np.abs(r - med) <= 4.0 * scale
            sel_idx = np.argwhere(sel)[good]
            labels[sel_idx[:, 0], sel_idx[:, 1]] = len(pts_list)
            pts_list.append(p[good])
            keep_peaks.append(pk)
        if len(pts_list) < 2:
            raise MetrologyError("fewer than 2 levels left after edge removal: no step")
        n, offsets, res, cov = _joint_parallel_planes(pts_list, n)
    order = np.argsort(offsets)
    offsets = offsets[order]
    K = len(offsets)
    cov_d = cov[2:, 2:][np.ix_(order, order)]
    relabel = np.full(K + 1, -1, dtype=np.int64)
    relabel[order] = np.arange(K)
    labels = np.where(labels >= 0, relabel[labels], -1)
    heights = offsets - offsets[0]
    sig_h = np.array([np.sqrt(max(cov_d[k, k] + cov_d[0, 0] - 2 * cov_d[k, 0], 0.0))
                      for k in range(K)])
    steps = np.diff(offsets)
    sig_s = np.array([np.sqrt(max(cov_d[k + 1, k + 1] + cov_d[k, k] - 2 * cov_d[k + 1, k],
                                  0.0)) for k in range(K - 1)])
    rms = np.array([float(np.sqrt(np.mean(res[k] ** 2))) for k in order])
    npts = np.array([pts_list[k].shape[0] for k in order], dtype=np.int64)
    cents = np.array([pts_list[k].mean(axis=0) for k in order])
    return StepMeasurement(n, offsets, heights, sig_h, steps, sig_s, rms, npts, cents, labels)
