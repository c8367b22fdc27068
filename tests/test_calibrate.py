"""Calibration numerics on synthetic observations made with telefringe.model directly.

A paper-like rig (Tables 1 and 2 of the paper, world z toward the camera) observes a
9 x 11 grid at known poses; seeded Gaussian noise is added to the projected centres.
Tolerances are k standard deviations of the estimate, the standard deviations coming
from the calibration's own covariance (itself checked against Monte Carlo below).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from telefringe.calibration.device import _obs_from_array, calibrate_device
from telefringe.calibration.errors import CalibrationError
from telefringe.calibration.problem import BundleProblem
from telefringe.calibration.rig import calibrate_rig
from telefringe.calibration.solver import levenberg_marquardt
from telefringe.calibration.start_telecentric import (
    MirrorAmbiguityError,
    closed_form_device,
    mirror_pose,
)
from telefringe.devices.rig import Rig
from telefringe.devices.telecentric import Intrinsics, TelecentricDevice
from telefringe.geometry.so3 import left_jacobian, rotation_from_rotvec, skew

CAM_PIX = (0.0052, 0.0052)
PROJ_PIX = (0.0137, 0.0137)
CAM_SIZE = (1280, 1024)
PROJ_SIZE = (800, 600)
SIGMA_CAM = 0.02  # px
SIGMA_PROJ = 0.008  # projector px
_FLIP = np.diag([1.0, -1.0, -1.0])  # paper frame (z along the camera axis) -> z toward camera


# --------------------------------------------------------------------------- helpers
def paper_like_rig(*, distortion=True) -> Rig:
    Rc = rotation_from_rotvec([-0.09134, 0.16807, -3.04052]) @ _FLIP
    Rp = rotation_from_rotvec([-0.78604, 0.06802, -3.10345]) @ _FLIP
    f = 1.0 if distortion else 0.0
    kc = Intrinsics(m=0.1597, du=CAM_PIX[0], dv=CAM_PIX[1], u0=474.92, v0=513.08,
                    k1=2e-4 * f, s1=3e-4 * f, s2=-2e-4 * f, width=1280, height=1024)
    kp = Intrinsics(m=0.11733, du=PROJ_PIX[0], dv=PROJ_PIX[1], u0=460.33, v0=468.24,
                    k1=1.3e-4 * f, s1=2e-4 * f, s2=-3e-4 * f, width=800, height=600)
    centre = np.array([15.0, 12.0, 0.0])

    def t_for(R, k, pix):
        return (np.array(pix) - (k.u0, k.v0)) * (k.du, k.dv) / k.m - R[:2] @ centre

    return Rig(TelecentricDevice(kc, Rc, t_for(Rc, kc, (639.5, 511.5))),
               TelecentricDevice(kp, Rp, t_for(Rp, kp, (399.5, 299.5))))


def grid_points(rows=9, cols=11, pitch=3.0) -> np.ndarray:
    r, c = np.mgrid[0:rows, 0:cols]
    return np.stack([c.ravel() * pitch, r.ravel() * pitch, np.zeros(r.size)], axis=1)


def target_poses(n, rng, *, tilt_deg=12.0, centre=(15.0, 12.0, 0.0)):
    """Pose 0 = identity (the reference); the others tilted about axes spread around the
    circle, so that half of them fall on each side of every device's mirror ambiguity."""
    centre = np.asarray(centre, dtype=float)
    Rs, Ts = [np.eye(3)], [np.zeros(3)]
    for i in range(1, n):
        ang = np.radians(tilt_deg) * (0.5 + 0.5 * rng.random())
        phi = 2 * np.pi * i / (n - 1) + 0.3 * rng.random()
        R = (rotation_from_rotvec(ang * np.array([np.cos(phi), np.sin(phi), 0.0]))
             @ rotation_from_rotvec([0.0, 0.0, np.radians(8.0) * (rng.random() - 0.5)]))
        T = centre - R @ centre + np.array([*rng.normal(0.0, 1.0, 2), rng.uniform(-2, 2)])
        Rs.append(R)
        Ts.append(T)
    return np.array(Rs), np.array(Ts)


