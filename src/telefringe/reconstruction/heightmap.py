"""Height maps: an organised cloud resampled on a regular XY grid."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from telefringe.reconstruction.cloud import PointCloud, TriangulationError, _readonly

__all__ = ["HeightMap", "height_map"]


@dataclass(frozen=True, eq=False)
class HeightMap:
    """Heights on a regular XY grid (north-up, like the camera image of the world frame).

    Attributes
    ----------
    z : (H, W) ndarray of float32
        Height (world z, mm) at ``x = x0 + j * pixel_mm``, ``y = y0 - i * pixel_mm`` for
        row i and column j; NaN where there is no data.
    x0, y0 : float
        World x and y (mm) of the centre of pixel [0, 0] (the top-left one).
    pixel_mm : float
        Grid spacing (mm), the same along x and y.
    sigma_z : (H, W) ndarray of float32 or None
        Standard uncertainty of ``z`` (mm), interpolated like ``z``.

    ``z`` and ``sigma_z`` are read-only copies of the arrays given.
    """

    z: np.ndarray
    x0: float
    y0: float
    pixel_mm: float
    sigma_z: np.ndarray | None = None

    def __post_init__(self):
        # read-only copies: the caller's arrays are never changed (nor made read-only)
        z = np.array(self.z)
        if z.ndim != 2:
            raise TriangulationError(f"HeightMap.z must be a (H, W) array, got {z.shape}")
        object.__setattr__(self, "z", _readonly(z))
        if self.sigma_z is not None:
            s = np.array(self.sigma_z)
            if s.shape != z.shape:
                raise TriangulationError(f"HeightMap.sigma_z has shape {s.shape}, z {z.shape}")
            object.__setattr__(self, "sigma_z", _readonly(s))

    @property
    def x(self) -> np.ndarray:
        """World x (mm) of each column, (W,)."""
        return self.x0 + self.pixel_mm * np.arange(self.z.shape[1])

    @property
    def y(self) -> np.ndarray:
        """World y (mm) of each row, (H,) (decreasing)."""
        return self.y0 - self.pixel_mm * np.arange(self.z.shape[0])

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(left, right, bottom, top) in mm of the pixels' outer edges (for imshow)."""
        h, w = self.z.shape
        p = self.pixel_mm
        return (self.x0 - p / 2, self.x0 + (w - 0.5) * p, self.y0 - (h - 0.5) * p,
                self.y0 + p / 2)

    def binned(self, factor: int) -> HeightMap:
        """The map on a grid ``factor`` times coarser: each pixel the mean of the valid
        pixels of its ``factor x factor`` block (NaN where none is), e.g. for a preview.

        The block [0, 0] starts at this map's pixel [0, 0]; the edges' partial blocks
        average what they hold. ``sigma_z`` is averaged likewise (an upper bound on the
        uncertainty of the mean, whose errors are correlated along the camera lines).
        """
        f = int(factor)
        if f < 1:
            raise TriangulationError(f"factor must be a positive integer, got {factor!r}")
        if f == 1:
            return self
        p = self.pixel_mm
        return HeightMap(_block_mean(self.z, f), self.x0 + (f - 1) / 2 * p,
                         self.y0 - (f - 1) / 2 * p, f * p,
                         None if self.sigma_z is None else _block_mean(self.sigma_z, f))


