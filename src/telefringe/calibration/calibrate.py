"""Calibration of telecentric devices and of a telecentric camera-projector rig.

The camera and the projector share one model (:mod:`telefringe.devices.telecentric`); the projector
is an inverse camera whose "image" of each circle centre is read from the phase maps
(:func:`telefringe.targets.projector_observations`).

Steps
-----
1. :func:`closed_form_device`: per pose, an affine fit of the planar target's image
   (telecentric views of a plane are affine), factorised into the magnification (the
   largest singular value of the 2 x 2 block: every 2 x 2 block of a rotation has
   singular values 1 and cos(tilt)), a rotation and an in-plane translation. Never a
   zero start.
2. :func:`calibrate_device`: Levenberg-Marquardt refinement (analytic Jacobian
   assembled sparse, Marquardt-scaled normal equations; see
   :func:`_levenberg_marquardt` for why not ``scipy.optimize.least_squares``) of
   m, (u0, v0), k1, s1, s2 and every pose, with outlier rejection.
3. :func:`calibrate_rig`: joint adjustment of both devices over one set of target poses
   (world frame = target at the reference pose), relative pose of the devices as
   unknowns; parameter covariance from the Jacobian.

What makes telecentric calibration different
--------------------------------------------
- No tz: depth along a device's axis never changes its image. Each target pose's depth
  is seen only through the *other* device (the projector), so a single device has 5
  pose parameters per view and the joint problem 6.
- Planar target, one device: the two tilts ``R`` and ``D R D`` (``D = diag(1, 1, -1)``,
  i.e. the third column's x, y entries change sign) give identical images, so a
  device calibrated alone knows each pose's rotation only up to this mirror. The joint
  adjustment picks, per pose, the branch that keeps the rig rigid.
- What rigidity cannot fix: reflecting the whole scene along the camera axis (every
  pose ``R -> D R D`` for both devices) leaves *every* image of a flat target unchanged.
  The two solutions differ in the side the projector lights from and give heights of
  opposite sign. ``projector_side`` (where the projector is, seen in the camera image)
  chooses; without it the convention below is used and a warning says so.
- (u0, v0) are only seen through the distortion (a shift of the principal point is
  otherwise a shift of t); they can be estimated with a weak prior at the image centre
  (default) or held fixed (``principal_point="fixed"``). The report flags them as weak
  (:func:`_pp_weak`) when no distortion coefficient is significant or their standard
  deviation exceeds 1 % of the image diagonal; a weak principal point costs little
  accuracy, since it then barely changes any image.

Mirror convention (no ``projector_side``): the solution in which the projector
coordinate most sensitive to depth (u_p or v_p) *increases with depth along the camera
axis* (decreases as a surface rises toward the camera), as in the paper's rig.

Units: mm in the world and on sensors, px in images, radians. Reprojection "RMS" is
the root mean square of the 2-D error length over points (px of the device).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from telefringe.devices.rig import Rig
from telefringe.devices.telecentric import Intrinsics, TelecentricDevice
from telefringe.geometry.so3 import (
    chordal_mean,
    left_jacobian,
    project_to_rotation,
    rotation_from_rotvec,
    skew,
)

__all__ = [
    "INTRINSIC_NAMES",
    "RIG_PARAMETER_NAMES",
    "CalibrationError",
    "DeviceStart",
    "DeviceCalibration",
    "Outlier",
    "RigCalibration",
    "closed_form_device",
    "calibrate_device",
    "calibrate_rig",
    "calibrate_from_scans",
    "mirror_pose",
]

INTRINSIC_NAMES = ("m", "u0", "v0", "k1", "s1", "s2")
_DEV_NAMES = INTRINSIC_NAMES + ("rot_x", "rot_y", "rot_z", "tx", "ty")
#: Names of :attr:`RigCalibration.parameters` (rotations as small left perturbations of
#: ``R_dev_world``, radians, in the device frame).
RIG_PARAMETER_NAMES = tuple(f"camera.{n}" for n in _DEV_NAMES) + tuple(
    f"projector.{n}" for n in _DEV_NAMES)
_SIDES = {"left": (-1.0, 0.0), "right": (1.0, 0.0), "top": (0.0, -1.0), "bottom": (0.0, 1.0)}
_D = np.diag([1.0, 1.0, -1.0])


class CalibrationError(ValueError):
    """Calibration cannot proceed: too few poses, degenerate views, no convergence."""


def mirror_pose(R: np.ndarray) -> np.ndarray:
    """The other tilt of a planar target giving the same telecentric image: ``D R D``.

    ``R`` (..., 3, 3) target -> device rotation; ``D = diag(1, 1, -1)``. The first two
    rows of the first two columns are unchanged, the third column's x, y entries and the
    third row's x, y entries change sign.
    """
    return _D @ np.asarray(R, dtype=float) @ _D


# --------------------------------------------------------------------------- projection
def _project_jac(q, du, dv, R, t, X):
    """Project points ``X`` (n, 3) through a device with intrinsics ``q`` = (m, u0, v0,
    k1, s1, s2), rotation ``R`` (3, 3) and translation ``t`` (2,).

    Returns ``uv`` (n, 2) px, ``J_q`` (n, 2, 6), ``J_t`` (n, 2, 2), ``J_Y`` (n, 2, 3)
    (derivative with respect to ``Y = R X``) and ``Y`` (n, 3).
    """
    m, u0, v0, k1, s1, s2 = q
    Y = X @ R.T
    a = Y[:, 0] + t[0]
    b = Y[:, 1] + t[1]
    xu = m * a
    yu = m * b
    r2 = xu * xu + yu * yu
    xd = xu + k1 * xu * r2 + s1 * r2
    yd = yu + k1 * yu * r2 + s2 * r2
    uv = np.stack([u0 + xd / du, v0 + yd / dv], axis=1)
    n = X.shape[0]
    # distortion Jacobian d(xd, yd)/d(xu, yu), scaled to pixels
    G = np.empty((n, 2, 2))
    G[:, 0, 0] = (1.0 + k1 * (r2 + 2.0 * xu * xu) + 2.0 * s1 * xu) / du
    G[:, 0, 1] = (2.0 * k1 * xu * yu + 2.0 * s1 * yu) / du
    G[:, 1, 0] = (2.0 * k1 * xu * yu + 2.0 * s2 * xu) / dv
    G[:, 1, 1] = (1.0 + k1 * (r2 + 2.0 * yu * yu) + 2.0 * s2 * yu) / dv
    J_q = np.zeros((n, 2, 6))
    J_q[:, :, 0] = G[:, :, 0] * a[:, None] + G[:, :, 1] * b[:, None]
    J_q[:, 0, 1] = 1.0
    J_q[:, 1, 2] = 1.0
    J_q[:, 0, 3] = xu * r2 / du
    J_q[:, 1, 3] = yu * r2 / dv
    J_q[:, 0, 4] = r2 / du
    J_q[:, 1, 5] = r2 / dv
    J_t = m * G
    J_Y = np.zeros((n, 2, 3))
    J_Y[:, :, :2] = J_t
    return uv, J_q, J_t, J_Y, Y


# --------------------------------------------------------------------------- the problem
@dataclass
class _Obs:
    """Observations of one device: pose index, point index, measured (u, v) px."""

    pose: np.ndarray
    point: np.ndarray
    uv: np.ndarray


class _Problem:
    """A bundle adjustment over devices and target poses (internal).

    Full parameter vector: per device [m, u0, v0, k1, s1, s2, dw(3), t(2)] (11), then per
    pose [dw(3), T(3)] (6). Rotations are ``R = R(dw) R0`` (left perturbation).
    Residuals: per device, per observation (u, v) (pred - meas) / sigma; then priors.
    """

    def __init__(self, points, obs, pixel_sizes, q0, devR0, devt0, poseR0, poseT0,
                 free, sigmas, priors):
        self.P = np.asarray(points, dtype=float)
        self.obs = obs
        self.pixel_sizes = pixel_sizes
        self.n_dev = len(obs)
        self.n_pose = len(poseR0)
        self.devR0 = np.asarray(devR0, dtype=float)
        self.poseR0 = np.asarray(poseR0, dtype=float)
        full = []
        for d in range(self.n_dev):
            full += list(q0[d]) + [0.0, 0.0, 0.0] + list(devt0[d])
        for i in range(self.n_pose):
            full += [0.0, 0.0, 0.0] + list(poseT0[i])
        self.full0 = np.array(full, dtype=float)
        self.free = np.asarray(free, dtype=bool)
        self.colmap = np.full(self.full0.size, -1)
        self.colmap[self.free] = np.arange(int(self.free.sum()))
        self.sigmas = np.asarray(sigmas, dtype=float)
        self.priors = priors  # list of (full index, centre, sigma)
        self._cache_x = None
        self._cache = None

    @property
    def x0(self) -> np.ndarray:
        return self.full0[self.free].copy()

    def full(self, x) -> np.ndarray:
        f = self.full0.copy()
        f[self.free] = x
        return f

    def unpack(self, x):
        """Current (q (n_dev, 6), R_dev (n_dev, 3, 3), t_dev (n_dev, 2), R_pose, T_pose)."""
        f = self.full(x)
        dev = f[:11 * self.n_dev].reshape(self.n_dev, 11)
        pose = f[11 * self.n_dev:].reshape(self.n_pose, 6)
        Rd = np.array([rotation_from_rotvec(dev[d, 6:9]) @ self.devR0[d]
                       for d in range(self.n_dev)])
        Rp = np.array([rotation_from_rotvec(pose[i, :3]) @ self.poseR0[i]
                       for i in range(self.n_pose)])
        return dev[:, :6].copy(), Rd, dev[:, 9:11].copy(), Rp, pose[:, 3:].copy(), dev, pose

    def predict(self, x, d):
        """Predicted (u, v) of device ``d``'s observations, and the parts of the chain."""
        q, Rd, td, Rp, Tp, dev, pose = self.unpack(x)
        o = self.obs[d]
        RP = np.einsum("nij,nj->ni", Rp[o.pose], self.P[o.point])
        X = RP + Tp[o.pose]
        du, dv = self.pixel_sizes[d]
        uv, J_q, J_t, J_Y, Y = _project_jac(q[d], du, dv, Rd[d], td[d], X)
        return uv, (J_q, J_t, J_Y, Y, RP, Rd[d], dev[d], pose)

    def _evaluate(self, x):
        if self._cache_x is not None and np.array_equal(x, self._cache_x):
            return self._cache
        res, rows, cols, vals = [], [], [], []
        row0 = 0
        for d in range(self.n_dev):
            o = self.obs[d]
            n = o.pose.size
            if n == 0:
                continue
            uv, (J_q, J_t, J_Y, Y, RP, Rdev, devp, pose) = self.predict(x, d)
            s = self.sigmas[d]
            res.append(((uv - o.uv) / s).ravel())
            J_dw = J_Y @ (-skew(Y)) @ left_jacobian(devp[6:9])
            J_X = J_Y @ Rdev
            Jl_pose = np.array([left_jacobian(pose[i, :3]) for i in range(self.n_pose)])
            J_pw = J_X @ (-skew(RP)) @ Jl_pose[o.pose]
            blocks = np.concatenate([J_q, J_dw, J_t, J_pw, J_X], axis=2) / s  # (n, 2, 17)
            c_dev = 11 * d + np.arange(11)
            c_pose = 11 * self.n_dev + 6 * o.pose[:, None] + np.arange(6)[None, :]
            c = np.concatenate([np.broadcast_to(c_dev, (n, 11)), c_pose], axis=1)  # (n, 17)
            r = row0 + 2 * np.arange(n)[:, None] + np.arange(2)[None, :]  # (n, 2)
            rows.append(np.broadcast_to(r[:, :, None], blocks.shape).ravel())
            cols.append(np.broadcast_to(c[:, None, :], blocks.shape).ravel())
            vals.append(blocks.ravel())
            row0 += 2 * n
        f = self.full(x)
        for j, (idx, centre, sig) in enumerate(self.priors):
            res.append(np.array([(f[idx] - centre) / sig]))
            rows.append(np.array([row0 + j]))
            cols.append(np.array([idx]))
            vals.append(np.array([1.0 / sig]))
        nrow = row0 + len(self.priors)
        r = np.concatenate(res) if res else np.zeros(0)
        rows = np.concatenate(rows)
        cols = self.colmap[np.concatenate(cols)]
        vals = np.concatenate(vals)
        keep = cols >= 0
        import scipy.sparse as sp  # (here: loading the rig need not import scipy)

        J = sp.csr_matrix((vals[keep], (rows[keep], cols[keep])),
                          shape=(nrow, int(self.free.sum())))
        self._cache_x = np.array(x, copy=True)
        self._cache = (r, J)
        return r, J

    def residuals(self, x):
        return self._evaluate(x)[0]

    def jacobian(self, x):
        return self._evaluate(x)[1]

    def solve(self, *, max_iter: int = 100):
        """Minimise the sum of squared residuals from ``x0`` (see :func:`_levenberg_marquardt`)."""
        n = int(self.free.sum())
        m = self.residuals(self.x0).size
        if m < n:
            raise CalibrationError(
                f"{m} residuals for {n} unknowns: too few observed markers or poses")
        return _levenberg_marquardt(self._evaluate, self.x0, max_iter=max_iter)

    def covariance(self, x):
        """Parameter covariance (free parameters) from the Jacobian, scaled by the
        reduced chi-square; rotations relinearised at the solution."""
        J = self.jacobian(x).toarray()
        r = self.residuals(x)
        dof = max(r.size - J.shape[1], 1)
        chi2 = float(r @ r) / dof
        JTJ = J.T @ J
        scale = np.sqrt(np.diag(JTJ))
        scale[scale == 0] = 1.0
        A = JTJ / np.outer(scale, scale)
        w = np.linalg.eigvalsh(A)
        if w[0] <= w[-1] * 1e-13:
            return None, chi2
        cov = np.linalg.inv(A) / np.outer(scale, scale)
        return cov * chi2, chi2