def observe(rig, P, Rs, Ts, rng, *, sc=SIGMA_CAM, sp=SIGMA_PROJ):
    cam, proj = [], []
    for R, T in zip(Rs, Ts, strict=True):
        X = P @ R.T + T
        cam.append(np.stack(rig.camera.project(X), 1) + rng.normal(0, sc, (len(P), 2)))
        proj.append(np.stack(rig.projector.project(X), 1) + rng.normal(0, sp, (len(P), 2)))
    return np.array(cam), np.array(proj)


def triangulate(rig: Rig, uv_cam, uv_proj) -> np.ndarray:
    """Eq. 8 with both projector coordinates: 4 linear equations in X, least squares.

    uv_cam, uv_proj : (n, 2) px. Returns (n, 3) world mm.
    """
    out = []
    for dev, uv in ((rig.camera, uv_cam), (rig.projector, uv_proj)):
        u, v = dev.undistort(uv[:, 0], uv[:, 1])
        k = dev.intrinsics
        xu = (u - k.u0) * k.du / k.m - dev.t_dev[0]
        yu = (v - k.v0) * k.dv / k.m - dev.t_dev[1]
        out.append((dev.R_dev_world[:2], np.stack([xu, yu], 1)))
    A = np.vstack([out[0][0], out[1][0]])
    b = np.hstack([out[0][1], out[1][1]])  # (n, 4)
    return np.linalg.lstsq(A, b.T, rcond=None)[0].T


def side_of(rig: Rig) -> str:
    """Where the projector is in the camera image (the truth for ``projector_side``)."""
    a = (rig.projector.R_dev_world @ rig.camera.R_dev_world.T)[2, :2]
    sides = {"left": (-1, 0), "right": (1, 0), "top": (0, -1), "bottom": (0, 1)}
    return min(sides, key=lambda s: float(a @ np.array(sides[s])))


def synthetic_calibration(seed: int = 11, *, outlier_threshold=None):
    """A RigCalibration of a paper-like rig from 6 synthetic poses of a 5 x 6 grid
    (projected points plus noise, no rendering): a parameter covariance of the right kind
    for tests that propagate one through another telecentric rig."""
    rng = np.random.default_rng(seed)
    rig0 = paper_like_rig()
    P = grid_points(5, 6, pitch=5.0)
    Rs, Ts = target_poses(6, rng, tilt_deg=15.0, centre=(12.5, 10.0, 0.0))
    cam, proj = observe(rig0, P, Rs, Ts, rng)
    kw = {} if outlier_threshold is None else {"outlier_threshold": outlier_threshold}
    return calibrate_rig(P, cam, proj, camera_pixel_size=CAM_PIX, projector_pixel_size=PROJ_PIX,
                         camera_size=CAM_SIZE, projector_size=PROJ_SIZE,
                         projector_side=side_of(rig0), **kw)


def rig_truth_vector(rig: Rig) -> np.ndarray:
    """True rig parameters in the order of RigCalibration.parameter_names (rotations:
    zeros), written out here rather than taken from the device's to_params."""
    out = []
    for d in (rig.camera, rig.projector):
        k = d.intrinsics
        out += [k.m, k.u0, k.v0, k.k1, k.s1, k.s2, 0.0, 0.0, 0.0, *d.t_dev]
    return np.array(out)


def rig_errors(calib, truth: Rig) -> np.ndarray:
    """Estimate - truth for every rig parameter (rotations as left perturbations)."""
    err = calib.parameters - rig_truth_vector(truth)
    for j, (est, tru) in enumerate(((calib.rig.camera, truth.camera),
                                    (calib.rig.projector, truth.projector))):
        dR = tru.R_dev_world @ est.R_dev_world.T  # truth = dR est
        w = 0.5 * np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]])
        i = calib.parameter_names.index(f"{('camera', 'projector')[j]}.rot_x")
        err[i:i + 3] = -w
    return err


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(20240611)
    rig = paper_like_rig()
    P = grid_points()
    Rs, Ts = target_poses(12, rng)
    cam, proj = observe(rig, P, Rs, Ts, rng)
    # pose 5: the grid half hidden (left half of the markers not seen by either device)
    hidden = (P[:, 0] < 15.0)
    cam[5, hidden] = np.nan
    proj[5, hidden] = np.nan
    return dict(rig=rig, P=P, Rs=Rs, Ts=Ts, cam=cam, proj=proj)


