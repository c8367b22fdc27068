"""Triangulation against the true model: exact recovery, flags, uncertainty by Monte Carlo."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from telefringe.devices.rig import Rig
from telefringe.devices.telecentric import Intrinsics, TelecentricDevice
from telefringe.geometry.distortion import ConvergenceError
from telefringe.geometry.so3 import rotation_from_rotvec
from telefringe.reconstruction.cloud import (
    FLAG_INCONSISTENT,
    FLAG_NO_PHASE,
    FLAG_OUTSIDE,
    FLAG_UNCERTAIN,
    PointCloud,
    TriangulationError,
)
from telefringe.reconstruction.heightmap import HeightMap, height_map
from telefringe.reconstruction.telecentric import Triangulator, triangulate, triangulate_pixels

SHAPE = (96, 128)


def make_rig(*, k1_p=3e-4, s1_p=5e-5, s2_p=-8e-5, k1_c=2e-3, s1_c=2e-4, s2_c=-1e-4,
             angle_deg=25.0, shape=SHAPE) -> Rig:
    """A small rig like the paper's: a camera looking down (-z), the projector tilted.

    The camera sees about 4 x 3 mm; the distortions move the image corners by a few
    tenths of a pixel (camera) and a few pixels (projector).
    """
    rows, cols = shape
    # camera: device x = world x, device y = -world y (image v runs down), z = -world z
    R_c = rotation_from_rotvec([0.01, -0.02, 0.03]) @ np.diag([1.0, -1.0, -1.0])
    cam = TelecentricDevice(
        Intrinsics(m=1.0, du=0.03, dv=0.03, u0=(cols - 1) / 2 + 1.3, v0=(rows - 1) / 2 - 0.7,
                   k1=k1_c, s1=s1_c, s2=s2_c, width=cols, height=rows),
        R_c, np.array([0.05, -0.02]))
    a = np.radians(angle_deg)
    # projector looks along (sin a, 0, -cos a): rotated about world y
    R_p = rotation_from_rotvec([0.0, -a, 0.0]) @ np.diag([1.0, -1.0, -1.0])
    R_p = rotation_from_rotvec([0.0, 0.0, 0.05]) @ R_p
    prj = TelecentricDevice(
        Intrinsics(m=0.5, du=0.0137, dv=0.0137, u0=400.0, v0=300.0, k1=k1_p, s1=s1_p,
                   s2=s2_p, width=800, height=600),
        R_p, np.array([0.3, -0.2]))
    return Rig(cam, prj)


@dataclass(frozen=True)
class Coords:
    u_p: np.ndarray
    v_p: np.ndarray | None = None
    mask: np.ndarray | None = None
    sigma_u_p: np.ndarray | None = None
    sigma_v_p: np.ndarray | None = None


def surface_points(rig, shape=SHAPE, *, seed=0, depth=2.0):
    """True points on each pixel's line at random depths (mm) and their projector pixels."""
    tri = Triangulator.for_shape(rig, shape)
    rng = np.random.default_rng(seed)
    s = rng.uniform(-depth, depth, size=shape)
    X = tri.line_points(s)
    up, vp = rig.projector.project(X)
    return X, up, vp


def _device(k, *, m=0.8, seed=7):
    rng = np.random.default_rng(seed)
    return TelecentricDevice(
        Intrinsics(m=m, du=0.0052, dv=0.0047, u0=640.3, v0=511.8, k1=k[0], s1=k[1], s2=k[2],
                   width=1280, height=1024),
        rotation_from_rotvec(rng.normal(0, 1, 3)), rng.normal(0, 2, 2))


@pytest.mark.parametrize("k", [(2e-3, 2e-4, -1e-4), (0.0, 0.0, 0.0), (-5e-3, 0.0, 1e-3)])
def test_compiled_device_model_matches_the_numpy_model(k):
    # the kernels' telecentric model (devices/_telecentric_kernels) against
    # TelecentricDevice, to rounding: 2x the measured worst of these three cases, 5.7e-13
    # px for the projection (the kernels multiply by 1 / pitch where the NumPy model
    # divides) and 1.8e-15 mm for the back-projection (the same Newton iteration)
    from telefringe.devices import _telecentric_kernels as tk

    dev = _device(k)
    rng = np.random.default_rng(5)
    X = rng.uniform(-4, 4, (1000, 3))
    u, v = tk.project_many(X, *tk.kernel_args(dev))
    u_ref, v_ref = dev.project(X)
    assert np.max(np.abs(u - u_ref)) < 1.2e-12 and np.max(np.abs(v - v_ref)) < 1.2e-12
    u = rng.uniform(-0.5, 1279.5, 1000)
    v = rng.uniform(-0.5, 1023.5, 1000)
    u[3] = np.nan
    intr, R, t_dev = tk.kernel_args(dev)
    a, b = np.empty(1000), np.empty(1000)
    assert tk.backproject_lines(u, v, intr, t_dev, a, b) == 0
    origin, direction = dev.backproject(u, v)
    mine = a[:, None] * R[0] + b[:, None] * R[1]
    ok = np.isfinite(u)
    assert np.max(np.abs(mine[ok] - origin[ok])) < 4e-15  # mm
    assert np.isnan(a[3]) and np.all(np.isnan(origin[3]))
    np.testing.assert_array_equal(direction, R[2])
    # beyond the invertible range: counted by the kernel, raised by the model
    strong = _device((-0.05, 0.0, 0.0))
    a1, b1 = np.empty(1), np.empty(1)
    intr, R, t_dev = tk.kernel_args(strong)
    assert tk.backproject_lines(np.array([6000.0]), np.array([6000.0]), intr, t_dev, a1, b1) == 1
    with pytest.raises(ConvergenceError):
        strong.backproject(6000.0, 6000.0)
    with pytest.raises(ConvergenceError):
        Triangulator.for_pixels(Rig(strong, make_rig().projector), 6000.0, 6000.0)


