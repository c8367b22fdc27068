"""Projector observations read at the camera's detected centres (calibration/problem.py,
``coupled_to``): the camera's detection error is in both observations, and the coupled
adjustment is the generalised least squares of that correlated noise, exactly."""

from __future__ import annotations

import numpy as np
import pytest

from telefringe.calibration.problem import BundleProblem, Observations
from telefringe.simulate.calibration import simulate_calibration_poses
from telefringe.simulate.presets import get_preset

SIG_C = 0.005  # px, camera detection noise
SIG_P = (0.0016, 0.0024)  # px, the projector's own noise per axis


@pytest.fixture(scope="module")
def data():
    """The fast rig's true devices, 4 poses of its plate, camera observations with
    detection noise and projector observations read at the noisy camera centres."""
    vrig = get_preset("fast")
    cam, proj, T = vrig.rig.camera, vrig.rig.projector, vrig.target
    poses = simulate_calibration_poses(vrig, n_poses=4, seed=2, half_hidden=False)
    r, c = np.mgrid[0:T.rows, 0:T.cols]
    P = np.stack([c.ravel() * T.pitch_mm, r.ravel() * T.pitch_mm, np.zeros(r.size)], 1)
    rng = np.random.default_rng(7)
    pi, ki, uc, up = [], [], [], []
    for j, p in enumerate(poses):
        X = P @ p.R_world_target.T + p.t_world_target
        co = np.stack(cam.project(X), 1) + rng.normal(0, SIG_C, (len(P), 2))
        o, d = cam.backproject(co[:, 0], co[:, 1])
        n = p.R_world_target[:, 2]
        s = ((p.t_world_target - o) @ n) / (d @ n)
        po = np.stack(proj.project(o + s[:, None] * d), 1)
        pi.append(np.full(len(P), j))
        ki.append(np.arange(len(P)))
        uc.append(co)
        up.append(po + rng.normal(0, 1, po.shape) * SIG_P)
    pose, point = np.concatenate(pi), np.concatenate(ki)
    R0 = np.array([p.R_world_target for p in poses])
    T0 = np.array([p.t_world_target for p in poses])
    return (P, Observations(pose, point, np.concatenate(uc)),
            Observations(pose.copy(), point.copy(), np.concatenate(up)), [cam, proj], R0, T0)


def _problem(data, coupled, cam_obs=None):
    P, oc, op, devs, R0, T0 = data
    return BundleProblem(P, [oc if cam_obs is None else cam_obs, op], devs, R0, T0,
                         sigmas=[SIG_C, SIG_P] if coupled else [1.0, 1.0],
                         coupled_to={1: 0} if coupled else None)


def test_coupled_adjustment_is_the_generalised_least_squares(data):
    """Whitened residuals and normal equations equal those of the raw residuals under
    their joint covariance (camera sigma_c^2 I; projector A sigma_c^2 A^T + diag(sigma_p^2);
    between them A sigma_c^2): cost and J^T J to 1e-9 relative. A wrong sign or a missing
    camera column in the projector's rows breaks both."""
    wp = _problem(data, True)
    raw = _problem(data, False)
    x = wp.x0
    r_w, J_w = wp.residuals(x), wp.jacobian(x).toarray()
    r, J = raw.residuals(x), raw.jacobian(x).toarray()
    n = data[1].pose.size
    A = wp._A[1]
    assert A.shape == (n, 2, 2) and np.abs(A).max() > 0.3  # the coupling is there
    # the joint covariance of (camera rows, projector rows), observation-major (u, v)
    S = np.zeros((4 * n, 4 * n))
    Sp = np.diag(np.square(SIG_P))
    for i in range(n):
        c, p = slice(2 * i, 2 * i + 2), slice(2 * n + 2 * i, 2 * n + 2 * i + 2)
        S[c, c] = SIG_C**2 * np.eye(2)
        S[p, p] = SIG_C**2 * A[i] @ A[i].T + Sp
        S[p, c] = SIG_C**2 * A[i]
        S[c, p] = S[p, c].T
    W = np.linalg.inv(S)
    assert r_w @ r_w == pytest.approx(r @ W @ r, rel=1e-9)
    N_gls = J.T @ W @ J
    assert np.allclose(J_w.T @ J_w, N_gls, rtol=1e-9, atol=1e-9 * np.abs(N_gls).max())
    # the projector's errors given the camera's: its own noise only
    e = wp.errors(x, 1)
    assert np.allclose(e, (raw.predict(x, 1) - data[2].uv)
                       - np.einsum("nij,nj->ni", A, raw.predict(x, 0) - data[1].uv))
    assert np.std(e, axis=0) == pytest.approx(SIG_P, rel=0.15)


def test_projector_observation_without_its_camera_partner_is_dropped(data):
    P, oc, op, devs, R0, T0 = data
    keep = np.ones(oc.pose.size, dtype=bool)
    keep[[3, 50, 200]] = False
    fewer = Observations(oc.pose[keep], oc.point[keep], oc.uv[keep])
    wp = _problem(data, True, cam_obs=fewer)
    o = wp.obs[1]
    assert o.pose.size == op.pose.size - 3
    gone = {(int(op.pose[i]), int(op.point[i])) for i in (3, 50, 200)}
    assert not gone & set(zip(o.pose.tolist(), o.point.tolist(), strict=True))
    # partners line up: the same pose and point
    k = wp._partner[1]
    assert np.array_equal(fewer.pose[k], o.pose) and np.array_equal(fewer.point[k], o.point)
