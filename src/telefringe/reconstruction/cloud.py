"""The organised point cloud that triangulation makes: one point per camera pixel, with
its viewing ray, its uncertainty along that ray and why it is invalid where it is."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
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
    if a is not None:
        a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class PointCloud:
    """An organised point cloud: one point per camera pixel.

    Attributes
    ----------
    xyz : (rows, cols, 3) ndarray of float64
        World coordinates in mm; NaN where ``mask`` is false.
    mask : (rows, cols) ndarray of bool
        True for valid points.
    sigma_line : (rows, cols) ndarray of float64
        Standard uncertainty (mm) of the point along its camera line, from the decoder's
        ``sigma_u_p`` (and ``sigma_v_p``); NaN where invalid or where the decoder gave no
        uncertainty. The covariance of a point is ``sigma_line**2 * outer(direction,
        direction)``: the errors of X, Y and Z are fully correlated (see ``sigma_xyz``,
        ``sigma_z``).
    residual : (rows, cols) ndarray of float64 or None
        Distance (projector px) between the observed and the predicted projector pixel
        when both fringe axes were used; None with u fringes only.
    flags : (rows, cols) ndarray of uint8
        Why a point is invalid (bit set of ``FLAG_*``; 0 for valid points).
    direction : (3,) ndarray of float64
        The camera's unit viewing direction in the world frame.
    """

    xyz: np.ndarray
    mask: np.ndarray
    sigma_line: np.ndarray
    residual: np.ndarray | None
    flags: np.ndarray
    direction: np.ndarray

    def __post_init__(self):
        for name in ("xyz", "mask", "sigma_line", "residual", "flags", "direction"):
            _readonly(getattr(self, name))

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
    def sigma_xyz(self) -> np.ndarray:
        """(rows, cols, 3) standard uncertainties of X, Y, Z (mm), NaN where invalid."""
        return self.sigma_line[..., None] * np.abs(self.direction)

    @property
    def sigma_x(self) -> np.ndarray:
        """(rows, cols) standard uncertainty of X (mm)."""
        return self.sigma_line * abs(self.direction[0])

    @property
    def sigma_y(self) -> np.ndarray:
        """(rows, cols) standard uncertainty of Y (mm)."""
        return self.sigma_line * abs(self.direction[1])

    @property
    def sigma_z(self) -> np.ndarray:
        """(rows, cols) standard uncertainty of Z (mm)."""
        return self.sigma_line * abs(self.direction[2])

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

        ``sigma_z`` (rows, cols), if given, is taken as the uncertainty along a camera
        line of unit ``direction`` (default: straight down, -z).
        """
        xyz = np.array(xyz, dtype=np.float64)
        if xyz.ndim != 3 or xyz.shape[2] != 3:
            raise TriangulationError(f"xyz must have shape (rows, cols, 3), got {xyz.shape}")
        d = np.asarray(direction, dtype=np.float64).reshape(3)
        nd = float(np.linalg.norm(d))
        if not np.isfinite(nd) or nd == 0 or abs(d[2]) < 1e-12 * nd:
            raise TriangulationError("direction must be a finite vector with a z component")
        d = d / nd
        mask = np.all(np.isfinite(xyz), axis=2)
        xyz[~mask] = np.nan
        if sigma_z is None:
            sigma_line = np.full(mask.shape, np.nan)
        else:
            sz = np.asarray(sigma_z, dtype=np.float64)
            if sz.shape != mask.shape:
                raise TriangulationError(f"sigma_z must have shape {mask.shape}, got {sz.shape}")
            sigma_line = np.where(mask, sz / abs(d[2]), np.nan)
        flags = np.where(mask, 0, FLAG_NO_PHASE).astype(np.uint8)
        return cls(xyz, mask, sigma_line, None, flags, d)


