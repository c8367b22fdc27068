"""The virtual rig is a measuring instrument: test its physics against independent
computations (plain numpy decoding, analytic geometry, the noise model)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from telefringe.fringes.scan import PhaseGroup
from telefringe.geometry.distortion import undistort_sensor
from telefringe.geometry.so3 import rotation_from_rotvec
from telefringe.simulate.presets import crop_camera, get_preset
from telefringe.simulate.render import (
    PROFILE_STEP_PX,
    _integrate,
    default_groups,
    projector_profile,
    projector_profile_exact,
    render_scan,
    trace_geometry,
)
from telefringe.simulate.scenes import (
    CirclePlate,
    HeightField,
    Sphere,
    TiltedPlane,
    default_bga,
    default_steps,
    plate_at_z,
    tilted_plane,
)


@pytest.fixture(scope="module")
def fast():
    return get_preset("fast")


@pytest.fixture(scope="module")
def paper():
    return get_preset("paper")


def noise_free(vrig):
    """The rig without shot or read noise (quantisation kept)."""
    return vrig.with_photometry(full_well_e=1e12, read_noise_e=0.0)


# --------------------------------------------------------------------------- helpers
def wrapped_phase(stack):
    """Plain N-step phase (DESIGN convention), modulation B and mean A."""
    st = stack.astype(float)
    n = st.shape[0]
    d = 2 * np.pi * np.arange(n) / n
    s = -(st * np.sin(d)[:, None, None]).sum(0)
    c = (st * np.cos(d)[:, None, None]).sum(0)
    return np.mod(np.arctan2(s, c), 2 * np.pi), 2.0 / n * np.hypot(s, c), st.mean(0)


def decode_axis(scan, axis):
    """Temporal unwrapping along the ladder (coarse to fine). Returns x (projector px),
    B and A of the finest group."""
    groups = sorted(((g, s) for g, s in zip(scan.manifest.groups, scan.stacks, strict=True)
                     if g.axis == axis and g.exposure == 1.0), key=lambda gs: gs[0].periods)
    Phi, prev = None, None
    for g, s in groups:
        ph, B, A = wrapped_phase(s)
        if Phi is None:
            Phi = ph
        else:
            k = np.round((Phi * g.periods / prev - ph) / (2 * np.pi))
            Phi = ph + 2 * np.pi * k
        prev = g.periods
    L = scan.manifest.axis_length(axis)
    return Phi * L / (2 * np.pi * prev), B, A, prev


def predicted_sigma_x(vrig, A, B, L, periods, steps=4):
    """sigma_phi = sqrt(2/N) sigma_I / B with sigma_I from the sensor model, in px."""
    ph = vrig.photometry
    conv = 255.0 / ph.full_well_e
    sigma_I = np.sqrt(A * conv + (ph.read_noise_e * conv) ** 2 + 1.0 / 12.0)
    return np.sqrt(2.0 / steps) * sigma_I / B * L / (2 * np.pi * periods)


def away_from_edges(truth, r=3):
    """Pixels whose (2r+1)^2 neighbourhood sees one lit part (no edge nearby)."""
    part = np.where(truth.lit, truth.part, -1)
    ok = truth.lit.copy()
    rows, cols = part.shape
    for dr in range(-r, r + 1):
        for dc in range(-r, r + 1):
            sh = np.full_like(part, -2)
            sh[max(dr, 0):rows + min(dr, 0), max(dc, 0):cols + min(dc, 0)] = \
                part[max(-dr, 0):rows + min(-dr, 0), max(-dc, 0):cols + min(-dc, 0)]
            ok &= sh == part
    return ok


# --------------------------------------------------------------------------- presets
@pytest.mark.parametrize("name", ["paper", "fast"])
def test_preset_geometry(name):
    vr = get_preset(name)
    cam, proj = vr.camera, vr.projector
    assert cam.axis_world[2] < -0.98                     # looking down
    angle = np.degrees(np.arccos(cam.axis_world @ proj.axis_world))
    assert angle == pytest.approx(25.75, abs=0.05)       # Tables 1/2 of the paper
    # x to the right and y up in the camera image; origin circle bottom-left
    u0, v0 = cam.project(np.zeros(3))
    u1, _ = cam.project(np.array([1.0, 0.0, 0.0]))
    _, v1 = cam.project(np.array([0.0, 1.0, 0.0]))
    assert u1 > u0 and v1 < v0
    centres = plate_at_z(0.0).circle_centres_world()
    u, v = cam.project(centres)
    assert u0 < cam.intrinsics.width / 2 and v0 > cam.intrinsics.height / 2
    assert u.min() > 0.05 * cam.intrinsics.width and u.max() < 0.95 * cam.intrinsics.width
    assert v.min() > 0.05 * cam.intrinsics.height and v.max() < 0.95 * cam.intrinsics.height
    up, vp = proj.project(centres)
    assert up.min() > 0 and up.max() < proj.intrinsics.width
    assert vp.min() > 0 and vp.max() < proj.intrinsics.height


@pytest.mark.parametrize("name", ["paper", "fast"])
def test_preset_distortion_moves_corners_a_few_pixels(name):
    for dev in (get_preset(name).camera, get_preset(name).projector):
        k = dev.intrinsics
        u = np.array([0.0, k.width - 1, 0.0, k.width - 1])
        v = np.array([0.0, 0.0, k.height - 1, k.height - 1])
        xd, yd = dev.pixel_to_sensor(u, v)
        xu, yu = undistort_sensor(xd, yd, *k.distortion)
        uu, vv = dev.sensor_to_pixel(xu, yu)
        shift = np.hypot(uu - u, vv - v)
        assert 1.5 <= shift.max() <= 4.5, shift
        assert shift.min() > 0.2, shift


def test_crop_camera_is_a_window(paper):
    crop = crop_camera(paper, col0=100, row0=50, width=64, height=32)
    pts = np.array([[10.0, 5.0, 0.3], [12.0, 7.0, -1.0]])
    u, v = paper.camera.project(pts)
    uc, vc = crop.camera.project(pts)
    np.testing.assert_allclose(uc, u - 100, atol=1e-9)
    np.testing.assert_allclose(vc, v - 50, atol=1e-9)
    with pytest.raises(ValueError, match="not inside"):
        crop_camera(paper, col0=1270, row0=0, width=64, height=32)


# --------------------------------------------------------------------------- projector
def test_projector_profile_table_error_is_bounded():
    """The tabulated projector (box pixels * Gaussian, linear interpolation) against the
    exact error-function sum: <= 2e-4 of the pixel contrast at sigma = 0.6 px."""
    rng = np.random.default_rng(3)
    vals = rng.random(60)
    prof, x0 = projector_profile(vals, sigma=0.6)
    nodes = x0 + PROFILE_STEP_PX * np.arange(prof.size)
    np.testing.assert_allclose(prof, projector_profile_exact(vals, nodes, sigma=0.6),
                               atol=1e-12)
    x = rng.uniform(-4, 64, 200_000)
    approx = np.interp(x, nodes, prof, left=0.0, right=0.0)
    assert np.abs(approx - projector_profile_exact(vals, x, sigma=0.6)).max() < 2e-4
    # the profile integrates to the total light (energy conserved by the blur)
    assert prof.sum() * PROFILE_STEP_PX == pytest.approx(vals.sum(), rel=1e-3)


# --------------------------------------------------------------------------- decoding
@pytest.fixture(scope="module")
def tilted_linear(fast):
    """Tilted plane, gamma 1 (so that the only phase error left is noise)."""
    vr = fast.with_photometry(gamma=1.0)
    scan, truth = render_scan(vr, tilted_plane(8.0), default_groups(vr), seed=11)
    return vr, scan, truth


@pytest.mark.parametrize("axis", ["u", "v"])
def test_numpy_decode_matches_truth_within_noise(tilted_linear, axis):
    vr, scan, truth = tilted_linear
    x, B, A, periods = decode_axis(scan, axis)
    L = scan.manifest.axis_length(axis)
    true = truth.u_p if axis == "u" else truth.v_p
    m = truth.lit & (B > 20)
    assert m.mean() > 0.95
    err = (x - true)[m]
    sig = predicted_sigma_x(vr, A[m], B[m], L, periods)
    z = err / sig
    assert np.sqrt(np.mean(z ** 2)) == pytest.approx(1.0, abs=0.05)   # no systematic error
    assert abs(np.mean(err)) < 5 * np.sqrt(np.mean(sig ** 2)) / np.sqrt(err.size)
    assert np.abs(z).max() < 6.0                                        # no outliers
    assert np.abs(err).max() < 0.5 * L / periods                        # no wrong order


def test_plate_decode_default_gamma_has_no_wrong_order(fast):
    scan, truth = render_scan(fast, plate_at_z(0.7), default_groups(fast), seed=2)
    for axis in ("u", "v"):
        x, B, A, periods = decode_axis(scan, axis)
        L = scan.manifest.axis_length(axis)
        true = truth.u_p if axis == "u" else truth.v_p
        m = truth.lit & (B > 15)
        err = (x - true)[m]
        assert np.abs(err).max() < 0.5 * L / periods
        # away from marker edges, 4 steps at 64 periods leave little of the gamma
        # (its 3rd harmonic, aliased onto the phase, is blurred away by the projector)
        ok = away_from_edges(truth) & (B > 15)
        sig = predicted_sigma_x(fast, A[ok], B[ok], L, periods)
        rms_ratio = np.sqrt(np.mean((x - true)[ok] ** 2) / np.mean(sig ** 2))
        assert rms_ratio < 1.3


def test_gamma_visibly_distorts_three_step_phase(fast):
    """3 steps alias the gamma's second harmonic onto the phase: a clear systematic
    error with gamma 2.2 and none (within noise) with gamma 1."""
    group = (PhaseGroup(axis="u", periods=8, steps=3),)
    ratios = {}
    for gamma in (1.0, 2.2):
        vr = fast.with_photometry(gamma=gamma)
        scan, truth = render_scan(vr, tilted_plane(5.0), group, white=False, black=False,
                                  seed=5)
        ph, B, A = wrapped_phase(scan.stacks[0])
        W = scan.manifest.projector_width
        true = np.mod(2 * np.pi * 8 * truth.u_p / W, 2 * np.pi)
        m = truth.lit & (B > 20)
        err = np.angle(np.exp(1j * (ph - true)))[m]
        conv = 255.0 / vr.photometry.full_well_e
        sI = np.sqrt(A * conv + (vr.photometry.read_noise_e * conv) ** 2 + 1 / 12)[m]
        sig = np.sqrt(2.0 / 3) * sI / B[m]
        ratios[gamma] = np.sqrt(np.mean(err ** 2) / np.mean(sig ** 2))
    assert ratios[1.0] == pytest.approx(1.0, abs=0.07)
    assert ratios[2.2] > 5.0


# --------------------------------------------------------------------------- noise
def white_plane():
    """A flat white plate (albedo 0.9, like the calibration plate's light area)."""
    return TiltedPlane(albedo=0.9)


def test_noise_is_about_two_dn_on_bright_white(fast):
    scene = white_plane()
    a, _ = render_scan(fast, scene, default_groups(fast)[:1], seed=1)
    b, truth = render_scan(fast, scene, default_groups(fast)[:1], seed=2)
    m = away_from_edges(truth)
    wa, wb = a.white.astype(float)[m], b.white.astype(float)[m]
    assert 190 < wa.mean() < 210                  # bright but unsaturated
    assert np.std(wa - wb) / np.sqrt(2) == pytest.approx(2.0, abs=0.2)
    assert np.all(a.white < 255)


def test_bit_depth_12_is_msb_aligned(fast):
    vr = fast.with_photometry(bit_depth=12)
    scan, truth = render_scan(vr, white_plane(), default_groups(vr)[:1], seed=1)
    assert scan.white.dtype == np.uint16 and scan.max_value == 65535
    low = scan.white & 0xF
    assert np.array_equal(low, scan.white >> 12)      # top bits replicated below
    mean = scan.white[away_from_edges(truth)].mean()
    assert mean / 65535 == pytest.approx(200 / 255, abs=0.05)


def test_hdr_groups_repeat_per_exposure(fast):
    groups = default_groups(fast, axes=("u",), periods_u=(8,))
    scan, _ = render_scan(fast, tilted_plane(3.0), groups, exposures=(1.0, 0.25), seed=3)
    exps = [g.exposure for g in scan.manifest.groups]
    assert exps == [1.0, 0.25]
    assert {g.key for g in scan.manifest.groups} == {groups[0].key}
    m1, m2 = (s.astype(float).mean() for s in scan.stacks)
    assert m2 / m1 == pytest.approx(0.25, rel=0.03)


# --------------------------------------------------------------------------- geometry
def test_truth_agrees_with_the_model(fast):
    """The compiled tracer's truth is what the (numpy) device model says."""
    scene = Sphere(center=np.array([15.0, 12.0, -0.5]), radius=4.0)
    g = trace_geometry(fast, scene)
    t = g.truth
    m = t.lit
    up, vp = fast.projector.project(t.xyz_world[m])
    np.testing.assert_allclose(up, t.u_p[m], atol=1e-9)
    np.testing.assert_allclose(vp, t.v_p[m], atol=1e-9)
    u, v = fast.camera.project(t.xyz_world[m])
    rows, cols = np.nonzero(m)
    np.testing.assert_allclose(u, cols, atol=1e-8)
    np.testing.assert_allclose(v, rows, atol=1e-8)
    # points lie on the scene's surfaces
    p = t.xyz_world[m & (t.part == 1)]
    np.testing.assert_allclose(np.linalg.norm(p - scene.center, axis=1), scene.radius,
                               atol=1e-9)


def test_smooth_pixel_integration_error_is_bounded(fast):
    """Interpolated Gauss-Legendre sub-samples on smooth pixels against exactly traced
    7 x 7 midpoint sub-samples everywhere, on a sphere (curved, foreshortened flanks):
    the noise-free images agree to a tenth of the noise (2 DN) at worst, 1 % in RMS
    (the 7 x 7 midpoint reference itself errs by ~0.03 DN on the finest fringes)."""
    vr = noise_free(fast)
    scene = Sphere(center=np.array([15.0, 12.0, -1.0]), radius=4.5)
    g_fast = trace_geometry(vr, scene)
    g_exact = trace_geometry(vr, scene, exact=True)
    levels = np.round(255 * (0.5 + 0.5 * np.cos(2 * np.pi * 64 * np.arange(400) / 400)))
    a = _integrate(g_fast, vr, "u", levels)
    b = _integrate(g_exact, vr, "u", levels)
    smooth = np.ones(a.shape, bool)
    smooth.ravel()[g_fast.edge_pixels] = False
    diff = np.abs(a - b)[smooth]
    assert diff.max() < 0.2
    assert np.sqrt(np.mean(diff ** 2)) < 0.02


def test_shiny_pixels_are_traced_not_interpolated(paper):
    """Specular lobes vary too fast to interpolate: on the BGA the fast geometry must
    give the exactly traced images (highlights included)."""
    vr = crop_camera(paper, col0=543, row0=415, width=96, height=96)
    bga = default_bga(0)
    g_fast = trace_geometry(vr, bga)
    g_exact = trace_geometry(vr, bga, exact=True)
    W = vr.projector.intrinsics.width
    levels = np.round(255 * (0.5 + 0.5 * np.cos(2 * np.pi * 64 * np.arange(W) / W)))
    a = _integrate(g_fast, vr, "u", levels)
    b = _integrate(g_exact, vr, "u", levels)
    assert b.max() > 500                           # highlights are there
    assert np.abs(a - b).max() < 0.05


def test_dark_blobs_sit_where_the_model_projects_circle_centres(fast):
    """Darkness-weighted centroid of each marker (noise free) against project(centre),
    on a tilted plate. The rendering's own centroid error (7 x 7 integration of edge
    pixels, about 0.004 px RMS on these 11 px markers; 0.001 px from the distortion's
    curvature) must stay well below the scatter that 2 DN of noise gives this
    estimator (about 0.012 px)."""
    vr = noise_free(fast)
    R = rotation_from_rotvec(np.radians([8.0, -6.0, 4.0]))
    centre_t = np.array([15.0, 12.0, 0.0])
    plate = CirclePlate(R_world_target=R, t_world_target=centre_t - R @ centre_t)
    scan, truth = render_scan(vr, plate, default_groups(vr)[:1], black=False, seed=0)
    img = scan.white.astype(float)
    centres = truth.features["circle_centres_px"]
    r_px = 0.5 * 1.5 * vr.camera.intrinsics.m / vr.camera.intrinsics.du
    light = np.median(img[truth.lit & (truth.part == 0)])
    errs = []
    vv, uu = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    for cu, cv in centres:
        win = (np.hypot(uu - cu, vv - cv) < r_px + 3)
        dark = np.clip(light - img, 0, None) * win
        errs.append([(dark * uu).sum() / dark.sum() - cu, (dark * vv).sum() / dark.sum() - cv])
    errs = np.array(errs)
    assert np.abs(errs).max() < 0.015, np.abs(errs).max()
    assert np.sqrt(np.mean(errs ** 2)) < 0.005


def test_step_shadows_appear_where_geometry_says(fast):
    """Independent geometry: a point on step k is shadowed iff its ray toward the
    projector passes through step k + 1. The white frame is dark exactly there."""
    steps = default_steps(heights=(0.5, 2.0, 2.5, 4.0))
    vr = fast
    scan, truth = render_scan(vr, steps, default_groups(vr)[:1], black=False, seed=4)
    img = scan.white.astype(float)
    to_proj = -vr.projector.axis_world
    assert to_proj[0] > 0.3                       # the projector lights from +x
    rows, cols = img.shape
    vv, uu = np.mgrid[0:rows, 0:cols]
    origin, d = vr.camera.backproject(uu.astype(float), vv.astype(float))
    blocks = steps.blocks
    predicted_shadow = np.zeros(img.shape, bool)
    predicted_lit = np.zeros(img.shape, bool)
    for k in range(len(blocks) - 1):
        x0, x1, y0, y1, _, h = blocks[k]
        t = (h - origin[..., 2]) / d[2]
        P = origin + t[..., None] * d
        on_top = (P[..., 0] > x0) & (P[..., 0] < x1) & (P[..., 1] > y0) & (P[..., 1] < y1)
        nx0, nx1, ny0, ny1, _, nh = blocks[k + 1]
        s = (nh - h) / to_proj[2]                 # reach the next step's top height
        # the ray toward the projector enters block k+1 through its -x wall, below its top
        sx = (nx0 - P[..., 0]) / to_proj[0]
        y_at_wall = P[..., 1] + sx * to_proj[1]
        hits_wall = (sx > 0) & (sx < s) & (y_at_wall > ny0) & (y_at_wall < ny1)
        predicted_shadow |= on_top & hits_wall
        predicted_lit |= on_top & ~hits_wall
    # stay 2 px away from the predicted boundaries (blur, sampling)
    def erode(m, r=2):
        out = m.copy()
        for dr in range(-r, r + 1):
            for dc in range(-r, r + 1):
                out &= np.roll(np.roll(m, dr, 0), dc, 1)
        return out
    sh, li = erode(predicted_shadow), erode(predicted_lit)
    assert sh.sum() > 100 and li.sum() > 1000
    assert np.all(img[sh] < 12)                   # ambient only
    assert np.all(img[li] > 120)
    assert not truth.lit[sh].any() and truth.lit[li].all()


def test_sphere_shadow_is_on_the_side_away_from_the_projector(fast):
    scene = Sphere(center=np.array([15.0, 12.0, 1.0]), radius=3.0)
    g = trace_geometry(fast, scene)
    t = g.truth
    plane_unlit = t.visible & (t.part == 0) & ~t.lit
    assert plane_unlit.sum() > 50
    # the shadow's pixels see plane points on the -x side of the sphere (light from +x)
    origin, d = fast.camera.backproject(*np.nonzero(plane_unlit)[::-1])
    P = origin + ((0.0 - origin[:, 2]) / d[2])[:, None] * d
    assert np.all(P[:, 0] < scene.center[0])
    # and every one of them is analytically shadowed: its ray to the projector meets
    # the sphere
    to_proj = -fast.projector.axis_world
    q = P - scene.center
    b = q @ to_proj
    disc = b ** 2 - (np.einsum("ij,ij->i", q, q) - scene.radius ** 2)
    assert np.all(disc > -1e-9) and np.all(-b + np.sqrt(np.clip(disc, 0, None)) > 0)


def test_heightfield_matches_the_analytic_plane(fast):
    plane = tilted_plane(6.0, z0=0.4)
    x = np.arange(-5.0, 36.0, 0.25)
    y = np.arange(-5.0, 30.0, 0.25)
    X, Y = np.meshgrid(x, y)
    hf = HeightField(z=plane.height_at(X, Y), pixel_size=0.25, origin=np.array([-5.0, -5.0]))
    ta = trace_geometry(fast, plane).truth
    tb = trace_geometry(fast, hf).truth
    m = ta.lit & tb.lit
    assert m.mean() > 0.95
    np.testing.assert_allclose(tb.xyz_world[m], ta.xyz_world[m], atol=1e-6)
    np.testing.assert_allclose(tb.u_p[m], ta.u_p[m], atol=1e-5)


# --------------------------------------------------------------------------- BGA / HDR
def test_bga_highlights_saturate_at_default_exposure_only(paper):
    vr = crop_camera(paper, col0=543, row0=415, width=128, height=128)
    bga = default_bga(0)
    groups = default_groups(vr, axes=("u",), periods_u=(64,))
    scan, truth = render_scan(vr, bga, groups, exposures=(1.0, 0.1), seed=0)
    balls = truth.part == 2
    assert balls.mean() > 0.15
    sat = [(s == 255).any(axis=0) for s in scan.stacks]
    assert sat[0][balls].mean() > 0.02            # highlights saturate at exposure 1
    assert not sat[0][~balls].any()               # the matte substrate does not
    assert not sat[1].any()                       # a shorter exposure does not
    f = truth.features
    assert len(f["missing"]) == 4
    assert f["apexes_world"].shape == (24 * 24 - 4, 3)


def test_bga_missing_balls_and_heights(fast):
    bga = default_bga(1)
    f = bga.features()
    present = bga.present()
    for i, j in bga.missing:
        assert not present[i, j]
    off = f["height_offsets_mm"]
    assert np.isclose(off.max(), 0.03) and np.isclose(off.min(), -0.04)
    np.testing.assert_allclose(f["apexes_world"][:, 2] - f["centres_world"][:, 2], 0.225)
    # a vertical ray through an apex hits it
    ap = f["apexes_world"][:5]
    h = bga.intersect(ap + np.array([0.0, 0.0, 10.0]), np.array([0.0, 0.0, -1.0]))
    np.testing.assert_allclose(h.t, 10.0, atol=1e-12)
    np.testing.assert_allclose(h.normal, np.tile([0.0, 0.0, 1.0], (5, 1)), atol=1e-12)


def test_scene_validation():
    with pytest.raises(ValueError):
        CirclePlate(diameter=3.5)
    with pytest.raises(ValueError):
        replace(default_bga(0), missing=((99, 0),))
    with pytest.raises(ValueError):
        HeightField(z=np.zeros(3), pixel_size=0.1)
    with pytest.raises(ValueError):
        get_preset("nope")
    with pytest.raises(ValueError):
        render_scan(get_preset("fast"), plate_at_z(0), ())
