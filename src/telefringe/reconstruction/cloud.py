"""The organised point cloud that triangulation makes: one point per camera pixel, with
its viewing ray, its uncertainty along that ray and why it is invalid where it is."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from telefringe.geometry.rays import Rays

__all__ = [
    "projector_axes",
    "TriangulationError",
    "PointCloud",
    "FLAG_NO_PHASE",
    "FLAG_INCONSISTENT",
    "FLAG_OUTSIDE",
    "FLAG_NOT_CONVERGED",
    "FLAG_UNCERTAIN",
]

#: ``PointCloud.flags`` bits (0 = valid point).
FLAG_NO_PHASE = 1  #: the decoder's mask is false, or u_P (or a needed v_P) is not finite
FLAG_INCONSISTENT = 2  #: |observed - predicted| projector pixel above ``max_residual``
FLAG_OUTSIDE = 4  #: the solution falls outside the projector's image
FLAG_NOT_CONVERGED = 8  #: the per-pixel solve did not converge
FLAG_UNCERTAIN = 16  #: sigma_z above ``max_sigma_z``


class TriangulationError(ValueError):
    """The rig or the coordinates cannot be triangulated (degenerate geometry, shapes)."""


def _readonly(a):
    """``a`` made read-only (None stays None): for arrays this package has just made."""
    if a is not None:
        a.setflags(write=False)
    return a


def _frozen_copy(a, name, dtype, shape):
    """A read-only copy of ``a`` (the caller's array is never changed), of ``shape``."""
    arr = np.array(a, dtype=dtype)  # np.array copies
    if arr.shape != tuple(shape):
        raise TriangulationError(f"PointCloud.{name} must have shape {tuple(shape)}, "
                                 f"got {arr.shape}")
    arr.setflags(write=False)
    return arr


def _unit_directions(d, shape):
    """Viewing directions (3,) or shape + (3,), normalised; NaN allowed per pixel."""
    d = np.array(d, dtype=np.float64)
    if d.shape not in ((3,), tuple(shape) + (3,)):
        raise TriangulationError(
            f"PointCloud.directions must have shape (3,) (one for every pixel) or "
            f"{tuple(shape) + (3,)}, got {d.shape}")
    n = np.linalg.norm(d, axis=-1)
    fin = np.isfinite(n)
    if d.ndim == 1 and not fin:
        raise TriangulationError("PointCloud.directions must be finite")
    if np.any(np.abs(n[fin] - 1.0) > 1e-6):
        raise TriangulationError("PointCloud.directions must be unit vectors")
    # normalised where not unit to rounding already (unit vectors are kept bit for bit)
    with np.errstate(invalid="ignore"):
        d = np.where(np.abs(n - 1.0)[..., None] > 1e-15, d / n[..., None], d)
    d.setflags(write=False)
    return d


@dataclass(frozen=True, eq=False)
class PointCloud:
    """An organised point cloud: one point per camera pixel, with its viewing ray.

    Attributes
    ----------
    xyz : (rows, cols, 3) ndarray of float64
        World coordinates in mm; NaN where ``mask`` is false.
    mask : (rows, cols) ndarray of bool
        True for valid points.
    sigma_line : (rows, cols) ndarray of float64
        Standard uncertainty (mm) of the point along its camera line, from the decoder's
        ``sigma_u_p`` (and ``sigma_v_p``); NaN where invalid or where the decoder gave no
        uncertainty. The covariance of a point is ``sigma_line**2 * outer(d, d)`` with
        ``d`` its viewing direction: the errors of X, Y and Z are fully correlated (see
        ``sigma_xyz``, ``sigma_z``).
    residual : (rows, cols) ndarray of float64 or None
        Distance (projector px) between the observed and the predicted projector pixel
        when both fringe axes were used; None with u fringes only.
    flags : (rows, cols) ndarray of uint8
        Why a point is invalid (bit set of ``FLAG_*``; 0 for valid points).
    directions : (3,) or (rows, cols, 3) ndarray of float64
        Each pixel's unit viewing direction (world frame, from the camera into the scene),
        broadcast over the pixels: (3,) for a camera whose lines are all parallel (a
        telecentric one), (rows, cols, 3) otherwise (NaN allowed where a pixel has no
        line). The pixel's viewing ray is the line through its point along it
        (:attr:`rays`).

    All arrays are read-only copies of those given (the caller's arrays are never
    changed). Raises :class:`TriangulationError` for inconsistent shapes or directions
    that are not unit vectors (to 1e-6; they are stored normalised).
    """

    xyz: np.ndarray
    mask: np.ndarray
    sigma_line: np.ndarray
    residual: np.ndarray | None
    flags: np.ndarray
    directions: np.ndarray

    def __post_init__(self):
        xyz = np.array(self.xyz, dtype=np.float64)
        if xyz.ndim != 3 or xyz.shape[2] != 3:
            raise TriangulationError(f"PointCloud.xyz must have shape (rows, cols, 3), got "
                                     f"{xyz.shape}")
        xyz.setflags(write=False)
        shape = xyz.shape[:2]
        put = object.__setattr__
        put(self, "xyz", xyz)
        put(self, "mask", _frozen_copy(self.mask, "mask", bool, shape))
        put(self, "sigma_line", _frozen_copy(self.sigma_line, "sigma_line", np.float64, shape))
        if self.residual is not None:
            put(self, "residual", _frozen_copy(self.residual, "residual", np.float64, shape))
        put(self, "flags", _frozen_copy(self.flags, "flags", np.uint8, shape))
        put(self, "directions", _unit_directions(self.directions, shape))

    @classmethod
    def _adopt(cls, xyz, mask, sigma_line, residual, flags, directions) -> PointCloud:
        """A cloud of arrays the caller has just made for it and gives up: no copy and no
        checks (the triangulators' fast exit); the arrays are made read-only."""
        obj = object.__new__(cls)
        values = (xyz, mask, sigma_line, residual, flags, directions)
        for f, val in zip(fields(cls), values, strict=True):
            object.__setattr__(obj, f.name, _readonly(val))
        return obj

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of the camera grid."""
        return self.mask.shape

    @property
    def x(self) -> np.ndarray:
        return self.xyz[..., 0]

    @property
    def y(self) -> np.ndarray:
        return self.xyz[..., 1]

    @property
    def z(self) -> np.ndarray:
        return self.xyz[..., 2]

    @property
    def direction(self) -> np.ndarray:
        """The viewing direction (3,) common to every pixel (a telecentric camera).

        Raises :class:`TriangulationError` when the pixels' directions differ (by more than
        1e-12): code that must work for every camera uses :attr:`directions` or
        :attr:`rays`.
        """
        d = self.directions
        if d.ndim == 1:
            return d
        flat = d.reshape(-1, 3)
        fin = flat[np.all(np.isfinite(flat), axis=1)]
        if fin.shape[0] == 0:
            raise TriangulationError("the cloud has no finite viewing direction")
        if np.max(np.abs(fin - fin[0])) > 1e-12:
            raise TriangulationError(
                "the cloud's viewing directions differ from pixel to pixel (a perspective "
                "camera): there is no common direction; use cloud.directions or cloud.rays")
        out = fin[0].copy()
        out.setflags(write=False)
        return out

    @property
    def rays(self) -> Rays:
        """Each pixel's viewing ray, shape (rows, cols): the line through its point
        (``origin`` = ``xyz``, NaN where invalid) along its viewing direction."""
        return Rays(self.xyz, self.directions)

    @property
    def sigma_xyz(self) -> np.ndarray:
        """(rows, cols, 3) standard uncertainties of X, Y, Z (mm), NaN where invalid."""
        return self.sigma_line[..., None] * np.abs(self.directions)

    @property
    def sigma_x(self) -> np.ndarray:
        """(rows, cols) standard uncertainty of X (mm)."""
        return self.sigma_line * np.abs(self.directions[..., 0])

    @property
    def sigma_y(self) -> np.ndarray:
        """(rows, cols) standard uncertainty of Y (mm)."""
        return self.sigma_line * np.abs(self.directions[..., 1])

    @property
    def sigma_z(self) -> np.ndarray:
        """(rows, cols) standard uncertainty of Z (mm)."""
        return self.sigma_line * np.abs(self.directions[..., 2])

    @property
    def count(self) -> int:
        """Number of valid points."""
        return int(np.count_nonzero(self.mask))

    def points(self) -> np.ndarray:
        """The valid points as an (n, 3) float64 array (mm), row-major pixel order."""
        return self.xyz[self.mask]

    @classmethod
    def from_xyz(cls, xyz, *, sigma_z=None, direction=(0.0, 0.0, -1.0)) -> PointCloud:
        """A cloud from an (rows, cols, 3) array (NaN = invalid), e.g. read from points.npz.

        ``sigma_z`` (rows, cols), if given, is taken as the uncertainty along each pixel's
        camera line of ``direction``: (3,) for all pixels (default: straight down, -z) or
        (rows, cols, 3) per pixel; normalised here, and it must have a z component.
        ``xyz`` is copied.
        """
        xyz = np.array(xyz, dtype=np.float64)
        if xyz.ndim != 3 or xyz.shape[2] != 3:
            raise TriangulationError(f"xyz must have shape (rows, cols, 3), got {xyz.shape}")
        d = np.asarray(direction, dtype=np.float64)
        if d.shape != (3,) and d.shape != xyz.shape:
            raise TriangulationError(f"direction must have shape (3,) or {xyz.shape}, got "
                                     f"{d.shape}")
        nd = np.linalg.norm(d, axis=-1)
        if (not np.all(np.isfinite(nd)) or np.any(nd == 0)
                or np.any(np.abs(d[..., 2]) < 1e-12 * nd)):
            raise TriangulationError("direction must be a finite vector with a z component")
        d = d / nd[..., None] if d.ndim > 1 else d / nd
        mask = np.all(np.isfinite(xyz), axis=2)
        xyz[~mask] = np.nan
        if sigma_z is None:
            sigma_line = np.full(mask.shape, np.nan)
        else:
            sz = np.asarray(sigma_z, dtype=np.float64)
            if sz.shape != mask.shape:
                raise TriangulationError(f"sigma_z must have shape {mask.shape}, got {sz.shape}")
            sigma_line = np.where(mask, sz / np.abs(d[..., 2]), np.nan)
        flags = np.where(mask, 0, FLAG_NO_PHASE).astype(np.uint8)
        return cls._adopt(xyz, mask, sigma_line, None, flags, d)


@dataclass(frozen=True)
class PixelCoords:
    """Projector coordinates of a list of camera pixels, as one (1, n) row (what the
    triangulators' ``triangulate`` reads like a decoded scan's coordinates)."""

    u_p: np.ndarray | None
    v_p: np.ndarray | None
    mask: np.ndarray | None
    sigma_u_p: np.ndarray | None
    sigma_v_p: np.ndarray | None


def pixel_rows(u_c, v_c, u_p, v_p=None, sigma_u_p=None, sigma_v_p=None):
    """Camera pixels and their projector coordinates as (1, n) rows.

    Parameters
    ----------
    u_c, v_c : (n,) array_like of float, camera pixel (column, row), px.
    u_p, v_p, sigma_u_p, sigma_v_p : (n,) array_like of float or None, projector px.

    Returns
    -------
    u_c, v_c : (1, n) ndarray of float64
    coords : PixelCoords with (1, n) rows (None where not given).

    Raises
    ------
    TriangulationError
        When the arrays differ in length.
    """
    u_c = np.atleast_1d(np.asarray(u_c, dtype=np.float64)).reshape(1, -1)
    v_c = np.atleast_1d(np.asarray(v_c, dtype=np.float64)).reshape(1, -1)
    if u_c.shape != v_c.shape:
        raise TriangulationError("u_c and v_c must have the same length")

    def row(x):
        if x is None:
            return None
        x = np.atleast_1d(np.asarray(x, dtype=np.float64)).reshape(1, -1)
        if x.shape != u_c.shape:
            raise TriangulationError("all per-point arrays must have the same length")
        return x

    return u_c, v_c, PixelCoords(row(u_p), row(v_p), None, row(sigma_u_p), row(sigma_v_p))


def projector_axes(coords, shape):
    """The decoded coordinates a triangulator reads, checked against its camera ``shape``
    (rows, cols): ``(a, b, sigma_a, sigma_b, mask, swap)`` with ``a`` the primary axis
    (``u_p``; ``v_p`` when there are v fringes only, then ``swap`` is True and ``b`` None),
    ``b`` the other axis or None, their sigmas (or None) and ``coords.mask`` (or None), as
    given. Raises TriangulationError when there is no axis or a shape differs."""
    up = getattr(coords, "u_p", None)
    vp = getattr(coords, "v_p", None)
    su = getattr(coords, "sigma_u_p", None)
    sv = getattr(coords, "sigma_v_p", None)
    # v fringes only: the same solve with the projector's axes swapped
    swap = up is None
    if swap:
        if vp is None:
            raise TriangulationError("coords has neither u_p nor v_p")
        up, vp, su, sv = vp, None, sv, None
    up = np.asarray(up)
    shape = tuple(shape)
    if up.shape != shape:
        raise TriangulationError(
            f"the projector coordinates have shape {up.shape} but the triangulator was "
            f"built for {shape}")
    mask = getattr(coords, "mask", None)
    for name, arr in (("mask", mask), ("v_p", vp), ("sigma_u_p", su), ("sigma_v_p", sv)):
        if arr is not None and np.shape(arr) != shape:
            raise TriangulationError(
                f"{name} has shape {np.shape(arr)}, expected {shape} like u_p")
    return up, vp, su, sv, mask, swap