@pytest.mark.parametrize("k_p", [(3e-4, 5e-5, -8e-5), (2e-1, 3e-2, -3e-2)])
def test_projector_cubics_are_the_device_model(k_p):
    # the fast path's special form (the projector's distorted sensor coordinates as cubics
    # in s along a camera line) against the device model's projection of the line's points
    from telefringe.reconstruction import telecentric as tel

    rig = make_rig(k1_p=k_p[0], s1_p=k_p[1], s2_p=k_p[2])
    tri = Triangulator.for_shape(rig, SHAPE)
    ki = rig.projector.intrinsics
    coef = tri.coef
    t_p = ki.m * rig.projector.t_dev
    kp = np.zeros(20)
    kp[4:7] = ki.k1, ki.s1, ki.s2
    kp[9:15] = coef[0, 0], coef[0, 1], coef[0, 2], coef[1, 0], coef[1, 1], coef[1, 2]
    kp[15:17] = t_p
    rng = np.random.default_rng(8)
    for i, j in ((0, 0), (40, 70), (95, 127)):
        for s in rng.uniform(-6, 6, 4):
            c = tel._line_cubics(tri.a[i, j], tri.b[i, j], kp)
            xd = ((c[3] * s + c[2]) * s + c[1]) * s + c[0]
            yd = ((c[7] * s + c[6]) * s + c[5]) * s + c[4]
            u, v = rig.projector.project(tri.line_points(np.full(SHAPE, s))[i, j])
            xd_ref, yd_ref = rig.projector.pixel_to_sensor(u, v)
            # rounding: measured worst 5.6e-16 and 1.8e-15 mm for the two cases
            assert abs(xd - xd_ref) < 4e-15 and abs(yd - yd_ref) < 4e-15


@pytest.mark.parametrize("k_c", [(2e-3, 2e-4, -1e-4), (0.0, 0.0, 0.0), (1e-1, 1e-2, -1e-2)])
def test_grid_set_up_is_the_per_pixel_set_up(k_c):
    # for_shape's fused kernel (fixed Newton steps, failures redone by the iterating
    # inversion) against for_pixels (the model's inversion, to its 1e-12 mm residual):
    # the same lines to 1e-11 mm. The strong distortion leaves corner pixels to the redo.
    rig = make_rig(k1_c=k_c[0], s1_c=k_c[1], s2_c=k_c[2])
    grid = Triangulator.for_shape(rig, SHAPE)
    v, u = np.mgrid[0:SHAPE[0], 0:SHAPE[1]]
    ref = Triangulator.for_pixels(rig, u, v)
    assert grid.shape == ref.shape == SHAPE
    assert np.max(np.abs(grid.a - ref.a)) < 1e-11
    assert np.max(np.abs(grid.b - ref.b)) < 1e-11
    np.testing.assert_array_equal(grid.coef, ref.coef)


def test_camera_looks_down():
    rig = make_rig()
    assert rig.camera.axis_world[2] < -0.99
    ang = np.degrees(np.arccos(rig.camera.axis_world @ rig.projector.axis_world))
    assert 20 < ang < 30


@pytest.mark.parametrize("use_v", [False, True])
def test_exact_recovery_without_noise(use_v):
    rig = make_rig()
    X, up, vp = surface_points(rig)
    sig = np.full(SHAPE, 0.02)
    c = Coords(up, vp if use_v else None, None, sig, sig if use_v else None)
    cloud = triangulate(rig, c)
    assert cloud.count == X.shape[0] * X.shape[1]
    assert np.max(np.abs(cloud.xyz - X)) < 1e-9
    if use_v:
        assert np.nanmax(cloud.residual) < 1e-9
    else:
        assert cloud.residual is None
    assert cloud.xyz.shape == SHAPE + (3,)
    assert np.all(cloud.flags == 0)


def test_exact_recovery_strong_distortion():
    # distortion strong enough that the fixed-step pass leaves pixels to the slow pass
    rig = make_rig(k1_p=2e-2, s1_p=3e-3, s2_p=-3e-3)
    X, up, vp = surface_points(rig, depth=6.0)
    from telefringe.reconstruction import telecentric as rec

    tri = Triangulator.for_shape(rig, SHAPE)
    calls = []
    orig = rec._solve_slow

    def spy(*args):
        calls.append(1)
        return orig(*args)

    rec._solve_slow = spy
    try:
        cloud = tri.triangulate(Coords(up), check_bounds=False)
        n_u = len(calls)
        cloud2 = tri.triangulate(Coords(up, vp), check_bounds=False)
    finally:
        rec._solve_slow = orig
    # by both kernels (u only, and u + v: each counts the pixels it leaves)
    assert n_u == 1 and len(calls) == 2, "the slow pass was not exercised"
    assert cloud.count == cloud2.count == X.shape[0] * X.shape[1]
    assert np.max(np.abs(cloud.xyz - X)) < 1e-9
    assert np.max(np.abs(cloud2.xyz - X)) < 1e-9