@pytest.fixture(scope="module")
def calibrated(scene):
    return calibrate_rig(scene["P"], scene["cam"], scene["proj"], camera_pixel_size=CAM_PIX,
                         projector_pixel_size=PROJ_PIX, camera_size=CAM_SIZE,
                         projector_size=PROJ_SIZE, grid_shape=(9, 11),
                         pose_names=[f"pose_{i:02d}" for i in range(12)],
                         projector_side=side_of(scene["rig"]))


# --------------------------------------------------------------------------- derivatives
def test_rotation_helpers():
    rng = np.random.default_rng(1)
    for _ in range(5):
        w = rng.normal(size=3) * 1.5
        x = rng.normal(size=3)
        J = left_jacobian(w)
        eps = 1e-6
        num = np.column_stack([(rotation_from_rotvec(w + eps * e) @ x
                                - rotation_from_rotvec(w - eps * e) @ x) / (2 * eps)
                               for e in np.eye(3)])
        ana = -skew(rotation_from_rotvec(w) @ x) @ J
        np.testing.assert_allclose(ana, num, atol=1e-8)
    R = rotation_from_rotvec([0.2, -0.1, 2.5])
    M = mirror_pose(R)
    np.testing.assert_allclose(M[:2, :2], R[:2, :2])
    np.testing.assert_allclose(M[:2, 2], -R[:2, 2])
    assert np.isclose(np.linalg.det(M), 1.0)


def _joint_problem(scene, *, poses=range(12)):
    poses = list(poses)
    rig = scene["rig"]
    keep = np.ones(scene["cam"].shape[:2], dtype=bool)
    obs = [_obs_from_array(scene["cam"], poses, keep),
           _obs_from_array(scene["proj"], poses, keep)]
    free = np.ones(22 + 6 * len(poses), dtype=bool)  # 11 per device, 6 per pose
    free[22:28] = False  # the reference pose
    return BundleProblem(scene["P"], obs, [rig.camera, rig.projector], scene["Rs"][poses],
                         scene["Ts"][poses], sigmas=[SIGMA_CAM, SIGMA_PROJ], free=free,
                         priors=[("camera.u0", 639.5, 800.0), ("projector.u0", 399.5, 500.0)])


def test_analytic_jacobian_matches_finite_differences(scene, jacobian_error):
    problem = _joint_problem(scene, poses=[0, 1, 2, 3])
    rng = np.random.default_rng(3)
    x = problem.x0 + rng.normal(0, 1e-3, problem.x0.size) * np.maximum(np.abs(problem.x0), 1e-3)
    assert jacobian_error(problem, x) < 1e-5


def test_levenberg_marquardt_reaches_the_scipy_minimum(scene):
    """Our LM and scipy's MINPACK LM land on the same minimum (to 1e-4 sigma)."""
    problem = _joint_problem(scene, poses=range(6))
    x0 = problem.x0 * (1 + 1e-4)
    problem.full0[problem.free] = x0
    ours = levenberg_marquardt(problem._evaluate, x0)
    ref = least_squares(problem.residuals, x0, jac=lambda x: problem.jacobian(x).toarray(),
                        method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=5000)
    cov, _ = problem.covariance(ref.x)
    sd = np.sqrt(np.diag(cov))
    assert np.max(np.abs(ours.x - ref.x) / sd) < 1e-4
    assert ours.cost <= 2 * ref.cost * (1 + 1e-12)


