"""The generic camera + projector triangulation (reconstruction/generic.py) on every mix of
telecentric and pinhole devices: analytic truth (render-free: known points projected by
the devices), sigma per point against Monte Carlo, flags, and the telecentric fast path
against it."""

from __future__ import annotations

import numpy as np
import pytest
from anyrig_rigs import MIXES, SHAPE, Coords, rig_of, surface_truth

from telefringe.devices.rig import Rig
from telefringe.reconstruction import generic, pipeline, telecentric
from telefringe.reconstruction.cloud import (
    FLAG_INCONSISTENT,
    FLAG_NO_PHASE,
    FLAG_OUTSIDE,
    FLAG_UNCERTAIN,
    TriangulationError,
)

# The solve stops when Newton's step is below 1e-12 mm (relative to 1 + |s|, s <= 250 mm
# here): 1e-9 mm leaves a factor 4 over that for rounding.
TOL_EXACT = 1e-9


@pytest.mark.parametrize("mix", MIXES)
@pytest.mark.parametrize("axes", ["u", "uv", "v"])
def test_exact_on_every_mix(mix, axes):
    rig = rig_of(mix)
    X, up, vp = surface_truth(rig)
    c = Coords(up if "u" in axes else None, vp if "v" in axes else None)
    cloud = generic.triangulate(rig, c)
    assert cloud.count == X.shape[0] * X.shape[1]
    assert np.max(np.abs(cloud.xyz - X)) < TOL_EXACT
    # the cloud carries the camera's lines: one direction for a telecentric camera, one
    # per pixel for a pinhole one; each passes through its point and the camera
    if mix[0] == "t":
        assert cloud.directions.shape == (3,)
    else:
        assert cloud.directions.shape == SHAPE + (3,)
        centre = rig.camera.centre_world
        to_c = centre - cloud.xyz
        cross = np.cross(to_c, cloud.directions)
        assert np.max(np.linalg.norm(cross, axis=-1)) < 1e-9
    if axes == "uv":
        assert np.nanmax(cloud.residual) < 1e-9
    else:
        assert cloud.residual is None


@pytest.mark.parametrize("mix", MIXES)
def test_sigma_matches_monte_carlo(mix):
    """sigma_z per point within 10 % of the spread of Monte Carlo solutions (the decoder's
    noise on u_p and v_p, 0.05 and 0.08 px), each axis alone and both combined."""
    rig = rig_of(mix)
    X, up, vp = surface_truth(rig, seed=3)
    rng = np.random.default_rng(11)
    pix = rng.choice(up.size, size=24, replace=False)
    r, c = np.unravel_index(pix, up.shape)
    n_mc = 400
    su, sv = 0.05, 0.08
    uc = np.tile(c.astype(float), n_mc)
    vc = np.tile(r.astype(float), n_mc)
    u0 = np.tile(up[r, c], n_mc)
    v0 = np.tile(vp[r, c], n_mc)
    for use in ("u", "uv"):
        nu = u0 + rng.normal(0.0, su, u0.size)
        nv = v0 + rng.normal(0.0, sv, v0.size) if use == "uv" else None
        cl = generic.triangulate_pixels(rig, uc, vc, nu, nv, sigma_u_p=np.full(u0.size, su),
                                        sigma_v_p=np.full(u0.size, sv))
        assert cl.count == u0.size
        z = cl.xyz[0, :, 2].reshape(n_mc, -1)
        mc = z.std(axis=0, ddof=1)
        pred = cl.sigma_z[0].reshape(n_mc, -1)
        # sigma depends on the solution only to first order: take the mean prediction
        ratio = mc / pred.mean(axis=0)
        # a std from 400 samples scatters by 3.5 %: 10 % per point is 2.8 of that, and the
        # mean over 24 points is held to 3 %
        assert np.all(np.abs(ratio - 1.0) < 0.10), (use, ratio)
        assert abs(np.sqrt(np.mean(ratio ** 2)) - 1.0) < 0.03


@pytest.mark.parametrize("mix", ["tt", "pp"])
def test_flags(mix):
    rig = rig_of(mix)
    X, up, vp = surface_truth(rig, seed=5)
    mask = np.ones(SHAPE, dtype=bool)
    mask[0, :5] = False
    up = up.copy()
    vp = vp.copy()
    up[1, 0] = np.nan
    up[2, 0] = -40.0  # far outside the projector
    vp[3, :4] += 3.0  # a fringe-order slip across the epipolar line
    sig = np.full(SHAPE, 0.05)
    cl = generic.triangulate(rig, Coords(up, vp, mask, sig, sig), max_residual=1.0,
                             use_v_p=False)
    assert np.all(cl.flags[0, :5] == FLAG_NO_PHASE)
    assert cl.flags[1, 0] == FLAG_NO_PHASE
    assert cl.flags[2, 0] & FLAG_OUTSIDE
    assert np.all(cl.flags[3, :4] & FLAG_INCONSISTENT)
    assert np.all(np.isnan(cl.xyz[~cl.mask]))
    good = np.ones(SHAPE, dtype=bool)
    good[0, :5] = good[1, 0] = good[2, 0] = False
    good[3, :4] = False
    assert np.array_equal(cl.mask, good)
    assert np.max(np.abs(cl.xyz[good] - X[good])) < TOL_EXACT
    # max_sigma_z: everything above a bound below the median is flagged uncertain
    cl0 = generic.triangulate(rig, Coords(up, None, mask, sig))
    lim = float(np.nanmedian(cl0.sigma_z))
    cl1 = generic.triangulate(rig, Coords(up, None, mask, sig), max_sigma_z=lim)
    unc = (cl1.flags & FLAG_UNCERTAIN) != 0
    assert unc.any() and np.all(cl0.sigma_z[unc] > lim) and np.all(cl1.sigma_z[cl1.mask] <= lim)


