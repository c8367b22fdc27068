"""A camera and a projector calibrated jointly over one set of target poses.

Units: mm in the world and on sensors, px in images, radians. Reprojection "RMS" is the
root mean square of the 2-D error length over points (px of the device). The principal
point is only seen through the distortion (a shift of the principal point is otherwise a
shift of t); it is estimated with a weak prior at the image centre (default) or held
fixed, and flagged as weak when no distortion coefficient is significant or its standard
deviation exceeds 1 % of the image diagonal (a weak principal point costs little
accuracy, since it then barely changes any image).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from telefringe.calibration.device import (
    DeviceCalibration,
    Outlier,
    _adjust_with_rejection,
    _pp_setup,
    _pp_weak,
    _rms,
    calibrate_device,
)
from telefringe.calibration.errors import CalibrationError
from telefringe.calibration.problem import BundleProblem, ParameterLayout, check_observations
from telefringe.calibration.starts import PROJECTOR_SIDES, rig_rotations
from telefringe.devices.base import ROTATION_NAMES, Device
from telefringe.devices.rig import Rig
from telefringe.geometry.so3 import chordal_mean

__all__ = ["RigCalibration", "calibrate_rig", "rig_parameter_names"]


def rig_parameter_names(rig: Rig) -> tuple[str, ...]:
    """The names of a rig's parameter vector: ``"camera.<p>"`` for each of the camera's
    ``param_names``, then ``"projector.<p>"`` (see :class:`RigCalibration`)."""
    return (tuple(f"camera.{p}" for p in rig.camera.param_names)
            + tuple(f"projector.{p}" for p in rig.projector.param_names))


@dataclass(frozen=True, eq=False)
class RigCalibration:
    """A calibrated camera-projector rig and its report.

    Attributes
    ----------
    rig : Rig, both devices in the world frame (the target at the reference pose: x
        along the grid's columns, y along its rows, z toward the camera).
    pose_names : tuple of str, every pose given (used or not).
    reference_pose : str
    used : (n_poses,) bool, poses in the joint adjustment.
    R_world_target : (n_poses, 3, 3) ndarray; NaN for unused poses.
    t_world_target : (n_poses, 3) ndarray, mm; NaN for unused poses.
    points_target : (n_points, 3) ndarray, mm.
    grid_shape : (rows, cols) or None.
    parameter_names : tuple of str, ``"camera.<name>"`` for each of the camera's
        ``param_names``, then ``"projector.<name>"`` (:mod:`telefringe.devices.base`).
    parameters : (n_params,) ndarray, the rig parameters named by ``parameter_names``
        (each device's ``to_params()``: rotations as zero perturbations; their
        uncertainty is the covariance).
    covariance : (n_params, n_params) ndarray, parameter covariance from the Jacobian
        (scaled by the reduced chi-square; NaN rows/columns for fixed parameters).
    std : (n_params,) ndarray, sqrt of the covariance's diagonal.
    sigma_camera, sigma_projector : float, px, per-coordinate noise estimated from the
        residuals (the weights of the adjustment).
    residuals_camera, residuals_projector : (n_poses, n_points, 2) ndarray, px
        (predicted - observed); NaN where not observed, rejected or unused.
    rms_camera, rms_projector : float, px, RMS reprojection error (2-D length).
    rms_per_pose : (n_poses, 2) ndarray, px (camera, projector); NaN for unused poses.
    outliers : tuple of Outlier.
    camera_observations, projector_observations : (n_poses, n_points, 2) ndarray, px,
        the observations given (NaN where missing).
    principal_point : str, "estimate" or "fixed"; principal_point_weak : (bool, bool)
        for (camera, projector).
    mirror : str, how the global mirror ambiguity was resolved ("projector_side=...",
        to which ``telefringe calibrate`` adds where the side came from).
    warnings : tuple of str, things a person should read (skipped poses, conventions).
    camera_alone, projector_alone : DeviceCalibration or None, the single-device
        calibrations that started the joint adjustment (not stored in rig.json).
    phase_errors : dict ``(axis, periods, steps) -> PhaseErrorModel``, the projector
        nonlinearity learned from the calibration scans (mean over the poses of each
        pose's fit, :func:`telefringe.gamma.mean_model`); empty when it was not learned.
        Pass it to :func:`telefringe.fringes.decode.decode` to skip learning it from every scan.
    """

    rig: Rig
    pose_names: tuple[str, ...]
    reference_pose: str
    used: np.ndarray
    R_world_target: np.ndarray
    t_world_target: np.ndarray
    points_target: np.ndarray
    grid_shape: tuple[int, int] | None
    parameter_names: tuple[str, ...]
    parameters: np.ndarray
    covariance: np.ndarray
    std: np.ndarray
    sigma_camera: float
    sigma_projector: float
    residuals_camera: np.ndarray
    residuals_projector: np.ndarray
    rms_camera: float
    rms_projector: float
    rms_per_pose: np.ndarray
    outliers: tuple[Outlier, ...]
    camera_observations: np.ndarray
    projector_observations: np.ndarray
    principal_point: str
    principal_point_weak: tuple[bool, bool]
    mirror: str
    warnings: tuple[str, ...] = ()
    camera_alone: DeviceCalibration | None = field(default=None, repr=False)
    projector_alone: DeviceCalibration | None = field(default=None, repr=False)
    phase_errors: dict = field(default_factory=dict, repr=False)

    @property
    def camera(self) -> Device:
        """The calibrated camera (``rig.camera``): a RigCalibration can stand for a Rig."""
        return self.rig.camera

    @property
    def projector(self) -> Device:
        """The calibrated projector (``rig.projector``)."""
        return self.rig.projector

    def std_of(self, name: str) -> float:
        """Standard deviation of one parameter by name (see ``parameter_names``), e.g.
        ``"camera.m"``. Raises KeyError for an unknown name."""
        if name not in self.parameter_names:
            raise KeyError(f"no rig parameter {name!r}; known: {', '.join(self.parameter_names)}")
        return float(self.std[self.parameter_names.index(name)])


def calibrate_rig(points_target, camera_observations, projector_observations, *,
                  camera_pixel_size, projector_pixel_size, camera_size, projector_size,
                  reference_pose: int = 0, pose_names=None, grid_shape=None,
                  projector_side: str | None = None, principal_point: str = "estimate",
                  principal_point_sigma: float | None = None,
                  outlier_threshold: float = 5.0, max_rounds: int = 3,
                  min_poses: int = 4, min_points: int = 6,
                  warnings: Sequence[str] = ()) -> RigCalibration:
    """Joint calibration of a camera and a projector from target poses.

    Each device is first calibrated alone (:func:`~telefringe.calibration.device.calibrate_device`);
    telecentric devices leave a mirror ambiguity, settled per pose by rigidity and globally
    by ``projector_side`` (:func:`telefringe.calibration.starts.rig_rotations`). One joint
    adjustment of both devices and every pose follows (world frame = target at the
    reference pose), with the parameter covariance from its Jacobian.

    Parameters
    ----------
    points_target : (n_points, 3) array_like, mm, target points (z = 0), in the order
        of the observations (row-major (row, col) for a grid).
    camera_observations : (n_poses, n_points, 2) array_like, camera px; NaN = missing.
    projector_observations : (n_poses, n_points, 2) array_like, projector px (u_p, v_p
        at each circle centre); NaN = missing.
    camera_pixel_size, projector_pixel_size : (du, dv), mm.
    camera_size, projector_size : (width, height), px.
    reference_pose : int, the pose whose target frame is the world frame.
    pose_names : sequence of str, names for the report; grid_shape : (rows, cols).
    projector_side : {"left", "right", "top", "bottom"} or None
        Where the projector is, as seen in the camera image (the side the light comes
        from; shadows fall away from it). Resolves the global mirror ambiguity of a flat
        target (see the module notes). For two telecentric devices it is required: None
        raises :class:`~telefringe.calibration.start_telecentric.MirrorAmbiguityError`.
    principal_point, principal_point_sigma : see :func:`calibrate_device`.
    outlier_threshold, max_rounds : outlier rejection (robust sigmas, rounds).
    min_poses : int, fewest poses seen by both devices.
    warnings : sequence of str, earlier warnings to carry into the result.

    Returns
    -------
    RigCalibration

    Raises
    ------
    CalibrationError
        Too few poses, the reference pose unusable, degenerate poses (e.g. all with the
        same tilt), or no convergence.
    """
    P, cam = check_observations(points_target, camera_observations, "camera_observations")
    _, proj = check_observations(points_target, projector_observations,
                                 "projector_observations")
    if cam.shape != proj.shape:
        raise CalibrationError("camera and projector observations must have the same shape")
    if projector_side is not None and projector_side not in PROJECTOR_SIDES:
        raise ValueError(f"projector_side must be one of {sorted(PROJECTOR_SIDES)}, got "
                         f"{projector_side!r}")
    n_poses = cam.shape[0]
    names = [str(i) for i in range(n_poses)] if pose_names is None else [str(p) for p in
                                                                          pose_names]
    if len(names) != n_poses:
        raise ValueError("pose_names must have one name per pose")
    ref = int(reference_pose)
    if not 0 <= ref < n_poses:
        raise ValueError(f"reference_pose {ref} out of range 0..{n_poses - 1}")
    warns = list(warnings)
    common = dict(principal_point=principal_point, principal_point_sigma=principal_point_sigma,
                  outlier_threshold=outlier_threshold, max_rounds=max_rounds,
                  min_points=min_points, min_poses=min(min_poses, 3), pose_names=names,
                  grid_shape=grid_shape)
    cal_c = calibrate_device(P, cam, pixel_size=camera_pixel_size, image_size=camera_size,
                             name="camera", **common)
    cal_p = calibrate_device(P, proj, pixel_size=projector_pixel_size,
                             image_size=projector_size, name="projector", **common)
    both = cal_c.used & cal_p.used
    for i in range(n_poses):
        if not both[i] and not any(w.startswith(f"pose {names[i]}:") for w in warns):
            who = [n for n, c in (("camera", cal_c), ("projector", cal_p)) if not c.used[i]]
            warns.append(f"pose {names[i]}: too few markers seen by the {' and '.join(who)}; "
                         "pose not used")
    if not both[ref]:
        raise CalibrationError(f"reference pose {names[ref]} is not usable (too few markers "
                               "seen by both devices): the world frame is the target there")
    poses = [ref] + [i for i in np.flatnonzero(both) if i != ref]
    if len(poses) < min_poses:
        raise CalibrationError(f"{len(poses)} pose(s) seen by both devices, at least "
                               f"{min_poses} needed")
    R_ct, R_pt, R_pc, mirror, more = rig_rotations(
        cal_c.device.model, cal_p.device.model, cal_c.R_dev_target[poses],
        cal_p.R_dev_target[poses], projector_side)
    warns += more
    # degenerate pose sets: every target normal (in the camera) nearly the same
    normals = R_ct[:, :, 2]
    spread = np.degrees(np.max(np.arccos(np.clip(normals @ normals[0], -1, 1))))
    if spread < 1.0:
        raise CalibrationError(
            f"the target has the same tilt in every pose (spread {spread:.2f} deg): depth "
            "cannot be calibrated; tilt the target in several directions")
    R_cw = R_ct[0]
    R_pw = R_pc @ R_cw
    R_wt = np.array([chordal_mean([R_cw.T @ R_ct[j], R_pw.T @ R_pt[j]])
                     for j in range(len(poses))])
    R_wt[0] = np.eye(3)
    t_c = cal_c.t_dev[poses]
    t_p = cal_p.t_dev[poses]
    M = np.vstack([R_cw[:2], R_pw[:2]])
    T = np.zeros((len(poses), 3))
    for j in range(1, len(poses)):
        T[j] = np.linalg.lstsq(M, np.concatenate([t_c[j] - t_c[0], t_p[j] - t_p[0]]),
                               rcond=None)[0]
    names_d = ("camera", "projector")
    cam_size = tuple(int(v) for v in camera_size)
    proj_size = tuple(int(v) for v in projector_size)
    centre_c, sig_c = _pp_setup(principal_point, None, principal_point_sigma, cam_size)
    centre_p, sig_p = _pp_setup(principal_point, None, principal_point_sigma, proj_size)
    devs0 = []
    for dev_alone, R_dw, t_d, centre in ((cal_c.device, R_cw, t_c[0], centre_c),
                                          (cal_p.device, R_pw, t_p[0], centre_p)):
        p = dev_alone.to_params()
        if principal_point == "fixed":
            for nm, val in zip(dev_alone.principal_point_names, centre, strict=True):
                p[dev_alone.param_names.index(nm)] = val
        devs0.append(dev_alone.from_params(p).with_pose(R_dw, t_d))
    n_u = len(poses)
    layout = ParameterLayout(names_d, tuple(tuple(d.param_names) for d in devs0), n_u)
    free = np.ones(layout.size, dtype=bool)
    free[layout.pose_slice(0)] = False  # reference pose = world frame
    priors = []
    for dname, dev, centre, sig in (("camera", devs0[0], centre_c, sig_c),
                                    ("projector", devs0[1], centre_p, sig_p)):
        pp = [f"{dname}.{n}" for n in dev.principal_point_names]
        if principal_point == "fixed":
            free[layout.indices(pp)] = False
        else:
            priors += [(pp[0], centre[0], sig), (pp[1], centre[1], sig)]
    sig0 = [max(cal_c.rms, 1e-6) / np.sqrt(2), max(cal_p.rms, 1e-6) / np.sqrt(2)]

    def build(obs_list, sigmas, prev):
        if prev is None:
            return BundleProblem(P, obs_list, devs0, R_wt, T, sigmas=sig0, free=free,
                                 priors=priors, device_names=names_d)
        devs, R_wt_prev, T_wt_prev = prev[0].unpack(prev[1])
        return BundleProblem(P, obs_list, devs, R_wt_prev, T_wt_prev,
                             sigmas=sig0 if sigmas is None else sigmas, free=free,
                             priors=priors, device_names=names_d)

    problem, x, keeps, outliers, sigmas = _adjust_with_rejection(
        build, [cam, proj], [poses, poses], threshold=outlier_threshold,
        max_rounds=max_rounds, names=list(names_d), pose_names=names,
        grid_shape=grid_shape)
    problem, x = problem.rebased(x)
    devs, R_wt_final, T_wt_final = problem.unpack(x)
    rig = Rig(camera=devs[0], projector=devs[1])
    residuals = []
    for d in range(2):
        o = problem.obs[d]
        res = np.full(cam.shape, np.nan)
        res[np.asarray(poses)[o.pose], o.point] = problem.predict(x, d) - o.uv
        residuals.append(res)
    rms_c, per_c = _rms(residuals[0], n_poses)
    rms_p, per_p = _rms(residuals[1], n_poses)
    cov_free, _ = problem.covariance(x)
    if cov_free is None:
        raise CalibrationError("the poses do not determine the rig (singular normal "
                               "equations): tilt the target in several directions")
    cov = problem.device_covariance(cov_free)
    std = np.sqrt(np.diag(cov))
    param_names = layout.device_parameter_names
    rot_std = std[layout.indices([f"{d}.{r}" for d in names_d for r in ROTATION_NAMES])]
    if np.any(rot_std > 0.05):
        raise CalibrationError(
            "the poses barely determine the rig's rotations (std up to "
            f"{np.nanmax(rot_std):.3g} rad): tilt the target more, in several directions")
    params = np.concatenate([d.to_params() for d in devs])
    if principal_point == "estimate":
        weak = tuple(_pp_weak(dev, std[layout.device_slice(d)], size) for d, (dev, size)
                     in enumerate(((devs[0], cam_size), (devs[1], proj_size))))
    else:
        weak = (True, True)
    for dname, w in zip(names_d, weak, strict=True):
        if w and principal_point == "estimate":
            warns.append(f"{dname}: the principal point is weakly determined by the data "
                         "(little distortion); it stays near the image-centre prior, which "
                         "costs little accuracy")
    R_all = np.full((n_poses, 3, 3), np.nan)
    T_all = np.full((n_poses, 3), np.nan)
    R_all[poses] = R_wt_final
    T_all[poses] = T_wt_final
    used = np.zeros(n_poses, dtype=bool)
    used[poses] = True
    return RigCalibration(
        rig=rig, pose_names=tuple(names), reference_pose=names[ref], used=used,
        R_world_target=R_all, t_world_target=T_all, points_target=P.copy(),
        grid_shape=None if grid_shape is None else tuple(int(v) for v in grid_shape),
        parameter_names=param_names, parameters=params, covariance=cov, std=std,
        sigma_camera=float(sigmas[0]), sigma_projector=float(sigmas[1]),
        residuals_camera=residuals[0],
        residuals_projector=residuals[1], rms_camera=rms_c, rms_projector=rms_p,
        rms_per_pose=np.column_stack([per_c, per_p]), outliers=tuple(outliers),
        camera_observations=cam.copy(), projector_observations=proj.copy(),
        principal_point=principal_point, principal_point_weak=weak, mirror=mirror,
        warnings=tuple(warns), camera_alone=cal_c, projector_alone=cal_p)