@pytest.mark.parametrize("k_p", [(3e-4, 5e-5, -8e-5), (2e-2, 3e-3, -3e-3),
                                 (2e-1, 3e-2, -3e-2)])
def test_u_only_kernel_matches_the_iterated_solution(k_p):
    """The lean u-only kernel (chord steps + one Newton step, reciprocal slope reused for
    sigma) against the general kernel, which iterates Newton on u_p and checks v_p (here
    with no residual limit, so the flags mean the same): the same points to 1e-9 mm
    (1e-6 um), the same sigma to 1e-9 relative, the same flags. The u_p are noisy, so
    the points are not the ones the observations were made from."""
    rig = make_rig(k1_p=k_p[0], s1_p=k_p[1], s2_p=k_p[2])
    X, up, vp = surface_points(rig, depth=6.0, seed=3)
    rng = np.random.default_rng(4)
    sig = rng.uniform(0.01, 0.1, SHAPE)
    up = up + sig * rng.standard_normal(SHAPE)
    up[5, 7] = np.nan
    mask = np.ones(SHAPE, dtype=bool)
    mask[9, 11] = False
    # a limit on sigma_z that flags about a tenth of the points
    max_sz = float(np.nanpercentile(triangulate(rig, Coords(up, None, mask, sig)).sigma_z, 90))
    fast = triangulate(rig, Coords(up, None, mask, sig), max_sigma_z=max_sz)
    ref = triangulate(rig, Coords(up, vp, mask, sig, sig), use_v_p=False, max_residual=None,
                      max_sigma_z=max_sz)
    assert fast.residual is None and ref.residual is not None
    np.testing.assert_array_equal(fast.flags, ref.flags)
    np.testing.assert_array_equal(fast.mask, ref.mask)
    assert 0.5 * up.size < fast.count < 0.95 * up.size
    assert np.any(fast.flags & FLAG_UNCERTAIN) and np.any(fast.flags & FLAG_NO_PHASE)
    m = fast.mask
    assert np.max(np.abs(fast.xyz[m] - ref.xyz[m])) < 1e-9
    assert np.max(np.abs(fast.sigma_line[m] / ref.sigma_line[m] - 1)) < 1e-9
    # and the solution is the root: the model projects it back onto the observed u_p
    u_back, _ = rig.projector.project(fast.xyz[m])
    assert np.max(np.abs(u_back - up[m])) < 1e-8
    # the strong distortion puts points beyond the radius where the kernel can skip the
    # fold check (they are solved again with it)
    from telefringe.geometry._distortion_kernels import unfolded_radius2

    xu, yu = rig.projector.world_to_sensor(fast.xyz[m])
    assert np.any(xu**2 + yu**2 > unfolded_radius2(*k_p)) == (k_p[0] > 0.1)


@pytest.mark.parametrize("k", [(7e-5, 1e-5, -2e-5), (-2e-2, 3e-3, -3e-3), (0.0, 0.0, 1e-2),
                               (-5e-1, 0.0, 0.0), (0.0, 0.0, 0.0)])
def test_no_fold_within_the_unfolded_radius(k):
    from telefringe.geometry._distortion_kernels import unfolded_radius2

    k1, s1, s2 = k
    r2 = unfolded_radius2(*k)
    rng = np.random.default_rng(6)
    r = np.sqrt(min(r2, 1e4)) * np.sqrt(rng.uniform(0, 1, 20000))
    r[:100] = np.sqrt(min(r2, 1e4))  # the rim
    t = rng.uniform(0, 2 * np.pi, r.size)
    xu, yu = r * np.cos(t), r * np.sin(t)
    q = xu**2 + yu**2
    fa = 1 + k1 * (q + 2 * xu**2) + 2 * s1 * xu
    fb = 2 * k1 * xu * yu + 2 * s1 * yu
    fc = 2 * k1 * xu * yu + 2 * s2 * xu
    fd = 1 + k1 * (q + 2 * yu**2) + 2 * s2 * yu
    assert np.all(fa * fd - fb * fc > 0) and np.all(fa + fd > 0)
    if k1 < 0 and s1 == s2 == 0:
        # pure barrel distortion folds at r^2 = 1 / (3 |k1|): the bound is within 2x of it
        assert 0.25 / (3 * abs(k1)) < r2 < 1 / (3 * abs(k1))


def test_v_fringes_only():
    rig = make_rig()
    # the projector turned by 90 deg about its axis: v now carries the depth
    quarter = rotation_from_rotvec([0.0, 0.0, np.pi / 2])
    prj = TelecentricDevice(rig.projector.intrinsics, quarter @ rig.projector.R_dev_world,
                            rig.projector.t_dev[::-1].copy())
    rig_v = Rig(rig.camera, prj)
    X, up, vp = surface_points(rig_v)
    sig = np.full(SHAPE, 0.02)
    cloud = triangulate(rig_v, Coords(None, vp, None, None, sig))
    assert cloud.count == up.size
    assert np.max(np.abs(cloud.xyz - X)) < 1e-9
    assert np.all(np.isfinite(cloud.sigma_z)) and cloud.residual is None
    # u_p alone still triangulates here (the projector is turned by 3 deg about its
    # axis) but with ~20 times less depth sensitivity
    cloud_u = triangulate(rig_v, Coords(up, None, None, sig))
    assert np.nanmedian(cloud_u.sigma_z / cloud.sigma_z) > 10
    flat = Rig(rig.camera, TelecentricDevice(rig.projector.intrinsics,
                                             quarter @ rig.camera.R_dev_world, np.zeros(2)))
    with pytest.raises(TriangulationError, match="v_p barely changes"):
        triangulate(flat, Coords(None, vp))
    with pytest.raises(TriangulationError, match="neither"):
        triangulate(rig, Coords(None))


