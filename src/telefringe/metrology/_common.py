"""Shared helpers of the metrology package: the error type, robust constants,
the tangent basis of a plane, frozen copies of arrays."""

from __future__ import annotations

import numpy as np

_MAD = 1.482602218505602  # MAD -> standard deviation for Gaussian data
_TUKEY_C = 4.685  # Tukey biweight tuning constant (95 % efficiency at the Gaussian)


class MetrologyError(ValueError):
    """A measurement cannot be made from this input (too few points, degenerate shape)."""


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
