"""Devices calibrated jointly over one set of target poses: a camera and a projector,
each telecentric or pinhole, or two cameras with an optional projector
(:func:`calibrate_devices`; :func:`calibrate_rig` for one camera and a projector).

Each device starts from the closed form of its model, alone; the starts are put in one
world frame (the target at the reference pose) through their per-pose rotations, on one
rigid branch of the telecentric mirror ambiguity (a pinhole device settles it, else the
projector's side); one bundle adjustment over every device and pose follows, weighted by
each device's noise, with outlier rejection and the parameter covariance.

Units: mm in the world and on sensors, px in images, radians. Reprojection "RMS" is the
root mean square of the 2-D error length over points (px of the device). The principal
point is only seen through the distortion (a shift of the principal point is otherwise a
shift of t); it is estimated with a weak prior at the image centre (default) or held
fixed, and flagged as weak when no distortion coefficient is significant or its standard
deviation exceeds 1 % of the image diagonal (a weak principal point costs little
accuracy, since it then barely changes any image).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from telefringe.calibration.centres import circle_image_centres
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
from telefringe.calibration.starts import PROJECTOR_SIDES, joint_rotations
from telefringe.devices.base import ROTATION_NAMES, Device
from telefringe.devices.rig import Rig
from telefringe.geometry.so3 import chordal_mean

__all__ = ["DeviceReport", "RigCalibration", "calibrate_devices", "calibrate_rig",
           "rig_parameter_names"]


def rig_parameter_names(rig: Rig) -> tuple[str, ...]:
    """The names of a rig's parameter vector: ``"<camera>.<p>"`` for each camera's
    ``param_names`` (``camera``, then ``camera_2``), then ``"projector.<p>"`` when the
    rig has a projector (see :class:`RigCalibration`)."""
    devs = list(rig.cameras.items())
    if rig.projector is not None:
        devs.append(("projector", rig.projector))
    return tuple(f"{n}.{p}" for n, d in devs for p in d.param_names)


@dataclass(frozen=True, eq=False)
class DeviceReport:
    """One device's part of a joint calibration.

    Attributes
    ----------
    model : str.
    sigma : float, px, per-coordinate noise estimated from the residuals.
    observations, residuals : (n_poses, n_points, 2) ndarray, px (residuals predicted -
        observed; NaN where not observed, rejected or unused).
    rms : float, px (2-D length); rms_per_pose : (n_poses,) px, NaN for unused poses.
    principal_point_weak : bool.
    alone : DeviceCalibration or None, its calibration alone (the start).
    sigma_uv : (2,) ndarray, px, the noise of each image axis (``sigma`` is their RMS);
        for a projector read at the camera's detected centres, its own noise (the part
        independent of the camera's detection error).
    """

    model: str
    sigma: float
    observations: np.ndarray
    residuals: np.ndarray
    rms: float
    rms_per_pose: np.ndarray
    principal_point_weak: bool
    alone: DeviceCalibration | None = field(default=None, repr=False)
    sigma_uv: np.ndarray | None = None


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
        residuals (the weights of the adjustment; the RMS of the two image axes, each
        weighted by its own: ``devices[name].sigma_uv``). A projector read at the
        camera's detected centres (``projector_at_camera_centres``) has here its own
        noise, without the part the camera's detection error puts in it.
    residuals_camera, residuals_projector : (n_poses, n_points, 2) ndarray, px
        (predicted - observed); NaN where not observed, rejected or unused.
    rms_camera, rms_projector : float, px, RMS reprojection error (2-D length).
    rms_per_pose : (n_poses, n_devices) ndarray, px, one column per device in the order of
        ``device_names`` ((camera, projector) for one camera); NaN for unused poses.
    outliers : tuple of Outlier.
    camera_observations, projector_observations : (n_poses, n_points, 2) ndarray, px,
        the observations given (NaN where missing).
    principal_point : str, "estimate" or "fixed"; principal_point_weak : tuple of bool,
        one per device in the order of ``device_names``.
    mirror : str, how the global mirror ambiguity was resolved ("projector_side=...",
        to which ``telefringe calibrate`` adds where the side came from).
    warnings : tuple of str, things a person should read (skipped poses, conventions).
    camera_alone, projector_alone : DeviceCalibration or None, the single-device
        calibrations that started the joint adjustment (not stored in rig.json).
    phase_errors : dict ``(axis, periods, steps) -> PhaseErrorModel``, the projector
        nonlinearity learned from the calibration scans (mean over the poses of each
        pose's fit, :func:`telefringe.gamma.mean_model`); empty when it was not learned.
        Pass it to :func:`telefringe.fringes.decode.decode` to skip learning it from every scan.
    devices : dict device name -> :class:`DeviceReport` (every device's part of the
        report, with its calibration alone); empty for a rig read from rig.json.
    rms_camera_2, sigma_camera_2, residuals_camera_2, camera_2_observations : the second
        camera's report (as the ``*_camera`` fields) for a two-camera rig; NaN / None
        otherwise. The ``*_projector`` fields are NaN when no projector is calibrated.
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
    devices: dict = field(default_factory=dict, repr=False)
    rms_camera_2: float = float("nan")
    sigma_camera_2: float = float("nan")
    residuals_camera_2: np.ndarray | None = field(default=None, repr=False)
    camera_2_observations: np.ndarray | None = field(default=None, repr=False)

    @property
    def device_names(self) -> tuple[str, ...]:
        """The calibrated devices in parameter order (cameras, then the projector)."""
        return tuple(self.devices) if self.devices else ("camera", "projector")

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
                  warnings: Sequence[str] = (), camera_model: str = "telecentric",
                  projector_model: str = "telecentric") -> RigCalibration:
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
    camera_pixel_size, projector_pixel_size : (du, dv), mm (None for a pinhole device).
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
    camera_model, projector_model : "telecentric" (default) or "pinhole"; a rig with a
        pinhole device has no mirror ambiguity (``projector_side`` is then not needed).

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
    return calibrate_devices(
        P, {"camera": cam, "projector": proj},
        models={"camera": camera_model, "projector": projector_model},
        pixel_sizes={"camera": camera_pixel_size, "projector": projector_pixel_size},
        image_sizes={"camera": camera_size, "projector": projector_size},
        reference_pose=ref, pose_names=names, grid_shape=grid_shape,
        projector_side=projector_side, principal_point=principal_point,
        principal_point_sigma=principal_point_sigma, outlier_threshold=outlier_threshold,
        max_rounds=max_rounds, min_poses=min_poses, min_points=min_points, warnings=warns)


def calibrate_devices(points_target, observations: Mapping[str, np.ndarray], *,
                      models: Mapping[str, str], pixel_sizes: Mapping[str, object],
                      image_sizes: Mapping[str, object], reference_pose: int = 0,
                      pose_names=None, grid_shape=None, projector_side: str | None = None,
                      principal_point: str = "estimate",
                      principal_point_sigma: float | None = None,
                      outlier_threshold: float = 5.0, max_rounds: int = 3,
                      min_poses: int = 4, min_points: int = 6,
                      warnings: Sequence[str] = (),
                      marker_radius: float | None = None,
                      centre_bias: str = "full",
                      projector_at_camera_centres: bool = False) -> RigCalibration:
    """Joint calibration of any devices (one or two cameras, an optional projector).

    Each device is calibrated alone with the closed-form start of its model
    (:func:`~telefringe.calibration.device.calibrate_device`); their rotations are put on
    one rigid branch (:func:`telefringe.calibration.starts.joint_rotations`: telecentric
    devices leave a mirror ambiguity, which a pinhole device settles, or else
    ``projector_side``); one bundle adjustment over all devices and poses follows (world
    frame = target at the reference pose), with the parameter covariance.

    Parameters
    ----------
    points_target : (n_points, 3) mm on z = 0.
    observations : mapping device name -> (n_poses, n_points, 2) px, NaN where missing;
        names ``camera`` (first), optionally ``camera_2``, optionally ``projector``.
    models, pixel_sizes, image_sizes : mappings by device name (model "telecentric" or
        "pinhole"; pixel size (du, dv) mm, None for a pinhole device; (width, height) px).
    marker_radius : float, mm, the radius of the target's circles, or None. Given, the
        bias of the circle centres is corrected: the centre of a circle's image (what a
        detector measures) is not the image of its centre, through perspective (the
        eccentricity of a pinhole camera) and through the curvature of lens distortion
        (any model; :mod:`telefringe.calibration.centres`). With the current estimate
        each camera's observations are corrected by the centre of its own (full-model)
        image of the circle minus the image of the centre, and the projector's, read
        through the first camera's phase at that camera's image centre, by the
        projector's image of the plate point seen there minus that of the centre; the
        adjustment is then repeated (twice). Residuals are those of the corrected
        observations. None: no correction.
    centre_bias : "full" (default) or "perspective". "full" corrects every camera for
        the distortion curvature and perspective (on rendered calibrations of the `fast`
        rig the camera magnification bias goes from +4.8 to -0.04 of its sigma,
        benchmarks/centre_bias.py); "perspective" only the cameras that see depth
        (pinhole), as earlier versions did (kept to compare). A plate measured
        from detected centres needs the same correction
        (:func:`telefringe.metrology.plate.measure_plate` with the camera).
    projector_at_camera_centres : bool
        The projector's observations were read from the phase at the first camera's
        detected centres (what :func:`~telefringe.calibration.from_scans.calibrate_from_scans`
        does): the camera's detection error is then in the projector's observation too,
        and the adjustment takes the projector's error given the camera's
        (:mod:`telefringe.calibration.problem`), weighted by the projector's own noise
        (``sigma_projector`` is then that part). False: independent observations.
    Others : as :func:`calibrate_rig`.

    Returns
    -------
    RigCalibration (its ``devices`` holds every device's :class:`DeviceReport`; the
    ``*_projector`` fields are NaN when no projector is calibrated).

    Raises
    ------
    CalibrationError
    """
    names_d = tuple(observations)
    if not names_d or names_d[0] != "camera":
        raise ValueError("observations: the first device must be 'camera'")
    P = np.asarray(points_target, dtype=float)
    obs = {}
    for d in names_d:
        _, obs[d] = check_observations(P, observations[d], f"{d} observations")
    shape = obs["camera"].shape
    if any(o.shape != shape for o in obs.values()):
        raise CalibrationError("every device's observations must have the same shape")
    n_poses = shape[0]
    names = [str(i) for i in range(n_poses)] if pose_names is None else [str(p) for p in
                                                                          pose_names]
    if len(names) != n_poses:
        raise ValueError("pose_names must have one name per pose")
    ref = int(reference_pose)
    if not 0 <= ref < n_poses:
        raise ValueError(f"reference_pose {ref} out of range 0..{n_poses - 1}")
    if projector_side is not None and projector_side not in PROJECTOR_SIDES:
        raise ValueError(f"projector_side must be one of {sorted(PROJECTOR_SIDES)}, got "
                         f"{projector_side!r}")
    warns = list(warnings)
    common = dict(principal_point=principal_point, principal_point_sigma=principal_point_sigma,
                  outlier_threshold=outlier_threshold, max_rounds=max_rounds,
                  min_points=min_points, min_poses=min(min_poses, 3), pose_names=names,
                  grid_shape=grid_shape)
    alone = {d: calibrate_device(P, obs[d], pixel_size=pixel_sizes.get(d),
                                 image_size=image_sizes[d], name=d, model=models[d],
                                 **common) for d in names_d}
    both = np.logical_and.reduce([alone[d].used for d in names_d])
    for i in range(n_poses):
        if not both[i] and not any(w.startswith(f"pose {names[i]}:") for w in warns):
            who = [d for d in names_d if not alone[d].used[i]]
            warns.append(f"pose {names[i]}: too few markers seen by the {' and '.join(who)}; "
                         "pose not used")
    if not both[ref]:
        raise CalibrationError(f"reference pose {names[ref]} is not usable (too few markers "
                               "seen by every device): the world frame is the target there")
    poses = [ref] + [i for i in np.flatnonzero(both) if i != ref]
    if len(poses) < min_poses:
        raise CalibrationError(f"{len(poses)} pose(s) seen by every device, at least "
                               f"{min_poses} needed")
    proj_index = names_d.index("projector") if "projector" in names_d else None
    R_dt, R_rel, mirror, more = joint_rotations(
        [alone[d].device.model for d in names_d], [alone[d].R_dev_target[poses]
                                                   for d in names_d],
        projector_side, projector_index=proj_index)
    warns += more
    # degenerate pose sets: every target normal (in the camera) nearly the same
    normals = R_dt[0][:, :, 2]
    spread = np.degrees(np.max(np.arccos(np.clip(normals @ normals[0], -1, 1))))
    if spread < 1.0:
        raise CalibrationError(
            f"the target has the same tilt in every pose (spread {spread:.2f} deg): depth "
            "cannot be calibrated; tilt the target in several directions")
    R_cw = R_dt[0][0]
    R_dw = [R @ R_cw for R in R_rel]
    R_wt = np.array([chordal_mean([R_dw[k].T @ R_dt[k][j] for k in range(len(names_d))])
                     for j in range(len(poses))])
    R_wt[0] = np.eye(3)
    t_d = [alone[d].t_dev[poses] for d in names_d]
    # t_dev(pose j) = R_dw T_j + t_dw (the rows each device sees); T_0 = 0
    M = np.vstack([R_dw[k][:t_d[k].shape[1]] for k in range(len(names_d))])
    T = np.zeros((len(poses), 3))
    for j in range(1, len(poses)):
        T[j] = np.linalg.lstsq(M, np.concatenate([t_d[k][j] - t_d[k][0]
                                                  for k in range(len(names_d))]),
                               rcond=None)[0]
    sizes = {d: tuple(int(v) for v in image_sizes[d]) for d in names_d}
    pp = {d: _pp_setup(principal_point, None, principal_point_sigma, sizes[d])
          for d in names_d}
    devs0 = []
    for k, d in enumerate(names_d):
        dev_alone = alone[d].device
        p = dev_alone.to_params()
        if principal_point == "fixed":
            for nm, val in zip(dev_alone.principal_point_names, pp[d][0], strict=True):
                p[dev_alone.param_names.index(nm)] = val
        devs0.append(dev_alone.from_params(p).with_pose(R_dw[k], t_d[k][0]))
    n_u = len(poses)
    layout = ParameterLayout(names_d, tuple(tuple(d.param_names) for d in devs0), n_u)
    free = np.ones(layout.size, dtype=bool)
    free[layout.pose_slice(0)] = False  # reference pose = world frame
    priors = []
    for k, d in enumerate(names_d):
        ppn = [f"{d}.{n}" for n in devs0[k].principal_point_names]
        if principal_point == "fixed":
            free[layout.indices(ppn)] = False
        else:
            centre, sig = pp[d]
            priors += [(ppn[0], centre[0], sig), (ppn[1], centre[1], sig)]
    sig0 = [max(alone[d].rms, 1e-6) / np.sqrt(2) for d in names_d]

    # the projector read at the first camera's detected centres: its error given the
    # camera's (problem.py's module notes)
    coupled = ({proj_index: 0} if projector_at_camera_centres and proj_index is not None
               else None)

    def build(obs_list, sigmas, prev):
        if prev is None:
            return BundleProblem(P, obs_list, devs0, R_wt, T, sigmas=sig0, free=free,
                                 priors=priors, device_names=names_d, coupled_to=coupled)
        devs, R_wt_prev, T_wt_prev = prev[0].unpack(prev[1])
        return BundleProblem(P, obs_list, devs, R_wt_prev, T_wt_prev,
                             sigmas=sig0 if sigmas is None else sigmas, free=free,
                             priors=priors, device_names=names_d, coupled_to=coupled)

    problem, x, keeps, outliers, sigmas = _adjust_with_rejection(
        build, [obs[d] for d in names_d], [poses] * len(names_d),
        threshold=outlier_threshold, max_rounds=max_rounds, names=list(names_d),
        pose_names=names, grid_shape=grid_shape)
    if centre_bias not in ("perspective", "full"):
        raise ValueError(f"centre_bias must be 'perspective' or 'full', got {centre_bias!r}")
    full = centre_bias == "full"
    if marker_radius is not None and (full or any(
            dev.sees_depth for d, dev in zip(names_d, devs0, strict=True) if d != "projector")):
        # a circle's image centre is not the image of its centre (perspective, lens
        # distortion); correct the observations with the current estimate, adjust again
        for _ in range(2):
            shift = _eccentricity(problem, x, names_d, poses, shape, float(marker_radius),
                                  full=full)
            fixed = [obs[d] - shift[k] for k, d in enumerate(names_d)]
            prev = (problem, x)
            problem, x, keeps, outliers, sigmas = _adjust_with_rejection(
                lambda o, s_, p_, prev=prev: build(o, s_, prev if p_ is None else p_),
                fixed, [poses] * len(names_d), threshold=outlier_threshold,
                max_rounds=max_rounds, names=list(names_d), pose_names=names,
                grid_shape=grid_shape)
    problem, x = problem.rebased(x)
    devs, R_wt_final, T_wt_final = problem.unpack(x)
    cams = {d: devs[k] for k, d in enumerate(names_d) if d != "projector"}
    rig = Rig(cameras=cams, projector=None if proj_index is None else devs[proj_index])
    residuals = []
    for k in range(len(names_d)):
        o = problem.obs[k]
        res = np.full(shape, np.nan)
        res[np.asarray(poses)[o.pose], o.point] = problem.predict(x, k) - o.uv
        residuals.append(res)
    rms = [_rms(r, n_poses) for r in residuals]
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
        weak = tuple(_pp_weak(devs[k], std[layout.device_slice(k)], sizes[d])
                     for k, d in enumerate(names_d))
    else:
        weak = (True,) * len(names_d)
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
    reports = {d: DeviceReport(model=devs[k].model,
                               sigma=float(np.sqrt(np.mean(np.square(sigmas[k])))),
                               sigma_uv=np.array(sigmas[k], dtype=float),
                               observations=obs[d].copy(), residuals=residuals[k],
                               rms=rms[k][0], rms_per_pose=rms[k][1],
                               principal_point_weak=bool(weak[k]), alone=alone[d])
               for k, d in enumerate(names_d)}
    nan_arr = np.full(shape, np.nan)
    pr = reports.get("projector")
    return RigCalibration(
        rig=rig, pose_names=tuple(names), reference_pose=names[ref], used=used,
        R_world_target=R_all, t_world_target=T_all, points_target=P.copy(),
        grid_shape=None if grid_shape is None else tuple(int(v) for v in grid_shape),
        parameter_names=param_names, parameters=params, covariance=cov, std=std,
        sigma_camera=reports["camera"].sigma,
        sigma_projector=pr.sigma if pr else float("nan"),
        residuals_camera=reports["camera"].residuals,
        residuals_projector=pr.residuals if pr else nan_arr,
        rms_camera=reports["camera"].rms, rms_projector=pr.rms if pr else float("nan"),
        rms_per_pose=np.column_stack([reports[d].rms_per_pose for d in names_d]),
        outliers=tuple(outliers),
        camera_observations=obs["camera"].copy(),
        projector_observations=obs["projector"].copy() if pr else nan_arr.copy(),
        principal_point=principal_point,
        principal_point_weak=tuple(reports[d].principal_point_weak for d in names_d),
        mirror=mirror, warnings=tuple(warns), camera_alone=alone["camera"],
        projector_alone=alone.get("projector"), devices=reports,
        **({} if "camera_2" not in reports else dict(
            rms_camera_2=reports["camera_2"].rms, sigma_camera_2=reports["camera_2"].sigma,
            residuals_camera_2=reports["camera_2"].residuals,
            camera_2_observations=reports["camera_2"].observations)))


def _circle_image_centre(dev, R, T, centres_target, radius):
    """Centres (m, 2) px of the images of circles of ``radius`` mm centred at
    ``centres_target`` (m, 3) on the target plane at pose (R (m, 3, 3), T (m, 3)): the
    area centroids of their images through ``dev``'s full model
    (:func:`telefringe.calibration.centres.circle_image_centres`)."""
    X = np.einsum("mij,mj->mi", R, centres_target) + T
    return circle_image_centres(dev, X, R[:, :, 2], radius)


def _eccentricity(problem: BundleProblem, x, names_d, poses, shape, radius, *, full=False):
    """Per device (n_poses, n_points, 2) px: observed centre minus image of the centre,
    predicted at ``x`` with each device's full model (zero for unused poses, and unless
    ``full``, for cameras that do not see depth)."""
    devs, R_wt, T_wt = problem.unpack(x)
    n_u = len(poses)
    P = problem.P
    m = P.shape[0]
    pose_idx = np.repeat(np.arange(n_u), m)
    pt_idx = np.tile(np.arange(m), n_u)
    R = R_wt[pose_idx]
    T = T_wt[pose_idx]
    Xc = np.einsum("mij,mj->mi", R, P[pt_idx]) + T
    out = []
    first = devs[0]
    cam_centre = None
    for k, d in enumerate(names_d):
        dev = devs[k]
        shift = np.zeros((len(pt_idx), 2))
        if d != "projector" and (full or dev.sees_depth):
            c = _circle_image_centre(dev, R, T, P[pt_idx], radius)
            shift = c - np.stack(dev.project(Xc), axis=1)
            if k == 0:
                cam_centre = c
        elif d == "projector" and cam_centre is not None:
            # the plate point the first camera sees at its circle image's centre
            rays = first.backproject(cam_centre[:, 0], cam_centre[:, 1])
            o = np.broadcast_to(rays.origin, Xc.shape)
            dirs = np.broadcast_to(rays.direction, Xc.shape)
            nrm = R[:, :, 2]
            s = np.einsum("mi,mi->m", T - o, nrm) / np.einsum("mi,mi->m", dirs, nrm)
            Xs = o + s[:, None] * dirs
            shift = np.stack(dev.project(Xs), axis=1) - np.stack(dev.project(Xc), axis=1)
        grid = np.zeros(shape)
        grid[np.asarray(poses)[pose_idx], pt_idx] = shift
        out.append(grid)
    return out
