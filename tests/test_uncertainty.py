"""The calibration's uncertainty propagated into points and measurements.

- The point Jacobian (implicit function theorem through the Device protocol) against
  central differences of a re-triangulation, for the telecentric fast path (u only and
  both axes) and for a pinhole projector triangulated here by a 1-D root search.
- Central differences through a quantity (``propagate_fd``) against the linearised plane
  fit of ``plate_uncertainty``: their agreement bounds the error of both.
- A Monte Carlo on synthetic calibrations (no rendering: projected grid points plus
  seeded noise, as in test_calibrate.py): the rig is calibrated S times, the same exact
  decoded coordinates of three scenes (a tilted circle plate, a step gauge, a sphere on a
  plane) are triangulated with each calibrated rig and measured; each quantity's RMS
  deviation from its measurement with the true rig must match the predicted u_cal within
  4 sampling errors of a standard deviation from S samples (+-45 % with S = 40: a
  propagation wrong by 2x fails).
"""

from __future__ import annotations

import numpy as np
import pytest
from test_calibrate import (
    CAM_PIX,
    CAM_SIZE,
    PROJ_PIX,
    PROJ_SIZE,
    grid_points,
    observe,
    paper_like_rig,
    side_of,
    target_poses,
)

from telefringe.calibration.rig import calibrate_rig
from telefringe.calibration.uncertainty import (
    covariance_factor,
    point_jacobian,
    point_jacobian_fd,
    point_sigma,
    propagate_fd,
)
from telefringe.devices.rig import Rig
from telefringe.geometry.so3 import rotation_from_rotvec
from telefringe.metrology import measure_plate, measure_sphere, measure_steps
from telefringe.metrology.uncertainty import (
    Uncertainty,
    plate_uncertainty,
    sphere_uncertainty,
    steps_uncertainty,
)
from telefringe.reconstruction.telecentric import Triangulator, triangulate_pixels
from telefringe.simulate.scenes import Sphere, default_steps, plate_from_target
from telefringe.targets.grid import CircleGridTarget


def _calibrate(rig, rng, *, n_poses=6):
    P = grid_points(5, 6, pitch=5.0)
    Rs, Ts = target_poses(n_poses, rng, tilt_deg=15.0, centre=(12.5, 10.0, 0.0))
    cam, proj = observe(rig, P, Rs, Ts, rng)
    return calibrate_rig(P, cam, proj, camera_pixel_size=CAM_PIX,
                         projector_pixel_size=PROJ_PIX, camera_size=CAM_SIZE,
                         projector_size=PROJ_SIZE, outlier_threshold=np.inf,
                         projector_side=side_of(rig))


@pytest.fixture(scope="module")
def one_calibration():
    rig = paper_like_rig()
    return rig, _calibrate(rig, np.random.default_rng(7))


def _rig_of(cal, theta):
    nc = len(cal.rig.camera.param_names)
    return Rig(cal.rig.camera.from_params(theta[:nc]), cal.rig.projector.from_params(theta[nc:]))


def _random_points(rig, n, rng):
    X = np.column_stack([rng.uniform(2, 28, n), rng.uniform(2, 22, n), rng.uniform(-2, 2, n)])
    return X, rig.camera.project(X), rig.projector.project(X)


@pytest.mark.parametrize("both_axes", [False, True])
def test_point_jacobian_matches_retriangulation(one_calibration, both_axes):
    _, cal = one_calibration
    rng = np.random.default_rng(3)
    _, (uc, vc), (up, vp) = _random_points(cal.rig, 40, rng)
    vv = vp if both_axes else None

    def tri(theta):
        return triangulate_pixels(_rig_of(cal, theta), uc, vc, up, vv).xyz[0]

    X0 = tri(cal.parameters)
    L = covariance_factor(cal.covariance)
    J = point_jacobian(cal, X0, weight_v=1.0 if both_axes else 0.0) @ L
    # the differences' own error falls as the step squared (measured 1.9e-4, 1.9e-6 and
    # 1.9e-8 of the largest displacement at 1, 0.1 and 0.01 sigma): the analytic
    # Jacobian is exact to first order, and differences over +-1 sigma (propagate_fd's
    # step) are good to 2e-4
    for frac, bound in ((1.0, 4e-4), (0.01, 4e-8)):
        Jfd = point_jacobian_fd(tri, cal.parameters, steps=frac * cal.std) @ L
        err = np.max(np.abs(J - Jfd)) / np.max(np.abs(J))
        assert err < bound, (frac, err)
    # the per-point sigmas are those of the same Jacobian
    ps = point_sigma(cal, X0[None], cal.covariance, weight_v=1.0 if both_axes else 0.0)
    np.testing.assert_allclose(ps.calibration[0], np.sqrt(np.sum(J ** 2, axis=2)), rtol=1e-12)