# The compiled solvers take sigma from the slopes at their last iterate, which the
# convergence test (|u''/u'| step^2 <= 1e-12 (1 + |s|) mm) places within |u''/u'| |step|
# <= sqrt(1e-12 (1 + |s|) |u''/u'|) ~ 1.4e-6 (s ~ 200 mm, |u''/u'| ~ 0.01 / mm) of the
# solution's, relatively: far below sigma's own uncertainty.
TOL_SIGMA = 2e-6


def test_telecentric_fast_path_equals_generic():
    """Same rig, same noisy coordinates: the fast path and the generic path solve the same
    equations to 1e-12 mm; they agree within 1e-9 mm (points), TOL_SIGMA (sigma) and
    1e-9 px (residual), and flag the same pixels."""
    rig = rig_of("tt", (96, 128))
    X, up, vp = surface_truth(rig, (96, 128), seed=2)
    rng = np.random.default_rng(4)
    up = up + rng.normal(0, 0.05, up.shape)
    vp = vp + rng.normal(0, 0.3, vp.shape)
    vp[5, 5:9] += 2.0
    sig_u = np.full(up.shape, 0.05)
    sig_v = np.full(up.shape, 0.3)
    for c in (Coords(up, None, None, sig_u), Coords(up, vp, None, sig_u, sig_v),
              Coords(None, vp, None, None, sig_v)):
        for use_v_p in (True, False):
            a = telecentric.triangulate(rig, c, use_v_p=use_v_p)
            b = generic.triangulate(rig, c, use_v_p=use_v_p)
            assert np.array_equal(a.flags, b.flags)
            assert a.count > 0.9 * up.size
            assert np.nanmax(np.abs(a.xyz - b.xyz)) < 1e-9
            if c.sigma_u_p is not None or c.u_p is None:
                assert np.nanmax(np.abs(a.sigma_line / b.sigma_line - 1)) < TOL_SIGMA
            if a.residual is not None:
                assert np.nanmax(np.abs(a.residual - b.residual)) < 1e-9
            assert np.allclose(a.directions, b.directions, atol=1e-15)
            # and the NumPy reference
            r = generic.triangulate(rig, c, use_v_p=use_v_p, compiled=False)
            assert np.array_equal(a.flags, r.flags)
            assert np.nanmax(np.abs(a.xyz - r.xyz)) < 1e-9
            if c.sigma_u_p is not None or c.u_p is None:
                assert np.nanmax(np.abs(a.sigma_line / r.sigma_line - 1)) < 1e-9


def test_pipeline_dispatch():
    for mix in MIXES:
        rig = rig_of(mix)
        _, up, vp = surface_truth(rig)
        cl = pipeline.triangulate(rig, Coords(up, vp))
        ref = generic.triangulate(rig, Coords(up, vp))
        assert np.nanmax(np.abs(cl.xyz - ref.xyz)) < 1e-9


def test_triangulate_pixels_and_errors():
    rig = rig_of("pp")
    X, up, vp = surface_truth(rig)
    cl = generic.triangulate_pixels(rig, [3.0, 10.0], [4.0, 20.0], up[[4, 20], [3, 10]],
                                    vp[[4, 20], [3, 10]])
    assert np.max(np.abs(cl.xyz[0] - X[[4, 20], [3, 10]])) < TOL_EXACT
    with pytest.raises(TriangulationError, match="does not belong"):
        generic.triangulate(rig, Coords(np.zeros((10, 10))))
    with pytest.raises(TriangulationError, match="neither"):
        generic.triangulate(rig, Coords(None))
    with pytest.raises(TriangulationError, match="no projector"):
        generic.triangulate(Rig(cameras={"a": rig.camera, "b": rig.camera}), Coords(up))
    # a projector looking along the camera's lines: u_p does not change with depth
    cam = rig.camera
    same = Rig(cam, rig_of("pp").camera.with_pose(cam.R_dev_world, cam.t_dev + [0.0, 1.0, 0.0]))
    with pytest.raises(TriangulationError, match="barely changes"):
        generic.triangulate(same, Coords(np.full(SHAPE, 30.0)))