@dataclass(frozen=True)
class _LMResult:
    x: np.ndarray
    cost: float
    iterations: int


def _levenberg_marquardt(fun_jac, x0, *, max_iter: int = 100, tol: float = 1e-8):
    """Levenberg-Marquardt on the normal equations of a sparse Jacobian.

    ``fun_jac(x) -> (r (m,), J (m, n) sparse)``. Marquardt's scaling (damping
    proportional to diag(J^T J)) makes it invariant to the parameters' units. Stops when
    a step changes no parameter by more than ``tol`` of its (Jacobi) standard deviation
    or lowers the cost by less than 1e-8 of the mean squared residual (in chi-square
    units, a change of 1e-8: parameters are then within about 1e-4 standard deviations
    of the minimum, even along the slow modes of nearly frontal poses).

    Why not ``scipy.optimize.least_squares``: its exact trust-region solver takes an SVD
    of the dense (m, n) Jacobian at every iteration (about 0.3 s for 12 poses on a loaded
    2-core machine), and its sparse LSMR solver stalls before metrology precision on these
    ill-scaled problems; the normal equations of the sparse Jacobian are (n, n), n < 200.
    ``tests/test_calibrate.py`` checks that both reach the same minimum.
    """
    x = np.array(x0, dtype=float)
    r, J = fun_jac(x)
    cost = float(r @ r)
    lam = 1e-4
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007
        A = (J.T @ J).toarray()
        g = J.T @ r
        dA = np.diag(A).copy()
        dA[dA <= 0] = 1.0
        sc = 1.0 / np.sqrt(dA)
        As = A * np.outer(sc, sc)  # Jacobi-scaled normal equations (unit diagonal)
        gs = g * sc
        while True:
            try:
                step = -sc * np.linalg.solve(As + lam * np.eye(As.shape[0]), gs)
            except np.linalg.LinAlgError:
                step = np.full_like(x, np.nan)
            if np.all(np.isfinite(step)):
                x_new = x + step
                r_new, J_new = fun_jac(x_new)
                cost_new = float(r_new @ r_new)
                if np.isfinite(cost_new) and cost_new <= cost:
                    break
            lam *= 10.0
            if lam > 1e16:
                return _LMResult(x, cost, it)
        rms = max(np.sqrt(cost / max(r.size, 1)), 1e-300)
        small_step = float(np.max(np.abs(step) / sc)) <= tol * rms
        small_cost = cost - cost_new <= 1e-8 * cost / max(r.size, 1)
        x, r, J, cost = x_new, r_new, J_new, cost_new
        lam = max(lam / 10.0, 1e-12)
        if small_step or small_cost:
            break
    if not np.all(np.isfinite(x)):
        raise CalibrationError("the adjustment diverged")
    return _LMResult(x, cost, it)


