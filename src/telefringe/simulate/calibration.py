"""Simulated calibration sets: plate poses and their scans.

The reference pose (the first, ``pose_00``) is the identity target pose, so the world
frame of the virtual rig is the world frame a calibration from this set should find.
The other poses tilt the plate by up to ``max_tilt_deg`` (5 deg at least), turn it in
its plane by up to ``max_spin_deg`` and move it by up to ``max_shift_mm``, keeping every
circle centre within ``max_depth_mm`` of Z = 0 and inside both fields of view. One pair
of poses is a mirror pair (the camera sees both identically: the telecentric tilt-sign
ambiguity), and optionally the last pose has part of its grid outside the camera image.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from telefringe.calibration.manifest import CalibrationSetManifest
from telefringe.fringes.scan import Scan
from telefringe.geometry.so3 import rotation_from_rotvec
from telefringe.simulate.presets import VirtualRig
from telefringe.simulate.render import Truth, default_groups, image_radius_px, render_scan
from telefringe.simulate.scenes import CirclePlate, plate_from_target

__all__ = ["CalibrationPose", "simulate_calibration_poses", "mirror_pose",
           "render_calibration_set", "iter_calibration_set", "calibration_manifest",
           "projector_side"]


@dataclass(frozen=True, eq=False)
class CalibrationPose:
    """One plate pose: ``X_world = R_world_target @ X_target + t_world_target``.

    ``kind``: "reference", "random", "mirror-a", "mirror-b" (the camera sees a mirror
    pair identically) or "half-hidden" (part of the grid outside the camera image).
    """

    name: str
    R_world_target: np.ndarray
    t_world_target: np.ndarray
    kind: str = "random"


def _centre_target(vrig: VirtualRig) -> np.ndarray:
    t = vrig.target
    return np.array([(t.cols - 1) * t.pitch_mm / 2, (t.rows - 1) * t.pitch_mm / 2, 0.0])


def _pose_about_centre(R: np.ndarray, centre_world: np.ndarray, c_t: np.ndarray):
    """(R, t) placing the target's centre ``c_t`` at ``centre_world``."""
    return R, centre_world - R @ c_t


def mirror_pose(vrig: VirtualRig, R_world_target, t_world_target):
    """The pose the camera cannot tell from the given one (telecentric tilt ambiguity).

    With ``D = diag(1, 1, -1)`` and ``Rc = R_cam_world``: ``R' = Rc^T D Rc R D``, which
    keeps the first two rows and columns of ``R_cam_target`` (all an orthographic camera
    sees of a plane), and ``t'`` keeps the plate centre in place.
    """
    Rc = vrig.camera.R_dev_world
    D = np.diag([1.0, 1.0, -1.0])
    R = np.asarray(R_world_target, dtype=float)
    R2 = Rc.T @ D @ Rc @ R @ D
    c_t = _centre_target(vrig)
    centre = R @ c_t + np.asarray(t_world_target, dtype=float)
    return _pose_about_centre(R2, centre, c_t)


def _fits(vrig: VirtualRig, R, t, *, max_depth_mm: float, margin_px: float,
          need_all_visible: bool = True) -> bool:
    pts = plate_from_target(vrig.target, R, t).circle_centres_world()
    if np.max(np.abs(pts[:, 2])) > max_depth_mm:
        return False
    proj = vrig.projector
    tgt = vrig.target
    inside = np.ones(len(pts), dtype=bool)
    for cam in vrig.rig.cameras.values():
        r_cam = image_radius_px(cam, pts, 0.5 * tgt.diameter_mm) + margin_px
        u, v = cam.project(pts)
        inside &= ((u >= r_cam) & (u <= cam.intrinsics.width - 1 - r_cam)
                   & (v >= r_cam) & (v <= cam.intrinsics.height - 1 - r_cam))
    r_proj = image_radius_px(proj, pts, 0.5 * tgt.diameter_mm) + 2
    up, vp = proj.project(pts)
    lit = ((up >= r_proj) & (up <= proj.intrinsics.width - 1 - r_proj)
           & (vp >= r_proj) & (vp <= proj.intrinsics.height - 1 - r_proj))
    if need_all_visible:
        return bool(np.all(lit) and np.all(inside))
    return bool(np.mean(lit & inside) >= 0.3)


