"""One device calibrated alone, and the machinery every calibration shares: outlier
rejection between solves, principal-point priors, the per-pose report."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from telefringe.calibration.errors import CalibrationError
from telefringe.calibration.problem import (
    BundleProblem,
    Observations,
    ParameterLayout,
    check_observations,
)
from telefringe.calibration.solver import robust_sigma_axes
from telefringe.calibration.starts import device_start
from telefringe.devices.base import Device

__all__ = ["DeviceCalibration", "Outlier", "calibrate_device"]


@dataclass(frozen=True)
class Outlier:
    """An observation rejected by the adjustment.

    Attributes
    ----------
    device : str, "camera" or "projector" (or the device's name).
    pose : str, pose name (or its index as text).
    marker : (row, col) of the circle in the target grid (or (0, index) without a grid).
    residual : (du, dv) px of that device, at rejection.
    """

    device: str
    pose: str
    marker: tuple[int, int]
    residual: tuple[float, float]


@dataclass(frozen=True, eq=False)
class DeviceCalibration:
    """A device calibrated alone from planar target views.

    Attributes
    ----------
    device : Device, the calibrated device at the identity pose (its frame is the
        device frame); ``intrinsics`` is ``device.intrinsics``.
    R_dev_target : (n_poses, 3, 3) ndarray, target -> device; for a telecentric device
        one of the two mirror tilts per pose
        (:func:`~telefringe.calibration.start_telecentric.mirror_pose`); NaN for unused poses.
    t_dev : (n_poses, n_t) ndarray, mm, the target's translation in the device frame
        (n_t = 2 for a device that does not see depth: tx, ty); NaN for unused poses.
    used : (n_poses,) bool.
    residuals : (n_poses, n_points, 2) ndarray, px (predicted - observed); NaN where
        not observed or rejected.
    rms : float, px, RMS reprojection error (2-D error length) over used observations.
    rms_per_pose : (n_poses,) ndarray, px (NaN for unused poses).
    std : (n_intrinsics,) ndarray, standard deviations of the intrinsics named by
        ``device.intrinsic_names``; NaN if fixed.
    principal_point_weak : bool, the data barely constrain (u0, v0) (the prior or the
        fixed value decides them).
    start : the closed-form start of the device's model (e.g.
        :class:`~telefringe.calibration.start_telecentric.DeviceStart`).
    outliers : tuple of Outlier.
    """

    device: Device
    R_dev_target: np.ndarray
    t_dev: np.ndarray
    used: np.ndarray
    residuals: np.ndarray
    rms: float
    rms_per_pose: np.ndarray
    std: np.ndarray
    principal_point_weak: bool
    start: object
    outliers: tuple[Outlier, ...] = ()

    @property
    def intrinsics(self):
        """The device's intrinsics (``device.intrinsics``)."""
        return self.device.intrinsics


def _pp_setup(mode, value, sigma, size):
    w, h = (int(v) for v in size)
    centre = ((w - 1) / 2.0, (h - 1) / 2.0) if value is None else tuple(float(v) for v in value)
    if mode not in ("estimate", "fixed"):
        raise ValueError(f"principal_point must be 'estimate' or 'fixed', got {mode!r}")
    if sigma is None:
        sigma = 0.5 * float(np.hypot(w, h)) if w > 0 and h > 0 else 1000.0
    if not (np.isfinite(sigma) and sigma > 0):
        raise ValueError(f"principal_point_sigma must be > 0, got {sigma!r}")
    return centre, float(sigma)


def _pp_weak(device, std, size) -> bool:
    """Whether the principal point is weakly determined: no distortion coefficient
    differs from zero by 5 standard deviations (the principal point is then fixed by
    noise-level distortion, where the linear uncertainty is not to be trusted), or the
    standard deviation of either principal-point coordinate exceeds 1 % of the image
    diagonal. ``std`` (n_intrinsics,) as :attr:`DeviceCalibration.std`."""
    names = list(device.intrinsic_names)
    q = device.to_params()[:len(names)]
    std = np.asarray(std, dtype=float)[:len(names)]
    if not np.all(np.isfinite(std)):
        return True
    dist = [names.index(n) for n in device.distortion_names]
    pp = [names.index(n) for n in device.principal_point_names]
    significant = np.any(np.abs(q[dist]) > 5.0 * std[dist])
    return bool(not significant or max(std[pp]) > 0.01 * float(np.hypot(*size)))


