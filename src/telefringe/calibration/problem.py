"""A bundle adjustment over any devices and the poses of a planar target.

The parameter vector is assembled from blocks that the devices declare (their
``param_names``, see :mod:`telefringe.devices.base`), then one block per target pose,
``POSE_PARAMETER_NAMES`` (a left rotation perturbation, rad, and the translation T, mm,
of ``X_world = R_world_target P + T``). Names address parameters, never positions:
``layout.index("camera.u0")``, ``layout.index("pose_3.z")``. Residuals: per device, per
observation, ``(predicted - measured) / sigma`` in its pixels (one sigma per image axis);
then the Gaussian priors.

Observations read at another device's observations (``coupled_to``): a projector's
coordinates are read from the phase at the camera's *detected* marker centre, so the
camera's detection error e_c moves the plate point they are read at, and the projector
observation carries ``A e_c`` besides its own noise, ``A`` (2 x 2) the derivative of the
projector pixel with respect to the camera pixel along the target plane (from both
devices' point Jacobians at the current estimate). Treated as independent, the two
observations would count that one error twice (on the fast rig ``A e_c`` is about 70 % of
the projector observation's variance; it over-states the plate height's calibration
uncertainty by 1.8 x, benchmarks/uncertainty.py). Such a device's residual is the
projector's error given the camera's, ``(e_p - A e_c) / sigma_p``, exactly independent of
the camera's to first order, with ``sigma_p`` the projector's own noise; its Jacobian rows
hold ``-A`` times the camera's. An observation without its camera partner is dropped.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from telefringe.calibration.errors import CalibrationError
from telefringe.calibration.solver import LMResult, levenberg_marquardt
from telefringe.devices.base import ROTATION_NAMES, Device
from telefringe.geometry.so3 import left_jacobian, rotation_from_rotvec, skew

__all__ = [
    "POSE_PARAMETER_NAMES",
    "BundleProblem",
    "Observations",
    "ParameterLayout",
    "check_observations",
]

#: The parameters of each target pose: rotation perturbation (rad), translation (mm).
POSE_PARAMETER_NAMES = ROTATION_NAMES + ("x", "y", "z")


@dataclass
class Observations:
    """Observations of one device: pose index (n,), point index (n,), measured uv (n, 2) px."""

    pose: np.ndarray
    point: np.ndarray
    uv: np.ndarray


@dataclass(frozen=True)
class ParameterLayout:
    """Where each named parameter sits in the full vector.

    Attributes
    ----------
    device_names : tuple of str, e.g. ("camera", "projector").
    device_params : tuple of tuples of str, each device's ``param_names``.
    n_poses : int.
    """

    device_names: tuple[str, ...]
    device_params: tuple[tuple[str, ...], ...]
    n_poses: int

    @property
    def device_offsets(self) -> tuple[int, ...]:
        return tuple(int(v) for v in np.cumsum([0] + [len(p) for p in self.device_params])[:-1])

    @property
    def n_device_params(self) -> int:
        """Number of device parameters (all blocks): the rig's parameter vector."""
        return int(sum(len(p) for p in self.device_params))

    @property
    def size(self) -> int:
        return self.n_device_params + len(POSE_PARAMETER_NAMES) * self.n_poses

    @property
    def device_parameter_names(self) -> tuple[str, ...]:
        """``"device.param"`` for every device parameter, in order."""
        return tuple(f"{d}.{p}" for d, ps in zip(self.device_names, self.device_params,
                                                 strict=True) for p in ps)

    @property
    def names(self) -> tuple[str, ...]:
        """Every parameter's name: the device parameters, then ``"pose_<i>.<name>"``."""
        return self.device_parameter_names + tuple(
            f"pose_{i}.{p}" for i in range(self.n_poses) for p in POSE_PARAMETER_NAMES)

    def device_slice(self, d: int) -> slice:
        o = self.device_offsets[d]
        return slice(o, o + len(self.device_params[d]))

    def pose_slice(self, i: int) -> slice:
        o = self.n_device_params + len(POSE_PARAMETER_NAMES) * i
        return slice(o, o + len(POSE_PARAMETER_NAMES))

    def index(self, name: str) -> int:
        """Position of parameter ``name`` (``"camera.u0"``, ``"pose_2.z"``)."""
        head, _, tail = name.partition(".")
        if head.startswith("pose_") and head[5:].isdigit():
            i = int(head[5:])
            if 0 <= i < self.n_poses and tail in POSE_PARAMETER_NAMES:
                return self.pose_slice(i).start + POSE_PARAMETER_NAMES.index(tail)
        elif head in self.device_names:
            d = self.device_names.index(head)
            if tail in self.device_params[d]:
                return self.device_slice(d).start + self.device_params[d].index(tail)
        raise KeyError(f"no parameter named {name!r}")

    def indices(self, names: Sequence[str]) -> np.ndarray:
        return np.array([self.index(n) for n in names], dtype=int)