def simulate_calibration_poses(vrig: VirtualRig, *, n_poses: int = 12, seed: int = 0,
                               max_tilt_deg: float | None = None, max_spin_deg: float = 10.0,
                               max_shift_mm: float = 2.0, max_depth_mm: float | None = None,
                               mirror_pair: bool | None = None, half_hidden: bool = True
                               ) -> tuple[CalibrationPose, ...]:
    """Plate poses for a calibration set (see the module docstring).

    Parameters
    ----------
    vrig : VirtualRig
    n_poses : int
        Number of poses including the reference (>= 3 with a mirror pair; >= 4 with the
        half-hidden pose too).
    seed : int
    max_tilt_deg : float, deg (default: the rig's ``calibration_tilt_deg``).
    max_spin_deg : float, deg.  max_shift_mm : float, mm.
    max_depth_mm : float, optional
        Largest |Z| of any circle centre (default: half the rig's depth of field + 0.5).
    mirror_pair : bool, default: whether the camera is telecentric (only a telecentric
        camera sees both tilts of a mirror pair identically).
    half_hidden : bool

    Returns
    -------
    tuple of CalibrationPose, named ``pose_00`` ... in order; ``pose_00`` is the
    reference (identity).
    """
    if max_tilt_deg is None:
        max_tilt_deg = float(vrig.calibration_tilt_deg)
    if mirror_pair is None:
        mirror_pair = vrig.camera.model == "telecentric"
    need = 1 + (2 if mirror_pair else 0) + (1 if half_hidden else 0)
    if n_poses < max(need, 2):
        raise ValueError(f"n_poses must be at least {max(need, 2)} with these options, "
                         f"got {n_poses}")
    if not 0 < max_tilt_deg < 60:
        raise ValueError("max_tilt_deg must be in (0, 60)")
    if max_depth_mm is None:
        max_depth_mm = vrig.depth_of_field_mm / 2 + 0.5
    rng = np.random.default_rng(seed)
    c_t = _centre_target(vrig)
    c_w = c_t.copy()  # the reference plate centre, in the world
    poses = [CalibrationPose("pose_00", np.eye(3), np.zeros(3), "reference")]
    min_tilt = min(5.0, max_tilt_deg)

    def random_pose(tilt_lo: float):
        for _ in range(2000):
            tilt = np.radians(rng.uniform(tilt_lo, max_tilt_deg))
            az = rng.uniform(0, 2 * np.pi)
            spin = np.radians(rng.uniform(-max_spin_deg, max_spin_deg))
            R = (rotation_from_rotvec(tilt * np.array([np.cos(az), np.sin(az), 0.0]))
                 @ rotation_from_rotvec([0.0, 0.0, spin]))
            shift = np.array([rng.uniform(-max_shift_mm, max_shift_mm),
                              rng.uniform(-max_shift_mm, max_shift_mm),
                              rng.uniform(-1.0, 1.0)])
            R, t = _pose_about_centre(R, c_w + shift, c_t)
            if _fits(vrig, R, t, max_depth_mm=max_depth_mm, margin_px=3.0):
                yield R, t
        raise ValueError("could not place a plate pose inside both fields of view and the "
                         "depth limit; relax max_tilt_deg / max_shift_mm / max_depth_mm")

    n_random = n_poses - need
    if mirror_pair:
        for R, t in random_pose(max(min_tilt, 0.6 * max_tilt_deg)):
            R2, t2 = mirror_pose(vrig, R, t)
            if _fits(vrig, R2, t2, max_depth_mm=max_depth_mm, margin_px=3.0):
                poses.append(CalibrationPose("", R, t, "mirror-a"))
                poses.append(CalibrationPose("", R2, t2, "mirror-b"))
                break
    gen = random_pose(min_tilt)
    for _ in range(n_random):
        R, t = next(gen)
        poses.append(CalibrationPose("", R, t, "random"))
    if half_hidden:
        cam = vrig.camera
        # slide the plate along the camera's +u direction until ~40% of the grid is out
        for R, t in random_pose(min_tilt):
            du_dir = cam.R_dev_world[0] - cam.R_dev_world[0] @ R[:, 2] * R[:, 2]
            du_dir /= np.linalg.norm(du_dir)
            width = (vrig.target.cols - 1) * vrig.target.pitch_mm
            t = t + 0.7 * width * du_dir
            pts = plate_from_target(vrig.target, R, t).circle_centres_world()
            u, v = cam.project(pts)
            frac = np.mean((u >= 0) & (u <= cam.intrinsics.width - 1)
                           & (v >= 0) & (v <= cam.intrinsics.height - 1))
            if (0.4 <= frac <= 0.8 and _fits(vrig, R, t, max_depth_mm=max_depth_mm,
                                             margin_px=0.0, need_all_visible=False)):
                poses.append(CalibrationPose("", R, t, "half-hidden"))
                break
    return tuple(CalibrationPose(f"pose_{i:02d}", p.R_world_target, p.t_world_target, p.kind)
                 for i, p in enumerate(poses))


