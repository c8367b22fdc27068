"""Calibration from the scans of a calibration set: decode each pose, find the target's
markers, read the projector at them, learn the projector's nonlinearity, calibrate."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping

import numpy as np

from telefringe.calibration.errors import CalibrationError
from telefringe.calibration.rig import RigCalibration, calibrate_devices

__all__ = ["calibrate_from_scans"]


def calibrate_from_scans(scans: Iterable, target, camera_pixel_size, projector_pixel_size,
                         reference_pose: str, *, progress: Callable | None = None,
                         projector_side: str | None = None, min_poses: int = 4,
                         decode_options: dict | None = None,
                         models: Mapping[str, str] | None = None,
                         pixel_sizes: Mapping[str, object] | None = None,
                         **kwargs) -> RigCalibration:
    """Decode, detect and calibrate from the scans of a calibration set.

    Parameters
    ----------
    scans : iterable of (name, Scan) or (name, {camera name: Scan})
        One scan per target pose (one per camera and pose for two cameras: a mapping
        ``{"camera": scan, "camera_2": scan}``), consumed one at a time (pass a
        generator to keep memory bounded). The first camera's scans need phase groups on
        both projector axes when the projector is calibrated.
    target : object with ``rows``, ``cols``, ``pitch_mm``, ``diameter_mm`` and
        ``circles`` ("dark-on-light" or "light-on-dark"), e.g.
        :class:`telefringe.targets.grid.CircleGridTarget`.
    camera_pixel_size, projector_pixel_size : (du, dv), mm, or None (a pinhole device).
    reference_pose : str, name of the pose defining the world frame.
    progress : callable ``progress(done, name)`` or None, called after each pose.
    projector_side, min_poses, **kwargs : passed to
        :func:`~telefringe.calibration.rig.calibrate_devices`.
    decode_options : dict, keyword arguments for :func:`telefringe.fringes.decode.decode`
        (default: its defaults, the projector's nonlinearity learned and removed). Without
        that correction (``{"gamma_correction": False}``, faster) the decoded coordinate
        keeps a fixed error along each projector axis, a function of the projector
        coordinate (the coarser groups fused into it bring their nonlinearity errors at
        periods the fit over a marker's surround does not average out: 0.0019 px RMS in
        the v observations of the fast rig's reference pose, 0.0005 with it), which the
        calibration absorbs into the projector's intrinsics (about one standard deviation
        of m, u0, v0 and k1 on the fast rig, the same in every calibration;
        tests/test_projector_observations.py).
    models : mapping device name -> model (default: a telecentric camera and projector);
        names ``camera``, optionally ``camera_2``, optionally ``projector`` (a two-camera
        rig may leave the projector uncalibrated).
    pixel_sizes : mapping device name -> (du, dv) mm (default: from the two arguments).

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

    if models is None:
        models = {"camera": "telecentric", "projector": "telecentric"}
    models = dict(models)
    if pixel_sizes is None:
        pixel_sizes = {"camera": camera_pixel_size, "projector": projector_pixel_size}
    cameras = [d for d in models if d != "projector"]
    with_projector = "projector" in models
    rows, cols = int(target.rows), int(target.cols)
    r, c = np.mgrid[0:rows, 0:cols]
    P = np.stack([c.ravel() * float(target.pitch_mm), r.ravel() * float(target.pitch_mm),
                  np.zeros(r.size)], axis=1)
    dark = getattr(target, "circles", "dark-on-light") == "dark-on-light"
    names, warns, good = [], [], []
    obs: dict[str, list] = {d: [] for d in models}
    learned: dict[tuple[str, int, int], list] = {}
    sizes: dict = {}
    missing = np.full((rows * cols, 2), np.nan)
    for done, (name, item) in enumerate(scans, start=1):
        by_cam = dict(item) if isinstance(item, Mapping) else {cameras[0]: item}
        if set(by_cam) != set(cameras):
            raise CalibrationError(f"pose {name}: scans of {sorted(by_cam)} given, the rig's "
                                   f"cameras are {cameras}")
        names.append(str(name))
        dets = {}
        for cam in cameras:
            scan = by_cam[cam]
            man = scan.manifest
            rows_px, cols_px = scan.shape
            this = {cam: (cols_px, rows_px), "projector": (man.projector_width,
                                                           man.projector_height)}
            for k, v in this.items():
                if sizes.setdefault(k, v) != v:
                    raise CalibrationError(f"pose {name}: image or projector size differs "
                                           "from the first pose")
            det = detect_circle_grid(fringe_free_image(scan), rows=rows, cols=cols, dark=dark)
            if not det:
                who = f" ({cam})" if len(cameras) > 1 else ""
                warns.append(f"pose {name}: skipped, {det.reason}{who}")
            dets[cam] = det
        ok = all(bool(dets[cam]) for cam in cameras)
        good.append(ok)
        for cam in cameras:
            obs[cam].append(np.where(dets[cam].found[:, None], dets[cam].centers, np.nan)
                            if ok else missing)
        if with_projector:
            if not ok:
                obs["projector"].append(missing)
            else:
                scan = by_cam[cameras[0]]
                if {g.axis for g in scan.manifest.phase_groups} != {"u", "v"}:
                    raise CalibrationError(f"pose {name}: calibration needs fringes along "
                                           "both projector axes (u and v phase groups)")
                coords = decode(scan, **(decode_options or {}))
                if getattr(coords, "v_p", None) is None:
                    raise CalibrationError(f"pose {name}: the decoder returned no v_p")
                for key, model in _learned_models(scan, coords).items():
                    learned.setdefault(key, []).append(model)
                pobs = projector_observations(coords.u_p, coords.v_p, coords.mask,
                                              dets[cameras[0]])
                obs["projector"].append(pobs.uv)
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
    calib = calibrate_devices(P, {d: np.array(obs[d]) for d in models}, models=models,
                              pixel_sizes={d: pixel_sizes.get(d) for d in models},
                              image_sizes={d: sizes[d] for d in models},
                              reference_pose=names.index(reference_pose), pose_names=names,
                              grid_shape=(rows, cols), projector_side=projector_side,
                              min_poses=min_poses, warnings=warns,
                              marker_radius=0.5 * float(target.diameter_mm),
                              **{"projector_at_camera_centres": True, **kwargs})
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