def test_point_jacobian_any_device_model():
    """A pinhole projector (OpenCV's model) beside a telecentric camera: the implicit
    function Jacobian against differences of a triangulation by root search along the
    camera's line (written here: no triangulator for the pair is needed)."""
    from scipy.optimize import brentq

    from telefringe.devices.pinhole import PinholeDevice, PinholeIntrinsics

    tele = paper_like_rig()
    cam = tele.camera
    R = tele.projector.R_dev_world  # looking at the scene like the telecentric one
    centre_world = np.array([15.0, 12.0, 0.0]) - 200.0 * R[2]
    intr = PinholeIntrinsics(fx=4000.0, fy=4000.0, cx=400.0, cy=300.0, k1=0.05, k2=-0.1,
                             p1=0.001, p2=0.0005, width=800, height=600)
    proj = PinholeDevice(intr, R, -R @ centre_world)
    rig = Rig(cam, proj)
    rng = np.random.default_rng(5)
    X, (uc, vc), (up, _) = _random_points(rig, 12, rng)
    nc = len(cam.param_names)

    def tri(theta):
        c = cam.from_params(theta[:nc])
        p = proj.from_params(theta[nc:])
        o, d = c.backproject(uc, vc)
        d = np.broadcast_to(d, o.shape)
        out = []
        for k in range(uc.size):
            s0 = float((X[k] - o[k]) @ d[k])

            def f(s, k=k):
                return float(p.project((o[k] + s * d[k])[None])[0][0] - up[k])

            out.append(o[k] + brentq(f, s0 - 5, s0 + 5, xtol=1e-13, rtol=1e-15) * d[k])
        return np.array(out)

    theta = np.concatenate([cam.to_params(), proj.to_params()])
    steps = np.abs(theta) * 1e-6 + 1e-6
    X0 = tri(theta)
    np.testing.assert_allclose(X0, X, atol=1e-9)
    J = point_jacobian(rig, X0)
    Jfd = point_jacobian_fd(tri, theta, steps=steps)
    # compared as the displacements the steps cause (mm): the root search's 1e-13 mm
    # tolerance does not get divided by the step then
    D, Dfd = J * steps, Jfd * steps
    err = np.max(np.abs(D - Dfd), axis=(0, 1))
    scale = np.max(np.abs(D), axis=(0, 1))
    print("pinhole projector: largest displacement error", err.max(), "mm; relative",
          np.max(err / np.maximum(scale, 1e-300)))
    assert np.all(err <= 1e-4 * scale + 1e-12), err / np.maximum(scale, 1e-300)


# --------------------------------------------------------------------------- scenes
STRIDE = 8  # camera pixels between the scenes' samples (a 160 x 128 grid)
TARGET = CircleGridTarget(rows=9, cols=11, pitch_mm=3.0, diameter_mm=1.5)


SIGMA_P = 0.01  # projector px, the decoded coordinates' noise (one draw, every rig)


def _coords(rig, scene, seed):
    """Decoded coordinates of ``scene`` on a strided camera grid, with one draw of noise:
    (u, v, u_p, v_p, true points)."""
    v, u = np.mgrid[0:CAM_SIZE[1]:STRIDE, 0:CAM_SIZE[0]:STRIDE].astype(float)
    o, d = rig.camera.backproject(u, v)
    start = o - 200.0 * d
    hits = scene.intersect(start.reshape(-1, 3), d)
    X = start.reshape(-1, 3) + hits.t[:, None] * d
    X[~hits.hit] = np.nan
    X = X.reshape(u.shape + (3,))
    up, vp = rig.projector.project(X)
    rng = np.random.default_rng(seed)
    up = up + rng.normal(0.0, SIGMA_P, up.shape)
    vp = vp + rng.normal(0.0, SIGMA_P, vp.shape)
    return u, v, up, vp, X