# --------------------------------------------------------------------------- closed form
def test_closed_form_is_exact_without_noise_or_distortion():
    rng = np.random.default_rng(7)
    rig = paper_like_rig(distortion=False)
    P = grid_points()
    Rs, Ts = target_poses(8, rng)
    cam, _ = observe(rig, P, Rs, Ts, rng, sc=0.0, sp=0.0)
    k = rig.camera.intrinsics
    st = closed_form_device(P, cam, pixel_size=CAM_PIX, principal_point=(k.u0, k.v0))
    assert st.usable.all()
    assert abs(st.m - k.m) < 1e-12
    for i in range(8):
        R_true = rig.camera.R_dev_world @ Rs[i]
        R = st.R_dev_target[i]
        # one of the two mirror tilts, exactly
        d = min(np.abs(R - R_true).max(), np.abs(mirror_pose(R) - R_true).max())
        assert d < 1e-9
        t_true = rig.camera.R_dev_world[:2] @ Ts[i] + rig.camera.t_dev
        np.testing.assert_allclose(st.t_dev[i], t_true, atol=1e-9)
    assert np.all(st.affine_rms < 1e-9)


def test_closed_form_start_is_close_on_the_paper_like_rig(scene):
    """With distortion and noise the closed form is a start, not an answer: m within
    0.5 %; every pose's rotation near one of its mirror tilts. The affine fit's relative
    error eps ~ 3 rms / extent perturbs cos(tilt) by eps, so near-frontal poses (the
    worst) get the tilt within sqrt(2 eps)."""
    rig = scene["rig"]
    st = closed_form_device(scene["P"], scene["cam"], pixel_size=CAM_PIX,
                            principal_point=(639.5, 511.5))
    assert abs(st.m / rig.camera.intrinsics.m - 1) < 5e-3
    for i in np.flatnonzero(st.usable):
        R_true = rig.camera.R_dev_world @ scene["Rs"][i]
        ang = [np.degrees(np.arccos(np.clip((np.trace(R.T @ R_true) - 1) / 2, -1, 1)))
               for R in (st.R_dev_target[i], mirror_pose(st.R_dev_target[i]))]
        eps = 3 * st.affine_rms[i] / np.ptp(scene["cam"][i][np.isfinite(scene["cam"][i])])
        assert min(ang) < np.degrees(np.sqrt(2 * eps))


# --------------------------------------------------------------------------- one device
def test_device_calibration_recovers_the_camera(scene):
    rig = scene["rig"]
    cal = calibrate_device(scene["P"], scene["cam"], pixel_size=CAM_PIX, image_size=CAM_SIZE,
                           name="camera")
    k, kt = cal.intrinsics, rig.camera.intrinsics
    est = np.array([k.m, k.u0, k.v0, k.k1, k.s1, k.s2])
    tru = np.array([kt.m, kt.u0, kt.v0, kt.k1, kt.s1, kt.s2])
    assert np.all(np.abs(est - tru) < 5 * cal.std)
    # a 2-D error length of N(0, s^2 I) has RMS s sqrt(2)
    assert abs(cal.rms / (SIGMA_CAM * np.sqrt(2)) - 1) < 0.1
    assert not cal.principal_point_weak
    assert cal.outliers == ()
    # the pose with half the grid hidden is used, its hidden markers have no residual
    assert cal.used[5] and np.isnan(cal.residuals[5, 0, 0])


def test_fixed_principal_point_and_weak_flag():
    rng = np.random.default_rng(11)
    rig = paper_like_rig(distortion=False)
    P = grid_points()
    Rs, Ts = target_poses(6, rng)
    cam, _ = observe(rig, P, Rs, Ts, rng)
    free = calibrate_device(P, cam, pixel_size=CAM_PIX, image_size=CAM_SIZE)
    assert free.principal_point_weak  # no distortion: only the prior holds (u0, v0)
    fixed = calibrate_device(P, cam, pixel_size=CAM_PIX, image_size=CAM_SIZE,
                             principal_point="fixed", principal_point_value=(600.0, 500.0))
    assert (fixed.intrinsics.u0, fixed.intrinsics.v0) == (600.0, 500.0)
    assert np.isnan(fixed.std[1]) and np.isnan(fixed.std[2])
    # without distortion a wrong principal point costs nothing
    assert abs(fixed.rms - free.rms) < 1e-3 * free.rms


