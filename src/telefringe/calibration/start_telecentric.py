"""Closed-form start of telecentric devices, and the mirror ambiguity of telecentric views.

What makes telecentric calibration different
--------------------------------------------
- No tz: depth along a device's axis never changes its image. Each target pose's depth
  is seen only through the *other* device (the projector), so a single device has 5
  pose parameters per view and the joint problem 6.
- Planar target, one device: the two tilts ``R`` and ``D R D`` (``D = diag(1, 1, -1)``,
  i.e. the third column's x, y entries change sign) give identical images, so a
  device calibrated alone knows each pose's rotation only up to this mirror. The joint
  adjustment picks, per pose, the branch that keeps the rig rigid
  (:func:`choose_branches`).
- What rigidity cannot fix: reflecting the whole scene along the camera axis (every
  pose ``R -> D R D`` for both devices) leaves *every* image of a flat target unchanged.
  The two solutions differ in the side the projector lights from and give heights of
  opposite sign. ``projector_side`` (where the projector is, seen in the camera image)
  chooses (:func:`mirror_needed`). Without it the calibration stops
  (:class:`MirrorAmbiguityError`): any convention would be a coin toss on someone's rig.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from telefringe.calibration.errors import CalibrationError
from telefringe.calibration.problem import check_observations
from telefringe.devices.telecentric import Intrinsics, TelecentricDevice
from telefringe.geometry.so3 import chordal_mean, project_to_rotation

__all__ = [
    "MIRROR_HELP",
    "MirrorAmbiguityError",
    "PROJECTOR_SIDES",
    "branches_against",
    "DeviceStart",
    "choose_branches",
    "closed_form_device",
    "mirror_needed",
    "mirror_pose",
    "resolve_rotations",
    "start_device",
]

#: Where the projector can be, seen in the camera image: image-axis direction (u, v).
PROJECTOR_SIDES = {"left": (-1.0, 0.0), "right": (1.0, 0.0), "top": (0.0, -1.0),
                   "bottom": (0.0, 1.0)}
_D = np.diag([1.0, 1.0, -1.0])

#: What to do when the side of the projector is not known (one line).
MIRROR_HELP = (
    "the side of the projector is needed: a flat target cannot tell this telecentric rig "
    "from its mirror image (heights of opposite sign). Stand an upright pin on the plate: "
    "its shadow falls away from the projector. Give the side where the projector is, seen "
    "in the camera image, as --projector-side left|right|top|bottom or as \"projector_side\" "
    "in calibration.json")


class MirrorAmbiguityError(CalibrationError):
    """A telecentric pair calibrated from a flat target without the projector's side."""


def mirror_pose(R: np.ndarray) -> np.ndarray:
    """The other tilt of a planar target giving the same telecentric image: ``D R D``.

    ``R`` (..., 3, 3) target -> device rotation; ``D = diag(1, 1, -1)``. The first two
    rows of the first two columns are unchanged, the third column's x, y entries and the
    third row's x, y entries change sign.
    """
    return _D @ np.asarray(R, dtype=float) @ _D


@dataclass(frozen=True)
class DeviceStart:
    """Closed-form start for one device (see :func:`closed_form_device`).

    Attributes
    ----------
    m : float, magnification.
    u0, v0 : float, principal point used (px).
    R_dev_target : (n_poses, 3, 3) ndarray, target -> device rotations (one of the two
        mirror tilts: the one with non-negative (0, 2) entry); NaN for unusable poses.
    t_dev : (n_poses, 2) ndarray, mm; NaN for unusable poses.
    usable : (n_poses,) bool, poses with at least 4 non-collinear observed markers.
    affine_rms : (n_poses,) ndarray, px, RMS of the per-pose affine fit.
    """

    m: float
    u0: float
    v0: float
    R_dev_target: np.ndarray
    t_dev: np.ndarray
    usable: np.ndarray
    affine_rms: np.ndarray


