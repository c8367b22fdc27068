"""Shared helpers of the metrology package: the error type, robust constants, points and
weights from a cloud or an array, the tangent basis of a plane, frozen copies of arrays."""

from __future__ import annotations

import numpy as np

_MAD = 1.482602218505602  # MAD -> standard deviation for Gaussian data
_TUKEY_C = 4.685  # Tukey biweight tuning constant (95 % efficiency at the Gaussian)


class MetrologyError(ValueError):
    """A measurement cannot be made from this input (too few points, degenerate shape)."""


def _points_and_weights(points, weights, *, sigma_weights: bool = False):
    """The points of a fit and their weights.

    ``points``: a PointCloud (its valid points) or an (n, 3) array (rows with a non-finite
    coordinate are left out). ``weights``: (n,) or None; None gives unit weights, or with
    ``sigma_weights`` and a cloud, ``1 / sigma_z**2`` per point: a point whose sigma is
    not finite and positive gets weight 0 (it does not take part), and only when no point
    has one are all weighted equally.

    Returns (p (n, 3) float64, w (n,) float64, finite (n,) bool: usable coordinates).
    Raises MetrologyError for a wrong shape.
    """
    from telefringe.reconstruction.cloud import PointCloud

    if isinstance(points, PointCloud):
        p = points.points()
        finite = np.ones(p.shape[0], dtype=bool)
        if weights is None and sigma_weights:
            s = points.sigma_z[points.mask]
            good = np.isfinite(s) & (s > 0)
            if good.any():
                weights = np.where(good, 1.0 / np.where(good, s, 1.0) ** 2, 0.0)
    else:
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise MetrologyError(f"points must have shape (n, 3), got {p.shape}")
        finite = np.all(np.isfinite(p), axis=1)
    n = p.shape[0]
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.shape != (n,):
        raise MetrologyError(f"weights must have {n} values, got {w.size}")
    return p, w, finite


def _freeze(obj, *names):
    """Replace the array fields ``names`` of the frozen dataclass ``obj`` by read-only
    copies: the caller's arrays are neither changed nor made read-only."""
    for name in names:
        a = getattr(obj, name)
        if isinstance(a, np.ndarray):
            a = a.copy()
            a.setflags(write=False)
            object.__setattr__(obj, name, a)


def _tangent_basis(n: np.ndarray) -> np.ndarray:
    """(2, 3) orthonormal basis of the plane normal to ``n``: e1 along world x's
    projection (or y's when n is near x), e2 = n x e1."""
    ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = ref - (ref @ n) * n
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    return np.stack([e1, e2])


def _poly_design(du: np.ndarray, dv: np.ndarray, degree: int) -> np.ndarray:
    cols = [np.ones_like(du)]
    for k in range(1, degree + 1):
        for j in range(k + 1):
            cols.append(du ** (k - j) * dv**j)
    return np.stack(cols, axis=1)


def _components(mask: np.ndarray):
    from scipy import ndimage

    labels, n = ndimage.label(mask, structure=np.ones((3, 3), dtype=bool))
    return labels, n