def test_float32_and_integer_inputs():
    rig = make_rig()
    X, up, vp = surface_points(rig)
    cloud = triangulate(rig, Coords(up.astype(np.float32)))
    # float32 rounding of u_p (~3e-5 px) moves the point by about that / |du_p/ds|
    assert np.max(np.abs(cloud.xyz - X)) < 1e-5
    cloud = triangulate(rig, Coords(np.round(up).astype(np.int32)))
    assert cloud.count == up.size


def test_mask_and_nan_are_invalid():
    rig = make_rig()
    X, up, vp = surface_points(rig)
    mask = np.ones(SHAPE, bool)
    mask[10:20, 30:40] = False
    up = up.copy()
    up[50, 60] = np.nan
    vp = vp.copy()
    vp[70, 80] = np.nan
    cloud = triangulate(rig, Coords(up, vp, mask))
    assert not cloud.mask[10:20, 30:40].any()
    assert np.all(np.isnan(cloud.xyz[10:20, 30:40]))
    assert np.all(cloud.flags[10:20, 30:40] == FLAG_NO_PHASE)
    assert not cloud.mask[50, 60] and not cloud.mask[70, 80]
    assert cloud.count == up.size - 100 - 2
    # without v_p in the solution, a NaN v_p does not invalidate the point
    cloud = triangulate(rig, Coords(up, vp, mask), use_v_p=False)
    assert cloud.mask[70, 80]
    assert np.isnan(cloud.residual[70, 80])


def test_wrong_fringe_order_is_inconsistent():
    rig = make_rig()
    X, up, vp = surface_points(rig)
    vp = vp.copy()
    period = 600 / 48
    # a fringe-order error on v: v_p barely depends on depth in this rig, so the error
    # lies across the epipolar line and the check sees it
    vp[5:8, 5:8] += period
    cloud = triangulate(rig, Coords(up, vp))
    assert np.all(cloud.flags[5:8, 5:8] & FLAG_INCONSISTENT)
    assert np.all(cloud.residual[5:8, 5:8] > 0.9 * period)
    ok = np.ones(SHAPE, bool)
    ok[5:8, 5:8] = False
    assert cloud.mask[ok].all()
    # the check can be switched off
    cloud = triangulate(rig, Coords(up, vp), max_residual=None)
    assert cloud.mask.all()
    # an error along the epipolar line (u_p here) only moves the point: the one-axis
    # depth sensitivity is what the check cannot see
    X, up, vp = surface_points(rig)
    up = up.copy()
    up[5:8, 5:8] += 800 / 64
    cloud = triangulate(rig, Coords(up, vp))
    tri = Triangulator.for_shape(rig, SHAPE)
    Ju = np.abs(tri.coef[0, 2]) / rig.projector.intrinsics.du  # px per mm, undistorted
    dz = np.abs(cloud.z[5:8, 5:8] - X[5:8, 5:8, 2])
    assert np.allclose(dz, 12.5 / Ju * abs(tri.direction[2]), rtol=0.05)
    assert np.all(cloud.residual[5:8, 5:8] < 1.0)


def test_outside_projector_and_max_sigma():
    rig = make_rig()
    X, up, vp = surface_points(rig)
    up = up.copy()
    up[0, 0] = 2000.0
    sig = np.full(SHAPE, 0.02)
    sig[1, 1] = 1.0
    cloud = triangulate(rig, Coords(up, None, None, sig), max_sigma_z=0.01)
    assert cloud.flags[0, 0] & FLAG_OUTSIDE
    assert cloud.flags[1, 1] & FLAG_UNCERTAIN
    assert cloud.count == up.size - 2


def test_no_sigma_gives_nan_uncertainty():
    rig = make_rig()
    X, up, vp = surface_points(rig)
    cloud = triangulate(rig, Coords(up, vp))
    assert np.all(np.isnan(cloud.sigma_z))
    assert np.max(np.abs(cloud.xyz - X)) < 1e-9