def closed_form_device(points_target, observations, *, pixel_size, principal_point,
                       min_points: int = 6) -> DeviceStart:
    """Closed-form start of a telecentric device from planar target views.

    Parameters
    ----------
    points_target : (n_points, 3) array_like, mm, target points (z = 0).
    observations : (n_poses, n_points, 2) array_like, px; NaN where not observed.
    pixel_size : (du, dv), mm.
    principal_point : (u0, v0), px, assumed principal point (e.g. the image centre).
    min_points : int, fewest markers for a pose to be usable.

    Returns
    -------
    DeviceStart

    Notes
    -----
    Per pose, ``(u, v) = A (x, y) + b`` is fitted (affine: distortion ignored); in
    sensor mm ``diag(du, dv) A = m B`` with ``B`` the top-left 2 x 2 block of the
    target -> device rotation, whose singular values are 1 and cos(tilt). So ``m`` is
    the largest singular value (median over poses), and ``B`` completes to a rotation
    up to the mirror tilt (:func:`mirror_pose`).
    """
    P, obs = check_observations(points_target, observations)
    du, dv = (float(v) for v in pixel_size)
    u0, v0 = (float(v) for v in principal_point)
    n_poses = obs.shape[0]
    A_mm = np.full((n_poses, 2, 2), np.nan)
    b_px = np.full((n_poses, 2), np.nan)
    rms = np.full(n_poses, np.nan)
    usable = np.zeros(n_poses, dtype=bool)
    scale = np.array([du, dv])
    for i in range(n_poses):
        ok = np.all(np.isfinite(obs[i]), axis=1)
        if ok.sum() < max(min_points, 4):
            continue
        M = np.column_stack([P[ok, 0], P[ok, 1], np.ones(ok.sum())])
        if np.linalg.matrix_rank(M[:, :2] - M[:, :2].mean(0), tol=1e-9) < 2:
            continue
        sol, *_ = np.linalg.lstsq(M, obs[i, ok], rcond=None)
        A = sol[:2].T  # (2, 2): columns d(u,v)/dx, d(u,v)/dy
        rms[i] = float(np.sqrt(np.mean(np.sum((M @ sol - obs[i, ok]) ** 2, axis=1))))
        A_mm[i] = scale[:, None] * A
        b_px[i] = sol[2]
        usable[i] = True
    if not usable.any():
        raise CalibrationError("no pose has enough observed markers for a closed-form start")
    sv = np.array([np.linalg.svd(A_mm[i], compute_uv=False)[0] for i in np.flatnonzero(usable)])
    m = float(np.median(sv))
    if not np.isfinite(m) or m <= 0:
        raise CalibrationError("closed-form start: degenerate views (zero magnification)")
    Rs = np.full((n_poses, 3, 3), np.nan)
    ts = np.full((n_poses, 2), np.nan)
    for i in np.flatnonzero(usable):
        B = A_mm[i] / m
        U, S, Vt = np.linalg.svd(B)
        V = Vt.T
        c = S[1] / S[0]
        if np.linalg.det(U) < 0:
            U[:, 1] *= -1.0
            c = -c
        if np.linalg.det(V) < 0:
            V[:, 1] *= -1.0
            c = -c
        c = float(np.clip(c, -1.0, 1.0))
        s = float(np.sqrt(max(0.0, 1.0 - c * c)))
        Rx = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
        Ue = np.eye(3)
        Ue[:2, :2] = U
        Ve = np.eye(3)
        Ve[:2, :2] = V
        R = project_to_rotation(Ue @ Rx @ Ve.T)
        if R[0, 2] < 0 or (R[0, 2] == 0 and R[1, 2] < 0):
            R = mirror_pose(R)
        Rs[i] = R
        ts[i] = (b_px[i] - (u0, v0)) * scale / m
    return DeviceStart(m=m, u0=u0, v0=v0, R_dev_target=Rs, t_dev=ts, usable=usable,
                       affine_rms=rms)


def start_device(points_target, observations, *, pixel_size, image_size, principal_point,
                 min_points: int = 6):
    """The start of a telecentric device calibrated alone: the device (identity pose) and,
    per usable pose, the target -> device rotation and translation (tz = 0).

    Returns (device, start, used (n_used,) pose indices, R (n_used, 3, 3), T (n_used, 3)).
    """
    if pixel_size is None:
        raise CalibrationError("a telecentric device needs its pixel size (pixel_size_mm): "
                               "only the magnification over the pixel pitch is seen")
    start = closed_form_device(points_target, observations, pixel_size=pixel_size,
                               principal_point=principal_point, min_points=min_points)
    used = np.flatnonzero(start.usable)
    w, h = (int(v) for v in image_size)
    du, dv = (float(v) for v in pixel_size)
    intr = Intrinsics(m=start.m, du=du, dv=dv, u0=float(principal_point[0]),
                      v0=float(principal_point[1]), width=w, height=h)
    T = np.column_stack([start.t_dev[used], np.zeros(used.size)])
    return TelecentricDevice(intr), start, used, start.R_dev_target[used], T