def _cloud(rig, c):
    u, v, up, vp, _ = c

    class Coords:
        pass

    k = Coords()
    k.u_p, k.v_p, k.mask = up, vp, np.isfinite(up)
    k.sigma_u_p = k.sigma_v_p = np.full(up.shape, SIGMA_P)
    return Triangulator.for_pixels(rig, u, v).triangulate(k, max_residual=None,
                                                          check_bounds=False)


@pytest.fixture(scope="module")
def scenes():
    rig = paper_like_rig()
    c_t = np.array([(TARGET.cols - 1) * 1.5, (TARGET.rows - 1) * 1.5, 0.0])
    R = rotation_from_rotvec(np.radians([5.0, -3.0, 2.0]))
    plate = plate_from_target(TARGET, R, c_t + np.array([0.4, -0.2, 0.6]) - R @ c_t)
    out = {"plate": _coords(rig, plate, 1), "steps": _coords(rig, default_steps(), 2),
           "sphere": _coords(rig, Sphere(center=np.array([15.0, 12.0, -1.0]), radius=2.5),
                             3)}
    # the plate's marker centres in the (strided) camera image, from the truth
    centres = plate.circle_centres_world()
    uc, vc = rig.camera.project(centres)
    out["plate_centres"] = np.column_stack([uc, vc]) / STRIDE
    return rig, out


def _measure(cal, scenes):
    """Quantities of the three scenes measured with ``cal``'s rig: dict name ->
    Uncertainty."""
    rig = cal.rig
    out = {}
    cloud = _cloud(rig, scenes["plate"])
    m = plate_uncertainty(measure_plate(cloud, scenes["plate_centres"], rows=9, cols=11,
                                        pitch_mm=3.0), cloud, cal)
    for k in ("z", "tilt_deg", "spacing_x", "spacing_y"):
        out[f"plate {k}"] = m.uncertainty[k]
    cloud = _cloud(rig, scenes["steps"])
    m = steps_uncertainty(measure_steps(cloud, min_points=50), cloud, cal)
    out["step heights"] = m.uncertainty["step_heights"]
    cloud = _cloud(rig, scenes["sphere"])
    m = sphere_uncertainty(measure_sphere(cloud), cloud, cal)
    out["sphere radius"] = m.uncertainty["radius"]
    out["sphere centre"] = m.uncertainty["centre"]
    return out


class _TrueCal:
    def __init__(self, rig, like):
        self.rig = rig
        self.covariance = like.covariance
        self.parameter_names = like.parameter_names


def test_plane_linearisation_matches_refits(one_calibration, scenes):
    """plate_uncertainty's linearised plane (Z at the centroid) against central
    differences of plane refits on re-triangulated points (the same pixels and weights:
    what the linearisation stands for)."""
    from telefringe.metrology.planes import Plane, fit_plane, plane_distance
    from telefringe.metrology.uncertainty import _fd_params, _perturbed_plane, _plane_jacobian

    _, cal = one_calibration
    _, sc = scenes
    L = covariance_factor(cal.covariance)[:, :6]  # the six largest principal directions
    cloud = _cloud(cal.rig, sc["plate"])
    m = measure_plate(cloud, sc["plate_centres"], rows=9, cols=11, pitch_mm=3.0)
    pl = m.plane
    sel = np.zeros(cloud.shape, dtype=bool)
    sel[cloud.mask] = pl.inliers
    w = 1.0 / cloud.sigma_z[sel] ** 2

    def z_refit(theta):
        c2 = _cloud(_rig_of(cal, theta), sc["plate"])
        f = fit_plane(c2.xyz[sel], weights=w)
        return plane_distance(f, Plane.horizontal(0.0)).distance

    h = 0.1  # a tenth of a sigma: the differences' own error 1e-2 of that at one sigma
    G = np.array([(z_refit(cal.parameters + h * L[:, k])
                   - z_refit(cal.parameters - h * L[:, k])) / (2 * h)
                  for k in range(L.shape[1])])
    Jp = _plane_jacobian(cal, cloud.xyz[sel], w, pl.normal, pl.centroid, pl.tangent, 1.0)

    def z_of(dp):
        n, d, c = _perturbed_plane(pl.normal, pl.offset, pl.centroid, pl.tangent, dp)
        return [plane_distance(Plane(n, d), Plane.horizontal(0.0), at=c).distance]

    Glin = _fd_params(z_of, Jp, L)[0]
    err = np.max(np.abs(Glin - G)) / np.max(np.abs(G))
    # measured 1.2e-4 (1.5e-3 with differences over one sigma): what the linearisation
    # leaves out, the points' residuals (the noise) times the fit's curvature
    print("plane linearisation: relative error", err)
    assert err < 2.5e-4, (Glin, G)
    # propagate_fd is exact for a linear quantity
    rng = np.random.default_rng(1)
    X, Jx = rng.normal(size=(5, 3)), rng.normal(size=(5, 3, L.shape[0]))
    Gf = propagate_fd(lambda P: P.sum(axis=0), X, Jx, L)
    np.testing.assert_allclose(Gf, Jx.sum(axis=0) @ L, rtol=1e-10, atol=1e-18)