def _marker_label(k: int, grid_shape) -> tuple[int, int]:
    if grid_shape is None:
        return (0, int(k))
    return tuple(int(v) for v in divmod(int(k), int(grid_shape[1])))


def _obs_from_array(obs: np.ndarray, poses: Sequence[int], keep: np.ndarray) -> Observations:
    """Collect finite, kept observations of the given poses (indices into ``obs``)."""
    pi, ki, uv = [], [], []
    for j, i in enumerate(poses):
        ok = np.flatnonzero(np.all(np.isfinite(obs[i]), axis=1) & keep[i])
        pi.append(np.full(ok.size, j))
        ki.append(ok)
        uv.append(obs[i, ok])
    return Observations(np.concatenate(pi).astype(int), np.concatenate(ki).astype(int),
                np.concatenate(uv).reshape(-1, 2))


def _adjust_with_rejection(build, obs_arrays, pose_lists, *, threshold, max_rounds,
                           names, pose_names, grid_shape):
    """Solve, reject observations whose error exceeds ``threshold`` robust sigmas, repeat.

    ``build(obs_list, sigmas, prev)`` -> BundleProblem, ``prev`` the (problem, x) of the
    previous round or None. Each device's noise is estimated per image axis from its
    errors (:meth:`BundleProblem.errors`: a coupled device's given its partner's).
    Returns (problem, x, keep masks, outliers, sigmas (per device, (sigma_u, sigma_v))).
    """
    keeps = [np.ones(o.shape[:2], dtype=bool) for o in obs_arrays]
    outliers: list[Outlier] = []
    sigmas = None
    prev = None
    for _round in range(max_rounds + 2):
        obs_list = [_obs_from_array(o, p, k) for o, p, k in zip(obs_arrays, pose_lists, keeps,
                                                                strict=True)]
        problem = build(obs_list, sigmas, prev)
        x = problem.solve().x
        prev = (problem, x)
        new_sigmas = []
        changed = False
        for d, p in enumerate(pose_lists):
            o = problem.obs[d]  # (a coupled device keeps the observations with a partner)
            e = problem.errors(x, d)
            sig = np.maximum(robust_sigma_axes(e), 1e-6)
            new_sigmas.append(sig)
            if threshold is None or not np.isfinite(threshold) or _round >= max_rounds:
                continue
            bad = np.flatnonzero(np.hypot(e[:, 0] / sig[0], e[:, 1] / sig[1]) > threshold)
            for b in bad:
                i = p[o.pose[b]]
                k = int(o.point[b])
                keeps[d][i, k] = False
                outliers.append(Outlier(names[d], pose_names[i], _marker_label(k, grid_shape),
                                        (float(e[b, 0]), float(e[b, 1]))))
                changed = True
        # relative weights matter only between devices
        stable = (len(new_sigmas) == 1 or sigmas is not None and np.all(
            np.abs(np.array(new_sigmas) / np.array(sigmas) - 1.0) < 0.1))
        if sigmas is None and len(new_sigmas) > 1:
            stable = False
        sigmas = new_sigmas
        if not changed and stable:
            break
    return problem, x, keeps, outliers, sigmas


