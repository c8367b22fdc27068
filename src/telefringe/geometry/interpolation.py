"""Bilinear interpolation of an image-like map with its gradient (for decoded projector
coordinates sampled at sub-pixel positions)."""

from __future__ import annotations

import numpy as np

__all__ = ["bilinear"]


def bilinear(M, u, v):
    """Value, gradient and cell of the bilinear interpolation of ``M`` at (u, v).

    Parameters
    ----------
    M : (rows, cols) ndarray, any units; NaN marks invalid samples.
    u, v : ndarray (any shape, the same), column and row positions, px.

    Returns
    -------
    value, d_du, d_dv : ndarrays shaped like ``u`` (units of M, per px for the gradient);
        NaN outside the map or where a corner of the cell is NaN.
    corners : (i, j, fx, fy), the cell's top-left row and column and the fractions within
        it (for the variance of the interpolation).

    >>> M = np.array([[0.0, 1.0], [2.0, 3.0]])
    >>> [float(x) for x in bilinear(M, np.array(0.5), np.array(0.25))[:3]]
    [1.0, 1.0, 2.0]
    """
    rows, cols = M.shape
    with np.errstate(invalid="ignore"):
        inside = (u >= 0) & (u <= cols - 1) & (v >= 0) & (v <= rows - 1)
    uu = np.where(inside, u, 0.0)
    vv = np.where(inside, v, 0.0)
    j = np.minimum(np.floor(uu).astype(np.intp), cols - 2)
    i = np.minimum(np.floor(vv).astype(np.intp), rows - 2)
    fx = uu - j
    fy = vv - i
    m00 = M[i, j]
    m01 = M[i, j + 1]
    m10 = M[i + 1, j]
    m11 = M[i + 1, j + 1]
    val = (1 - fy) * ((1 - fx) * m00 + fx * m01) + fy * ((1 - fx) * m10 + fx * m11)
    gu = (1 - fy) * (m01 - m00) + fy * (m11 - m10)
    gv = (1 - fx) * (m10 - m00) + fx * (m11 - m01)
    val = np.where(inside, val, np.nan)
    gu = np.where(inside, gu, np.nan)
    gv = np.where(inside, gv, np.nan)
    return val, gu, gv, (i, j, fx, fy)
