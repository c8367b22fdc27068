"""Property tests of the telecentric device model (telefringe.model).

Tolerances: the model is exact arithmetic on sensor coordinates of a few mm, so every
round trip is limited by double rounding (~1e-15 mm, ~1e-13 px). The bounds below
(1e-10 px, 1e-9 mm, 1e-12 rad) are the issue's requirements and leave that margin.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from telefringe.devices.telecentric import Intrinsics, TelecentricDevice
from telefringe.geometry.distortion import ConvergenceError, distort_sensor, undistort_sensor
from telefringe.geometry.so3 import rotation_from_rotvec, rotvec_from_rotation

FAST = settings(max_examples=60, deadline=None, derandomize=True)
PX_TOL = 1e-10  # px, issue 2
MM_TOL = 1e-9  # mm, issue 2

seeds = st.integers(0, 2**32 - 1)


def _corner_radius_mm(width, height, u0, v0, du, dv) -> float:
    """Sensor distance (mm) from the principal point to the farthest image corner."""
    cu = np.array([-0.5, width - 0.5]) - u0
    cv = np.array([-0.5, height - 0.5]) - v0
    return float(np.sqrt(np.max(np.abs(cu)) ** 2 * du**2 + np.max(np.abs(cv)) ** 2 * dv**2))


@st.composite
def intrinsics(draw, *, radial_px=7.0, prism_px=1.5):
    """Realistic intrinsics whose distortion moves the image corners by up to ~10 px.

    ``radial_px``: the radial term's displacement at the farthest corner, px (either
    sign); ``prism_px``: each thin-prism term's displacement there.
    """
    width = draw(st.integers(320, 2048))
    height = draw(st.integers(240, 2048))
    du = draw(st.floats(2e-3, 20e-3))
    dv = du * draw(st.floats(0.9, 1.1))
    u0 = (width - 1) / 2 + draw(st.floats(-0.1, 0.1)) * width
    v0 = (height - 1) / 2 + draw(st.floats(-0.1, 0.1)) * height
    m = draw(st.floats(0.05, 2.0))
    rc = _corner_radius_mm(width, height, u0, v0, du, dv)
    k1 = draw(st.floats(-radial_px, radial_px)) * du / rc**3
    s1 = draw(st.floats(-prism_px, prism_px)) * du / rc**2
    s2 = draw(st.floats(-prism_px, prism_px)) * du / rc**2
    return Intrinsics(m=m, du=du, dv=dv, u0=u0, v0=v0, k1=k1, s1=s1, s2=s2,
                      width=width, height=height)


@st.composite
def rotvecs(draw):
    """Rotation vectors with angles in [0, pi], stressing 0 and pi."""
    axis = np.array(draw(st.tuples(*[st.floats(-1, 1)] * 3)))
    assume(np.linalg.norm(axis) > 1e-3)
    axis /= np.linalg.norm(axis)
    angle = draw(st.one_of(
        st.just(0.0), st.just(math.pi),
        st.floats(0.0, 1e-6), st.floats(0.0, math.pi),
        st.floats(0.0, 1e-6).map(lambda e: math.pi - e),
        st.floats(1e-12, 1e-3).map(lambda e: math.pi - e),
    ))
    return angle * axis


def _image_pixels(k: Intrinsics, rng, n=300):
    """Random pixels over the whole image area, corners included, (n + 4,) each."""
    u = rng.uniform(-0.5, k.width - 0.5, n)
    v = rng.uniform(-0.5, k.height - 0.5, n)
    u = np.concatenate([u, [-0.5, k.width - 0.5, -0.5, k.width - 0.5]])
    v = np.concatenate([v, [-0.5, -0.5, k.height - 0.5, k.height - 0.5]])
    return u, v


def _device(k: Intrinsics, rotvec, t):
    return TelecentricDevice.from_rotvec(k, rotvec, t)


# --------------------------------------------------------------------------- distortion
@FAST
@given(k=intrinsics(), seed=seeds)
def test_distort_then_undistort_round_trip(k, seed):
    dev = TelecentricDevice(k)
    u, v = _image_pixels(k, np.random.default_rng(seed))
    ud, vd = dev.distort(u, v)
    u2, v2 = dev.undistort(ud, vd)
    assert np.max(np.abs(u2 - u)) < PX_TOL
    assert np.max(np.abs(v2 - v)) < PX_TOL


@FAST
@given(k=intrinsics(), seed=seeds)
def test_undistort_then_distort_round_trip(k, seed):
    dev = TelecentricDevice(k)
    u, v = _image_pixels(k, np.random.default_rng(seed))
    ui, vi = dev.undistort(u, v)
    u2, v2 = dev.distort(ui, vi)
    assert np.max(np.abs(u2 - u)) < PX_TOL
    assert np.max(np.abs(v2 - v)) < PX_TOL


@FAST
@given(k=intrinsics(), seed=seeds)
def test_corner_displacement_is_at_most_about_ten_pixels(k, seed):
    """The strategy is what it claims (and distortion is not a no-op)."""
    dev = TelecentricDevice(k)
    u, v = _image_pixels(k, np.random.default_rng(seed))
    ud, vd = dev.distort(u, v)
    assert np.max(np.hypot(ud - u, vd - v)) < 7.0 + 2 * 1.5 * math.sqrt(2) + 1e-9


def test_distortion_matches_the_documented_formula():
    """k1 alone moves a point radially by k1 r^3; s1, s2 shift it by (s1, s2) r^2."""
    k = Intrinsics(m=0.16, du=0.005, dv=0.004, u0=100.0, v0=50.0, k1=2e-3, width=200,
                   height=100)
    dev = TelecentricDevice(k)
    u, v = dev.distort(100.0 + 80.0, 50.0 + 30.0)  # sensor (0.4, 0.12) mm
    x, y, r2 = 0.4, 0.12, 0.4**2 + 0.12**2
    assert u == pytest.approx(100.0 + (x + 2e-3 * x * r2) / 0.005, abs=1e-12)
    assert v == pytest.approx(50.0 + (y + 2e-3 * y * r2) / 0.004, abs=1e-12)
    xd, yd = distort_sensor(x, y, 0.0, 1e-3, -2e-3)
    assert xd == pytest.approx(x + 1e-3 * r2, abs=1e-15)
    assert yd == pytest.approx(y - 2e-3 * r2, abs=1e-15)


def test_undistort_keeps_nan_and_shapes():
    k = Intrinsics(m=0.2, du=0.005, dv=0.005, u0=320, v0=240, k1=1e-3, s1=2e-4,
                   width=640, height=480)
    dev = TelecentricDevice(k)
    u = np.array([[np.nan, 10.0], [300.0, 600.0]])
    v = np.array([[5.0, np.nan], [200.0, 470.0]])
    ui, vi = dev.undistort(u, v)
    assert ui.shape == vi.shape == (2, 2)
    assert np.isnan(ui[0, 0]) and np.isnan(vi[0, 1])
    assert np.all(np.isfinite(ui[1])) and np.all(np.isfinite(vi[1]))


# --------------------------------------------------------------------------- non-invertible
@FAST
@given(k1=st.floats(-0.1, -1e-4), angle=st.floats(0, 2 * math.pi),
       beyond=st.floats(1.0001, 1e6))
def test_convergence_error_beyond_the_fold(k1, angle, beyond):
    """Barrel distortion folds at r* = 1/sqrt(-3 k1), where r + k1 r^3 peaks at 2/3 r*.

    A distorted point farther out has no inverse on its side of the centre; its only
    roots lie on the mirrored outer branch. Undistortion must say so, never return them.
    """
    rmax = 2.0 / 3.0 / math.sqrt(-3.0 * k1)
    r = rmax * beyond
    xd, yd = r * math.cos(angle), r * math.sin(angle)
    with pytest.raises(ConvergenceError, match="not invertible"):
        undistort_sensor(np.array([0.0, xd]), np.array([0.0, yd]), k1, 0.0, 0.0)


@FAST
@given(k1=st.floats(-0.1, -1e-4), angle=st.floats(0, 2 * math.pi),
       inside=st.floats(0.0, 0.95))
def test_undistort_inside_the_fold_is_the_inner_root(k1, angle, inside):
    rstar = 1.0 / math.sqrt(-3.0 * k1)
    r = 2.0 / 3.0 * rstar * inside
    xd, yd = r * math.cos(angle), r * math.sin(angle)
    xu, yu = undistort_sensor(xd, yd, k1, 0.0, 0.0)
    assert math.hypot(xu, yu) < rstar  # the inner branch
    x2, y2 = distort_sensor(xu, yu, k1, 0.0, 0.0)
    assert abs(x2 - xd) < 1e-12 and abs(y2 - yd) < 1e-12


def test_device_undistort_error_message_is_clear():
    k = Intrinsics(m=0.16, du=0.005, dv=0.005, u0=640, v0=512, k1=-0.05, width=1280,
                   height=1024)
    dev = TelecentricDevice(k)
    with pytest.raises(ConvergenceError) as info:
        dev.undistort(np.array([640.0, 5000.0, 9000.0]), np.array([512.0, 512.0, 512.0]))
    msg = str(info.value)
    assert "2 of 3 point(s)" in msg and "k1=-0.05" in msg and "not invertible" in msg
    assert isinstance(info.value, ValueError)
    with pytest.raises(ConvergenceError):
        dev.backproject(5000.0, 512.0)


# --------------------------------------------------------------------------- project / back
@FAST
@given(k=intrinsics(), rv=rotvecs(), t=st.tuples(st.floats(-20, 20), st.floats(-20, 20)),
       seed=seeds)
def test_backprojected_line_passes_through_the_point(k, rv, t, seed):
    dev = _device(k, rv, t)
    rng = np.random.default_rng(seed)
    # world points whose ideal images fill the image area, at depths of +-10 mm
    ui, vi = _image_pixels(k, rng, 100)
    xu, yu = (ui - k.u0) * k.du, (vi - k.v0) * k.dv
    local = np.stack([xu / k.m - dev.t_dev[0], yu / k.m - dev.t_dev[1],
                      rng.uniform(-10, 10, ui.size)], axis=-1)
    X = local @ dev.R_dev_world  # device -> world (R^T applied to rows)
    u_ideal, v_ideal = dev.project_undistorted(X)
    assert np.max(np.abs(u_ideal - ui)) < PX_TOL and np.max(np.abs(v_ideal - vi)) < PX_TOL
    u, v = dev.project(X)
    origin, direction = dev.backproject(u, v)
    assert origin.shape == X.shape and direction.shape == (3,)
    assert abs(np.linalg.norm(direction) - 1.0) < 1e-15
    d = X - origin
    perp = d - (d @ direction)[:, None] * direction
    assert np.max(np.linalg.norm(perp, axis=1)) < MM_TOL
    # the origin is the point of zero depth along the device axis
    assert np.max(np.abs(origin @ direction)) < MM_TOL


@FAST
@given(k=intrinsics(), rv=rotvecs(), t=st.tuples(st.floats(-20, 20), st.floats(-20, 20)),
       depth=st.floats(-50, 50), seed=seeds)
def test_project_of_backprojected_point_is_the_pixel(k, rv, t, depth, seed):
    dev = _device(k, rv, t)
    u, v = _image_pixels(k, np.random.default_rng(seed), 100)
    origin, direction = dev.backproject(u, v)
    u2, v2 = dev.project(origin + depth * direction)
    assert np.max(np.abs(u2 - u)) < PX_TOL and np.max(np.abs(v2 - v)) < PX_TOL


def test_project_known_values_and_shapes():
    k = Intrinsics(m=0.5, du=0.01, dv=0.02, u0=10.0, v0=20.0, width=40, height=30)
    dev = TelecentricDevice(k, np.eye(3), np.array([1.0, 2.0]))
    u, v = dev.project([3.0, 4.0, 99.0])  # depth does not change the image
    assert u == pytest.approx(10.0 + 0.5 * (3 + 1) / 0.01, abs=1e-12)
    assert v == pytest.approx(20.0 + 0.5 * (4 + 2) / 0.02, abs=1e-12)
    X = np.zeros((2, 5, 3))
    u, v = dev.project(X)
    assert u.shape == v.shape == (2, 5)
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        dev.project(np.zeros((4, 2)))
    # a camera looking straight down: its axis is -z in the world (z toward the camera)
    down = TelecentricDevice(k, np.diag([1.0, -1.0, -1.0]))
    assert np.allclose(down.axis_world, [0.0, 0.0, -1.0])


# --------------------------------------------------------------------------- rotations
@settings(max_examples=100, deadline=None, derandomize=True)
@given(rv=rotvecs())
def test_rotvec_round_trip_including_0_and_pi(rv):
    R = rotation_from_rotvec(rv)
    assert np.allclose(R, Rotation.from_rotvec(rv).as_matrix(), atol=1e-14, rtol=0)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-14) and np.linalg.det(R) > 0
    back = rotvec_from_rotation(R)
    assert np.linalg.norm(back) <= math.pi + 1e-15
    angle = np.linalg.norm(rv)
    if math.pi - angle < 1e-14:
        # at pi, r and -r are the same rotation
        err = min(np.max(np.abs(back - rv)), np.max(np.abs(back + rv)))
    else:
        err = np.max(np.abs(back - rv))
    assert err < 1e-12, (rv, back)
    assert np.max(np.abs(rotation_from_rotvec(back) - R)) < 1e-14


@FAST
@given(rv=rotvecs(), turns=st.integers(-2, 2))
def test_rotvec_of_equivalent_vector_is_canonical(rv, turns):
    """r and r + 2 pi k r/|r| are the same rotation: the inverse returns angle <= pi."""
    angle = np.linalg.norm(rv)
    assume(angle > 1e-3)
    rv2 = rv / angle * (angle + 2 * math.pi * turns)
    back = rotvec_from_rotation(rotation_from_rotvec(rv2))
    assert np.max(np.abs(rotation_from_rotvec(back) - rotation_from_rotvec(rv))) < 1e-13


@pytest.mark.parametrize("bad", [
    np.diag([1.0, 1.0, -1.0]),  # reflection
    2.0 * np.eye(3),  # scaled
    np.array([[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),  # sheared
    np.full((3, 3), np.nan),
    np.eye(2),
])
def test_rotvec_from_rotation_rejects_non_rotations(bad):
    with pytest.raises(ValueError, match="R "):
        rotvec_from_rotation(bad)


@pytest.mark.parametrize("bad", [[np.nan, 0, 0], [0, np.inf, 0], [1.0, 2.0]])
def test_rotation_from_rotvec_rejects_bad_vectors(bad):
    with pytest.raises(ValueError, match="rotvec"):
        rotation_from_rotvec(bad)


# --------------------------------------------------------------------------- validation
GOOD = dict(m=0.16, du=0.0052, dv=0.0052, u0=640.0, v0=512.0, k1=1e-3, s1=1e-4, s2=-1e-4,
            width=1280, height=1024)


@pytest.mark.parametrize("name", ["m", "du", "dv", "u0", "v0", "k1", "s1", "s2"])
@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf, "1", None, True])
def test_intrinsics_rejects_non_finite(name, value):
    with pytest.raises(ValueError, match=f"Intrinsics.{name} "):
        Intrinsics(**{**GOOD, name: value})


@pytest.mark.parametrize("name", ["m", "du", "dv"])
@pytest.mark.parametrize("value", [0.0, -1e-3])
def test_intrinsics_rejects_non_positive_scales(name, value):
    with pytest.raises(ValueError, match=f"Intrinsics.{name} must be > 0"):
        Intrinsics(**{**GOOD, name: value})


@pytest.mark.parametrize("name", ["width", "height"])
@pytest.mark.parametrize("value", [-1, -1280, 1.5, np.nan, np.inf, True, "1280", None])
def test_intrinsics_rejects_bad_sizes(name, value):
    with pytest.raises(ValueError, match=f"Intrinsics.{name} must be an integer"):
        Intrinsics(**{**GOOD, name: value})


def test_intrinsics_sizes_become_ints():
    k = Intrinsics(**{**GOOD, "width": np.int64(1280), "height": 1024.0})
    assert type(k.width) is int and type(k.height) is int and k.shape == (1024, 1280)


@pytest.mark.parametrize("R", [
    np.diag([1.0, 1.0, -1.0]),
    np.diag([1.0, 1.0, 1.0 + 1e-6]),
    np.eye(3) * np.nan,
    np.zeros((3, 3)),
    np.eye(4),
])
def test_device_rejects_non_rotations(R):
    with pytest.raises(ValueError, match="R_dev_world"):
        TelecentricDevice(Intrinsics(**GOOD), R)


@pytest.mark.parametrize("t", [[0.0, np.nan], [0.0, 0.0, 0.0], [np.inf, 1.0]])
def test_device_rejects_bad_translations(t):
    with pytest.raises(ValueError, match="t_dev"):
        TelecentricDevice(Intrinsics(**GOOD), np.eye(3), t)


def test_device_does_not_alias_the_callers_arrays():
    R = rotation_from_rotvec([0.1, 0.2, 0.3])
    t = np.array([1.0, 2.0])
    dev = TelecentricDevice(Intrinsics(**GOOD), R, t)
    R[0, 0] = 5.0
    t[0] = 7.0
    assert dev.R_dev_world[0, 0] != 5.0 and dev.t_dev[0] == 1.0
    with pytest.raises(ValueError):
        dev.R_dev_world[0, 0] = 1.0
