"""The projector's view of each circle centre: the decoded projector coordinates over a
marker's surround, fitted and read at the circle's centre (the bridge from decoding to
calibration)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from telefringe.targets.circle_grid import GridDetection

__all__ = ["ProjectorObservations", "projector_observations"]


# --------------------------------------------------------------------------- projector
@dataclass(frozen=True, eq=False)
class ProjectorObservations:
    """The projector's coordinates of each circle centre.

    Attributes
    ----------
    uv : (n, 2) ndarray, projector px (u_p, v_p) at each centre; NaN where the light
        surround had too few valid pixels or the centre itself was NaN.
    sigma : (n, 2) ndarray, projector px, standard deviation of each value from the
        fit's residuals.
    n_pixels : (n,) ndarray of int, surround pixels used.
    """

    uv: np.ndarray
    sigma: np.ndarray
    n_pixels: np.ndarray


def _surround_fit_py(u_p, v_p, valid, cu, cv, R, exps, reject, min_pixels):
    """Robust polynomial fit of u_p, v_p over the valid pixels of a disc of radius ``R``
    around (cu, cv); returns (u, v, sigma_u, sigma_v, n_used) with n_used = 0 on failure.
    Plain code, compiled by numba when available (:func:`_surround_kernel`)."""
    H, W = u_p.shape
    ri = int(np.ceil(R)) + 1
    ic, jc = int(np.floor(cv + 0.5)), int(np.floor(cu + 0.5))
    nmax = (2 * ri + 1) * (2 * ri + 1)
    t = exps.shape[0]
    A = np.empty((nmax, t))
    Y = np.empty((nmax, 2))
    m = 0
    quads = np.zeros(4)
    xp = np.ones(4)
    yp = np.ones(4)
    for i in range(max(ic - ri, 0), min(ic + ri + 1, H)):
        dy = (i - cv) / R
        for j in range(max(jc - ri, 0), min(jc + ri + 1, W)):
            if not valid[i, j]:
                continue
            dx = (j - cu) / R
            if dx * dx + dy * dy > 1.0:
                continue
            for q in range(1, 4):
                xp[q] = xp[q - 1] * dx
                yp[q] = yp[q - 1] * dy
            for q in range(t):
                A[m, q] = xp[exps[q, 0]] * yp[exps[q, 1]]
            Y[m, 0] = u_p[i, j]
            Y[m, 1] = v_p[i, j]
            quads[(1 if dx >= 0 else 0) * 2 + (1 if dy >= 0 else 0)] += 1
            m += 1
    out = np.zeros(5)
    if m < min_pixels or quads.min() < 0.05 * m:
        return out
    keep = np.ones(m, dtype=np.bool_)
    coef = np.zeros((t, 2))
    Ninv = np.zeros((t, t))
    res = np.zeros((m, 2))
    for _ in range(5):
        N = np.zeros((t, t))
        b = np.zeros((t, 2))
        for r in range(m):
            if keep[r]:
                for p in range(t):
                    b[p, 0] += A[r, p] * Y[r, 0]
                    b[p, 1] += A[r, p] * Y[r, 1]
                    for q in range(p, t):
                        N[p, q] += A[r, p] * A[r, q]
        for p in range(t):
            for q in range(p):
                N[p, q] = N[q, p]
        if np.linalg.matrix_rank(N) < t:
            return out
        Ninv = np.linalg.inv(N)
        coef = Ninv @ b
        nk = 0
        for r in range(m):
            for a in range(2):
                acc = Y[r, a]
                for p in range(t):
                    acc -= A[r, p] * coef[p, a]
                res[r, a] = acc
        # robust scale: median absolute residual of (a regular subsample of) the kept
        # pixels; 2000 values give it to about 3 %, plenty for a 5-sigma cut
        stride = max(1, m // 2000)
        absu = np.empty(m // stride + 1)
        absv = np.empty(m // stride + 1)
        for r in range(0, m, stride):
            if keep[r]:
                absu[nk] = abs(res[r, 0])
                absv[nk] = abs(res[r, 1])
                nk += 1
        if nk < 10:
            return out
        su = max(1.4826 * np.median(absu[:nk]), 1e-9)
        sv = max(1.4826 * np.median(absv[:nk]), 1e-9)
        changed = False
        for r in range(m):
            new = abs(res[r, 0]) <= reject * su and abs(res[r, 1]) <= reject * sv
            if new != keep[r]:
                changed = True
            keep[r] = new
        if not changed:
            break
    nk = 0
    ssu = 0.0
    ssv = 0.0
    for r in range(m):
        if keep[r]:
            nk += 1
            ssu += res[r, 0] ** 2
            ssv += res[r, 1] ** 2
    if nk < min_pixels:
        return out
    dof = max(nk - t, 1)
    out[0] = coef[0, 0]
    out[1] = coef[0, 1]
    out[2] = np.sqrt(ssu / dof * Ninv[0, 0])
    out[3] = np.sqrt(ssv / dof * Ninv[0, 0])
    out[4] = nk
    return out


_SURROUND = None


def _surround_kernel():
    global _SURROUND
    if _SURROUND is None:
        try:
            import numba

            _SURROUND = numba.njit(cache=True, fastmath=False)(_surround_fit_py)
        except ImportError:  # pragma: no cover - numba is a dependency
            _SURROUND = _surround_fit_py
    return _SURROUND


def projector_observations(u_p, v_p, mask, centers, *, ellipses=None,
                           marker_radius_px: float | None = None, window_px=None,
                           exclude_scale: float = 1.3, exclude_margin_px: float = 3.0,
                           degree: int = 2, min_pixels: int = 50,
                           reject_sigmas: float = 5.0) -> ProjectorObservations:
    """Projector coordinates (u_p, v_p) at each circle centre, read from the light
    surround of the marker.

    The dark marker has little modulation, and camera blur mixes its edge into the
    phase, so the phase is not read there: a polynomial of ``degree`` in (u, v) is fitted
    to u_p and to v_p over the valid pixels of a disc around the centre, minus every
    marker scaled by ``exclude_scale`` and grown by ``exclude_margin_px``, and evaluated at
    the centre. Pixels off the fit by more than ``reject_sigmas`` robust standard
    deviations (a wrong fringe order, a speck) are dropped and the fit repeated.

    Parameters
    ----------
    u_p, v_p : (H, W) array_like of float, projector px per camera pixel (NaN invalid).
    mask : (H, W) array_like of bool, valid pixels.
    centers : GridDetection or (n, 2) array_like, camera px (NaN = skip).
    ellipses : (n, 5) array_like, (u_c, v_c, a, b, theta) of each marker; taken from a
        GridDetection; else circles of ``marker_radius_px``.
    window_px : float, px, radius of the disc; default 0.9 of the shorter grid step
        (from a GridDetection) or 3.5 marker radii.
    degree : int, 1..3.
    min_pixels : int, fewest surround pixels for a value.

    Returns
    -------
    ProjectorObservations

    Raises
    ------
    ValueError
        Inconsistent shapes, or no way to know the marker size.
    """
    import cv2

    u_p = np.asarray(u_p, dtype=float)
    v_p = np.asarray(v_p, dtype=float)
    mask = np.asarray(mask, dtype=bool)
    if u_p.shape != v_p.shape or u_p.shape != mask.shape or u_p.ndim != 2:
        raise ValueError("u_p, v_p and mask must be 2-D arrays of the same shape")
    if not 1 <= int(degree) <= 3:
        raise ValueError(f"degree must be 1, 2 or 3, got {degree!r}")
    lattice = None
    if isinstance(centers, GridDetection):
        det = centers
        pts = np.where(det.found[:, None], det.centers, np.nan)
        if ellipses is None:
            ellipses = det.ellipses
        lattice = det.lattice
    else:
        pts = np.asarray(centers, dtype=float).reshape(-1, 2)
    n = pts.shape[0]
    if ellipses is None:
        if marker_radius_px is None or not marker_radius_px > 0:
            raise ValueError("give ellipses, a GridDetection or marker_radius_px")
        r = float(marker_radius_px)
        ellipses = np.column_stack([pts, np.full(n, r), np.full(n, r), np.zeros(n)])
    ellipses = np.asarray(ellipses, dtype=float).reshape(n, 5)
    if window_px is None:
        if lattice is not None and np.all(np.isfinite(lattice)):
            window_px = 0.9 * float(min(np.hypot(*lattice[:, 0]), np.hypot(*lattice[:, 1])))
        else:
            window_px = 3.5 * float(np.nanmedian(ellipses[:, 2]))
    R = float(window_px)
    H, W = u_p.shape
    # exclusion mask: every known marker, scaled and grown
    excl = np.zeros((H, W), dtype=np.uint8)
    shift = 4
    for e in ellipses:
        if not np.all(np.isfinite(e)):
            continue
        ax = (int(round((e[2] * exclude_scale + exclude_margin_px) * 2**shift)),
              int(round((e[3] * exclude_scale + exclude_margin_px) * 2**shift)))
        cv2.ellipse(excl, (int(round(e[0] * 2**shift)), int(round(e[1] * 2**shift))), ax,
                    float(np.degrees(e[4])), 0.0, 360.0, 1, thickness=-1, lineType=cv2.LINE_8,
                    shift=shift)
    valid = mask & (excl == 0) & np.isfinite(u_p) & np.isfinite(v_p)
    out = np.full((n, 2), np.nan)
    sig = np.full((n, 2), np.nan)
    npx = np.zeros(n, dtype=int)
    exps = np.array([(i, j) for i in range(degree + 1) for j in range(degree + 1 - i)],
                    dtype=np.int64)
    fit = _surround_kernel()
    up = np.ascontiguousarray(u_p, dtype=np.float64)
    vp = np.ascontiguousarray(v_p, dtype=np.float64)
    va = np.ascontiguousarray(valid)
    for k in range(n):
        c = pts[k]
        if not np.all(np.isfinite(c)):
            continue
        res = fit(up, vp, va, float(c[0]), float(c[1]), R, exps, float(reject_sigmas),
                  int(min_pixels))
        if res[4] <= 0:
            continue
        out[k] = res[0], res[1]
        sig[k] = res[2], res[3]
        npx[k] = int(res[4])
    return ProjectorObservations(out, sig, npx)
