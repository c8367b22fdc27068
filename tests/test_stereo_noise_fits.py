"""The fits' covariance with the stereo matches' correlated noise (issue 11): neighbouring
matches interpolate the same pixels of the second camera, so a fit that treats the points
as independent understates its noise; with the match's noise split
(:func:`telefringe.reconstruction.stereo.match_noise`) the plane
(``fit_plane(..., noise=)``) and the sphere (``measure_sphere(..., noise=)``) carry the
sandwich of the points' exact covariance. Monte Carlo over noise seeds on small stereo
scenes (white noise of the decoded sigmas on exact phase maps, the second camera 2.5
times noisier than the first, so its shared part dominates); and the compact form
points.npz keeps (:class:`StereoNoiseMaps`)."""

from __future__ import annotations

import numpy as np
import pytest
from anyrig_rigs import noisy_coords as _coords
from anyrig_rigs import stereo_rig_of, stereo_truth
from anyrig_rigs import var_ratio_tol as _var_ratio_tol

from telefringe.io.errors import InputError
from telefringe.io.points_npz import load_points, write_points
from telefringe.metrology import MetrologyError, measure_sphere
from telefringe.metrology.planes import fit_plane
from telefringe.reconstruction.stereo import (
    StereoNoise,
    StereoNoiseMaps,
    match_noise,
    match_noise_maps,
    match_stereo,
)

_S1, _S2 = 0.02, 0.05  # projector px: the first and the second camera's decoded sigma


@pytest.mark.parametrize("kind", ["pp", "tt"])
def test_plane_sigma_with_correlated_noise_matches_monte_carlo(kind):
    """A plane matched by two cameras, 150 noise seeds: the variances of the two tilts
    and of the plane's height at a fixed point (the noise-free fit's centroid) over the
    seeds within 3 sigma of the mean predicted by ``fit_plane(..., noise=)`` (a variance
    of 150 draws scatters by 12 %; measured pp 0.83, 1.14, 0.95, tt 0.91, 1.02, 0.99);
    the usual covariance (independent points) is exceeded by far more (measured 1.5-2.3 in
    variance) on the height."""
    shape = (24, 32)
    rig = stereo_rig_of(kind, shape)
    _, (u1, v1), (u2, v2) = stereo_truth(rig, shape)
    p0 = fit_plane(match_stereo(rig, _coords(u1, v1, _S1), _coords(u2, v2, _S2),
                                max_residual=None).cloud)
    c0, T0 = p0.centroid, p0.tangent
    rng = np.random.default_rng(5)
    n_runs = 150
    vals, pred, indep = [], [], []
    for _ in range(n_runs):
        a, b = _coords(u1, v1, _S1, rng), _coords(u2, v2, _S2, rng)
        m = match_stereo(rig, a, b, max_residual=None)
        fc = fit_plane(m.cloud, noise=match_noise(rig, a, b, m))
        fi = fit_plane(m.cloud)
        np.testing.assert_array_equal(fc.normal, fi.normal)  # the same fit
        assert fc.offset == fi.offset and fc.correlated and not fi.correlated
        vals.append([fc.normal @ T0[0], fc.normal @ T0[1], fc.offset - fc.normal @ c0])
        pred.append([fc.tilt_covariance[0, 0], fc.tilt_covariance[1, 1],
                     fc.sigma_at(c0) ** 2])
        indep.append([fi.tilt_covariance[0, 0], fi.tilt_covariance[1, 1],
                      fi.sigma_at(c0) ** 2])
    emp = np.var(np.array(vals), axis=0, ddof=1)
    r = emp / np.mean(pred, axis=0)
    ri = emp / np.mean(indep, axis=0)
    tol = _var_ratio_tol(n_runs)
    print(kind, "variance MC / predicted: correlated", r, "independent", ri, "tol", tol)
    assert np.all(np.abs(r - 1.0) <= tol), r
    assert ri[2] - 1.0 > tol, ri  # the correlation matters for the height