def projector_side(rig, camera: str | None = None) -> str:
    """Where the projector of ``rig`` (a Rig or VirtualRig) is, seen in the image of
    ``camera`` (default: the first): "left", "right", "top" or "bottom" (what
    ``projector_side`` of calibration.json says; shadows fall away from that side).

    The direction from the scene toward the projector (against a telecentric
    projector's axis; toward a pinhole projector's centre from the point its axis meets
    in front of the camera), expressed in the camera's frame, is largest along one image
    axis.
    """
    rig = getattr(rig, "rig", rig)
    cam = rig.cameras[camera or rig.camera_names[0]]
    proj = rig.projector
    if proj.model == "telecentric":
        toward = -proj.R_dev_world[2]
    else:
        centre = proj.R_dev_world.T @ (-np.asarray(proj.t_dev, dtype=float))
        toward = -proj.R_dev_world[2]
        # the scene point on the projector's axis nearest the camera's axis
        if cam.model != "telecentric":
            c_cam = cam.R_dev_world.T @ (-np.asarray(cam.t_dev, dtype=float))
            d_cam, d_proj = cam.R_dev_world[2], proj.R_dev_world[2]
            A = np.array([[d_proj @ d_proj, -d_proj @ d_cam], [d_proj @ d_cam, -d_cam @ d_cam]])
            b = np.array([(c_cam - centre) @ d_proj, (c_cam - centre) @ d_cam])
            s = np.linalg.solve(A, b)[0]
            toward = -s * d_proj
    x, y, _ = cam.R_dev_world @ toward
    if abs(x) >= abs(y):
        return "right" if x > 0 else "left"
    return "bottom" if y > 0 else "top"


def calibration_manifest(vrig: VirtualRig, poses) -> CalibrationSetManifest:
    """The calibration-set manifest of a virtual rig's poses (reference = first): each
    device's model (and pixel size where telecentric) and, for one camera, the side of
    its projector (:func:`projector_side`), as a user would note it."""
    names = tuple(p.name for p in poses)
    devices = dict(vrig.rig.cameras)
    devices["projector"] = vrig.projector
    models = {k: d.model for k, d in devices.items()}
    sizes = {k: (float(d.intrinsics.du), float(d.intrinsics.dv)) for k, d in devices.items()
             if d.model == "telecentric"}
    side = projector_side(vrig) if len(vrig.rig.cameras) == 1 else None
    return CalibrationSetManifest(target=vrig.target,
                                  camera_pixel_size=sizes.get("camera"),
                                  projector_pixel_size=sizes.get("projector"),
                                  poses=names, reference_pose=names[0], models=models,
                                  pixel_sizes=sizes, projector_side=side)


def _pose_seed(seed: int, k: int, camera_index: int = 0) -> int:
    key = [int(seed), int(k)] + ([int(camera_index)] if camera_index else [])
    return int(np.random.SeedSequence(key).generate_state(1)[0])


def iter_calibration_set(vrig: VirtualRig, poses, *, groups=None, seed: int = 0,
                         progress: Callable | None = None, camera: str | None = None
                         ) -> Iterator[tuple[str, Scan, Truth, CalibrationPose]]:
    """Render the poses one by one (bounded memory): yields (name, scan, truth, pose).

    ``progress(done, total)`` counts poses. ``camera``: which camera of the rig renders
    (default the first; each camera has its own noise).
    """
    if groups is None:
        groups = default_groups(vrig)
    ci = 0 if camera is None else vrig.rig.camera_names.index(camera)
    view = vrig if camera is None else vrig.for_camera(camera)
    for k, pose in enumerate(poses):
        plate = CirclePlate(R_world_target=pose.R_world_target,
                            t_world_target=pose.t_world_target, rows=vrig.target.rows,
                            cols=vrig.target.cols, pitch=vrig.target.pitch_mm,
                            diameter=vrig.target.diameter_mm)
        scan, truth = render_scan(view, plate, groups, seed=_pose_seed(seed, k, ci))
        truth.features["pose_kind"] = pose.kind
        if progress is not None:
            progress(k + 1, len(poses))
        yield pose.name, scan, truth, pose


def render_calibration_set(vrig: VirtualRig, *, n_poses: int = 12, seed: int = 0,
                           groups=None, progress: Callable | None = None, **pose_options
                           ) -> tuple[list[tuple[str, Scan, Truth]], CalibrationSetManifest]:
    """Simulate a whole calibration set in memory.

    Returns
    -------
    poses : list of (name, Scan, Truth), the reference pose first.
    manifest : CalibrationSetManifest (what ``calibration.json`` holds).

    For the paper rig this holds all images in memory (about 35 MB per pose); the
    command line writes pose by pose with :func:`iter_calibration_set` instead.
    """
    poses = simulate_calibration_poses(vrig, n_poses=n_poses, seed=seed, **pose_options)
    out = [(name, scan, truth) for name, scan, truth, _ in
           iter_calibration_set(vrig, poses, groups=groups, seed=seed, progress=progress)]
    return out, calibration_manifest(vrig, poses)