def _rebased(problem: _Problem, x) -> tuple[_Problem, np.ndarray]:
    """The same problem with rotations re-centred at ``x`` (perturbations zero)."""
    q, Rd, td, Rp, Tp, dev, pose = problem.unpack(x)
    new = _Problem(problem.P, problem.obs, problem.pixel_sizes, q, Rd, td, Rp, Tp,
                   problem.free, problem.sigmas, problem.priors)
    return new, new.x0


def _robust_sigma(e: np.ndarray) -> float:
    """Robust per-coordinate standard deviation from 2-D errors (n, 2) (MAD)."""
    if e.size == 0:
        return float("nan")
    return float(1.4826 * np.median(np.abs(e - np.median(e, axis=0))))


# --------------------------------------------------------------------------- closed form
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


def _check_inputs(points_target, observations, what="observations"):
    P = np.asarray(points_target, dtype=float)
    obs = np.asarray(observations, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3 or not np.all(np.isfinite(P)):
        raise CalibrationError("points_target must be a finite (n_points, 3) array (mm)")
    if not np.allclose(P[:, 2], 0.0):
        raise CalibrationError("points_target must lie in the target plane z = 0")
    if obs.ndim != 3 or obs.shape[1:] != (P.shape[0], 2):
        raise CalibrationError(
            f"{what} must be (n_poses, {P.shape[0]}, 2) px, got {obs.shape}")
    return P, obs


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
    P, obs = _check_inputs(points_target, observations)
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


# --------------------------------------------------------------------------- one device
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
    """A telecentric device calibrated alone from planar target views.

    Attributes
    ----------
    intrinsics : Intrinsics
    R_dev_target : (n_poses, 3, 3) ndarray, target -> device, one of the two mirror
        tilts per pose (see :func:`mirror_pose`); NaN for unused poses.
    t_dev : (n_poses, 2) ndarray, mm; NaN for unused poses.
    used : (n_poses,) bool.
    residuals : (n_poses, n_points, 2) ndarray, px (predicted - observed); NaN where
        not observed or rejected.
    rms : float, px, RMS reprojection error (2-D error length) over used observations.
    rms_per_pose : (n_poses,) ndarray, px (NaN for unused poses).
    std : (6,) ndarray, standard deviations of (m, u0, v0, k1, s1, s2); NaN if fixed.
    principal_point_weak : bool, the data barely constrain (u0, v0) (the prior or the
        fixed value decides them).
    start : DeviceStart, the closed-form start.
    outliers : tuple of Outlier.
    """

    intrinsics: Intrinsics
    R_dev_target: np.ndarray
    t_dev: np.ndarray
    used: np.ndarray
    residuals: np.ndarray
    rms: float
    rms_per_pose: np.ndarray
    std: np.ndarray
    principal_point_weak: bool
    start: DeviceStart
    outliers: tuple[Outlier, ...] = ()


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


def _pp_weak(q, std, size) -> bool:
    """Whether (u0, v0) are weakly determined: no distortion coefficient (k1, s1, s2)
    differs from zero by 5 standard deviations (the principal point is then fixed by
    noise-level distortion, where the linear uncertainty is not to be trusted), or the
    standard deviation of u0 or v0 exceeds 1 % of the image diagonal."""
    q = np.asarray(q, dtype=float)
    std = np.asarray(std, dtype=float)
    if not np.all(np.isfinite(std[:6])):
        return True
    significant = np.any(np.abs(q[3:6]) > 5.0 * std[3:6])
    return bool(not significant or max(std[1], std[2]) > 0.01 * float(np.hypot(*size)))


def _marker_label(k: int, grid_shape) -> tuple[int, int]:
    if grid_shape is None:
        return (0, int(k))
    return tuple(int(v) for v in divmod(int(k), int(grid_shape[1])))


def _obs_from_array(obs: np.ndarray, poses: Sequence[int], keep: np.ndarray) -> _Obs:
    """Collect finite, kept observations of the given poses (indices into ``obs``)."""
    pi, ki, uv = [], [], []
    for j, i in enumerate(poses):
        ok = np.flatnonzero(np.all(np.isfinite(obs[i]), axis=1) & keep[i])
        pi.append(np.full(ok.size, j))
        ki.append(ok)
        uv.append(obs[i, ok])
    return _Obs(np.concatenate(pi).astype(int), np.concatenate(ki).astype(int),
                np.concatenate(uv).reshape(-1, 2))


def _adjust_with_rejection(build, obs_arrays, pose_lists, *, threshold, max_rounds,
                           names, pose_names, grid_shape):
    """Solve, reject observations whose error exceeds ``threshold`` robust sigmas, repeat.

    ``build(obs_list, sigmas, x_prev)`` -> _Problem. Returns (problem, x, keep masks,
    outliers, sigmas).
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
        for d, (o, p) in enumerate(zip(obs_list, pose_lists, strict=True)):
            uv, _ = problem.predict(x, d)
            e = uv - o.uv
            sig = max(_robust_sigma(e), 1e-6)
            new_sigmas.append(sig)
            if threshold is None or not np.isfinite(threshold) or _round >= max_rounds:
                continue
            bad = np.flatnonzero(np.hypot(e[:, 0], e[:, 1]) > threshold * sig)
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


def _warm_start(problem_prev, x_prev):
    """Unpacked state of a previous solve, for warm starts."""
    if problem_prev is None:
        return None
    return problem_prev.unpack(x_prev)


def calibrate_device(points_target, observations, *, pixel_size, image_size,
                     principal_point: str = "estimate", principal_point_value=None,
                     principal_point_sigma: float | None = None, distortion: bool = True,
                     outlier_threshold: float = 5.0, max_rounds: int = 3,
                     min_points: int = 6, min_poses: int = 3, pose_names=None,
                     grid_shape=None, name: str = "device") -> DeviceCalibration:
    """Calibrate one telecentric device (camera, or projector as inverse camera).

    Parameters
    ----------
    points_target : (n_points, 3) array_like, mm, target points (z = 0).
    observations : (n_poses, n_points, 2) array_like, px; NaN where not observed.
    pixel_size : (du, dv), mm (known: only m/du is identifiable).
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

    Returns
    -------
    DeviceCalibration

    Raises
    ------
    CalibrationError
        Too few usable poses, or the adjustment fails.
    """
    P, obs = _check_inputs(points_target, observations)
    n_poses = obs.shape[0]
    pose_names = [str(i) for i in range(n_poses)] if pose_names is None else list(pose_names)
    centre, sigma_pp = _pp_setup(principal_point, principal_point_value,
                                 principal_point_sigma, image_size)
    start = closed_form_device(P, obs, pixel_size=pixel_size, principal_point=centre,
                               min_points=min_points)
    used = np.flatnonzero(start.usable)
    if used.size < min_poses:
        raise CalibrationError(f"{name}: {used.size} usable pose(s), at least {min_poses} needed")
    n_u = used.size
    free = np.ones(11 + 6 * n_u, dtype=bool)
    free[6:11] = False  # device frame = identity
    free[11 + 6 * np.arange(n_u) + 5] = False  # no tz
    if principal_point == "fixed":
        free[1:3] = False
    if not distortion:
        free[3:6] = False
    priors = [(1, centre[0], sigma_pp), (2, centre[1], sigma_pp)] \
        if principal_point == "estimate" else []
    ps = tuple(float(v) for v in pixel_size)

    def build(obs_list, sigmas, prev):
        st = _warm_start(*prev) if prev is not None else None
        if st is None:
            q0 = [[start.m, centre[0], centre[1], 0.0, 0.0, 0.0]]
            Rp = start.R_dev_target[used]
            Tp = np.column_stack([start.t_dev[used], np.zeros(n_u)])
        else:
            q0, Rp, Tp = st[0], st[3], st[4]
        sig = [1.0] if sigmas is None else sigmas
        return _Problem(P, obs_list, [ps], q0, [np.eye(3)], [np.zeros(2)], Rp, Tp, free,
                        sig, priors)

    problem, x, keeps, outliers, sigmas = _adjust_with_rejection(
        build, [obs], [used], threshold=outlier_threshold, max_rounds=max_rounds,
        names=[name], pose_names=pose_names, grid_shape=grid_shape)
    problem, x = _rebased(problem, x)
    q, _, _, Rp, Tp, _, _ = problem.unpack(x)
    w, h = (int(v) for v in image_size)
    intr = Intrinsics(m=float(q[0, 0]), du=ps[0], dv=ps[1], u0=float(q[0, 1]),
                      v0=float(q[0, 2]), k1=float(q[0, 3]), s1=float(q[0, 4]),
                      s2=float(q[0, 5]), width=w, height=h)
    R_all = np.full((n_poses, 3, 3), np.nan)
    t_all = np.full((n_poses, 2), np.nan)
    R_all[used] = Rp
    t_all[used] = Tp[:, :2]
    uv, _ = problem.predict(x, 0)
    o = problem.obs[0]
    res = np.full(obs.shape, np.nan)
    res[used[o.pose], o.point] = uv - o.uv
    rms, rms_pose = _rms(res, n_poses)
    cov, _ = problem.covariance(x)
    std = np.full(6, np.nan)
    weak = principal_point == "fixed"
    if cov is not None:
        cols = problem.colmap[:6]
        for j in range(6):
            if cols[j] >= 0:
                std[j] = float(np.sqrt(cov[cols[j], cols[j]]))
        if principal_point == "estimate":
            weak = _pp_weak(q[0], std, (w, h))
    return DeviceCalibration(intrinsics=intr, R_dev_target=R_all, t_dev=t_all,
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


# --------------------------------------------------------------------------- the rig
@dataclass(frozen=True, eq=False)
class RigCalibration:
    """A calibrated telecentric camera-projector rig and its report.

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
    parameters : (22,) ndarray, the rig parameters named by :data:`RIG_PARAMETER_NAMES`
        (rotations as zero perturbations; their uncertainty is the covariance).
    covariance : (22, 22) ndarray, parameter covariance from the Jacobian (scaled by
        the reduced chi-square; NaN rows/columns for fixed parameters).
    std : (22,) ndarray, sqrt of the covariance's diagonal.
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
    mirror : str, how the global mirror ambiguity was resolved ("projector_side=..."
        or "convention").
    warnings : tuple of str, things a person should read (skipped poses, conventions).
    camera_alone, projector_alone : DeviceCalibration or None, the single-device
        calibrations that started the joint adjustment (not stored in rig.json).
    phase_errors : dict ``(axis, periods, steps) -> PhaseErrorModel``, the projector
        nonlinearity learned from the calibration scans (mean over the poses of each
        pose's fit, :func:`telefringe.gamma.mean_model`); empty when it was not learned.
        Pass it to :func:`telefringe.decode.decode` to skip learning it from every scan.
    """

    rig: Rig
    pose_names: tuple[str, ...]
    reference_pose: str
    used: np.ndarray
    R_world_target: np.ndarray
    t_world_target: np.ndarray
    points_target: np.ndarray
    grid_shape: tuple[int, int] | None
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
    def camera(self) -> TelecentricDevice:
        """The calibrated camera (``rig.camera``): a RigCalibration can stand for a Rig."""
        return self.rig.camera

    @property
    def projector(self) -> TelecentricDevice:
        """The calibrated projector (``rig.projector``)."""
        return self.rig.projector

    def std_of(self, name: str) -> float:
        """Standard deviation of one parameter by name (see :data:`RIG_PARAMETER_NAMES`)."""
        return float(self.std[RIG_PARAMETER_NAMES.index(name)])


def _choose_branches(Rc, Rp):
    """Per pose mirror branch of camera and projector keeping R_proj_cam rigid.

    ``Rc``, ``Rp``: (n, 3, 3) target -> device rotations from the single-device
    calibrations (arbitrary branch). Returns the chosen (Rc, Rp) with the reference
    (index 0) camera branch kept, and the spread (max Frobenius distance) of R_proj_cam.
    """
    n = Rc.shape[0]
    best = None
    for q0 in (0, 1):
        Rp0 = mirror_pose(Rp[0]) if q0 else Rp[0]
        ref = Rp0 @ Rc[0].T
        cost = 0.0
        choice = [(0, q0)]
        for i in range(1, n):
            cands = []
            for s in (0, 1):
                for q in (0, 1):
                    c = mirror_pose(Rc[i]) if s else Rc[i]
                    p = mirror_pose(Rp[i]) if q else Rp[i]
                    cands.append((np.linalg.norm(p @ c.T - ref), s, q))
            dmin, s, q = min(cands)
            cost += dmin
            choice.append((s, q))
        if best is None or cost < best[0]:
            best = (cost, choice)
    _, choice = best
    Rc2 = np.array([mirror_pose(Rc[i]) if s else Rc[i] for i, (s, _) in enumerate(choice)])
    Rp2 = np.array([mirror_pose(Rp[i]) if q else Rp[i] for i, (_, q) in enumerate(choice)])
    return Rc2, Rp2


def _mirror_needed(R_pc: np.ndarray, projector_side: str | None) -> bool:
    """Whether the global mirror must be applied to meet the hint or the convention."""
    if projector_side is not None:
        s = np.array(_SIDES[projector_side])
        # projector viewing direction in camera image axes; the projector sits opposite
        a = R_pc[2, :2]
        dot = float(a @ s)
        if abs(dot) < 0.02:
            raise CalibrationError(
                f"projector_side={projector_side!r}: the projector's axis is not tilted "
                "toward that side of the camera image (it is tilted along the other image "
                "axis); give the side along which it is tilted")
        return dot > 0
    j = 0 if abs(R_pc[0, 2]) >= abs(R_pc[1, 2]) else 1
    return R_pc[j, 2] < 0


def calibrate_rig(points_target, camera_observations, projector_observations, *,
                  camera_pixel_size, projector_pixel_size, camera_size, projector_size,
                  reference_pose: int = 0, pose_names=None, grid_shape=None,
                  projector_side: str | None = None, principal_point: str = "estimate",
                  principal_point_sigma: float | None = None,
                  outlier_threshold: float = 5.0, max_rounds: int = 3,
                  min_poses: int = 4, min_points: int = 6,
                  warnings: Sequence[str] = ()) -> RigCalibration:
    """Joint calibration of a telecentric camera and projector from target poses.

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
        target (see the module notes); None uses the convention and adds a warning.
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
    P, cam = _check_inputs(points_target, camera_observations, "camera_observations")
    _, proj = _check_inputs(points_target, projector_observations, "projector_observations")
    if cam.shape != proj.shape:
        raise CalibrationError("camera and projector observations must have the same shape")
    if projector_side is not None and projector_side not in _SIDES:
        raise ValueError(f"projector_side must be one of {sorted(_SIDES)}, got "
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
    Rc, Rp = _choose_branches(cal_c.R_dev_target[poses], cal_p.R_dev_target[poses])
    R_pc = chordal_mean(Rp @ np.transpose(Rc, (0, 2, 1)))
    if _mirror_needed(R_pc, projector_side):
        Rc, Rp, R_pc = mirror_pose(Rc), mirror_pose(Rp), mirror_pose(R_pc)
    if projector_side is None:
        mirror = "convention"
        warns.append("projector_side not given: the mirror ambiguity of a flat target was "
                     "resolved by convention (the projector coordinate most sensitive to depth "
                     "decreases as a surface rises toward the camera); if heights come out "
                     "inverted, calibrate again with the projector's side")
    else:
        mirror = f"projector_side={projector_side}"
    # degenerate pose sets: every target normal (in the camera) nearly the same
    normals = Rc[:, :, 2]
    spread = np.degrees(np.max(np.arccos(np.clip(normals @ normals[0], -1, 1))))
    if spread < 1.0:
        raise CalibrationError(
            f"the target has the same tilt in every pose (spread {spread:.2f} deg): depth "
            "cannot be calibrated; tilt the target in several directions")
    R_cw = Rc[0]
    R_pw = R_pc @ R_cw
    R_wt = np.array([chordal_mean([R_cw.T @ Rc[j], R_pw.T @ Rp[j]])
                     for j in range(len(poses))])
    R_wt[0] = np.eye(3)
    t_c = cal_c.t_dev[poses]
    t_p = cal_p.t_dev[poses]
    M = np.vstack([R_cw[:2], R_pw[:2]])
    T = np.zeros((len(poses), 3))
    for j in range(1, len(poses)):
        T[j] = np.linalg.lstsq(M, np.concatenate([t_c[j] - t_c[0], t_p[j] - t_p[0]]),
                               rcond=None)[0]
    q0 = [_q_of(cal_c.intrinsics), _q_of(cal_p.intrinsics)]
    n_u = len(poses)
    free = np.ones(22 + 6 * n_u, dtype=bool)
    free[22:28] = False  # reference pose = world frame
    cam_size = tuple(int(v) for v in camera_size)
    proj_size = tuple(int(v) for v in projector_size)
    centre_c, sig_c = _pp_setup(principal_point, None, principal_point_sigma, cam_size)
    centre_p, sig_p = _pp_setup(principal_point, None, principal_point_sigma, proj_size)
    priors = []
    if principal_point == "fixed":
        free[[1, 2, 12, 13]] = False
        q0[0][1:3] = centre_c
        q0[1][1:3] = centre_p
    else:
        priors = [(1, centre_c[0], sig_c), (2, centre_c[1], sig_c),
                  (12, centre_p[0], sig_p), (13, centre_p[1], sig_p)]
    pix = [tuple(float(v) for v in camera_pixel_size),
           tuple(float(v) for v in projector_pixel_size)]
    sig0 = [max(cal_c.rms, 1e-6) / np.sqrt(2), max(cal_p.rms, 1e-6) / np.sqrt(2)]

    def build(obs_list, sigmas, prev):
        if prev is None:
            return _Problem(P, obs_list, pix, q0, [R_cw, R_pw], [t_c[0], t_p[0]], R_wt, T,
                            free, sig0, priors)
        st = _warm_start(*prev)
        return _Problem(P, obs_list, pix, st[0], st[1], st[2], st[3], st[4], free,
                        sig0 if sigmas is None else sigmas, priors)

    problem, x, keeps, outliers, sigmas = _adjust_with_rejection(
        build, [cam, proj], [poses, poses], threshold=outlier_threshold,
        max_rounds=max_rounds, names=["camera", "projector"], pose_names=names,
        grid_shape=grid_shape)
    problem, x = _rebased(problem, x)
    q, Rd, td, Rpose, Tpose, _, _ = problem.unpack(x)
    devs = []
    for d, (ps, size) in enumerate(((pix[0], cam_size), (pix[1], proj_size))):
        intr = Intrinsics(m=float(q[d, 0]), du=ps[0], dv=ps[1], u0=float(q[d, 1]),
                          v0=float(q[d, 2]), k1=float(q[d, 3]), s1=float(q[d, 4]),
                          s2=float(q[d, 5]), width=size[0], height=size[1])
        devs.append(TelecentricDevice(intr, Rd[d], td[d]))
    rig = Rig(camera=devs[0], projector=devs[1])
    residuals = []
    for d in range(2):
        uv, _ = problem.predict(x, d)
        o = problem.obs[d]
        res = np.full(cam.shape, np.nan)
        res[np.asarray(poses)[o.pose], o.point] = uv - o.uv
        residuals.append(res)
    rms_c, per_c = _rms(residuals[0], n_poses)
    rms_p, per_p = _rms(residuals[1], n_poses)
    cov_free, _ = problem.covariance(x)
    if cov_free is None:
        raise CalibrationError("the poses do not determine the rig (singular normal "
                               "equations): tilt the target in several directions")
    cov = np.full((22, 22), np.nan)
    cols = problem.colmap[:22]
    idx = np.flatnonzero(cols >= 0)
    cov[np.ix_(idx, idx)] = cov_free[np.ix_(cols[idx], cols[idx])]
    std = np.sqrt(np.diag(cov))
    rot_std = std[[6, 7, 8, 17, 18, 19]]
    if np.any(rot_std > 0.05):
        raise CalibrationError(
            "the poses barely determine the rig's rotations (std up to "
            f"{np.nanmax(rot_std):.3g} rad): tilt the target more, in several directions")
    params = np.concatenate([q[0], [0, 0, 0], td[0], q[1], [0, 0, 0], td[1]])
    if principal_point == "estimate":
        weak = (_pp_weak(q[0], std[:11], cam_size), _pp_weak(q[1], std[11:], proj_size))
    else:
        weak = (True, True)
    for dname, w in zip(("camera", "projector"), weak, strict=True):
        if w and principal_point == "estimate":
            warns.append(f"{dname}: the principal point is weakly determined by the data "
                         "(little distortion); it stays near the image-centre prior, which "
                         "costs little accuracy")
    R_all = np.full((n_poses, 3, 3), np.nan)
    T_all = np.full((n_poses, 3), np.nan)
    R_all[poses] = Rpose
    T_all[poses] = Tpose
    used = np.zeros(n_poses, dtype=bool)
    used[poses] = True
    return RigCalibration(
        rig=rig, pose_names=tuple(names), reference_pose=names[ref], used=used,
        R_world_target=R_all, t_world_target=T_all, points_target=P.copy(),
        grid_shape=None if grid_shape is None else tuple(int(v) for v in grid_shape),
        parameters=params, covariance=cov, std=std, sigma_camera=float(sigmas[0]),
        sigma_projector=float(sigmas[1]), residuals_camera=residuals[0],
        residuals_projector=residuals[1], rms_camera=rms_c, rms_projector=rms_p,
        rms_per_pose=np.column_stack([per_c, per_p]), outliers=tuple(outliers),
        camera_observations=cam.copy(), projector_observations=proj.copy(),
        principal_point=principal_point, principal_point_weak=weak, mirror=mirror,
        warnings=tuple(warns), camera_alone=cal_c, projector_alone=cal_p)


def _q_of(k: Intrinsics) -> list[float]:
    return [k.m, k.u0, k.v0, k.k1, k.s1, k.s2]


# --------------------------------------------------------------------------- pipeline
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
        :class:`telefringe.io.scan.CircleGridTarget`.
    camera_pixel_size, projector_pixel_size : (du, dv), mm.
    reference_pose : str, name of the pose defining the world frame.
    progress : callable ``progress(done, name)`` or None, called after each pose.
    projector_side, min_poses, **kwargs : passed to :func:`calibrate_rig`.
    decode_options : dict, keyword arguments for :func:`telefringe.decode.decode` (e.g.
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
    from telefringe.targets.circle_grid import detect_circle_grid, projector_observations

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