def calibrate_device(points_target, observations, *, pixel_size=None, image_size,
                     principal_point: str = "estimate", principal_point_value=None,
                     principal_point_sigma: float | None = None, distortion: bool = True,
                     outlier_threshold: float = 5.0, max_rounds: int = 3,
                     min_points: int = 6, min_poses: int = 3, pose_names=None,
                     grid_shape=None, name: str = "device",
                     model: str = "telecentric") -> DeviceCalibration:
    """Calibrate one device alone (camera, or projector as inverse camera).

    The start is the closed form of the device's ``model``
    (:func:`telefringe.calibration.starts.device_start`).

    Parameters
    ----------
    points_target : (n_points, 3) array_like, mm, target points (z = 0).
    observations : (n_poses, n_points, 2) array_like, px; NaN where not observed.
    pixel_size : (du, dv), mm, for a telecentric device (known: only m/du is
        identifiable); a pinhole device needs none.
    image_size : (width, height), px.
    principal_point : {"estimate", "fixed"}
        "estimate": (u0, v0) free with a weak Gaussian prior at ``principal_point_value``
        (default: the image centre) of standard deviation ``principal_point_sigma`` px
        (default: half the image diagonal), which only matters when distortion does not
        determine them. "fixed": held at ``principal_point_value``.
    distortion : bool, estimate k1, s1, s2 (else held at 0).
    outlier_threshold : float, reject observations whose error exceeds this many robust
        standard deviations (per coordinate); ``inf`` disables.
    max_rounds : int, rejection rounds.
    min_points, min_poses : int, fewest markers for a usable pose, fewest usable poses.
    pose_names : sequence of str, for the outlier report; grid_shape : (rows, cols).
    name : str, the device's name in the outlier report.
    model : str, the device model (:data:`telefringe.calibration.starts.MODELS`).

    Returns
    -------
    DeviceCalibration

    Raises
    ------
    CalibrationError
        Too few usable poses, or the adjustment fails.
    """
    P, obs = check_observations(points_target, observations)
    n_poses = obs.shape[0]
    pose_names = [str(i) for i in range(n_poses)] if pose_names is None else list(pose_names)
    centre, sigma_pp = _pp_setup(principal_point, principal_point_value,
                                 principal_point_sigma, image_size)
    dev0, start, used, R0, T0 = device_start(model)(P, obs, pixel_size=pixel_size,
                                             image_size=image_size, principal_point=centre,
                                             min_points=min_points)
    if used.size < min_poses:
        raise CalibrationError(f"{name}: {used.size} usable pose(s), at least {min_poses} needed")
    n_u = used.size
    layout = ParameterLayout((name,), (tuple(dev0.param_names),), n_u)
    free = np.ones(layout.size, dtype=bool)
    free[layout.indices([f"{name}.{p}" for p in dev0.pose_names])] = False  # device frame
    if not dev0.sees_depth:  # the pose's depth along the axis is not seen
        free[layout.indices([f"pose_{i}.z" for i in range(n_u)])] = False
    pp_names = [f"{name}.{p}" for p in dev0.principal_point_names]
    if principal_point == "fixed":
        free[layout.indices(pp_names)] = False
    if not distortion:
        free[layout.indices([f"{name}.{p}" for p in dev0.distortion_names])] = False
    priors = ([(pp_names[0], centre[0], sigma_pp), (pp_names[1], centre[1], sigma_pp)]
              if principal_point == "estimate" else [])

    def build(obs_list, sigmas, prev):
        if prev is None:
            devs, R_dt, T_dt = [dev0], R0, T0
        else:
            devs, R_dt, T_dt = prev[0].unpack(prev[1])
        sig = [1.0] if sigmas is None else sigmas
        return BundleProblem(P, obs_list, devs, R_dt, T_dt, sigmas=sig, free=free,
                             priors=priors, device_names=[name])

    problem, x, keeps, outliers, sigmas = _adjust_with_rejection(
        build, [obs], [used], threshold=outlier_threshold, max_rounds=max_rounds,
        names=[name], pose_names=pose_names, grid_shape=grid_shape)
    problem, x = problem.rebased(x)
    devs, R_dt, T_dt = problem.unpack(x)
    device = devs[0]
    n_t = len(device.pose_names) - 3
    R_all = np.full((n_poses, 3, 3), np.nan)
    t_all = np.full((n_poses, n_t), np.nan)
    R_all[used] = R_dt
    t_all[used] = T_dt[:, :n_t]
    o = problem.obs[0]
    res = np.full(obs.shape, np.nan)
    res[used[o.pose], o.point] = problem.predict(x, 0) - o.uv
    rms, rms_pose = _rms(res, n_poses)
    cov, _ = problem.covariance(x)
    n_in = len(device.intrinsic_names)
    std = np.full(n_in, np.nan)
    weak = principal_point == "fixed"
    if cov is not None:
        std = np.sqrt(np.diag(problem.device_covariance(cov)))[:n_in]
        if principal_point == "estimate":
            weak = _pp_weak(device, std, image_size)
    else:
        weak = True  # singular normal equations: nothing is well determined
    return DeviceCalibration(device=device, R_dev_target=R_all, t_dev=t_all,
                             used=start.usable.copy(), residuals=res, rms=rms,
                             rms_per_pose=rms_pose, std=std, principal_point_weak=weak,
                             start=start, outliers=tuple(outliers))


def _rms(res: np.ndarray, n_poses: int):
    e2 = np.sum(res**2, axis=2)
    ok = np.isfinite(e2)
    rms = float(np.sqrt(np.mean(e2[ok]))) if ok.any() else float("nan")
    per = np.full(n_poses, np.nan)
    for i in range(n_poses):
        if ok[i].any():
            per[i] = float(np.sqrt(np.mean(e2[i][ok[i]])))
    return rms, per