def _block_mean(z, f):
    h, w = z.shape
    hp, wp = -(-h // f) * f, -(-w // f) * f
    zp = np.full((hp, wp), np.nan)
    zp[:h, :w] = z
    blocks = zp.reshape(hp // f, f, wp // f, f)
    fin = np.isfinite(blocks)
    n = fin.sum(axis=(1, 3))
    total = np.where(fin, blocks, 0.0).sum(axis=(1, 3))
    return np.where(n > 0, total / np.maximum(n, 1), np.nan).astype(np.float32)


def height_map(cloud: PointCloud, *, pixel_mm: float | None = None,
               max_pixels: int = 64_000_000) -> HeightMap:
    """Resample an organised cloud on a regular XY grid.

    Each 2 x 2 block of neighbouring camera pixels with four valid points is split into
    two triangles; grid nodes inside a triangle's XY footprint get the linear
    (barycentric) interpolation of its vertices' z (and sigma_z). Where triangles overlap
    in XY (a surface seen from the side), the highest z wins, as seen from above. No
    value is made up across invalid pixels.

    Parameters
    ----------
    cloud : PointCloud
    pixel_mm : float, optional
        Grid spacing in mm. Default: the median spacing of neighbouring points along the
        camera rows (the camera's footprint per pixel).
    max_pixels : int
        Refuse grids larger than this (a guard against a wrong ``pixel_mm``).

    Returns
    -------
    HeightMap
    """
    xyz = cloud.xyz
    mask = cloud.mask
    if cloud.count < 3:
        raise TriangulationError("the cloud has fewer than 3 valid points: no height map")
    if pixel_mm is None:
        # median spacing along the rows (from up to ~200 rows: a robust, cheap estimate)
        sub = xyz[::max(1, xyz.shape[0] // 200), :, :2]
        dx = np.linalg.norm(np.diff(sub, axis=1), axis=2)
        dx = dx[np.isfinite(dx)]
        if dx.size == 0:
            dx = np.linalg.norm(np.diff(xyz[:, :, :2], axis=0), axis=2)
            dx = dx[np.isfinite(dx)]
        if dx.size == 0:
            raise TriangulationError("no two neighbouring valid points: give pixel_mm")
        pixel_mm = float(np.median(dx))
    pixel_mm = float(pixel_mm)
    if not (np.isfinite(pixel_mm) and pixel_mm > 0):
        raise TriangulationError(f"pixel_mm must be finite and > 0, got {pixel_mm!r}")
    xmin, xmax, ymin, ymax = _xy_bounds(xyz, mask)
    x0 = np.floor(xmin / pixel_mm) * pixel_mm
    y0 = np.ceil(ymax / pixel_mm) * pixel_mm
    W = int(np.ceil((xmax - x0) / pixel_mm)) + 1
    H = int(np.ceil((y0 - ymin) / pixel_mm)) + 1
    if W * H > max_pixels:
        raise TriangulationError(
            f"a height map of {H} x {W} pixels at {pixel_mm} mm is too large")
    sz = cloud.sigma_z
    zmap = np.full((H, W), -np.inf)
    smap = np.full((H, W), np.nan)
    _raster_kernel(xyz, np.ascontiguousarray(sz), float(x0), float(y0), pixel_mm, zmap, smap)
    zmap[~np.isfinite(zmap)] = np.nan
    has_sigma = bool(np.any(np.isfinite(sz)))
    return HeightMap(zmap.astype(np.float32), float(x0), float(y0), pixel_mm,
                     smap.astype(np.float32) if has_sigma else None)


@njit(cache=True, nogil=True)
def _xy_bounds(xyz, mask):  # pragma: no cover - numba
    xmin = np.inf
    xmax = -np.inf
    ymin = np.inf
    ymax = -np.inf
    for r in range(mask.shape[0]):
        for c in range(mask.shape[1]):
            if mask[r, c]:
                x = xyz[r, c, 0]
                y = xyz[r, c, 1]
                xmin = min(xmin, x)
                xmax = max(xmax, x)
                ymin = min(ymin, y)
                ymax = max(ymax, y)
    return xmin, xmax, ymin, ymax


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _raster_tri(ja, ia, za, sa, jb, ib, zb, sb, jc, ic, zc, sc, zmap,
                smap):  # pragma: no cover - numba
    # vertices in grid coordinates (column j, row i); fill the nodes inside
    det = (jb - ja) * (ic - ia) - (jc - ja) * (ib - ia)
    if det == 0.0:
        return
    H, W = zmap.shape
    jlo = max(int(np.ceil(min(ja, jb, jc))), 0)
    jhi = min(int(np.floor(max(ja, jb, jc))), W - 1)
    ilo = max(int(np.ceil(min(ia, ib, ic))), 0)
    ihi = min(int(np.floor(max(ia, ib, ic))), H - 1)
    inv = 1.0 / det
    eps = -1e-12
    for i in range(ilo, ihi + 1):
        for j in range(jlo, jhi + 1):
            # barycentric coordinates of node (i, j)
            l1 = ((j - ja) * (ic - ia) - (jc - ja) * (i - ia)) * inv
            l2 = ((jb - ja) * (i - ia) - (j - ja) * (ib - ia)) * inv
            l0 = 1.0 - l1 - l2
            if l0 < eps or l1 < eps or l2 < eps:
                continue
            z = l0 * za + l1 * zb + l2 * zc
            if z > zmap[i, j]:
                zmap[i, j] = z
                smap[i, j] = l0 * sa + l1 * sb + l2 * sc


@njit(cache=True, nogil=True, error_model="numpy")
def _raster_kernel(xyz, sz, x0, y0, p, zmap, smap):  # pragma: no cover - numba
    rows, cols = xyz.shape[0], xyz.shape[1]
    ip = 1.0 / p
    # grid coordinates of one camera row, reused by the next row's quads
    j0 = np.empty(cols)
    i0 = np.empty(cols)
    j1 = np.empty(cols)
    i1 = np.empty(cols)
    for c in range(cols):
        j1[c] = (xyz[0, c, 0] - x0) * ip
        i1[c] = (y0 - xyz[0, c, 1]) * ip
    for r in range(rows - 1):
        for c in range(cols):
            j0[c] = j1[c]
            i0[c] = i1[c]
            j1[c] = (xyz[r + 1, c, 0] - x0) * ip
            i1[c] = (y0 - xyz[r + 1, c, 1]) * ip
        for c in range(cols - 1):
            z00 = xyz[r, c, 2]
            z01 = xyz[r, c + 1, 2]
            z10 = xyz[r + 1, c, 2]
            z11 = xyz[r + 1, c + 1, 2]
            if not (np.isfinite(z00) and np.isfinite(z01) and np.isfinite(z10)
                    and np.isfinite(z11)):
                continue
            _raster_tri(j0[c], i0[c], z00, sz[r, c], j0[c + 1], i0[c + 1], z01,
                        sz[r, c + 1], j1[c + 1], i1[c + 1], z11, sz[r + 1, c + 1], zmap, smap)
            _raster_tri(j0[c], i0[c], z00, sz[r, c], j1[c + 1], i1[c + 1], z11,
                        sz[r + 1, c + 1], j1[c], i1[c], z10, sz[r + 1, c], zmap, smap)