def test_fit_plane_noise_of_independent_points_is_the_usual_covariance():
    """A noise split without shared sources, of the cloud's own sigma (telecentric: one
    direction, equal sigmas): the sandwich is the usual covariance (the fit's weights
    1 / sigma_z^2 are then right)."""
    shape = (24, 32)
    rig = stereo_rig_of("tt", shape)
    _, (u1, v1), (u2, v2) = stereo_truth(rig, shape)
    rng = np.random.default_rng(1)
    a, b = _coords(u1, v1, _S1, rng), _coords(u2, v2, _S2, rng)
    m = match_stereo(rig, a, b, max_residual=None)
    cl = m.cloud
    s = np.where(cl.mask, np.nanmedian(cl.sigma_line[cl.mask]), np.nan)
    cl = type(cl)(cl.xyz, cl.mask, s, cl.residual, cl.flags, cl.directions)
    own = StereoNoise(s ** 2, np.zeros(shape + (1,)), np.full(shape + (1,), -1))
    fi, fc = fit_plane(cl, robust=True), fit_plane(cl, robust=True, noise=own)
    np.testing.assert_allclose(fc.tilt_covariance, fi.tilt_covariance, rtol=1e-9)
    assert fc.sigma_offset == pytest.approx(fi.sigma_offset, rel=1e-9)
    np.testing.assert_allclose(fc.tilt_offset_covariance, 0.0, atol=1e-9 * fc.sigma_offset
                               * np.sqrt(fc.tilt_covariance[0, 0]))
    with pytest.raises(MetrologyError, match="PointCloud"):
        fit_plane(cl.points(), noise=own)
    with pytest.raises(MetrologyError, match="noise has shape"):
        fit_plane(cl, noise=StereoNoise(np.zeros((2, 2)), np.zeros((2, 2, 1)),
                                        np.full((2, 2, 1), -1)))


def _sphere_scene(rig, shape, centre, radius):
    """Each camera's exact projector coordinates of a sphere standing on the plane z = 0
    (NaN where the projector does not light the point)."""
    out = []
    for cam in rig.cameras.values():
        rows, cols = shape
        v, u = np.mgrid[0:rows, 0:cols].astype(float)
        o, d = cam.backproject(u, v)
        o = np.broadcast_to(o, shape + (3,))
        d = np.broadcast_to(d, shape + (3,))
        t = np.minimum(_first_hit(o, d, centre, radius), -o[..., 2] / d[..., 2])
        X = o + t[..., None] * d
        up, vp = rig.projector.project(X)
        op, dp = rig.projector.backproject(up, vp)
        op = np.broadcast_to(op, X.shape)
        dp = np.broadcast_to(dp, X.shape)
        # shadowed: the projector's line meets the sphere before the point
        t_x = np.sum((X - op) * dp, -1)
        t_s = _first_hit(op, dp, centre, radius)
        lit = ~(t_s < t_x - 1e-6)
        out.append((np.where(lit, up, np.nan), np.where(lit, vp, np.nan)))
    return out