def test_uncertainty_dataclass():
    u = Uncertainty(1.0, 3e-3, 4e-3)
    assert u.u == pytest.approx(5e-3) and u.U == pytest.approx(1e-2) and u.k == 2.0
    v = Uncertainty(np.array([1.0, 2.0]), np.nan, np.array([1e-3, 2e-3]))
    np.testing.assert_allclose(v.u, [1e-3, 2e-3])
    assert np.isnan(Uncertainty(0.0, np.nan, np.nan).u)


def test_monte_carlo_over_calibrations(scenes):
    """S synthetic calibrations (6 poses, 5 x 6 grid): each quantity's RMS deviation
    from the true rig's measurement against the predicted u_cal."""
    rig0, sc = scenes
    S = 40
    rng = np.random.default_rng(2026)
    cals = [_calibrate(rig0, rng) for _ in range(S)]
    ref = _measure(_TrueCal(rig0, cals[0]), sc)
    dev = {k: [] for k in ref}
    pred = {k: [] for k in ref}
    for cal in cals:
        q = _measure(cal, sc)
        for k in ref:
            dev[k].append(np.ravel(q[k].value) - np.ravel(ref[k].value))
            pred[k].append(np.ravel(q[k].u_calibration))
    se = 1.0 / np.sqrt(2 * (S - 1))
    report = {}
    for k in ref:
        d = np.array(dev[k])
        p = np.median(np.array(pred[k]), axis=0)
        # each component on its own (the components of a vector are correlated)
        ratio = np.sqrt(np.mean(d ** 2, axis=0)) / p
        report[k] = np.round(ratio, 3)
    print(report)
    for k, ratio in report.items():
        assert np.all(np.abs(ratio - 1) < 4 * se), (k, ratio, report)


@pytest.mark.parametrize("mix", ["tt", "tp", "pt", "pp"])
@pytest.mark.parametrize("both_axes", [False, True])
def test_point_jacobian_every_device_mix(mix, both_axes):
    """Every camera + projector mix of the Device protocol (telecentric, pinhole): the
    implicit-function Jacobian against central differences of the generic triangulator
    (re-triangulating the same observations with perturbed parameters)."""
    from anyrig_rigs import rig_of, surface_truth

    from telefringe.reconstruction import generic

    rig = rig_of(mix)
    X, up, vp = surface_truth(rig)
    rows = np.array([4, 20, 30, 40, 11])
    cols = np.array([3, 10, 50, 33, 60])
    u_c, v_c = cols.astype(float), rows.astype(float)
    nc = len(rig.camera.param_names)
    theta = np.concatenate([rig.camera.to_params(), rig.projector.to_params()])

    def tri(th):
        r = Rig(rig.camera.from_params(th[:nc]), rig.projector.from_params(th[nc:]))
        return generic.triangulate_pixels(r, u_c, v_c, up[rows, cols],
                                          vp[rows, cols] if both_axes else None).xyz[0]

    X0 = tri(theta)
    np.testing.assert_allclose(X0, X[rows, cols], atol=1e-8)
    steps = 1e-5 * np.maximum(np.abs(theta), 1e-2)
    J = point_jacobian(rig, X0, weight_v=1.0 if both_axes else 0.0)
    D, Dfd = J * steps, point_jacobian_fd(tri, theta, steps=steps) * steps
    err = np.max(np.abs(D - Dfd), axis=(0, 1))
    scale = np.max(np.abs(D), axis=(0, 1))
    print(mix, both_axes, "largest displacement error", err.max(), "mm; of the largest",
          err.max() / scale.max())
    # measured: at most 3e-10 of the largest displacement, 5e-14 mm
    assert np.all(err <= 1e-6 * scale + 1e-12), (err, scale)
