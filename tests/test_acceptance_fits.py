"""The acceptance test's fits on reference data with a known least-squares solution
(built the way PTB's TraCIM builds test data for fitting software: the residuals are made
orthogonal to the fit's Jacobian at the chosen solution, so that solution is where the
sum of squares is stationary, a minimum for residuals small against the radius)."""

from __future__ import annotations

import numpy as np
import pytest

from telefringe.metrology._common import MetrologyError
from telefringe.metrology.acceptance import (
    artefact_regions,
    cap_half_angle,
    flatness_error,
    ls_plane,
    ls_sphere,
    probing_errors,
    sphere_spacing_error,
)
from telefringe.metrology.acceptance.fits import n_excluded


def _orthogonal(e, J):
    """``e`` with its projection on the columns of ``J`` removed."""
    return e - J @ np.linalg.lstsq(J, e, rcond=None)[0]


def sphere_reference(rng, centre, radius, n, cap_deg, noise):
    """Points whose free-radius LS sphere is exactly (centre, radius); their residuals."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    # directions uniform on the cap of half-angle cap_deg around axis
    cosmax = np.cos(np.radians(cap_deg))
    z = rng.uniform(cosmax, 1.0, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    s = np.sqrt(1 - z * z)
    e1 = np.cross(axis, [1.0, 0, 0] if abs(axis[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    u = (s * np.cos(phi))[:, None] * e1 + (s * np.sin(phi))[:, None] * e2 + z[:, None] * axis
    e = _orthogonal(rng.normal(0, noise, n), np.column_stack([u, np.ones(n)]))
    return np.asarray(centre) + (radius + e)[:, None] * u, e


def plane_reference(rng, point, normal, n, size, noise):
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    t1 = np.cross(normal, [1.0, 0, 0] if abs(normal[0]) < 0.9 else [0, 1.0, 0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(normal, t1)
    a = rng.uniform(-size, size, n)
    b = rng.uniform(-size / 3, size / 3, n)
    e = _orthogonal(rng.normal(0, noise, n), np.column_stack([np.ones(n), a, b]))
    return np.asarray(point) + a[:, None] * t1 + b[:, None] * t2 + e[:, None] * normal, e


@pytest.mark.parametrize("centre, radius, cap, noise", [
    ((0.0, 0.0, 0.0), 2.5, 180.0, 1e-3),        # whole sphere
    ((15.3, 12.1, -1.2), 2.7, 90.0, 2e-3),      # hemisphere, as a telecentric view
    ((1500.0, -800.0, 250.0), 3.0, 35.0, 5e-4),  # small cap far from the origin
    ((-4.0, 7.0, 1.0), 10.0, 60.0, 1e-2),
])
def test_sphere_fit_is_exact_on_reference_data(centre, radius, cap, noise):
    rng = np.random.default_rng(int(radius * 1000) + int(cap))
    pts, e = sphere_reference(rng, centre, radius, 300, cap, noise)
    fit = ls_sphere(pts)
    scale = np.linalg.norm(centre) + radius
    np.testing.assert_allclose(fit.centre, centre, rtol=0, atol=1e-12 * scale)
    assert fit.radius == pytest.approx(radius, abs=1e-12 * scale)
    np.testing.assert_allclose(fit.residuals, e, rtol=0, atol=1e-11 * scale)
    # 300 points: floor(0.9) = 0 excluded, PF is the range of the reference residuals
    t = probing_errors(pts, 2 * radius + 0.01)
    assert t.n_excluded == 0
    assert t.PF == pytest.approx(e.max() - e.min(), abs=1e-11 * scale)
    assert t.PS == pytest.approx(-0.01, abs=1e-11 * scale)
    # the cap's axis is the mean direction of a random sample: a few degrees off
    assert t.cap_half_angle_deg == pytest.approx(cap, abs=6.0 if cap < 180 else 40)


def test_the_largest_deviations_are_excluded_then_the_rest_refitted():
    rng = np.random.default_rng(7)
    centre, radius = np.array([3.0, -2.0, 0.5]), 2.0
    good, e = sphere_reference(rng, centre, radius, 1200, 80.0, 1e-3)
    # 1203 points: floor(3.609) = 3 excluded; three gross outliers among them
    u = (good[:3] - centre) / np.linalg.norm(good[:3] - centre, axis=1)[:, None]
    bad = centre + (radius + np.array([0.05, -0.04, 0.06]))[:, None] * u
    pts = np.vstack([good, bad])
    assert n_excluded(len(pts), 0.003) == 3
    t = probing_errors(pts, 4.0)
    assert t.n_excluded == 3 and not t.kept[-3:].any() and t.kept[:-3].all()
    np.testing.assert_allclose(t.fit.centre, centre, atol=1e-12)
    assert t.fit.radius == pytest.approx(radius, abs=1e-12)
    assert t.PF == pytest.approx(e.max() - e.min(), abs=1e-12)
    assert abs(t.PS) < 1e-12


@pytest.mark.parametrize("normal, noise", [((0.0, 0.0, 1.0), 1e-3), ((0.3, -0.2, 0.9), 5e-3),
                                           ((1.0, 2.0, 0.1), 1e-4)])
def test_plane_fit_is_exact_on_reference_data(normal, noise):
    rng = np.random.default_rng(3)
    point = np.array([100.0, -40.0, 7.0])
    pts, e = plane_reference(rng, point, normal, 2000, 15.0, noise)
    fit = ls_plane(pts)
    n = np.asarray(normal) / np.linalg.norm(normal)
    np.testing.assert_allclose(fit.normal, n * np.sign(n[2]), atol=1e-13)
    assert fit.normal @ fit.centroid == pytest.approx(fit.normal @ point, abs=1e-12)
    np.testing.assert_allclose(fit.residuals * np.sign(n[2]), e, atol=1e-12)
    # 2000 points: 6 excluded (the 6 largest |e|), the rest refitted: still their plane?
    # Not in general, so check the untrimmed range and the count here
    t = flatness_error(pts, exclude=0.0)
    assert t.F == pytest.approx(e.max() - e.min(), abs=1e-12)
    assert flatness_error(pts).n_excluded == 6


def test_flatness_exclusion_removes_the_worst_points():
    rng = np.random.default_rng(11)
    point, normal = np.array([1.0, 2.0, 3.0]), np.array([0.1, 0.2, 1.0])
    good, e = plane_reference(rng, point, normal, 997, 10.0, 1e-3)
    n = normal / np.linalg.norm(normal)
    bad = good[:3] + np.array([0.1, -0.08, 0.09])[:, None] * n
    t = flatness_error(np.vstack([good, bad]))  # 1000 points: 3 excluded
    assert t.n_excluded == 3 and not t.kept[-3:].any()
    assert t.F == pytest.approx(e.max() - e.min(), abs=1e-12)


def test_sphere_spacing_is_exact_on_reference_data():
    rng = np.random.default_rng(5)
    ca, cb = np.array([2.0, 3.0, -1.0]), np.array([14.0, 9.0, 0.5])
    pa, _ = sphere_reference(rng, ca, 2.6, 300, 85.0, 1e-3)  # 300: none excluded
    pb, _ = sphere_reference(rng, cb, 2.5, 300, 85.0, 1e-3)
    L = float(np.linalg.norm(cb - ca))
    t = sphere_spacing_error(pa, pb, L - 0.002, (5.2, 5.0))
    assert t.distance == pytest.approx(L, abs=1e-12)
    assert t.SD == pytest.approx(0.002, abs=1e-12)
    assert t.spheres[0].PS == pytest.approx(0.0, abs=1e-12)
    assert 0 < t.u_fit_distance < 1e-3


def test_fit_errors():
    with pytest.raises(MetrologyError, match="coplanar"):
        ls_sphere(np.column_stack([np.arange(10.0), np.arange(10.0) ** 2, np.zeros(10)]))
    with pytest.raises(MetrologyError, match="at least 4"):
        ls_sphere(np.zeros((3, 3)))
    with pytest.raises(MetrologyError, match="collinear"):
        ls_plane(np.column_stack([np.arange(5.0)] * 3))
    with pytest.raises(MetrologyError, match="finite"):
        ls_plane(np.array([[0, 0, 0], [1, 0, 0], [0, 1, np.nan]]))


def test_cap_half_angle_of_a_hemisphere():
    rng = np.random.default_rng(2)
    pts, _ = sphere_reference(rng, (0, 0, 0), 1.0, 5000, 90.0, 0.0)
    assert cap_half_angle(pts, np.zeros(3)) == pytest.approx(90.0, abs=2.0)


def test_artefact_regions_orders_left_to_right_and_erodes():
    m = np.zeros((30, 40), dtype=bool)
    m[5:15, 25:35] = True   # right, 100 px
    m[5:20, 2:12] = True    # left, 150 px
    m[25:27, 20:22] = True  # a speck
    a, b = artefact_regions(m, 2, erode_px=1)
    assert a[:, :20].any() and not a[:, 20:].any() and b[:, 20:].any()
    assert a.sum() == 13 * 8 and b.sum() == 8 * 8  # one pixel off every border
    with pytest.raises(MetrologyError, match="found 2"):
        artefact_regions(m, 3, min_pixels=1)


def test_spread_flag_compares_ps_with_the_model_within_their_fit_sigmas():
    """A test sphere's PS is flagged as the points' blur bias when the point-spread
    model's size error differs from it by more than 2 x the root sum of squares of the
    two fits' sigmas; no model, no flag; the model is the test sphere's only."""
    from dataclasses import replace

    from telefringe.metrology.acceptance import Position, SpreadSize, spread_probing_size

    rng = np.random.default_rng(3)
    p, _ = sphere_reference(rng, np.array([1.0, 2.0, 50.0]), 2.5, 400, 60.0, 0.003)
    t = probing_errors(p, 5.0)
    pos = Position("s", "sphere", t, [np.zeros((400, 2), dtype=int)], (20, 20))
    assert pos.spread_bias() is None
    u = 2.0 * np.hypot(t.u_fit_diameter, 0.002)
    near = replace(pos, spread=SpreadSize(t.PS - 0.99 * u, 0.002, 300, (0.3,)))
    far = replace(pos, spread=SpreadSize(t.PS + 1.01 * u, 0.002, 300, (0.3,)))
    assert near.spread_bias() is False and far.spread_bias() is True
    bar = Position("b", "ball_bar", t, [], (20, 20))
    with pytest.raises(MetrologyError, match="test sphere"):
        spread_probing_size(bar, None, None, None, None)
