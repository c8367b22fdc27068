"""The characteristics of VDI/VDE 2634 Part 2 at one position: probing errors PF and PS
on the test sphere, sphere-spacing error SD on the ball bar, flatness error F on the
plane. See docs/acceptance.md for where this follows the guideline and where it chose."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from telefringe.metrology._common import MetrologyError
from telefringe.metrology.acceptance.fits import (
    LSPlane,
    LSSphere,
    PointNoise,
    ls_plane,
    ls_sphere,
    trimmed,
)

__all__ = ["EXCLUDED_FRACTION", "SphereTest", "SpacingTest", "FlatnessTest", "cap_half_angle",
           "probing_errors", "sphere_spacing_error", "flatness_error"]

#: Share of the points with the largest deviations the guideline lets one exclude (0.3 %).
EXCLUDED_FRACTION = 0.003


def cap_half_angle(points, centre) -> float:
    """Half-angle (deg) of the cap of a sphere the points cover: the largest angle between
    a point's direction from ``centre`` and the mean of those directions (the cap's axis).

    A single view sees a cap (at most a hemisphere for a telecentric camera); the smaller
    it is, the less a free-radius fit pins the radius down (PS), which is why every
    sphere's cap is reported.

    Parameters
    ----------
    points : (n, 3) mm.   centre : (3,) mm.
    """
    v = np.asarray(points, dtype=np.float64) - np.asarray(centre, dtype=np.float64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    a = v.mean(axis=0)
    a /= np.linalg.norm(a)
    return float(np.degrees(np.arccos(np.clip(np.min(v @ a), -1.0, 1.0))))


@dataclass(frozen=True, eq=False)
class SphereTest:
    """The test sphere at one position.

    Attributes
    ----------
    PF : float, mm, range of the radial residuals of the kept points.
    PS : float, mm, measured minus calibrated diameter.
    fit : LSSphere of the kept points.   kept : (n,) bool, not excluded.
    n_points, n_excluded : int.
    cap_half_angle_deg : float, the cap the kept points cover (:func:`cap_half_angle`).
    u_fit_diameter : float, mm, standard uncertainty of the fitted diameter from the
        residuals' scatter (a repeatability; with the points' correlated noise when the
        fit was given it, ``fit.correlated``).
    """

    PF: float
    PS: float
    fit: LSSphere
    kept: np.ndarray
    n_points: int
    n_excluded: int
    cap_half_angle_deg: float
    u_fit_diameter: float

    @property
    def diameter(self) -> float:
        return self.fit.diameter


@dataclass(frozen=True, eq=False)
class SpacingTest:
    """The ball bar at one position.

    Attributes
    ----------
    SD : float, mm, measured minus calibrated centre distance.
    distance : float, mm, distance of the two fitted centres.
    spheres : (SphereTest, SphereTest), each sphere's fit (with its PF and PS against the
        bar's calibrated sphere diameters).
    u_fit_distance : float, mm, standard uncertainty of ``distance`` from the two fits.
    """

    SD: float
    distance: float
    spheres: tuple[SphereTest, SphereTest]
    u_fit_distance: float


@dataclass(frozen=True, eq=False)
class FlatnessTest:
    """The plane at one position.

    Attributes
    ----------
    F : float, mm, range of the signed distances of the kept points to their
        least-squares plane.
    fit : LSPlane of the kept points.   kept : (n,) bool.   n_points, n_excluded : int.
    residuals : (n,) mm, signed distance of every point (kept or not) to that plane.
    """

    F: float
    fit: LSPlane
    kept: np.ndarray
    n_points: int
    n_excluded: int
    residuals: np.ndarray


def probing_errors(points, calibrated_diameter: float, *,
                   exclude: float = EXCLUDED_FRACTION,
                   noise: PointNoise | None = None) -> SphereTest:
    """PF and PS of the test sphere at one position.

    Fits a least-squares sphere with free radius to all points, excludes the
    ``floor(exclude * n)`` points of largest |radial residual|, fits the rest again: PF is
    the range (max - min) of the kept points' radial residuals, PS the fitted diameter
    minus ``calibrated_diameter``.

    Parameters
    ----------
    points : (n, 3) mm, the points on the sphere (n >= 4, not coplanar).
    calibrated_diameter : float, mm.
    exclude : float, the share of points that may be excluded (default 0.3 %).
    noise : PointNoise of the n points, optional (a two-camera match's correlated noise):
        ``u_fit_diameter`` then holds it (:func:`~telefringe.metrology.acceptance.fits.
        ls_sphere`); the values are the same.

    Returns
    -------
    SphereTest
    """
    p = np.asarray(points, dtype=np.float64)
    if not (np.isfinite(calibrated_diameter) and calibrated_diameter > 0):
        raise MetrologyError(f"the calibrated diameter must be > 0, got {calibrated_diameter}")
    fit, kept = trimmed(p, ls_sphere, exclude, noise=noise)
    r = fit.residuals
    return SphereTest(PF=float(r.max() - r.min()), PS=float(fit.diameter - calibrated_diameter),
                      fit=fit, kept=kept, n_points=int(p.shape[0]),
                      n_excluded=int(p.shape[0] - kept.sum()),
                      cap_half_angle_deg=cap_half_angle(p[kept], fit.centre),
                      u_fit_diameter=float(2.0 * np.sqrt(fit.covariance[3, 3])))


def sphere_spacing_error(points_a, points_b, calibrated_distance: float,
                         calibrated_diameters=(None, None), *,
                         exclude: float = EXCLUDED_FRACTION,
                         noise: tuple | None = None) -> SpacingTest:
    """SD of the ball bar at one position: the distance of the centres of the two
    spheres' least-squares fits (free radius, the same exclusion as PF) minus
    ``calibrated_distance``.

    Parameters
    ----------
    points_a, points_b : (n, 3) mm, the points on each sphere.
    calibrated_distance : float, mm.
    calibrated_diameters : two floats or None, mm, for the spheres' own PS (reported
        only); None uses the fitted diameter (PS = 0).
    noise : (PointNoise, PointNoise) of the two point sets, optional (a two-camera
        match's correlated noise): ``u_fit_distance`` then holds it, the covariance of
        the two centres through the noise sources they share included.

    Returns
    -------
    SpacingTest
    """
    if not (np.isfinite(calibrated_distance) and calibrated_distance > 0):
        raise MetrologyError(f"the calibrated distance must be > 0, got {calibrated_distance}")
    noise = (None, None) if noise is None else tuple(noise)
    if len(noise) != 2:
        raise MetrologyError("noise must be one PointNoise per sphere (two)")
    tests = []
    for pts, d, nz in zip((points_a, points_b), calibrated_diameters, noise, strict=True):
        if d is None:
            d = ls_sphere(pts).diameter
        tests.append(probing_errors(pts, float(d), exclude=exclude, noise=nz))
    a, b = tests
    delta = b.fit.centre - a.fit.centre
    dist = float(np.linalg.norm(delta))
    g = delta / dist
    var = float(g @ a.fit.covariance[:3, :3] @ g + g @ b.fit.covariance[:3, :3] @ g)
    if a.fit.correlated and b.fit.correlated:
        # the two centres' covariance through the sources both fits see (none when the
        # spheres' matches read different pixels of the second camera)
        _, ia, ib = np.intersect1d(a.fit.sources, b.fit.sources, assume_unique=True,
                                   return_indices=True)
        cross = a.fit.source_gain[:3, ia] @ b.fit.source_gain[:3, ib].T
        var -= 2.0 * float(g @ cross @ g)
    return SpacingTest(SD=dist - float(calibrated_distance), distance=dist,
                       spheres=(a, b), u_fit_distance=float(np.sqrt(max(var, 0.0))))


def flatness_error(points, *, exclude: float = EXCLUDED_FRACTION) -> FlatnessTest:
    """F of the plane at one position: the range of the signed distances of the points
    to their least-squares plane, after excluding the ``floor(exclude * n)`` points of
    largest |distance| (and fitting the rest again).

    Parameters
    ----------
    points : (n, 3) mm (n >= 3, not collinear).

    Returns
    -------
    FlatnessTest
    """
    p = np.asarray(points, dtype=np.float64)
    fit, kept = trimmed(p, ls_plane, exclude)
    r = fit.residuals
    return FlatnessTest(F=float(r.max() - r.min()), fit=fit, kept=kept,
                        n_points=int(p.shape[0]), n_excluded=int(p.shape[0] - kept.sum()),
                        residuals=(p - fit.centroid) @ fit.normal)