def choose_branches(R_ct, R_pt):
    """Per pose mirror branch of camera and projector keeping R_proj_cam rigid.

    ``R_ct``, ``R_pt``: (n, 3, 3) target -> device rotations from the single-device
    calibrations (arbitrary branch). Returns the chosen (R_ct, R_pt) with the reference
    (index 0) camera branch kept, and the spread (max Frobenius distance) of R_proj_cam.
    """
    n = R_ct.shape[0]
    best = None
    for q0 in (0, 1):
        R_pt0 = mirror_pose(R_pt[0]) if q0 else R_pt[0]
        ref = R_pt0 @ R_ct[0].T
        cost = 0.0
        choice = [(0, q0)]
        for i in range(1, n):
            cands = []
            for s in (0, 1):
                for q in (0, 1):
                    c = mirror_pose(R_ct[i]) if s else R_ct[i]
                    p = mirror_pose(R_pt[i]) if q else R_pt[i]
                    cands.append((np.linalg.norm(p @ c.T - ref), s, q))
            dmin, s, q = min(cands)
            cost += dmin
            choice.append((s, q))
        if best is None or cost < best[0]:
            best = (cost, choice)
    _, choice = best
    R_ct2 = np.array([mirror_pose(R_ct[i]) if s else R_ct[i] for i, (s, _) in enumerate(choice)])
    R_pt2 = np.array([mirror_pose(R_pt[i]) if q else R_pt[i] for i, (_, q) in enumerate(choice)])
    return R_ct2, R_pt2


def mirror_needed(R_pc: np.ndarray, projector_side: str) -> bool:
    """Whether the global mirror must be applied to put the projector on ``projector_side``
    of the camera image ("left", "right", "top" or "bottom")."""
    s = np.array(PROJECTOR_SIDES[projector_side])
    # projector viewing direction in camera image axes; the projector sits opposite
    a = R_pc[2, :2]
    dot = float(a @ s)
    if abs(dot) < 0.02:
        raise CalibrationError(
            f"projector_side={projector_side!r}: the projector's axis is not tilted "
            "toward that side of the camera image (it is tilted along the other image "
            "axis); give the side along which it is tilted")
    return dot > 0


def resolve_rotations(R_cam_target, R_proj_target, projector_side: str | None):
    """Settle the mirror ambiguities of two telecentric devices calibrated alone.

    Parameters
    ----------
    R_cam_target, R_proj_target : (n, 3, 3) target -> device rotations of the same poses
        (the reference pose first), each on an arbitrary mirror branch.
    projector_side : where the projector is in the camera image ("left", "right", "top",
        "bottom"); None raises :class:`MirrorAmbiguityError`.

    Returns
    -------
    R_cam_target, R_proj_target : (n, 3, 3), on one rigid, globally chosen branch.
    R_proj_cam : (3, 3), their mean relative rotation.
    mirror : str, how the global ambiguity was resolved ("projector_side=...").
    warnings : list of str.

    Raises
    ------
    MirrorAmbiguityError
        Without ``projector_side``: the images cannot decide.
    """
    R_ct, R_pt = choose_branches(np.asarray(R_cam_target), np.asarray(R_proj_target))
    R_pc = chordal_mean(R_pt @ np.transpose(R_ct, (0, 2, 1)))
    if projector_side is None:
        raise MirrorAmbiguityError(MIRROR_HELP)
    if mirror_needed(R_pc, projector_side):
        R_ct, R_pt, R_pc = mirror_pose(R_ct), mirror_pose(R_pt), mirror_pose(R_pc)
    return R_ct, R_pt, R_pc, f"projector_side={projector_side}", []


def branches_against(R_anchor, R_dev):
    """Per-pose mirror branch of a telecentric device that keeps it rigid with respect to
    an anchor device whose rotations are settled (e.g. a pinhole device, which sees depth
    and so has no mirror ambiguity).

    ``R_anchor``, ``R_dev``: (n, 3, 3) target -> device rotations of the same poses.
    Returns ``R_dev`` (n, 3, 3) on the branch (one per pose) that makes
    ``R_dev R_anchor^T`` most nearly constant (both branches of the reference pose are
    tried; the one with the smaller total spread wins).
    """
    R_a = np.asarray(R_anchor, dtype=float)
    R_d = np.asarray(R_dev, dtype=float)
    best = None
    for q0 in (0, 1):
        first = mirror_pose(R_d[0]) if q0 else R_d[0]
        ref = first @ R_a[0].T
        chosen = [first]
        cost = 0.0
        for i in range(1, R_d.shape[0]):
            cands = [R_d[i], mirror_pose(R_d[i])]
            dist = [np.linalg.norm(c @ R_a[i].T - ref) for c in cands]
            k = int(np.argmin(dist))
            cost += dist[k]
            chosen.append(cands[k])
        if best is None or cost < best[0]:
            best = (cost, np.array(chosen))
    return best[1]
