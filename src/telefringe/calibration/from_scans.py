"""Calibration from the scans of a calibration set: decode each pose, find the target's
markers, read the projector at them, learn the projector's nonlinearity, calibrate."""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np

from telefringe.calibration.errors import CalibrationError
from telefringe.calibration.rig import RigCalibration, calibrate_rig

__all__ = ["calibrate_from_scans"]


def calibrate_from_scans(scans: Iterable, target, camera_pixel_size, projector_pixel_size,
                         reference_pose: str, *, progress: Callable | None = None,
                         projector_side: str | None = None, min_poses: int = 4,
                         decode_options: dict | None = None,
                         **kwargs) -> RigCalibration:
    """Decode, detect and calibrate from the scans of a calibration set.

    Parameters
    ----------
    scans : iterable of (name, Scan)
        One scan per target pose (consumed one at a time: pass a generator to keep
        memory bounded). Each needs phase groups on both projector axes.
    target : object with ``rows``, ``cols``, ``pitch_mm``, ``diameter_mm`` and
        ``circles`` ("dark-on-light" or "light-on-dark"), e.g.
        :class:`telefringe.targets.grid.CircleGridTarget`.
    camera_pixel_size, projector_pixel_size : (du, dv), mm.
    reference_pose : str, name of the pose defining the world frame.
    progress : callable ``progress(done, name)`` or None, called after each pose.
    projector_side, min_poses, **kwargs : passed to :func:`calibrate_rig`.
    decode_options : dict, keyword arguments for :func:`telefringe.fringes.decode.decode` (e.g.
        ``{"gamma_correction": False}``: 4-step fringes hide most of a projector gamma,
        and the fit over each marker's surround averages the rest).

    Returns
    -------
    RigCalibration
        Poses whose grid cannot be found or ordered are skipped; the reasons are in
        ``warnings``.

    Raises
    ------
    CalibrationError
        Fewer than ``min_poses`` good poses, or the reference pose is not good.
    """
    from telefringe.fringes.decode import decode
    from telefringe.fringes.images import fringe_free_image
    from telefringe.targets.circle_grid import detect_circle_grid
    from telefringe.targets.observations import projector_observations

    rows, cols = int(target.rows), int(target.cols)
    r, c = np.mgrid[0:rows, 0:cols]
    P = np.stack([c.ravel() * float(target.pitch_mm), r.ravel() * float(target.pitch_mm),
                  np.zeros(r.size)], axis=1)
    dark = getattr(target, "circles", "dark-on-light") == "dark-on-light"
    names, cam_obs, proj_obs, warns, good = [], [], [], [], []
    learned: dict[tuple[str, int, int], list] = {}
    cam_size = proj_size = None
    for done, (name, scan) in enumerate(scans, start=1):
        man = scan.manifest
        if {g.axis for g in man.phase_groups} != {"u", "v"}:
            raise CalibrationError(f"pose {name}: calibration needs fringes along both "
                                   "projector axes (u and v phase groups)")
        rows_px, cols_px = scan.shape
        if cam_size is None:
            cam_size = (cols_px, rows_px)
            proj_size = (man.projector_width, man.projector_height)
        elif cam_size != (cols_px, rows_px) or proj_size != (man.projector_width,
                                                             man.projector_height):
            raise CalibrationError(f"pose {name}: image or projector size differs from the "
                                   "first pose")
        image = fringe_free_image(scan)
        det = detect_circle_grid(image, rows=rows, cols=cols, dark=dark)
        if not det:
            warns.append(f"pose {name}: skipped, {det.reason}")
            names.append(str(name))
            cam_obs.append(np.full((rows * cols, 2), np.nan))
            proj_obs.append(np.full((rows * cols, 2), np.nan))
            good.append(False)
            if progress is not None:
                progress(done, name)
            continue
        coords = decode(scan, **(decode_options or {}))
        if getattr(coords, "v_p", None) is None:
            raise CalibrationError(f"pose {name}: the decoder returned no v_p")
        for key, model in _learned_models(scan, coords).items():
            learned.setdefault(key, []).append(model)
        pobs = projector_observations(coords.u_p, coords.v_p, coords.mask, det)
        names.append(str(name))
        cam_obs.append(np.where(det.found[:, None], det.centers, np.nan))
        proj_obs.append(pobs.uv)
        good.append(True)
        if progress is not None:
            progress(done, name)
    if reference_pose not in names:
        raise CalibrationError(f"reference pose {reference_pose} is not among the scans; the "
                               "world frame is the target at the reference pose")
    if not good[names.index(reference_pose)]:
        raise CalibrationError(f"reference pose {reference_pose}: grid not found "
                               f"({'; '.join(warns)}); the world frame is the target at the "
                               "reference pose")
    if sum(good) < min_poses:
        raise CalibrationError(f"only {sum(good)} good pose(s), at least {min_poses} needed"
                               + (f" ({'; '.join(warns)})" if warns else ""))
    calib = calibrate_rig(P, np.array(cam_obs), np.array(proj_obs),
                          camera_pixel_size=camera_pixel_size,
                          projector_pixel_size=projector_pixel_size, camera_size=cam_size,
                          projector_size=proj_size, reference_pose=names.index(reference_pose),
                          pose_names=names, grid_shape=(rows, cols),
                          projector_side=projector_side, min_poses=min_poses,
                          warnings=warns, **kwargs)
    if not learned:
        return calib
    from dataclasses import replace

    from telefringe.fringes.nonlinearity import mean_model

    return replace(calib, phase_errors={k: mean_model(v) for k, v in sorted(learned.items())})


def _learned_models(scan, coords) -> dict:
    """The nonlinearity models a decode learned from ``scan``: ``(axis, periods, steps) ->
    PhaseErrorModel`` (models given to the decoder or not learned are left out)."""
    from telefringe.fringes.scan import PhaseGroup

    out = {}
    for axis, ax in (getattr(coords, "axes", None) or {}).items():
        fit = getattr(ax, "phase_errors", None)
        if fit is None or not fit.n_samples:
            continue
        steps = {int(g.periods): int(g.steps) for g in scan.manifest.groups
                 if isinstance(g, PhaseGroup) and g.axis == axis}
        for m in fit.models:
            if int(m.periods) in steps:
                out[(axis, int(m.periods), steps[int(m.periods)])] = m
    return out