# --------------------------------------------------------------------------- the rig
def test_rig_recovers_the_truth_within_its_uncertainty(scene, calibrated):
    cal = calibrated
    err = rig_errors(cal, scene["rig"])
    z = err / cal.std
    bad = {n: round(float(v), 2) for n, v in zip(calibrated.parameter_names, z, strict=True)
           if abs(v) > 5}
    assert not bad, bad
    assert cal.mirror == f"projector_side={side_of(scene['rig'])}"
    assert abs(cal.sigma_camera / SIGMA_CAM - 1) < 0.1
    assert abs(cal.sigma_projector / SIGMA_PROJ - 1) < 0.1
    assert abs(cal.rms_camera / (SIGMA_CAM * np.sqrt(2)) - 1) < 0.1
    assert abs(cal.rms_projector / (SIGMA_PROJ * np.sqrt(2)) - 1) < 0.1
    assert cal.used.all() and cal.outliers == ()
    # every pose lands where it was (the sign ambiguity of each pose resolved)
    for i in range(12):
        R_err = np.degrees(np.arccos(np.clip(
            (np.trace(cal.R_world_target[i].T @ scene["Rs"][i]) - 1) / 2, -1, 1)))
        assert R_err < 0.01
        assert np.abs(cal.t_world_target[i] - scene["Ts"][i]).max() < 2e-3
    assert cal.rms_per_pose.shape == (12, 2) and np.all(np.isfinite(cal.rms_per_pose))
    assert cal.reference_pose == "pose_00"


def test_mirror_ambiguity_resolved_by_the_projector_side(scene, calibrated):
    """A held-out plate 1 mm above the reference triangulates to +1 mm with the true
    side, -1 mm (the mirror world) with the opposite side; the images are identical."""
    rig = scene["rig"]
    P = scene["P"]
    X = P + [0.0, 0.0, 1.0]
    rng = np.random.default_rng(5)
    cam, proj = observe(rig, P, np.eye(3)[None], np.array([[0, 0, 1.0]]), rng, sc=0, sp=0)
    xyz = triangulate(calibrated.rig, cam[0], proj[0])
    assert np.sqrt(np.mean(np.sum((xyz - X) ** 2, axis=1))) < 1e-3
    opposite = {"left": "right", "right": "left", "top": "bottom", "bottom": "top"}
    other = calibrate_rig(scene["P"], scene["cam"], scene["proj"], camera_pixel_size=CAM_PIX,
                          projector_pixel_size=PROJ_PIX, camera_size=CAM_SIZE,
                          projector_size=PROJ_SIZE, projector_side=opposite[side_of(rig)])
    assert abs(other.rms_camera - calibrated.rms_camera) < 1e-6
    assert abs(other.rms_projector - calibrated.rms_projector) < 1e-6
    z = triangulate(other.rig, cam[0], proj[0])[:, 2]
    assert np.all(np.abs(z + 1.0) < 2e-3)
    # no side given: no guess (any convention is a coin toss on someone's rig)
    with pytest.raises(MirrorAmbiguityError, match="shadow falls away from the projector"):
        calibrate_rig(scene["P"], scene["cam"], scene["proj"], camera_pixel_size=CAM_PIX,
                      projector_pixel_size=PROJ_PIX, camera_size=CAM_SIZE,
                      projector_size=PROJ_SIZE)


def test_outliers_are_rejected_and_reported(scene):
    cam = scene["cam"].copy()
    proj = scene["proj"].copy()
    cam[3, 14] += (0.8, -0.5)  # marker (1, 3) of pose_03
    proj[7, 50] += (0.0, 0.3)  # marker (4, 6) of pose_07
    cal = calibrate_rig(scene["P"], cam, proj, camera_pixel_size=CAM_PIX,
                        projector_pixel_size=PROJ_PIX, camera_size=CAM_SIZE,
                        projector_size=PROJ_SIZE, grid_shape=(9, 11),
                        pose_names=[f"pose_{i:02d}" for i in range(12)],
                        projector_side=side_of(scene["rig"]))
    found = {(o.device, o.pose, o.marker) for o in cal.outliers}
    assert ("camera", "pose_03", (1, 3)) in found
    assert ("projector", "pose_07", (4, 6)) in found
    assert len(found) <= 4  # at most a couple of honest 5-sigma events besides
    assert np.isnan(cal.residuals_camera[3, 14, 0])
    assert abs(cal.rms_camera / (SIGMA_CAM * np.sqrt(2)) - 1) < 0.1