def _first_hit(o, d, c, r):
    oc = o - c
    b = np.sum(d * oc, -1)
    disc = b * b - (np.sum(oc * oc, -1) - r * r)
    with np.errstate(invalid="ignore"):
        t = np.where(disc >= 0, -b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
    return np.where(t > 0, t, np.inf)


def test_sphere_sigma_with_correlated_noise_matches_monte_carlo():
    """A sphere (radius 0.8 mm) on a plane matched by two pinhole cameras, fitted through
    the cameras' point-spread model (one variance for both cameras: the data's choice
    between one and two would mix two estimators), 100 noise seeds: the variances of the
    centre and radius over the seeds within 3 sigma of the mean predicted with
    ``noise=`` (a variance of 100 draws scatters by 14 %; measured with 120 seeds 0.99,
    0.90, 0.88, 0.83, where the independent points' covariance gives 2.3, 1.1, 1.6, 2.1);
    each seed's sigmas larger than the independent fit's."""
    shape = (60, 80)
    rig = stereo_rig_of("pp", shape)
    (u1, v1), (u2, v2) = _sphere_scene(rig, shape, np.array([0.1, -0.05, 0.35]), 0.8)
    img = np.ones(shape)
    kw = {"rig": rig, "image": img, "image_2": img, "psf_shared": True}
    rng = np.random.default_rng(5)
    n_runs = 100
    vals, pred = [], []
    for k in range(n_runs):
        a, b = _coords(u1, v1, _S1, rng), _coords(u2, v2, _S2, rng)
        m = match_stereo(rig, a, b, max_residual=None)
        fc = measure_sphere(m.cloud, noise=match_noise(rig, a, b, m), **kw).sphere
        if k == 0:
            fi = measure_sphere(m.cloud, **kw).sphere
            assert fi.radius == fc.radius and fc.n_inliers > 300
            assert np.all(np.sqrt(np.diag(fc.covariance)) > np.sqrt(np.diag(fi.covariance)))
        vals.append([*fc.centre, fc.radius])
        pred.append(np.diag(fc.covariance))
    r = np.var(np.array(vals), axis=0, ddof=1) / np.mean(pred, axis=0)
    tol = _var_ratio_tol(n_runs)
    print("variance MC / predicted (centre x, y, z, radius)", r, "tol", tol)
    assert np.all(np.abs(r - 1.0) <= tol), r


def test_noise_maps_expand_and_points_npz(tmp_path):
    """The compact maps points.npz keeps expand to match_noise's split exactly and come
    back from the file unchanged; a file without them reads with ``stereo_noise`` None,
    one with some of them only is refused."""
    shape = (16, 24)
    rig = stereo_rig_of("pp", shape)
    _, (u1, v1), (u2, v2) = stereo_truth(rig, shape)
    rng = np.random.default_rng(3)
    a, b = _coords(u1, v1, _S1, rng), _coords(u2, v2, _S2, rng)
    m = match_stereo(rig, a, b)
    maps = match_noise_maps(rig, a, b, m)
    nz = match_noise(rig, a, b, m)
    ex = maps.expand()
    for f in ("var_own", "weights", "sources"):
        np.testing.assert_array_equal(getattr(ex, f), getattr(nz, f))
    assert maps.coef.shape == shape + (2,) and maps.sigma_2.shape == (2,) + shape
    write_points(tmp_path / "points.npz", m.cloud, stereo_noise=maps)
    back = load_points(tmp_path).stereo_noise
    assert isinstance(back, StereoNoiseMaps)
    for f in ("u2", "v2", "var_own", "coef", "sigma_2"):
        np.testing.assert_array_equal(getattr(back, f), getattr(maps, f))
    write_points(tmp_path / "old.npz", m.cloud)
    assert load_points(tmp_path / "old.npz").stereo_noise is None
    with np.load(tmp_path / "points.npz") as z:
        arrays = {k: z[k] for k in z.files if k != "stereo_coef"}
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(InputError, match="stereo_coef missing"):
        load_points(tmp_path / "bad.npz")
    with pytest.raises(ValueError, match="stereo_noise has shape"):
        write_points(tmp_path / "x.npz", m.cloud, stereo_noise=StereoNoiseMaps(
            *(np.zeros((2, 2)),) * 3, np.zeros((2, 2, 1)), np.zeros((1, 4, 4))))


def test_measure_plate_plane_takes_the_noise():
    """``measure_plate(..., noise=)``: its plane is ``fit_plane(cloud, robust=True,
    noise=)``'s (Z's sigma from it, the tilts' covariance too), larger than without."""
    from telefringe.metrology import measure_plate
    from telefringe.metrology.planes import Plane, plane_distance

    shape = (48, 64)
    rig = stereo_rig_of("pp", shape)
    _, (u1, v1), (u2, v2) = stereo_truth(rig, shape)
    rng = np.random.default_rng(4)
    a, b = _coords(u1, v1, _S1, rng), _coords(u2, v2, _S2, rng)
    m = match_stereo(rig, a, b)
    nz = match_noise(rig, a, b, m)
    uu, vv = np.meshgrid([18.0, 32.0, 46.0], [10.0, 24.0, 38.0])
    centres = np.stack([uu.ravel(), vv.ravel()], axis=1)
    pc = measure_plate(m.cloud, centres, rows=3, cols=3, pitch_mm=0.9, noise=nz)
    pi = measure_plate(m.cloud, centres, rows=3, cols=3, pitch_mm=0.9)
    fc = fit_plane(m.cloud, robust=True, noise=nz)
    assert pc.plane.correlated and not pi.plane.correlated
    np.testing.assert_array_equal(pc.plane.tilt_covariance, fc.tilt_covariance)
    assert pc.z.sigma == plane_distance(fc, Plane.horizontal(0.0)).sigma
    assert pc.z.distance == pi.z.distance and pc.z.sigma > pi.z.sigma
