"""Closed-form start of a pinhole device from planar target views (Zhang's method).

Per pose, the homography of the target plane to the image gives two constraints on the
image of the absolute conic; three or more poses determine the camera matrix
(``cv2.initCameraMatrix2D``), each pose then follows from its homography
(``cv2.solvePnP``). Distortion starts at zero; the bundle adjustment estimates it. A
pinhole device sees depth, so a device calibrated alone has no mirror ambiguity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from telefringe.calibration.errors import CalibrationError
from telefringe.calibration.problem import check_observations
from telefringe.devices.pinhole import PinholeDevice, PinholeIntrinsics
from telefringe.geometry.so3 import rotation_from_rotvec

__all__ = ["PinholeStart", "start_device"]


@dataclass(frozen=True)
class PinholeStart:
    """Closed-form start of a pinhole device.

    Attributes
    ----------
    camera_matrix : (3, 3) ndarray, K of the start (px).
    R_dev_target : (n_poses, 3, 3) ndarray, target -> device; NaN for unusable poses.
    t_dev : (n_poses, 3) ndarray, mm; NaN for unusable poses.
    usable : (n_poses,) bool, poses with enough non-collinear observed markers.
    """

    camera_matrix: np.ndarray
    R_dev_target: np.ndarray
    t_dev: np.ndarray
    usable: np.ndarray


def start_device(points_target, observations, *, pixel_size=None, image_size,
                 principal_point, min_points: int = 6):
    """The start of a pinhole device calibrated alone: the device (identity pose) and, per
    usable pose, the target -> device rotation and translation.

    Parameters
    ----------
    points_target : (n_points, 3) mm on z = 0; observations : (n_poses, n_points, 2) px,
        NaN where not observed; pixel_size : ignored (a pinhole model needs none);
    image_size : (width, height) px; principal_point : (cx, cy) px, the start of the
        principal point (the camera matrix's own estimate is used for the focal lengths).

    Returns (device, start, used (n_used,) pose indices, R (n_used, 3, 3), T (n_used, 3)).
    Raises CalibrationError with fewer than 3 usable poses or degenerate views.
    """
    import cv2

    P, obs = check_observations(points_target, observations)
    w, h = (int(v) for v in image_size)
    if w <= 0 or h <= 0:
        raise CalibrationError("a pinhole start needs the image size")
    n_poses = obs.shape[0]
    usable = np.zeros(n_poses, dtype=bool)
    obj, img = [], []
    for i in range(n_poses):
        ok = np.all(np.isfinite(obs[i]), axis=1)
        if ok.sum() >= max(min_points, 4) and np.linalg.matrix_rank(
                P[ok, :2] - P[ok, :2].mean(0), tol=1e-9) == 2:
            usable[i] = True
            obj.append(P[ok].astype(np.float32))
            img.append(obs[i, ok].astype(np.float32))
    if usable.sum() < 3:
        raise CalibrationError(f"{int(usable.sum())} usable pose(s): a pinhole start needs "
                               "at least 3 views of the plane in different tilts")
    K = cv2.initCameraMatrix2D(obj, img, (w, h))
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0):
        raise CalibrationError("pinhole start: the views do not determine the focal length "
                               "(tilt the target more, in several directions)")
    K = np.array(K, dtype=float)
    K[0, 2], K[1, 2] = (float(v) for v in principal_point)
    Rs = np.full((n_poses, 3, 3), np.nan)
    ts = np.full((n_poses, 3), np.nan)
    for j, i in enumerate(np.flatnonzero(usable)):
        ok_pnp, rvec, tvec = cv2.solvePnP(obj[j].astype(float), img[j].astype(float), K,
                                          np.zeros(5))
        if not ok_pnp or float(tvec[2, 0]) <= 0:
            usable[i] = False
            continue
        Rs[i] = rotation_from_rotvec(rvec.ravel())
        ts[i] = tvec.ravel()
    used = np.flatnonzero(usable)
    intr = PinholeIntrinsics(fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]),
                             cy=float(K[1, 2]), width=w, height=h)
    start = PinholeStart(K, Rs, ts, usable)
    return PinholeDevice(intr), start, used, Rs[used], ts[used]