class BundleProblem:
    """Least squares over devices and target poses (see the module notes).

    Parameters
    ----------
    points : (n_points, 3) array_like, target points, mm (z = 0).
    obs : sequence of :class:`Observations`, one per device.
    devices : sequence of Device, the start of each device; its rotation is the centre
        of the rotation perturbation (``R = R(dw) R0``).
    pose_R0 : (n_poses, 3, 3), pose_T0 : (n_poses, 3), start of the target poses.
    free : (layout.size,) bool, which parameters are estimated (default: all).
    sigmas : sequence, per-device observation noise (px): a float (both image axes) or
        (sigma_u, sigma_v).
    priors : sequence of (name, centre, sigma): Gaussian priors on named parameters.
    device_names : sequence of str (default "camera", "projector", "device_2", ...).
    coupled_to : mapping device index -> device index, optional: the observations of
        the first were read at the second's (see the module notes); held at the start's
        state (``A`` at ``devices``, ``pose_R0``, ``pose_T0``).
    """

    def __init__(self, points, obs, devices: Sequence[Device], pose_R0, pose_T0, *,
                 sigmas, free=None, priors=(), device_names=None, coupled_to=None):
        self.P = np.asarray(points, dtype=float)
        self.obs = list(obs)
        self.devices0 = list(devices)
        self.n_dev = len(self.devices0)
        if len(self.obs) != self.n_dev:
            raise ValueError("one Observations per device")
        if device_names is None:
            device_names = ["camera", "projector"][:self.n_dev] + [
                f"device_{d}" for d in range(2, self.n_dev)]
        self.poseR0 = np.asarray(pose_R0, dtype=float)
        self.n_pose = len(self.poseR0)
        self.layout = ParameterLayout(tuple(device_names),
                                      tuple(tuple(d.param_names) for d in self.devices0),
                                      self.n_pose)
        self._rot = [np.array([names.index(r) for r in ROTATION_NAMES])
                     for names in self.layout.device_params]
        full = [d.to_params() for d in self.devices0]
        T0 = np.asarray(pose_T0, dtype=float).reshape(self.n_pose, 3)
        full += [np.concatenate([np.zeros(3), T0[i]]) for i in range(self.n_pose)]
        self.full0 = np.concatenate(full) if full else np.zeros(0)
        self.free = (np.ones(self.layout.size, dtype=bool) if free is None
                     else np.asarray(free, dtype=bool))
        if self.free.shape != (self.layout.size,):
            raise ValueError(f"free must have {self.layout.size} entries")
        self.colmap = np.full(self.full0.size, -1)
        self.colmap[self.free] = np.arange(int(self.free.sum()))
        sig = [np.broadcast_to(np.asarray(v, dtype=float), (2,)) for v in sigmas]
        if len(sig) != self.n_dev:
            raise ValueError("one sigma (or pair) per device")
        self.sigmas = np.array(sig).reshape(self.n_dev, 2)
        self.coupled_to = {int(k): int(v) for k, v in dict(coupled_to or {}).items()}
        self._partner: dict[int, np.ndarray] = {}
        self._A: dict[int, np.ndarray] = {}
        T0r = np.asarray(pose_T0, dtype=float).reshape(self.n_pose, 3)
        for d, c in self.coupled_to.items():
            if d == c or not (0 <= d < self.n_dev and 0 <= c < self.n_dev):
                raise ValueError(f"coupled_to: bad device pair {d} -> {c}")
            if c in self.coupled_to:
                raise ValueError("coupled_to: a device read at a coupled device")
            self.obs[d], self._partner[d] = _with_partners(self.obs[d], self.obs[c])
            self._A[d] = _coupling(self.devices0[c], self.devices0[d], self.poseR0,
                                   T0r, self.P, self.obs[d])
        self.priors = [(self.layout.index(n) if isinstance(n, str) else int(n), float(c),
                        float(s)) for n, c, s in priors]
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
        """The state at ``x``: (devices (list of Device), R_world_target (n_poses, 3, 3),
        T (n_poses, 3) mm)."""
        f = self.full(x)
        devs = [self.devices0[d].from_params(f[self.layout.device_slice(d)])
                for d in range(self.n_dev)]
        pose = f[self.layout.n_device_params:].reshape(self.n_pose, 6)
        R_wt = np.array([rotation_from_rotvec(pose[i, :3]) @ self.poseR0[i]
                       for i in range(self.n_pose)]).reshape(self.n_pose, 3, 3)
        return devs, R_wt, pose[:, 3:].copy()

    def predict(self, x, d: int) -> np.ndarray:
        """Predicted (u, v) (n, 2) px of device ``d``'s observations at ``x``."""
        devs, R_wt, T_wt = self.unpack(x)
        o = self.obs[d]
        X = np.einsum("nij,nj->ni", R_wt[o.pose], self.P[o.point]) + T_wt[o.pose]
        u, v = devs[d].project(X)
        return np.stack([u, v], axis=1)

    def _device_terms(self, x):
        """Per device: errors (n, 2) px (predicted - measured) and the Jacobian blocks
        (n, 2, n_device_params) and (n, 2, 6) (pose) at ``x``."""
        f = self.full(x)
        devs, R_wt, T_wt = self.unpack(x)
        pose = f[self.layout.n_device_params:].reshape(self.n_pose, 6)
        Jl_pose = np.array([left_jacobian(pose[i, :3]) for i in range(self.n_pose)])
        out = []
        for d in range(self.n_dev):
            o = self.obs[d]
            if o.pose.size == 0:
                out.append(None)
                continue
            RP_world = np.einsum("nij,nj->ni", R_wt[o.pose], self.P[o.point])
            uv, J_dev, J_X = devs[d].project_jacobian(RP_world + T_wt[o.pose])
            blk = f[self.layout.device_slice(d)]
            rot = self._rot[d]
            # the device gives d/d(a fresh perturbation at R(dw) R0); chain it to dw
            J_dev[:, :, rot] = J_dev[:, :, rot] @ left_jacobian(blk[rot])
            J_pw = J_X @ (-skew(RP_world)) @ Jl_pose[o.pose]
            out.append((uv - o.uv, J_dev, np.concatenate([J_pw, J_X], axis=2)))
        return out

    def errors(self, x, d: int) -> np.ndarray:
        """Device ``d``'s observation errors (n, 2) px at ``x``, predicted - measured; for
        a coupled device its error given its partner's, ``e - A e_partner`` (the part
        independent of the partner's, whose spread is its own noise)."""
        terms = self._device_terms(x)
        if terms[d] is None:
            return np.zeros((0, 2))
        e = terms[d][0]
        if d in self.coupled_to:
            e = e - np.einsum("nij,nj->ni", self._A[d],
                              terms[self.coupled_to[d]][0][self._partner[d]])
        return e

    def _evaluate(self, x):
        if self._cache_x is not None and np.array_equal(x, self._cache_x):
            return self._cache
        f = self.full(x)
        terms = self._device_terms(x)
        res, rows, cols, vals = [], [], [], []
        row0 = 0
        npose = len(POSE_PARAMETER_NAMES)
        for d in range(self.n_dev):
            o = self.obs[d]
            n = o.pose.size
            if n == 0:
                continue
            e, J_dev, J_pose = terms[d]
            nb = J_dev.shape[2]
            c_dev = self.layout.device_slice(d).start + np.arange(nb)
            c_pose = (self.layout.n_device_params + npose * o.pose[:, None]
                      + np.arange(npose)[None, :])
            if d in self.coupled_to:
                c = self.coupled_to[d]
                A = self._A[d]
                k = self._partner[d]
                e_c, J_dev_c, J_pose_c = terms[c]
                e = e - np.einsum("nij,nj->ni", A, e_c[k])
                J_pose = J_pose - A @ J_pose_c[k]
                J_dev = np.concatenate([J_dev, -(A @ J_dev_c[k])], axis=2)
                c_dev = np.concatenate([c_dev, self.layout.device_slice(c).start
                                        + np.arange(J_dev_c.shape[2])])
            s = self.sigmas[d]
            res.append((e / s).ravel())
            blocks = np.concatenate([J_dev, J_pose], axis=2) / s[None, :, None]
            nb = J_dev.shape[2]
            cc = np.concatenate([np.broadcast_to(c_dev, (n, nb)), c_pose], axis=1)
            r = row0 + 2 * np.arange(n)[:, None] + np.arange(2)[None, :]  # (n, 2)
            rows.append(np.broadcast_to(r[:, :, None], blocks.shape).ravel())
            cols.append(np.broadcast_to(cc[:, None, :], blocks.shape).ravel())
            vals.append(blocks.ravel())
            row0 += 2 * n
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

    def solve(self, *, max_iter: int = 100) -> LMResult:
        """Minimise the sum of squared residuals from ``x0`` (see
        :func:`~telefringe.calibration.solver.levenberg_marquardt`)."""
        n = int(self.free.sum())
        m = self.residuals(self.x0).size
        if m < n:
            raise CalibrationError(
                f"{m} residuals for {n} unknowns: too few observed markers or poses")
        return levenberg_marquardt(self._evaluate, self.x0, max_iter=max_iter)

    def covariance(self, x):
        """Parameter covariance (free parameters) from the Jacobian, scaled by the
        reduced chi-square, and that chi-square; (None, chi2) when singular."""
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

    def device_covariance(self, cov_free) -> np.ndarray:
        """The covariance of the device parameters (layout.n_device_params square), NaN
        rows and columns for fixed parameters, from the free-parameter covariance."""
        nd = self.layout.n_device_params
        out = np.full((nd, nd), np.nan)
        cols = self.colmap[:nd]
        idx = np.flatnonzero(cols >= 0)
        out[np.ix_(idx, idx)] = cov_free[np.ix_(cols[idx], cols[idx])]
        return out

    def rebased(self, x) -> tuple[BundleProblem, np.ndarray]:
        """The same problem with rotations re-centred at ``x`` (perturbations zero)."""
        devs, R_wt, T_wt = self.unpack(x)
        new = BundleProblem(self.P, self.obs, devs, R_wt, T_wt, sigmas=self.sigmas,
                            free=self.free, priors=self.priors,
                            device_names=self.layout.device_names)
        # the same coupling (A held where this problem held it: rebasing moves no point)
        new.coupled_to = dict(self.coupled_to)
        new._partner = dict(self._partner)
        new._A = dict(self._A)
        return new, new.x0


