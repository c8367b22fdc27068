"""Circle-grid detection and projector observations on images synthesised here.

Images are rendered exactly: every sub-sample of every pixel is traced back through
the camera model (distortion included) onto the target plane and tested against the
circles; then blur, a light gradient, seeded noise and 8-bit quantisation.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from telefringe.devices.telecentric import Intrinsics, TelecentricDevice
from telefringe.geometry.so3 import rotation_from_rotvec
from telefringe.targets.circle_grid import GridDetection, detect_circle_grid
from telefringe.targets.ellipse import (
    _blurred_ellipse,
    _normal_equations,
    _normal_equations_py,
    fit_ellipse,
)
from telefringe.targets.observations import projector_observations

ROWS, COLS, PITCH, DIAM = 9, 11, 3.0, 1.5


def small_camera(*, k1=6e-4, s1=-8e-5, s2=1.2e-4) -> TelecentricDevice:
    """A 640 x 512 telecentric camera (10.4 um pixels) looking down at the grid; the
    grid's x to the right and y up in the image, as DESIGN.md's labelling expects."""
    k = Intrinsics(m=0.1597, du=0.0104, dv=0.0104, u0=300.0, v0=270.0, k1=k1, s1=s1,
                   s2=s2, width=640, height=512)
    R = np.diag([1.0, -1.0, -1.0])  # camera looks down -z; image v runs down world y
    centre = np.array([15.0, 12.0, 0.0])
    t = (np.array([319.5, 255.5]) - (k.u0, k.v0)) * k.du / k.m - R[:2] @ centre
    return TelecentricDevice(k, R, t)


def grid_target_points():
    r, c = np.mgrid[0:ROWS, 0:COLS]
    return np.stack([c.ravel() * PITCH, r.ravel() * PITCH, np.zeros(r.size)], axis=1)


def render(cam: TelecentricDevice, R_wt, t_wt, *, rng, ss=8, blur=0.6, noise=2.0,
           bright=200.0, dark_ratio=0.15, gradient=0.15, occlude=None, quantise=True):
    """8-bit image of the grid at pose (R_wt, t_wt), and the true centres (n, 2) px."""
    k = cam.intrinsics
    H, W = k.height, k.width
    off = (np.arange(ss) + 0.5) / ss - 0.5
    vv, uu = np.mgrid[0:H, 0:W]
    cover = np.zeros((H, W))
    # world plane of the target: X = R_wt (x, y, 0) + t_wt; camera rows 0, 1 of R_cw
    A = cam.R_dev_world[:2] @ R_wt[:, :2]  # (2, 2): target (x, y) -> camera (a, b) mm
    b0 = cam.R_dev_world[:2] @ t_wt + cam.t_dev
    Ainv = np.linalg.inv(A)

    def plane_xy(u, v):
        o, _ = cam.backproject(u, v)
        ab = np.stack([o @ cam.R_dev_world[0], o @ cam.R_dev_world[1]], -1) + cam.t_dev
        return (ab - b0) @ Ainv.T

    # target coordinates of the pixel centres and their derivatives along u and v: the
    # sub-samples follow linearly (the distortion's curvature over one pixel moves them
    # by < 1e-6 px)
    xy0 = plane_xy(uu, vv)
    dxy_du = plane_xy(uu + 0.5, vv) - plane_xy(uu - 0.5, vv)
    dxy_dv = plane_xy(uu, vv + 0.5) - plane_xy(uu, vv - 0.5)
    for dy in off:
        for dx in off:
            xy = xy0 + dx * dxy_du + dy * dxy_dv
            ci = np.clip(np.round(xy[..., 0] / PITCH), 0, COLS - 1)
            ri = np.clip(np.round(xy[..., 1] / PITCH), 0, ROWS - 1)
            d2 = (xy[..., 0] - ci * PITCH) ** 2 + (xy[..., 1] - ri * PITCH) ** 2
            cover += d2 <= (DIAM / 2) ** 2
    cover /= ss * ss
    light = bright * (1 + gradient * (uu / W - 0.5) + 0.5 * gradient * (vv / H - 0.5))
    img = light * (1 - (1 - dark_ratio) * cover)
    if occlude is not None:
        img[occlude] = 0.5 * bright
    img = gaussian_filter(img, blur) if blur > 0 else img
    img = img + rng.normal(0, noise, img.shape)
    if quantise:
        img = np.clip(np.round(img), 0, 255).astype(np.uint8)
    X = grid_target_points() @ R_wt.T + t_wt
    return img, np.stack(cam.project(X), axis=1)


@pytest.fixture(scope="module")
def views():
    rng = np.random.default_rng(42)
    cam = small_camera()
    centre = np.array([15.0, 12.0, 0.0])
    out = []
    for rv in ([0.25, 0.1, 0.3], [-0.2, 0.3, -0.5]):
        R = rotation_from_rotvec(rv)
        t = centre - R @ centre
        out.append((R, t) + render(cam, R, t, rng=rng))
    return cam, out


def test_fit_ellipse_exact_and_noisy():
    t = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    a, b, th, xc, yc = 20.0, 11.0, 0.6, 103.2, 55.7
    x = xc + a * np.cos(t) * np.cos(th) - b * np.sin(t) * np.sin(th)
    y = yc + a * np.cos(t) * np.sin(th) + b * np.sin(t) * np.cos(th)
    p, rms = fit_ellipse(x, y)
    np.testing.assert_allclose(p, [xc, yc, a, b, th], atol=1e-9)
    assert rms < 1e-9
    rng = np.random.default_rng(0)
    errs = []
    for _ in range(200):
        p, _ = fit_ellipse(x + rng.normal(0, 0.05, x.size), y + rng.normal(0, 0.05, x.size))
        errs.append(p[:2] - (xc, yc))
    errs = np.array(errs)
    # centre of an ellipse fitted to n points with noise s: about s sqrt(2 / n) per axis
    expected = 0.05 * np.sqrt(2 / x.size)
    assert np.all(np.abs(errs.mean(0)) < 4 * expected / np.sqrt(200))
    assert np.all(errs.std(0) < 1.5 * expected)
    with pytest.raises(ValueError):
        fit_ellipse(np.arange(10.0), 2 * np.arange(10.0))


@pytest.mark.parametrize("method, bound", [("model", 0.01), ("edge", 0.015)])
def test_centres_sub_pixel_and_ordered(views, method, bound):
    """Error budget (23 px markers, blur 0.6 px, 2 DN noise on ~170 DN contrast):
    noise ~0.005 px; marker-as-ellipse under this camera's distortion (4 px at the
    corners) up to ~0.004 px; the model fit's own bias ~0.003 px (measured without
    noise or distortion); the renderer's 8 x 8 sub-sampling ~0.002 px. The edge-point
    method adds its sampling-phase bias (~0.006 px)."""
    cam, vs = views
    for _R, _t, img, truth in vs:
        det = detect_circle_grid(img, rows=ROWS, cols=COLS, method=method)
        assert det, det.reason
        # all markers whose edge lies inside the image
        k = cam.intrinsics
        inside = ((truth[:, 0] > 15) & (truth[:, 0] < k.width - 16) & (truth[:, 1] > 15)
                  & (truth[:, 1] < k.height - 16))
        assert det.found[inside].all()
        ok = det.found
        err = det.centers[ok] - truth[ok]
        rms = np.sqrt(np.mean(np.sum(err**2, axis=1)))
        assert rms < bound, rms
        # handedness: the grid's +x and +y image with a negative determinant
        L = det.lattice
        assert L[0, 0] * L[1, 1] - L[1, 0] * L[0, 1] < 0


def test_labelling_follows_the_convention_when_the_plate_turns():
    """Turned by 180 degrees in its plane the grid is labelled from the other corner, so
    that circle (0, 0) stays nearest the bottom-left image corner."""
    rng = np.random.default_rng(3)
    cam = small_camera()
    centre = np.array([15.0, 12.0, 0.0])
    R = rotation_from_rotvec([0, 0, np.pi + 0.2])
    t = centre - R @ centre
    img, truth = render(cam, R, t, rng=rng)
    det = detect_circle_grid(img, rows=ROWS, cols=COLS)
    assert det, det.reason
    # truth lists the markers in the plate's own order: reversed relative to ours
    ok = det.found
    err = det.centers[ok] - truth[::-1][ok]
    assert np.sqrt(np.mean(np.sum(err**2, axis=1))) < 0.01
    H = cam.intrinsics.height
    d = np.hypot(truth[::-1][:, 0], truth[::-1][:, 1] - (H - 1))
    assert d[0] == d.min()


def test_missing_interior_marker_and_stray_blob():
    rng = np.random.default_rng(4)
    cam = small_camera()
    truth_c = np.stack(cam.project(grid_target_points()), 1)
    occl = np.zeros((512, 640), dtype=bool)
    c = truth_c[4 * COLS + 5]  # marker (4, 5)
    occl[int(c[1]) - 14:int(c[1]) + 15, int(c[0]) - 14:int(c[0]) + 15] = True
    img, truth = render(cam, np.eye(3), np.zeros(3), rng=rng, occlude=occl, ss=4)
    img[5:15, 5:15] = 20  # a stray dark speck off the grid
    det = detect_circle_grid(img, rows=ROWS, cols=COLS)
    assert det, det.reason
    assert not det.found[4 * COLS + 5] and det.n_found == ROWS * COLS - 1
    ok = det.found
    # coarse 4 x 4 rendering here: its own error is up to ~0.01 px
    assert np.sqrt(np.mean(np.sum((det.centers[ok] - truth[ok]) ** 2, axis=1))) < 0.02


def test_a_hole_in_the_image_drops_only_the_marker_it_touches(views):
    """A NaN pixel inside a marker must not be filled and fitted as plate (it would bias
    the centre): that marker is not found, every other centre is unchanged."""
    cam, out = views
    img = np.array(out[0][2], dtype=float)
    ref = detect_circle_grid(img, rows=ROWS, cols=COLS)
    k = 3 * COLS + 4
    cx, cy = ref.centers[k]
    holed = img.copy()
    holed[int(round(cy)) + 3, int(round(cx)) - 2] = np.nan  # inside marker (3, 4)
    det = detect_circle_grid(holed, rows=ROWS, cols=COLS)
    assert det and not det.found[k] and det.n_found == ref.n_found - 1
    others = det.found
    np.testing.assert_array_equal(det.centers[others], ref.centers[others])
    assert not detect_circle_grid(np.full_like(img, np.nan), rows=ROWS, cols=COLS)


def test_half_hidden_grid_is_refused_with_a_reason():
    rng = np.random.default_rng(5)
    cam = small_camera()
    occl = np.zeros((512, 640), dtype=bool)
    occl[:, :330] = True  # the left half of the plate covered
    img, _ = render(cam, np.eye(3), np.zeros(3), rng=rng, occlude=occl, ss=2)
    det = detect_circle_grid(img, rows=ROWS, cols=COLS)
    assert not det
    assert isinstance(det, GridDetection) and "hidden" in det.reason
    blank = np.full((100, 120), 180, dtype=np.uint8)
    det = detect_circle_grid(blank, rows=ROWS, cols=COLS)
    assert not det and det.reason


def test_light_on_dark_markers(views):
    _, vs = views
    R, t, img, truth = vs[0]
    det = detect_circle_grid(255 - img, rows=ROWS, cols=COLS, dark=False)
    ok = det.found
    assert det and ok.sum() >= ROWS * COLS - 2
    assert np.sqrt(np.mean(np.sum((det.centers[ok] - truth[ok]) ** 2, axis=1))) < 0.01


def test_projector_observations_read_the_surround(views):
    """u_p, v_p: a smooth map (affine + cubic distortion-like terms) with noise, garbage
    inside the markers and a few wrong-order pixels; the value at each centre comes back
    to well below the noise of one pixel."""
    cam, vs = views
    R, t, img, truth = vs[0]
    det = detect_circle_grid(img, rows=ROWS, cols=COLS)
    H, W = img.shape
    vv, uu = np.mgrid[0:H, 0:W].astype(float)

    def f_u(u, v):
        x, y = (u - 320) / 320, (v - 256) / 256
        return 400 + 0.28 * (u - 320) + 0.03 * (v - 256) + 2.0 * x**3 + 1.5 * x * y**2

    def f_v(u, v):
        x, y = (u - 320) / 320, (v - 256) / 256
        return 300 - 0.02 * (u - 320) + 0.27 * (v - 256) + 1.0 * y**3 - 2.0 * x * x * y

    rng = np.random.default_rng(9)
    s = 0.05
    u_p = f_u(uu, vv) + rng.normal(0, s, uu.shape)
    v_p = f_v(uu, vv) + rng.normal(0, s, uu.shape)
    inside = img < 120  # the markers: garbage there
    u_p[inside] += rng.normal(0, 3, inside.sum())
    v_p[inside] -= 5.0
    wrong = rng.random(uu.shape) < 0.002  # wrong fringe orders
    u_p[wrong] += 12.5
    mask = np.ones_like(inside)
    obs = projector_observations(u_p, v_p, mask, det)
    exp = np.stack([f_u(*truth.T), f_v(*truth.T)], 1)
    ok = det.found
    assert np.all(np.isfinite(obs.uv[ok])) and np.all(np.isnan(obs.uv[~ok]))
    err = obs.uv[ok] - exp[ok]
    # each value averages ~1000 pixels: error ~ s / sqrt(1000) ~ 0.002, plus the detected
    # centre's own error (~0.01 px x 0.28) at the true centre. Measured RMS 0.0027 (0.0026
    # to 0.0030 over 11 noise seeds): bound 2x the largest
    assert np.sqrt(np.mean(err**2)) < 0.006
    # sigma is the surround fit's: it must explain the error at the centre it was asked
    # for (the detected one). Measured rms(z) = 0.965 (0.935-1.035 over 11 seeds); with
    # n = 2 x 97 values its standard error is 1 / sqrt(2 n) = 5 %: 4 of them either side
    at_det = np.stack([f_u(*det.centers[ok].T), f_v(*det.centers[ok].T)], 1)
    z = (obs.uv[ok] - at_det) / obs.sigma[ok]
    assert abs(np.sqrt(np.mean(z**2)) - 1) < 4 / np.sqrt(2 * z.size), np.sqrt(np.mean(z**2))
    # a marker whose surround is invalid gets NaN
    mask2 = mask.copy()
    k = 4 * COLS + 5
    c = truth[k]
    mask2[int(c[1]) - 40:int(c[1]) + 40, int(c[0]) - 40:int(c[0]) + 40] = False
    obs2 = projector_observations(u_p, v_p, mask2, det)
    far = ok & (np.hypot(*(truth - c).T) > 120)
    assert np.all(np.isnan(obs2.uv[k])) and np.all(np.isfinite(obs2.uv[far]))


# ------------------------------------------------------------ blurred-ellipse edge model
def _ellipse_theta_and_pixels():
    """A 12 x 9 px ellipse turned by 0.4 rad, blur 0.8 px, on a tilted background; the
    pixels within 4 px of its edge (as _fit_blurred_ellipse selects them)."""
    a, b, ang = 12.0, 9.0, 0.4
    c, s = np.cos(ang), np.sin(ang)
    R = np.array([[c, -s], [s, c]])
    Q = R @ np.diag([1 / a**2, 1 / b**2]) @ R.T
    theta = np.array([0.3, -0.2, Q[0, 0], Q[0, 1], Q[1, 1], 0.8, 0.6, 100.0, 0.5, -0.3])
    yy, xx = np.mgrid[-16:17, -16:17].astype(float)
    px, py = xx - theta[0], yy - theta[1]
    F = Q[0, 0] * px**2 + 2 * Q[0, 1] * px * py + Q[1, 1] * py**2 - 1
    g = 2 * np.hypot(Q[0, 0] * px + Q[0, 1] * py, Q[0, 1] * px + Q[1, 1] * py)
    sel = np.abs(F / g) < 4.0
    return theta, xx[sel].copy(), yy[sel].copy()


def test_blurred_ellipse_jacobian_matches_finite_differences():
    theta, x, y = _ellipse_theta_and_pixels()
    model, J = _blurred_ellipse(theta, x, y, jacobian=True)
    assert np.array_equal(model, _blurred_ellipse(theta, x, y))
    assert J.shape == (x.size, 10)
    # central differences, step 1e-5 of each parameter's scale (1e-5 px for the centre, of
    # Q's entries for Q, ...): truncation ~h^2 f''' / 6 and rounding ~1e-16 f / h, both
    # below 1e-8 of a column's largest entry (measured: at most 1.0e-9, for q12); a wrong
    # term is an O(1e-2..1) error
    scale = np.array([1.0, 1.0, theta[2], theta[2], theta[4], 1.0, 1.0, 100.0, 1.0, 1.0])
    for k in range(10):
        h = 1e-5 * scale[k]
        up, dn = theta.copy(), theta.copy()
        up[k] += h
        dn[k] -= h
        fd = (_blurred_ellipse(up, x, y) - _blurred_ellipse(dn, x, y)) / (2 * h)
        err = np.max(np.abs(J[:, k] - fd)) / np.max(np.abs(fd))
        assert err < 1e-7, (k, err)


def test_compiled_normal_equations_equal_the_reference():
    theta, x, y = _ellipse_theta_and_pixels()
    rng = np.random.default_rng(4)
    z = _blurred_ellipse(theta + 0.01 * rng.standard_normal(10) * [1, 1, 1e-3, 1e-3, 1e-3, 1,
                                                                    1, 10, 0.1, 0.1], x, y)
    z = z + rng.normal(0.0, 1.0, z.size)
    A, g, cost = _normal_equations(theta, x, y, z)
    A_ref, g_ref, cost_ref = _normal_equations_py(theta, x, y, z)
    # the same sums in another order (and erfc vs ndtr): measured max difference relative
    # to the largest entry 3e-16 (A), 1e-15 (g)
    for got, ref in ((A, A_ref), (g, g_ref)):
        assert np.max(np.abs(got - ref)) <= 1e-12 * np.max(np.abs(ref))
    assert cost == pytest.approx(cost_ref, rel=1e-13)
    assert np.allclose(A, A.T, rtol=0, atol=0)