@pytest.mark.parametrize("use_v", [False, True])
def test_sigma_matches_monte_carlo(use_v):
    rig = make_rig()
    rng = np.random.default_rng(1)
    # a few pixels across the field, each repeated n times with noisy u_p (and v_p)
    pix = np.array([[3, 4], [50, 60], [90, 120], [10, 110]])
    n = 4000
    s_true = np.array([-1.5, 0.0, 1.0, 2.0])
    u_c = np.repeat(pix[:, 1].astype(float), n)
    v_c = np.repeat(pix[:, 0].astype(float), n)
    lines = Triangulator.for_pixels(rig, pix[:, 1].astype(float), pix[:, 0].astype(float))
    X = lines.line_points(s_true)
    up, vp = rig.projector.project(X)
    su = np.array([0.02, 0.05, 0.03, 0.08])
    sv = np.array([0.04, 0.02, 0.06, 0.03])
    up_n = np.repeat(up, n) + rng.standard_normal(4 * n) * np.repeat(su, n)
    vp_n = np.repeat(vp, n) + rng.standard_normal(4 * n) * np.repeat(sv, n)
    cloud = triangulate_pixels(rig, u_c, v_c, up_n, vp_n if use_v else None,
                               sigma_u_p=np.repeat(su, n),
                               sigma_v_p=np.repeat(sv, n) if use_v else None)
    pts = cloud.xyz[0].reshape(4, n, 3)
    # the predicted sigma at the true point
    exact = triangulate_pixels(rig, pix[:, 1], pix[:, 0], up, vp if use_v else None,
                               sigma_u_p=su, sigma_v_p=sv if use_v else None)
    sig_pred = exact.sigma_xyz[0]  # (4, 3)
    sig_mc = pts.std(axis=1, ddof=1)
    # the sample std of n Gaussian draws has a relative standard error 1/sqrt(2(n-1));
    # allow 4 of them (plus the tiny nonlinearity of the distortion)
    tol = 4.0 / np.sqrt(2 * (n - 1))
    assert np.all(np.abs(sig_mc / sig_pred - 1.0) < tol), (sig_mc, sig_pred)
    # unbiased: the mean lands within 4 standard errors of the truth
    mean_err = pts.mean(axis=1) - X
    assert np.all(np.abs(mean_err) < 4 * sig_pred / np.sqrt(n) + 1e-12)
    # the errors are along the camera line: X, Y, Z fully correlated
    d = rig.camera.axis_world
    dev = pts - pts.mean(axis=1, keepdims=True)
    perp = dev - (dev @ d)[..., None] * d
    assert np.max(np.abs(perp)) < 1e-9


def test_combining_v_reduces_uncertainty_only_by_its_depth_sensitivity():
    rig = make_rig()
    X, up, vp = surface_points(rig)
    s = np.full(SHAPE, 0.03)
    c_u = triangulate(rig, Coords(up, None, None, s))
    c_uv = triangulate(rig, Coords(up, vp, None, s, s))
    assert np.all(c_uv.sigma_z <= c_u.sigma_z * (1 + 1e-12))
    # sigma_z for u only = sigma_u / |du_p/ds| * |d_z|; check one pixel by finite differences
    tri = Triangulator.for_shape(rig, SHAPE)
    i, j = 40, 70
    s0 = (X[i, j] - tri.line_points(np.zeros(SHAPE))[i, j]) @ tri.direction
    h = 1e-4
    u1, _ = rig.projector.project(tri.line_points(np.full(SHAPE, s0 + h))[i, j])
    u0, _ = rig.projector.project(tri.line_points(np.full(SHAPE, s0 - h))[i, j])
    J = (u1 - u0) / (2 * h)
    assert c_u.sigma_line[i, j] == pytest.approx(0.03 / abs(J), rel=1e-6)
    assert c_u.sigma_z[i, j] == pytest.approx(0.03 / abs(J) * abs(tri.direction[2]), rel=1e-6)


def test_shape_and_geometry_errors():
    rig = make_rig()
    X, up, vp = surface_points(rig)
    with pytest.raises(TriangulationError, match="rig does not belong"):
        triangulate(rig, Coords(up[:-1]))
    tri = Triangulator.for_shape(rig, SHAPE)
    with pytest.raises(TriangulationError, match="shape"):
        tri.triangulate(Coords(up, vp[:, :-1]))
    # projector parallel to the camera: no depth information
    flat = Rig(rig.camera, TelecentricDevice(rig.projector.intrinsics,
                                             rig.camera.R_dev_world, np.zeros(2)))
    with pytest.raises(TriangulationError, match="depth"):
        triangulate(flat, Coords(up))
    with pytest.raises(TriangulationError, match="parallel"):
        triangulate(flat, Coords(up, vp))
    assert issubclass(TriangulationError, ValueError)


def test_triangulate_pixels_matches_grid():
    rig = make_rig()
    X, up, vp = surface_points(rig)
    rr, cc = np.mgrid[0:SHAPE[0]:7, 0:SHAPE[1]:9]
    cloud = triangulate_pixels(rig, cc.ravel(), rr.ravel(), up[rr, cc].ravel(),
                               vp[rr, cc].ravel())
    assert np.max(np.abs(cloud.xyz[0] - X[rr, cc].reshape(-1, 3))) < 1e-9


