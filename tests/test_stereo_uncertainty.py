"""The calibration part of stereo points: points matched between two cameras move, when
the rig's parameters change, as the two-ray triangulation with the matching's image
metric says (`stereo_calibration`). Checked against re-matching with perturbed rigs
(`match_stereo`, central differences), on both axes and on u alone, and through a
quantity (a plane's height) with `metrology.uncertainty`."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from telefringe.calibration.uncertainty import (
    StereoCalibration,
    point_jacobian,
    point_sigma,
    stereo_calibration,
)
from telefringe.devices.rig import Rig
from telefringe.reconstruction.stereo import match_stereo
from telefringe.simulate.presets import bin_camera_any, get_preset

_PLANE = np.array([0.02, -0.01, 0.5])  # z = a x + b y + c, mm


def _rig():
    return bin_camera_any(get_preset("stereo"), 32).rig  # two 40 x 32 pinhole cameras


def _coords(rig, name):
    """Exact projector coordinates of the plane seen by camera ``name``."""
    cam = rig.cameras[name]
    w, h = cam.image_size
    v, u = np.mgrid[0:h, 0:w].astype(float)
    o, d = cam.backproject(u.ravel(), v.ravel())
    o, d = np.broadcast_arrays(o, d)
    a, b, c = _PLANE
    s = (c + a * o[:, 0] + b * o[:, 1] - o[:, 2]) / (d[:, 2] - a * d[:, 0] - b * d[:, 1])
    X = o + s[:, None] * d
    up, vp = rig.projector.project(X)
    pw, ph = rig.projector.image_size
    ok = (up >= 0) & (up <= pw - 1) & (vp >= 0) & (vp <= ph - 1)
    up = np.where(ok, up, np.nan).reshape(h, w)
    vp = np.where(ok, vp, np.nan).reshape(h, w)
    sig = np.full((h, w), 0.02)
    return SimpleNamespace(u_p=up, v_p=vp, mask=ok.reshape(h, w), sigma_u_p=sig,
                           sigma_v_p=sig)


class _Cal:
    """The true rig as a calibration: parameters camera, camera_2, projector."""

    def __init__(self, rig):
        self.rig = rig
        self.devs = [*rig.cameras.items(), ("projector", rig.projector)]
        self.parameter_names = tuple(f"{n}.{p}" for n, d in self.devs for p in d.param_names)
        self.parameters = np.concatenate([d.to_params() for _, d in self.devs])
        self.covariance = np.eye(self.parameters.size)

    def with_params(self, theta):
        out, k = {}, 0
        for n, d in self.devs:
            m = len(d.param_names)
            out[n] = d.from_params(theta[k:k + m])
            k += m
        proj = out.pop("projector")
        return Rig(cameras=out, projector=proj)


@pytest.fixture(scope="module")
def stereo_case():
    rig = _rig()
    cal = _Cal(rig)
    c1, c2 = _coords(rig, "camera"), _coords(rig, "camera_2")
    return rig, cal, c1, c2


@pytest.mark.parametrize("both_axes", [True, False])
def test_stereo_point_jacobian_matches_rematching(stereo_case, both_axes):
    rig, cal, c1, c2 = stereo_case
    if not both_axes:
        c1 = SimpleNamespace(**{**vars(c1), "v_p": None, "sigma_v_p": None})
        c2 = SimpleNamespace(**{**vars(c2), "v_p": None, "sigma_v_p": None})
    m0 = match_stereo(rig, c1, c2)
    ok = m0.cloud.mask
    assert ok.sum() > 300
    X0 = m0.cloud.xyz[ok]
    maps = (c2.u_p, c2.v_p) if both_axes else c2.u_p
    sigs = (c2.sigma_u_p, c2.sigma_v_p) if both_axes else c2.sigma_u_p
    st = stereo_calibration(cal, maps, sigmas_2=sigs)
    J = point_jacobian(st, X0)
    assert J.shape == (X0.shape[0], 3, cal.parameters.size)
    n_cams = len(rig.camera.param_names) * 2
    assert np.all(J[:, :, n_cams:] == 0)  # the projector only labels the points
    th = cal.parameters
    worst = 0.0
    for k in range(n_cams):
        # a step moving the points by about 1e-5 mm: far above the matching's 1e-9 px
        # convergence, small enough for the central difference's second-order error
        h = 1e-5 / max(float(np.max(np.abs(J[:, :, k]))), 1e-9)
        e = np.zeros_like(th)
        e[k] = h
        xp = match_stereo(cal.with_params(th + e), c1, c2).cloud.xyz[ok]
        xm = match_stereo(cal.with_params(th - e), c1, c2).cloud.xyz[ok]
        fd = (xp - xm) / (2 * h)
        good = np.all(np.isfinite(fd), axis=1)
        assert good.mean() > 0.95
        scale = np.max(np.abs(fd[good])) + 1e-12
        worst = max(worst, float(np.max(np.abs(fd[good] - J[good, :, k])) / scale))
    print(f"stereo point Jacobian vs re-matching ({'u+v' if both_axes else 'u'}): "
          f"largest difference {worst:.2e} of the column's largest entry")
    assert worst < 1.4e-3  # 2x the largest seen (7.2e-4)


def test_stereo_needs_the_matching_and_a_plain_jacobian_refuses(stereo_case):
    rig, cal, _, c2 = stereo_case
    with pytest.raises(ValueError, match="two cameras"):
        point_jacobian(cal, np.zeros((1, 3)))
    st = stereo_calibration(cal, (c2.u_p, c2.v_p))
    assert isinstance(st, StereoCalibration) and st.covariance is cal.covariance
    with pytest.raises(ValueError, match="not inside a valid cell"):
        point_jacobian(st, np.array([[1e4, 1e4, 0.0]]))


def test_stereo_point_sigma_is_the_covariance_through_the_jacobian(stereo_case):
    rig, cal, c1, c2 = stereo_case
    m0 = match_stereo(rig, c1, c2)
    X0 = m0.cloud.xyz[m0.cloud.mask][:50]
    rng = np.random.default_rng(3)
    A = rng.normal(size=(cal.parameters.size, cal.parameters.size)) * 1e-4
    cov = A @ A.T
    st = stereo_calibration(cal, (c2.u_p, c2.v_p), sigmas_2=(c2.sigma_u_p, c2.sigma_v_p))
    pu = point_sigma(st, X0, cov)
    J = point_jacobian(st, X0)
    expect = np.sqrt(np.einsum("nik,kl,nil->ni", J, cov, J))
    np.testing.assert_allclose(pu.calibration, expect, rtol=1e-9)


def test_for_stereo_goes_where_a_calibration_goes(stereo_case):
    """metrology.uncertainty takes the stereo calibration: a plane over stereo points
    gets its calibration part through both cameras (its height moves with camera_2's
    parameters, not with the projector's)."""
    from telefringe.metrology._common import _tangent_basis
    from telefringe.metrology.uncertainty import _factor, _plane_jacobian, for_stereo

    rig, cal, c1, c2 = stereo_case
    st = for_stereo(cal, c2)
    assert len(st.maps) == 2 and len(for_stereo(cal, c2, use_v_p=False).maps) == 1
    assert _factor(st).shape[0] == cal.parameters.size
    m0 = match_stereo(rig, c1, c2)
    pts = m0.cloud.xyz[m0.cloud.mask]
    c = pts.mean(axis=0)
    n = np.linalg.svd(pts - c)[2][2]
    Jp = _plane_jacobian(st, pts, np.ones(len(pts)), n, c, _tangent_basis(n), 0.0)
    k2 = len(rig.camera.param_names)
    assert np.abs(Jp[2, k2:2 * k2]).max() > 0 and np.all(Jp[:, 2 * k2:] == 0)