def _with_partners(obs: Observations, ref: Observations):
    """``obs`` restricted to the observations ``ref`` also has (same pose and point), and
    for each the index of its partner in ``ref``."""
    if ref.pose.size == 0 or obs.pose.size == 0:
        return Observations(obs.pose[:0], obs.point[:0], obs.uv[:0]), np.zeros(0, dtype=int)
    m = int(max(ref.point.max(), obs.point.max())) + 1
    key_ref = ref.pose.astype(np.int64) * m + ref.point
    key = obs.pose.astype(np.int64) * m + obs.point
    order = np.argsort(key_ref, kind="stable")
    pos = np.minimum(np.searchsorted(key_ref[order], key), key_ref.size - 1)
    has = key_ref[order][pos] == key
    return Observations(obs.pose[has], obs.point[has], obs.uv[has]), order[pos[has]]


def _coupling(ref_dev: Device, dev: Device, R_wt, T_wt, P, obs: Observations) -> np.ndarray:
    """(n, 2, 2): d(dev pixel)/d(ref_dev pixel) for a point moving in the target plane of
    each observation's pose, ``Jd T (Jr T)^-1`` (T the plane's two axes)."""
    if obs.pose.size == 0:
        return np.zeros((0, 2, 2))
    R = R_wt[obs.pose]
    X = np.einsum("nij,nj->ni", R, P[obs.point]) + T_wt[obs.pose]
    _, _, Jr = ref_dev.project_jacobian(X)
    _, _, Jd = dev.project_jacobian(X)
    Tp = R[:, :, :2]
    return (Jd @ Tp) @ np.linalg.inv(Jr @ Tp)


def check_observations(points_target, observations, what="observations"):
    """Validated (points_target (n_points, 3) mm on z = 0, observations (n_poses, n_points,
    2) px, NaN where missing) as float arrays; raises CalibrationError."""
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