def test_marker_centres_on_a_pinhole_cloud():
    """metrology.plate.marker_centres_3d reads each point's own camera line (a pinhole
    camera's cloud has no common direction): on the plane z = 0 a marker centre lands on
    the camera pixel's point of that plane."""
    from telefringe.metrology.plate import marker_centres_3d

    rig = rig_of("pp")
    X, up, vp = surface_truth(rig, depth=0.0)
    sig = np.full(SHAPE, 0.05)
    cloud = generic.triangulate(rig, Coords(up, vp, None, sig, sig))
    with pytest.raises(TriangulationError, match="no common direction"):
        _ = cloud.direction
    mc = marker_centres_3d(cloud, [[30.4, 20.7]], inner_px=3.0, outer_px=8.0)
    o, d = rig.camera.backproject(30.4, 20.7)
    truth = o - o[2] / d[2] * d
    assert np.max(np.abs(mc.xyz[0] - truth)) < 1e-6


def test_pinhole_kernel_projection_equals_model():
    from telefringe.devices import _pinhole_kernels as pk

    prj = rig_of("pp").projector
    rng = np.random.default_rng(3)
    P = rng.normal(0.0, 8.0, (500, 3))
    P[:3] = prj.centre_world + [[0, 0, 0], [1e-3, 0, 0], [0, 0, 5]]  # at/behind the centre
    u, v = pk.project_many(np.ascontiguousarray(P), *pk.kernel_args(prj))
    ur, vr = prj.project(P)
    fin = np.isfinite(ur)
    assert np.array_equal(fin, np.isfinite(u)) and not fin[:3].all()
    assert np.max(np.abs(np.hypot(u - ur, v - vr)[fin])) < 1e-9


@pytest.mark.parametrize("mix", MIXES)
def test_compiled_solver_equals_reference(mix):
    """The compiled solver (pinhole and telecentric projectors) against the NumPy
    reference: the same flags, points within 1e-9 mm, sigma within TOL_SIGMA, residuals
    within 1e-9 px (both stop at 1e-12 mm), with noise, a fringe-order slip, masked and
    off-projector pixels."""
    rig = rig_of(mix)
    X, up, vp = surface_truth(rig, seed=9)
    rng = np.random.default_rng(5)
    up = up + rng.normal(0, 0.05, up.shape)
    vp = vp + rng.normal(0, 0.3, vp.shape)
    vp[7, :6] += 4.0
    up[3, 3] = np.nan
    up[4, 4] = 2000.0
    mask = np.ones(SHAPE, dtype=bool)
    mask[9, :7] = False
    su = np.full(SHAPE, 0.05)
    sv = np.full(SHAPE, 0.3)
    for c in (Coords(up, None, mask, su), Coords(up, vp, mask, su, sv),
              Coords(None, vp, mask, None, sv), Coords(up, vp)):
        for use_v_p in (True, False):
            a = generic.triangulate(rig, c, use_v_p=use_v_p, compiled=False)
            b = generic.triangulate(rig, c, use_v_p=use_v_p)
            assert np.array_equal(a.flags, b.flags)
            assert np.nanmax(np.abs(a.xyz - b.xyz)) < 1e-9
            if c.sigma_u_p is not None or c.u_p is None:
                assert np.nanmax(np.abs(a.sigma_line / b.sigma_line - 1)) < TOL_SIGMA
            if a.residual is not None:
                assert np.array_equal(np.isnan(a.residual), np.isnan(b.residual))
                assert np.nanmax(np.abs(a.residual - b.residual)) < 1e-9


@pytest.mark.parametrize("mix", ["tp", "pp"])
def test_compiled_camera_lines_equal_protocol(mix):
    """The camera's compiled back-projection (used to build the triangulator) gives the
    protocol's lines: directions within 1e-12, points of telecentric lines within 1e-9 mm;
    a pixel beyond the fold of a pinhole camera's distortion is bad, not wrong."""
    from telefringe.reconstruction._generic_kernels import camera_lines

    cam = rig_of(mix).camera
    rng = np.random.default_rng(2)
    u = rng.uniform(-5, SHAPE[1] + 5, 300)
    v = rng.uniform(-5, SHAPE[0] + 5, 300)
    o, d, bad = camera_lines(cam, u, v)
    o_ref, d_ref, bad_ref = generic.safe_backproject(cam, u, v)
    assert not bad.any() and not bad_ref.any()
    assert np.max(np.abs(np.broadcast_to(d, (300, 3)) - d_ref)) < 1e-12
    assert np.max(np.abs(np.broadcast_to(o, (300, 3)) - o_ref)) < 1e-9
    if mix[0] == "p":
        # a strong barrel distortion (k1 = -0.5) folds at a normalised radius of 0.54
        # (1730 px here): both refuse a pixel beyond it, and keep one inside
        from anyrig_rigs import pinhole

        barrel = pinhole((0.0, 0.0, 200.0), f=3200.0, size=(64, 48),
                         dist=(-0.5, 0.0, 0.0, 0.0, 0.0))
        uu = np.array([31.5 + 2500.0, 31.5 + 1000.0])
        vv = np.array([23.5, 23.5])
        _, _, bad = camera_lines(barrel, uu, vv)
        _, _, bad_ref = generic.safe_backproject(barrel, uu, vv)
        assert np.array_equal(bad, bad_ref) and bad[0] and not bad[1]