def test_point_cloud_is_read_only_and_from_xyz():
    rig = make_rig()
    X, up, vp = surface_points(rig)
    cloud = triangulate(rig, Coords(up))
    with pytest.raises(ValueError):
        cloud.xyz[0, 0, 0] = 1.0
    xyz = X.copy()
    xyz[3, 4] = np.nan
    c2 = PointCloud.from_xyz(xyz, sigma_z=np.full(SHAPE, 0.001))
    assert c2.count == X.shape[0] * X.shape[1] - 1
    assert np.allclose(c2.sigma_z[c2.mask], 0.001)
    assert np.allclose(c2.points(), X.reshape(-1, 3)[np.arange(X.size // 3) != 3 * 128 + 4])
    with pytest.raises(TriangulationError):
        PointCloud.from_xyz(np.zeros((3, 4)))


def test_point_cloud_copies_the_callers_arrays():
    # the arrays given are never changed nor made read-only; the cloud's are read-only
    rng = np.random.default_rng(2)
    xyz = rng.normal(size=SHAPE + (3,))
    mask = np.ones(SHAPE, bool)
    sig = np.full(SHAPE, 0.002)
    res = np.zeros(SHAPE)
    flags = np.zeros(SHAPE, np.uint8)
    d = np.array([0.0, 0.0, -1.0])
    given = [xyz, mask, sig, res, flags, d]
    before = [a.copy() for a in given]
    cloud = PointCloud(*given)
    for a, b in zip(given, before, strict=True):
        assert a.flags.writeable
        np.testing.assert_array_equal(a, b)
    xyz[0, 0, 0] = 99.0  # the caller changes its array: the cloud does not change
    assert cloud.xyz[0, 0, 0] == before[0][0, 0, 0]
    for name in ("xyz", "mask", "sigma_line", "residual", "flags", "directions"):
        assert not getattr(cloud, name).flags.writeable, name
    xyz2 = before[0].copy()
    c2 = PointCloud.from_xyz(xyz2, sigma_z=sig)
    assert xyz2.flags.writeable and not c2.xyz.flags.writeable
    np.testing.assert_array_equal(xyz2, before[0])
    z = np.ones((4, 5), np.float32)
    sz = np.full((4, 5), 0.001, np.float32)
    hm = HeightMap(z, 0.0, 0.0, 0.1, sigma_z=sz)
    assert z.flags.writeable and sz.flags.writeable
    assert not hm.z.flags.writeable and not hm.sigma_z.flags.writeable
    z[0, 0] = 5.0
    assert hm.z[0, 0] == 1.0
    with pytest.raises(TriangulationError, match="sigma_z"):
        HeightMap(z, 0.0, 0.0, 0.1, sigma_z=sz[:, :-1])


def test_point_cloud_per_pixel_directions():
    # a cloud from a camera whose lines converge (each pixel its own direction): the
    # uncertainties use each pixel's direction, and there is no common direction
    rng = np.random.default_rng(3)
    xyz = rng.normal(size=SHAPE + (3,))
    centre = np.array([0.0, 0.0, 100.0])
    d = xyz - centre
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    sig = rng.uniform(0.001, 0.003, SHAPE)
    cloud = PointCloud(xyz, np.ones(SHAPE, bool), sig, None, np.zeros(SHAPE, np.uint8), d)
    np.testing.assert_allclose(cloud.sigma_xyz, sig[..., None] * np.abs(d), rtol=1e-15)
    np.testing.assert_allclose(cloud.sigma_z, sig * np.abs(d[..., 2]), rtol=1e-15)
    assert cloud.sigma_x.shape == cloud.sigma_y.shape == SHAPE
    with pytest.raises(TriangulationError, match="differ from pixel to pixel"):
        _ = cloud.direction
    rays = cloud.rays
    assert rays.shape == SHAPE
    np.testing.assert_allclose(rays.point_at(np.zeros(SHAPE)), xyz)
    # per-pixel directions that are all the same: that common direction
    same = np.broadcast_to(d[0, 0], SHAPE + (3,))
    c2 = PointCloud(xyz, np.ones(SHAPE, bool), sig, None, np.zeros(SHAPE, np.uint8), same)
    np.testing.assert_array_equal(c2.direction, d[0, 0])
    # from_xyz takes them too, and needs a z component at every pixel
    c3 = PointCloud.from_xyz(xyz, sigma_z=sig, direction=d)
    np.testing.assert_allclose(c3.sigma_z, sig, rtol=1e-14)
    flat = d.copy()
    flat[3, 4] = (1.0, 0.0, 0.0)
    with pytest.raises(TriangulationError, match="z component"):
        PointCloud.from_xyz(xyz, direction=flat)
    # a triangulated telecentric cloud carries the camera's one direction
    rig = make_rig()
    X, up, vp = surface_points(rig)
    tc = triangulate(rig, Coords(up))
    assert tc.directions.shape == (3,)
    np.testing.assert_array_equal(tc.direction, rig.camera.axis_world)
    np.testing.assert_array_equal(tc.rays.directions()[5, 6], rig.camera.axis_world)


def test_point_cloud_checks_its_arrays():
    xyz = np.zeros(SHAPE + (3,))
    ok = np.ones(SHAPE, bool)
    sig = np.zeros(SHAPE)
    fl = np.zeros(SHAPE, np.uint8)
    with pytest.raises(TriangulationError, match="mask"):
        PointCloud(xyz, ok[:-1], sig, None, fl, (0.0, 0.0, 1.0))
    with pytest.raises(TriangulationError, match="unit"):
        PointCloud(xyz, ok, sig, None, fl, (0.0, 0.0, 2.0))
    with pytest.raises(TriangulationError, match="directions must have shape"):
        PointCloud(xyz, ok, sig, None, fl, np.zeros((2, 3)))
    with pytest.raises(TriangulationError, match="xyz"):
        PointCloud(xyz[..., :2], ok, sig, None, fl, (0.0, 0.0, 1.0))


def _shifted(rig, k):
    """The rig with its projector moved by k * 10 um: another rig (another cache key)."""
    prj = rig.projector
    return Rig(rig.camera, TelecentricDevice(prj.intrinsics, prj.R_dev_world,
                                             prj.t_dev + np.array([1e-2 * k, 0.0])))


def test_triangulator_cache_is_bounded_by_bytes():
    from telefringe.reconstruction.telecentric import _TriangulatorCache

    rig = make_rig()
    one = Triangulator.for_shape(rig, SHAPE)
    size = one.a.nbytes + one.b.nbytes + one.coef.nbytes
    cache = _TriangulatorCache(int(2.5 * size))  # room for two
    rigs = [_shifted(rig, k) for k in range(5)]
    for r in rigs:
        tri = cache.get(r, SHAPE)
        assert tri.rig is r
        assert cache.nbytes <= cache.max_bytes and len(cache) <= 2
    assert len(cache) == 2 and cache.nbytes == 2 * size
    # a hit returns the cached object; the least recently used goes first
    t4 = cache.get(rigs[4], SHAPE)
    t3 = cache.get(rigs[3], SHAPE)
    assert cache.get(rigs[3], SHAPE) is t3 and cache.get(rigs[4], SHAPE) is t4
    cache.get(rigs[3], SHAPE)
    cache.get(rigs[0], SHAPE)  # evicts rigs[4], keeps rigs[3] (used last)
    assert cache.get(rigs[3], SHAPE) is t3
    assert cache.get(rigs[4], SHAPE) is not t4  # built again
    # an entry larger than the budget is built and not kept
    small = _TriangulatorCache(size - 1)
    assert small.get(rig, SHAPE).rig is rig and len(small) == 0 and small.nbytes == 0
    # the module's cache has a budget of a few full-size cameras, not a count
    from telefringe.reconstruction import telecentric as tel

    assert tel._TRIANGULATORS.max_bytes == tel.TRIANGULATOR_CACHE_BYTES <= 64 * 2**20


def test_triangulator_cache_under_threads():
    from concurrent.futures import ThreadPoolExecutor

    from telefringe.reconstruction.telecentric import _TriangulatorCache

    rig = make_rig()
    X, up, vp = surface_points(rig)
    one = Triangulator.for_shape(rig, SHAPE)
    size = one.a.nbytes + one.b.nbytes + one.coef.nbytes
    rigs = [_shifted(rig, k) for k in range(6)]
    ref = [Triangulator.for_shape(r, SHAPE).triangulate(Coords(up)).xyz for r in rigs]
    cache = _TriangulatorCache(int(3.5 * size))
    seen = []

    def work(i):
        k = (7 * i) % len(rigs)
        tri = cache.get(rigs[k], SHAPE)
        seen.append(cache.nbytes)
        return k, tri.rig is rigs[k], tri.triangulate(Coords(up)).xyz

    with ThreadPoolExecutor(max_workers=8) as pool:
        out = list(pool.map(work, range(200)))
    for k, same_rig, xyz in out:
        assert same_rig
        np.testing.assert_array_equal(xyz, ref[k])
    assert max(seen) <= cache.max_bytes and len(cache) <= 3
    assert cache.nbytes == len(cache) * size


def test_rig_or_an_object_holding_one():
    rig = make_rig()
    X, up, vp = surface_points(rig)

    @dataclass(frozen=True)
    class Holder:
        rig: object

    expect = triangulate(rig, Coords(up)).xyz
    np.testing.assert_array_equal(triangulate(Holder(rig), Coords(up)).xyz, expect)

    @dataclass(frozen=True)
    class LooksLikeARig:  # duck typing is not taken
        camera: object
        projector: object

    for bad in (LooksLikeARig(rig.camera, rig.projector), Holder(rig.camera), rig.camera):
        with pytest.raises(TriangulationError, match="expected a telefringe.devices.rig.Rig"):
            triangulate(bad, Coords(up))
        with pytest.raises(TriangulationError, match="expected"):
            Triangulator.for_shape(bad, SHAPE)

    class Pinhole(TelecentricDevice):  # another device model: not for this triangulator,
        model = "pinhole"               # and it says so

    other = Pinhole(rig.projector.intrinsics, rig.projector.R_dev_world, rig.projector.t_dev)
    with pytest.raises(TriangulationError, match="telecentric projector.*'pinhole'"):
        triangulate(Rig(rig.camera, other), Coords(up))


# --- height map ------------------------------------------------------------------------
def plane_cloud(rig, coef=(0.05, -0.03, 0.2)):
    """Points where each camera line meets z = a x + b y + c."""
    tri = Triangulator.for_shape(rig, SHAPE)
    o = tri.line_points(np.zeros(SHAPE))
    d = tri.direction
    a, b, c = coef
    n = np.array([-a, -b, 1.0])
    s = (c - o @ n) / (d @ n)
    return tri.line_points(s)


def test_height_map_of_a_plane_is_exact():
    rig = make_rig()
    X = plane_cloud(rig)
    cloud = PointCloud.from_xyz(X, sigma_z=np.full(SHAPE, 0.002))
    hm = height_map(cloud, pixel_mm=0.02)
    assert isinstance(hm, HeightMap) and hm.z.dtype == np.float32
    yy, xx = np.meshgrid(hm.y, hm.x, indexing="ij")
    expect = 0.05 * xx - 0.03 * yy + 0.2
    ok = np.isfinite(hm.z)
    # the inner part of the footprint is covered
    assert ok.mean() > 0.8
    assert np.max(np.abs(hm.z[ok] - expect[ok])) < 1e-6  # float32 storage
    assert np.allclose(hm.sigma_z[ok], 0.002)
    # default pixel: the camera's footprint (0.03 mm pixels at m = 1)
    hm2 = height_map(cloud)
    assert hm2.pixel_mm == pytest.approx(0.03, rel=0.01)
    l, r, b, t = hm.extent
    assert l <= np.nanmin(X[..., 0]) and r >= np.nanmax(X[..., 0])
    assert b <= np.nanmin(X[..., 1]) and t >= np.nanmax(X[..., 1])


def test_height_map_of_a_sphere_within_interpolation_error():
    rig = make_rig()
    tri = Triangulator.for_shape(rig, SHAPE)
    o = tri.line_points(np.zeros(SHAPE))
    d = tri.direction
    c, R = np.array([0.2, -0.1, -5.0]), 6.0
    # nearest intersection with the sphere from the camera (largest z)
    w = o - c
    bq = w @ d
    disc = bq**2 - (np.sum(w * w, axis=-1) - R * R)
    s = -bq - np.sqrt(disc)
    X = tri.line_points(s)
    cloud = PointCloud.from_xyz(X)
    hm = height_map(cloud, pixel_mm=0.017)
    yy, xx = np.meshgrid(hm.y, hm.x, indexing="ij")
    expect = c[2] + np.sqrt(R * R - (xx - c[0]) ** 2 - (yy - c[1]) ** 2)
    ok = np.isfinite(hm.z)
    # linear interpolation on triangles of side h ~ 0.03*sqrt(2) mm of a surface with
    # curvature 1/R (slope < 0.5 here): error <= h^2 / (8 R) * (1 + slope^2)^1.5
    assert np.nanmax(np.hypot(X[..., 0] - c[0], X[..., 1] - c[1])) < 0.44 * R
    h = 0.03 * np.sqrt(2) * 1.05
    bound = h * h / (8 * R) * 1.25**1.5 + 1e-6
    assert ok.mean() > 0.8
    assert np.max(np.abs(hm.z[ok] - expect[ok])) < bound
    assert hm.sigma_z is None


def test_height_map_holes_and_errors():
    rig = make_rig()
    X = plane_cloud(rig).copy()
    X[40:60, 50:80] = np.nan
    cloud = PointCloud.from_xyz(X)
    hm = height_map(cloud, pixel_mm=0.03)
    # the hole stays a hole: world position of the hole's centre pixel
    xc, yc = plane_cloud(rig)[50, 65, :2]
    j = int(round((xc - hm.x0) / hm.pixel_mm))
    i = int(round((hm.y0 - yc) / hm.pixel_mm))
    assert np.isnan(hm.z[i, j])
    with pytest.raises(TriangulationError):
        height_map(cloud, pixel_mm=-1.0)
    with pytest.raises(TriangulationError, match="too large"):
        height_map(cloud, pixel_mm=1e-5)
    with pytest.raises(TriangulationError, match="fewer than 3"):
        height_map(PointCloud.from_xyz(np.full((4, 4, 3), np.nan)))


def test_binned_height_map():
    z = np.arange(35, dtype=np.float32).reshape(5, 7)
    z[0, 0] = np.nan
    z[3:5, 3:6] = np.nan  # a hole: the (partial, edge) block [2, 2] all NaN, others in part
    hm = HeightMap(z, 10.0, 20.0, 0.5, sigma_z=np.full((5, 7), 0.002, np.float32))
    b = hm.binned(2)
    assert b.z.shape == (3, 4) and b.pixel_mm == 1.0
    # each binned pixel sits at the centre of its block
    assert b.x[0] == pytest.approx(hm.x[:2].mean()) and b.y[0] == pytest.approx(hm.y[:2].mean())
    for i in range(3):
        for j in range(4):
            block = z[2 * i:2 * i + 2, 2 * j:2 * j + 2]
            fin = block[np.isfinite(block)]
            if fin.size:
                assert b.z[i, j] == pytest.approx(fin.mean())
            else:
                assert np.isnan(b.z[i, j])
    assert np.isnan(b.z[2, 2]) and b.z[0, 0] == pytest.approx((1 + 7 + 8) / 3)
    np.testing.assert_allclose(b.sigma_z[np.isfinite(b.z)], 0.002, rtol=1e-6)
    assert hm.binned(1) is hm
    with pytest.raises(TriangulationError, match="factor"):
        hm.binned(0)


def test_scan_radiance_takes_the_longest_unsaturated_exposure():
    from telefringe.fringes.images import scan_radiance
    from telefringe.fringes.scan import PhaseGroup, Scan, ScanManifest

    # two groups at exposure 1 and one at 0.25; the true radiance (DN at exposure 1) is
    # 100 on the left half and 400 (saturating exposure 1) on the right
    rad = np.array([[100.0, 100.0, 400.0, 400.0]] * 2)
    k = np.arange(4)[:, None, None]
    groups, stacks = [], []
    for periods, exposure in ((1, 1.0), (8, 1.0), (8, 0.25)):
        groups.append(PhaseGroup("u", periods, 4, exposure, 0.0,
                                 tuple(f"{periods}_{exposure}_{i}.png" for i in range(4))))
        img = exposure * rad * (1.0 + 0.5 * np.cos(np.pi * k / 2 + periods))
        stacks.append(np.clip(np.round(img), 0, 255).astype(np.uint8))
    scan = Scan(ScanManifest(64, 64, tuple(groups)), tuple(stacks))
    out = scan_radiance(scan)
    assert out.shape == (2, 4) and out.dtype == np.float32
    # left: mean of the 8 unsaturated images at exposure 1 (rounding to DN: <= 0.5 DN)
    assert np.allclose(out[:, :2], 100.0, atol=0.5)
    # right: exposure 1 saturates, so the 0.25 group divided by 0.25 (<= 0.5 / 0.25 DN)
    assert np.allclose(out[:, 2:], 400.0, atol=2.0)
    with pytest.raises(ValueError, match="no phase images"):
        scan_radiance(Scan(ScanManifest(64, 64, ()), ()))