def test_uncertainty_matches_monte_carlo():
    """The covariance against 100 noisy repeats (small grid and few poses for speed): each
    parameter's observed spread against its predicted standard deviation, and the
    Mahalanobis distance of each repeat's error under its own covariance (chi-square)."""
    rng = np.random.default_rng(2024)
    rig = paper_like_rig()
    P = grid_points(5, 6, pitch=5.0)
    Rs, Ts = target_poses(6, rng, tilt_deg=15.0, centre=(12.5, 10.0, 0.0))
    n_rep = 100
    errs, stds, d2 = [], [], []
    for _ in range(n_rep):
        cam, proj = observe(rig, P, Rs, Ts, rng)
        cal = calibrate_rig(P, cam, proj, camera_pixel_size=CAM_PIX,
                            projector_pixel_size=PROJ_PIX, camera_size=CAM_SIZE,
                            projector_size=PROJ_SIZE, outlier_threshold=np.inf,
                            projector_side=side_of(rig))
        e = rig_errors(cal, rig)
        errs.append(e)
        stds.append(cal.std)
        d2.append(float(e @ np.linalg.solve(cal.covariance, e)))
    errs, stds = np.array(errs), np.array(stds)
    k = errs.shape[1]  # every rig parameter is free here (the principal point has a prior)
    ratio = errs.std(axis=0) / stds.mean(axis=0)
    # sampling error of a standard deviation from n samples: 1/sqrt(2(n - 1)) = 7 %; the
    # bound is 4 of it (22 parameters compared)
    se = 1.0 / np.sqrt(2 * (n_rep - 1))
    assert np.all(np.abs(ratio - 1) < 4 * se), dict(zip(cal.parameter_names, ratio,
                                                        strict=True))
    # sum of n chi-square(k) variables: mean k n, sd sqrt(2 k n); bound 4 sd
    mean_d2 = np.mean(d2) / k
    print(f"spread / predicted {ratio.min():.3f}..{ratio.max():.3f}, mean d2 / k {mean_d2:.4f}")
    assert abs(mean_d2 - 1) < 4 * np.sqrt(2.0 / (k * n_rep)), mean_d2


# --------------------------------------------------------------------------- degenerate
def test_degenerate_inputs_raise(scene):
    P = scene["P"]
    same_cam = np.repeat(scene["cam"][1:2], 6, axis=0)
    same_proj = np.repeat(scene["proj"][1:2], 6, axis=0)
    kw = dict(camera_pixel_size=CAM_PIX, projector_pixel_size=PROJ_PIX,
              camera_size=CAM_SIZE, projector_size=PROJ_SIZE,
              projector_side=side_of(scene["rig"]))
    with pytest.raises(CalibrationError, match="same tilt"):
        calibrate_rig(P, same_cam, same_proj, **kw)
    with pytest.raises(CalibrationError, match="at least 4"):
        calibrate_rig(P, scene["cam"][:3], scene["proj"][:3], **kw)
    cam = scene["cam"].copy()
    cam[0] = np.nan
    with pytest.raises(CalibrationError, match="reference pose"):
        calibrate_rig(P, cam, scene["proj"], **kw)
    with pytest.raises(CalibrationError, match=r"\(n_poses, 99, 2\)"):
        calibrate_rig(P, scene["cam"][:, :50], scene["proj"], **kw)
    with pytest.raises(ValueError, match="projector_side"):
        calibrate_rig(P, scene["cam"], scene["proj"], **{**kw, "projector_side": "up"})
