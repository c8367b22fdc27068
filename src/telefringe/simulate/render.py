"""The virtual rig's renderer: scans of analytic scenes, with their ground truth.

Physics, in the order light meets it
------------------------------------
1. Projector: pattern levels quantised to ``projector_bit_depth`` bits (the same images
   :func:`telefringe.patterns.pattern_stack` makes), gamma and black level per pixel
   (``I = black + (1 - black) * p**gamma``), square pixels (fill factor 1) and a Gaussian
   defocus: the emitted intensity along the fringe axis is the exact convolution of the
   pixel values with box and Gaussian (error functions), tabulated every 1/32 projector
   pixel and linearly interpolated (error <= 1e-4 of the pattern contrast, tested).
   The panel edges (beyond which there is no light) are blurred the same way.
   A telecentric projector: collimated light along its axis. A pinhole projector: light
   from its projection centre, whose irradiance falls as the inverse square of the
   distance (relative to the depth of the world origin in the projector frame).
2. Scene: each camera sub-pixel ray meets the scene: orthographic rays through the
   inverse distortion for a telecentric camera, rays from the projection centre through
   the inverse distortion (``camera.backproject``) for a pinhole one. The hit point's
   projector coordinate comes from ``rig.projector.project`` (distortion included); a ray
   toward the projector (along its axis, or toward its centre) tests for shadow.
   Lambertian ``albedo * cos(incidence)``, plus a Gaussian specular lobe around the
   mirror direction for shiny parts, plus ambient light ``ambient * albedo``. A pinhole
   camera's lens passes ``cos^4`` of the ray's angle to the axis (natural vignetting).
3. Camera: integration over each square pixel: 2 x 2 Gauss-Legendre samples on pixels
   that see one smooth surface patch, ``edge_supersample`` x ``edge_supersample`` (>=
   ``supersample``) exactly traced midpoint samples on pixels that straddle an edge
   (marker, ball, shadow, wall, silhouette); Gaussian defocus (discrete normalised
   kernel), exposure, shot noise (Gaussian approximation of Poisson, in electrons) and
   read noise, quantisation to ``bit_depth`` bits, saturation.

The geometry (steps 2 and the sample weights) does not depend on the pattern: it is
computed once per scan and reused for every image.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.special import ndtr

from telefringe.devices import _telecentric_kernels as _tk
from telefringe.fringes.patterns import pattern_stack
from telefringe.fringes.scan import GrayGroup, PhaseGroup, Scan, ScanManifest
from telefringe.geometry.distortion import ConvergenceError
from telefringe.simulate import _kernels as _k
from telefringe.simulate.presets import VirtualRig

__all__ = ["Truth", "Geometry", "default_groups", "render_scan", "trace_geometry",
           "image_radius_px",
           "projector_profile", "projector_profile_exact", "render_images"]

#: Distance (mm) behind the scene from which rays start.
_RAY_START_MM = 500.0
#: A shadow ray counts as blocked if it meets the scene this much before the point (mm).
_SHADOW_EPS_MM = 1e-6
#: Tabulation step of the projector's emitted-intensity profile (projector pixels).
PROFILE_STEP_PX = 1.0 / 32.0
#: Normals of one pixel's samples differing by more than this flag the pixel as an edge.
_EDGE_NORMAL_COS = np.cos(np.radians(15.0))
#: Camera pixels traced at once (bounds memory).
_CHUNK_PIXELS = 65536
#: Projector coordinate standing for "no surface" (far outside any panel).
_FAR = -1e9


@dataclass(frozen=True, eq=False)
class Truth:
    """Ground truth of a rendered scan (at camera pixel centres).

    Attributes
    ----------
    xyz_world : (rows, cols, 3) ndarray of float, mm
        Surface point seen by each pixel centre where it is lit by the projector and
        visible; NaN elsewhere.
    u_p, v_p : (rows, cols) ndarray of float
        True projector coordinates (projector pixels, DESIGN convention, distortion
        included) of that point; NaN where not lit.
    lit : (rows, cols) ndarray of bool
        The pixel centre sees a surface point inside the projector's panel, facing the
        projector and not shadowed.
    features : dict
        Scene features (see each scene's ``features()``) plus their camera images, e.g.
        ``circle_centres_world`` (n, 3) and ``circle_centres_px`` (n, 2).
    visible : (rows, cols) ndarray of bool
        The pixel centre sees a surface (lit or not).
    part : (rows, cols) ndarray of int
        Scene part seen by the pixel centre (-1: nothing).
    """

    xyz_world: np.ndarray
    u_p: np.ndarray
    v_p: np.ndarray
    lit: np.ndarray
    features: dict = field(default_factory=dict)
    visible: np.ndarray | None = None
    part: np.ndarray | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.lit.shape)


def default_groups(vrig: VirtualRig, *, axes: Sequence[str] = ("u", "v"),
                   periods_u: Sequence[int] = (1, 8, 64), periods_v: Sequence[int] = (1, 8, 48),
                   steps: int = 4, exposure: float = 1.0) -> tuple[PhaseGroup, ...]:
    """The default fringe groups: ``steps``-step phase shifting at each period count of
    the ladder, for each axis in ``axes`` (u: vertical fringes, v: horizontal).

    ``vrig`` is accepted so that presets can change their ladders later; today both
    presets use the same one (>= 6 projector pixels per period on the fast rig).
    """
    del vrig
    groups = []
    for axis in axes:
        if axis not in ("u", "v"):
            raise ValueError(f"axes must contain 'u' and/or 'v', got {axis!r}")
        for p in (periods_u if axis == "u" else periods_v):
            groups.append(PhaseGroup(axis=axis, periods=int(p), steps=int(steps),
                                     exposure=float(exposure)))
    if not groups:
        raise ValueError("no groups: give at least one axis and one period count")
    return tuple(groups)


# --------------------------------------------------------------------------- projector
def _emitted(levels: np.ndarray, vrig: VirtualRig) -> np.ndarray:
    """Pattern levels (integers) -> relative emitted intensity per projector pixel."""
    ph = vrig.photometry
    top = float(2 ** ph.projector_bit_depth - 1)
    p = np.asarray(levels, dtype=float) / top
    return ph.black_level + (1.0 - ph.black_level) * p ** ph.gamma


def projector_profile_exact(pixel_values, x, *, sigma: float) -> np.ndarray:
    """Emitted intensity at projector coordinate(s) ``x`` of a 1-D row of square pixels.

    Pixel j covers ``[j - 0.5, j + 0.5]`` with intensity ``pixel_values[j]`` (0 outside
    the panel), convolved with a Gaussian of standard deviation ``sigma`` (projector px):
    ``sum_j I_j (Phi((x - j + 0.5) / sigma) - Phi((x - j - 0.5) / sigma))``.

    Parameters
    ----------
    pixel_values : (L,) array of float.  x : array of float, any shape.  sigma : float >= 0.
    """
    vals = np.asarray(pixel_values, dtype=float)
    x = np.asarray(x, dtype=float)
    L = vals.shape[0]
    if sigma <= 0:
        j = np.floor(x + 0.5).astype(np.int64)
        inside = (j >= 0) & (j < L)
        return np.where(inside, vals[np.clip(j, 0, L - 1)], 0.0)
    reach = int(np.ceil(8.0 * sigma)) + 1
    n = np.floor(x + 0.5).astype(np.int64)
    out = np.zeros(x.shape)
    for m in range(-reach, reach + 1):
        j = n + m
        inside = (j >= 0) & (j < L)
        v = np.where(inside, vals[np.clip(j, 0, L - 1)], 0.0)
        out += v * (ndtr((x - j + 0.5) / sigma) - ndtr((x - j - 0.5) / sigma))
    return out


def _kernel_reach(sigma: float) -> int:
    """Neighbouring pixels whose blurred light reaches a point (Gaussian tail < 1e-9)."""
    return int(np.ceil(6.0 * sigma)) + 1 if sigma > 0 else 0


def projector_profile(pixel_values, *, sigma: float):
    """Tabulate :func:`projector_profile_exact` every :data:`PROFILE_STEP_PX` for linear
    interpolation (the renderer's projector).

    The table's points sit at ``x = n - 0.5 + f / 32`` (f = 0..31), so each point sees
    the pixel kernel at one of 32 phases: the table is a small matrix product of the
    pixel values with those kernel values (the Gaussian is cut at 6 sigma, < 1e-9).

    Returns
    -------
    profile : (K,) ndarray, values at ``x_first + k * PROFILE_STEP_PX``.
    x_first : float.
    """
    vals = np.asarray(pixel_values, dtype=float)
    L = vals.shape[0]
    per = int(round(1.0 / PROFILE_STEP_PX))
    reach = _kernel_reach(sigma)
    pad = reach + 2
    ext = np.zeros(L + 2 * pad + 2 * reach)
    ext[pad + reach:pad + reach + L] = vals
    m = np.arange(-reach, reach + 1)
    f = np.arange(per)
    d = -m[:, None] - 0.5 + f[None, :] / per          # x - j for x in cell n, j = n + m
    if sigma > 0:
        kt = ndtr((d + 0.5) / sigma) - ndtr((d - 0.5) / sigma)
    else:
        kt = ((d >= -0.5) & (d < 0.5)).astype(float)
    win = np.lib.stride_tricks.sliding_window_view(ext, 2 * reach + 1)[:L + 2 * pad]
    prof = (win @ kt).ravel()
    return prof, -pad - 0.5


def _panel_window(x, length: int, sigma: float) -> np.ndarray:
    """Blurred panel extent along one axis: 1 inside [-0.5, L - 0.5], 0 outside."""
    x = np.asarray(x, dtype=float)
    if sigma <= 0:
        return ((x >= -0.5) & (x <= length - 0.5)).astype(float)
    return ndtr((x + 0.5) / sigma) - ndtr((x - length + 0.5) / sigma)


# --------------------------------------------------------------------------- geometry
@dataclass(frozen=True, eq=False)
class Geometry:
    """Pattern-independent part of a rendering (computed once per scene and rig).

    Samples are pixel-major: pixel p owns samples ``[p * n, (p + 1) * n)``.

    Attributes
    ----------
    shape : (rows, cols) of the traced image: the camera image grown by ``pad`` pixels
        on each side, so that the camera blur sees the scene beyond the sensor's edge.
    pad : int.
    n1 : int, samples per smooth pixel.
    cu1, cv1 : (rows * cols * n1,) projector coordinates of each sample.
    wu1, wv1 : (rows * cols * n1,) float32, weight of each sample for u- and v-axis
        patterns (8-bit DN at exposure 1 per unit emitted intensity, / n1, with the
        blurred panel window of the other axis and the shadow/back-facing test applied).
    ambient : (rows * cols,) float, ambient signal per pixel (DN at exposure 1).
    edge_pixels : (F,) int, flat indices of the refined (edge) pixels.
    n2, cu2, cv2, wu2, wv2 : the same for the refined pixels.
    truth : Truth
    """

    shape: tuple[int, int]
    pad: int
    n1: int
    cu1: np.ndarray
    cv1: np.ndarray
    wu1: np.ndarray
    wv1: np.ndarray
    ambient: np.ndarray
    edge_pixels: np.ndarray
    n2: int
    cu2: np.ndarray
    cv2: np.ndarray
    wu2: np.ndarray
    wv2: np.ndarray
    truth: Truth


def _blur_pad(sigma: float) -> int:
    """Margin (pixels) the camera blur reaches beyond the image (4 sigma kernel)."""
    return int(np.ceil(4.0 * sigma)) if sigma > 0 else 0


def _smooth_offsets(ph) -> np.ndarray:
    """Sample offsets (n, 2) on smooth pixels (equal weights): Gauss-Legendre 2 x 2
    (exact for cubics), the centre only, or the midpoint grid of ``supersample``."""
    if ph.smooth_gauss == 2:
        a = 0.5 / np.sqrt(3.0)
        return np.array([[-a, -a], [a, -a], [-a, a], [a, a]])
    if ph.smooth_gauss == 1:
        return np.zeros((1, 2))
    return _sub_offsets(int(ph.supersample))


def _sub_offsets(n: int) -> np.ndarray:
    """Midpoint-rule offsets of n x n samples over a unit pixel, (n * n, 2) as (du, dv)."""
    a = (np.arange(n) + 0.5) / n - 0.5
    dv, du = np.meshgrid(a, a, indexing="ij")
    return np.stack([du.ravel(), dv.ravel()], axis=1)


def _camera_rays(cam, u: np.ndarray, v: np.ndarray):
    """Rays of camera pixels (u, v) (N,): origins (N, 3) mm outside the scene, unit
    directions (N, 3), and the lens's relative illumination (N,) (1 for a telecentric
    lens; ``cos^4`` of the angle to the optical axis for a pinhole one: natural
    vignetting).

    Telecentric: parallel rays through the inverse distortion, starting 500 mm behind
    the zero-depth plane (compiled kernel). Any other model: ``cam.backproject`` (rays
    from the projection centre through the inverse distortion).
    """
    u = np.ascontiguousarray(u, dtype=float)
    v = np.ascontiguousarray(v, dtype=float)
    if cam.model == "telecentric":
        intr_c, R_c, t_c = _tk.kernel_args(cam)
        o, ok = _k.camera_rays(u, v, intr_c, R_c, t_c, _RAY_START_MM)
        if not np.all(ok):
            raise ConvergenceError(f"the camera's distortion cannot be inverted at "
                                   f"{int(np.count_nonzero(~ok))} sample(s)")
        d = np.ascontiguousarray(np.broadcast_to(cam.axis_world, o.shape))
        return o, d, np.ones(u.shape[0])
    rays = cam.backproject(u, v)
    d = np.ascontiguousarray(np.broadcast_to(rays.direction, (u.shape[0], 3)))
    o = np.ascontiguousarray(np.broadcast_to(rays.origin, (u.shape[0], 3)))
    cos_axis = d @ cam.R_dev_world[2]
    return o, d, cos_axis ** 4


def _projector_light(proj, P: np.ndarray):
    """How the projector lights world points P (N, 3) (NaN rows: no point).

    Returns the projector coordinates (up, vp) (N,) (distortion included), unit vectors
    toward the projector (N, 3), the distance (N,) mm from which a shadow ray toward P
    starts (it starts at ``P + distance * to_proj``), and the relative irradiance (N,)
    of the light at P (before the incidence cosine).

    Telecentric: collimated light along the axis (shadow rays from 500 mm away),
    irradiance 1. Any other model (a pinhole projector): light from the projection
    centre (shadow rays start there), irradiance falling as the inverse square of the
    distance, relative to the depth of the world origin in the projector frame.
    """
    if proj.model == "telecentric":
        up, vp = _tk.project_many(P, *_tk.kernel_args(proj))
        to_proj = np.ascontiguousarray(np.broadcast_to(-proj.axis_world, P.shape))
        n = P.shape[0]
        return up, vp, to_proj, np.full(n, _RAY_START_MM), np.ones(n)
    up, vp = proj.project(P)
    C = proj.centre_world
    vec = C - P
    dist = np.linalg.norm(vec, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        to_proj = np.ascontiguousarray(vec / dist[:, None])
        r_ref = float(proj.t_dev[2])  # depth of the world origin in the projector frame
        irr = (r_ref / dist) ** 2
    return up, vp, to_proj, dist, irr


def _trace(vrig: VirtualRig, scene, u: np.ndarray, v: np.ndarray) -> dict:
    """Trace camera rays through pixels (u, v) (N,) into the scene and shade them.

    Returns per-ray: hit, P (world point), up, vp (projector coordinates), normal, part,
    albedo, specular, lit (facing the projector, unshadowed, inside the panel), wu, wv
    (DN at exposure 1 per unit emitted intensity, times the blurred panel window of the
    other axis) and ambient (DN).
    """
    cam, proj = vrig.camera, vrig.projector
    ph = vrig.photometry
    o, d_cam, vignette = _camera_rays(cam, u, v)
    hits = scene.intersect(o, d_cam)
    hit = hits.hit
    P = _k.hit_points(o, d_cam, hits.t)
    up, vp, to_proj, start, irr = _projector_light(proj, P)
    shadow_origin = _k.shadow_origins(P, hits.normal, to_proj, start)
    # rays from the projector side toward each facing point: lit if nothing comes first
    first = scene.intersect(shadow_origin, -to_proj).t
    unshadowed = first >= start - _SHADOW_EPS_MM
    if cam.model == "telecentric" and proj.model == "telecentric":  # one half vector
        h1 = -proj.axis_world - cam.axis_world
        h_vec = np.ascontiguousarray(np.broadcast_to(h1 / np.linalg.norm(h1), P.shape))
    else:
        h_vec = to_proj - d_cam
        with np.errstate(invalid="ignore"):
            h_vec = np.ascontiguousarray(h_vec / np.linalg.norm(h_vec, axis=1,
                                                                keepdims=True))
    W, H = proj.intrinsics.width, proj.intrinsics.height
    wu, wv, amb, lit = _k.shade(hits.t, hits.normal, hits.albedo, hits.specular, unshadowed,
                                up, vp, to_proj, h_vec, np.radians(ph.specular_sigma_deg),
                                float(ph.dn_per_radiance), float(ph.ambient), float(W),
                                float(H), float(ph.projector_blur_px))
    if cam.model != "telecentric" or proj.model != "telecentric":
        gain = np.where(np.isfinite(irr), irr, 0.0) * vignette
        wu *= gain
        wv *= gain
        amb *= vignette
    return {"hit": hit, "P": P, "up": up, "vp": vp, "normal": hits.normal, "part": hits.part,
            "albedo": hits.albedo, "specular": hits.specular, "lit": lit, "wu": wu, "wv": wv,
            "ambient": amb}


def _trace_samples(vrig, scene, pix_u, pix_v, n_side):
    """Trace n_side x n_side samples of each listed pixel exactly, in chunks.

    Returns per-sample (pixel-major) cu, cv, wu, wv (weights already / n_side**2) and
    the ambient signal per pixel.
    """
    offs = _sub_offsets(n_side)
    ns = len(offs)
    npx = len(pix_u)
    cu = np.empty(npx * ns)
    cv = np.empty(npx * ns)
    wu = np.empty(npx * ns, dtype=np.float32)
    wv = np.empty(npx * ns, dtype=np.float32)
    amb = np.empty(npx)
    chunk = max(1, _CHUNK_PIXELS * 4 // ns)
    for a in range(0, npx, chunk):
        b = min(npx, a + chunk)
        su = (pix_u[a:b, None] + offs[None, :, 0]).ravel()
        sv = (pix_v[a:b, None] + offs[None, :, 1]).ravel()
        tr = _trace(vrig, scene, su, sv)
        sl = slice(a * ns, b * ns)
        cu[sl] = np.nan_to_num(tr["up"], nan=_FAR)
        cv[sl] = np.nan_to_num(tr["vp"], nan=_FAR)
        wu[sl] = tr["wu"] / ns
        wv[sl] = tr["wv"] / ns
        amb[a:b] = tr["ambient"].reshape(-1, ns).mean(axis=1)
    return cu, cv, wu, wv, amb


def _trace_centres(vrig, scene, rows, cols, pad):
    """Exact trace of every pixel centre, in chunks, for the image grown by ``pad`` pixels
    on each side; arrays shaped (rows + 2 pad, cols + 2 pad[, 3])."""
    rows, cols = rows + 2 * pad, cols + 2 * pad
    vv, uu = np.mgrid[0:rows, 0:cols]
    pu = uu.ravel().astype(float) - pad
    pv = vv.ravel().astype(float) - pad
    parts = []
    chunk = _CHUNK_PIXELS * 4
    for a in range(0, pu.size, chunk):
        parts.append(_trace(vrig, scene, pu[a:a + chunk], pv[a:a + chunk]))
    out = {}
    for key in parts[0]:
        arr = np.concatenate([p[key] for p in parts])
        out[key] = arr.reshape((rows, cols) + arr.shape[1:])
    return out


def _smooth_mask(c: dict) -> np.ndarray:
    """(rows, cols) bool: the pixel and its 8 neighbours see one smooth matte surface
    patch (same part, lit state and albedo, no specular, normals within 15 deg), away
    from the border."""
    rows, cols = c["part"].shape
    ok = np.zeros((rows, cols), dtype=bool)
    ok[1:-1, 1:-1] = True
    # a specular lobe varies too fast across a pixel to interpolate: trace shiny parts
    ok &= c["specular"] == 0
    centre = (slice(1, rows - 1), slice(1, cols - 1))
    nrm = c["normal"]
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr == 0 and dc == 0:
                continue
            nb = (slice(1 + dr, rows - 1 + dr), slice(1 + dc, cols - 1 + dc))
            same = ((c["part"][nb] == c["part"][centre]) & (c["lit"][nb] == c["lit"][centre])
                    & (c["albedo"][nb] == c["albedo"][centre])
                    & (c["specular"][nb] == c["specular"][centre])
                    & ((np.einsum("ijk,ijk->ij", nrm[nb], nrm[centre]) >= _EDGE_NORMAL_COS)
                       | ~c["hit"][centre]))
            ok[centre] &= same
    return ok


def trace_geometry(vrig: VirtualRig, scene, *, exact: bool = False) -> Geometry:
    """Trace the camera's pixels into ``scene`` once: everything but the pattern.

    Pixel centres are traced exactly. Where a pixel and its 8 neighbours see one smooth
    matte surface patch, the pixel integral uses the 2 x 2 Gauss-Legendre rule (exact for
    cubics; ``photometry.smooth_gauss``) whose sub-samples take their projector
    coordinates and weights from the quadratic through the 9 centres (errors bounded by
    tests); every other pixel (edges of markers, balls, shadows, walls, silhouettes,
    shiny surfaces, and the image border) traces ``max(edge_supersample, supersample)``**2 midpoint
    sub-samples exactly. ``exact=True`` traces every pixel that way.
    """
    ph = vrig.photometry
    cols0, rows0 = vrig.camera.image_size
    pad = _blur_pad(ph.camera_blur_px)
    rows, cols = rows0 + 2 * pad, cols0 + 2 * pad
    S = int(ph.supersample)
    E = max(int(ph.edge_supersample), S)
    c = _trace_centres(vrig, scene, rows0, cols0, pad)
    smooth = _smooth_mask(c) if not exact else np.zeros((rows, cols), dtype=bool)
    offs = _smooth_offsets(ph)
    n1 = len(offs)
    npx = rows * cols * n1
    cu1 = np.empty(npx)
    cv1 = np.empty(npx)
    wu1 = np.empty(npx, dtype=np.float32)
    wv1 = np.empty(npx, dtype=np.float32)
    _k.interp_samples(np.nan_to_num(c["up"], nan=_FAR), offs, 1.0, cu1)
    _k.interp_samples(np.nan_to_num(c["vp"], nan=_FAR), offs, 1.0, cv1)
    _k.interp_samples(c["wu"], offs, 1.0 / n1, wu1)
    _k.interp_samples(c["wv"], offs, 1.0 / n1, wv1)
    amb = c["ambient"].ravel().copy()
    edge_pix = np.flatnonzero(~smooth)
    vv, uu = np.divmod(edge_pix, cols)
    cu2, cv2, wu2, wv2, amb2 = _trace_samples(vrig, scene, uu.astype(float) - pad,
                                              vv.astype(float) - pad, E)
    amb[edge_pix] = amb2
    crop = (slice(pad, pad + rows0), slice(pad, pad + cols0))
    lit = c["lit"][crop]
    truth = Truth(xyz_world=np.where(lit[..., None], c["P"][crop], np.nan),
                  u_p=np.where(lit, c["up"][crop], np.nan),
                  v_p=np.where(lit, c["vp"][crop], np.nan),
                  lit=lit, features=_features(vrig, scene), visible=c["hit"][crop].copy(),
                  part=c["part"][crop].astype(np.int32))
    return Geometry(shape=(rows, cols), pad=pad, n1=n1, cu1=cu1, cv1=cv1, wu1=wu1, wv1=wv1,
                    ambient=amb, edge_pixels=edge_pix, n2=E * E, cu2=cu2, cv2=cv2, wu2=wu2,
                    wv2=wv2, truth=truth)


def image_radius_px(device, points_world, radius_mm: float) -> np.ndarray:
    """Largest image radius (px) of a circle of ``radius_mm`` centred at each of
    ``points_world`` (n, 3), whatever its orientation: the radius times the largest
    singular value of the device's projection Jacobian there. (n,) px."""
    P = np.asarray(points_world, dtype=float).reshape(-1, 3)
    J = device.project_jacobian(P)[2]
    return float(radius_mm) * np.linalg.svd(J, compute_uv=False)[:, 0]


def _features(vrig: VirtualRig, scene) -> dict:
    """Scene features plus their images in the camera (and projector) pixels."""
    f = dict(scene.features())
    cam, proj = vrig.camera, vrig.projector
    for key, name in (("circle_centres_world", "circle_centres"),
                      ("apexes_world", "apexes"), ("center_world", "center")):
        if key in f:
            pts = np.asarray(f[key], dtype=float)
            u, v = cam.project(pts)
            f[f"{name}_px"] = np.stack([u, v], axis=-1)
            up, vp = proj.project(pts)
            f[f"{name}_proj_px"] = np.stack([up, vp], axis=-1)
    if "circle_centres_px" in f:
        cols, rows = cam.image_size
        r_px = image_radius_px(cam, f["circle_centres_world"], 0.5 * float(f["diameter_mm"]))
        c = f["circle_centres_px"]
        f["circle_in_image"] = ((c[:, 0] >= r_px + 2) & (c[:, 0] <= cols - 3 - r_px)
                                & (c[:, 1] >= r_px + 2) & (c[:, 1] <= rows - 3 - r_px))
    return f


# --------------------------------------------------------------------------- images
def _line(group, vrig: VirtualRig, k: int | None, *, level: str | None = None) -> np.ndarray:
    """The 1-D pattern levels (along the group's axis) of image k of a group."""
    proj = vrig.projector.intrinsics
    top = 2 ** vrig.photometry.projector_bit_depth - 1
    if level is not None:
        n = proj.width
        return np.full(n, top if level == "white" else 0)
    stack = pattern_stack(group, width=proj.width, height=proj.height,
                          bit_depth=vrig.photometry.projector_bit_depth)
    return stack[k, 0, :] if group.axis == "u" else stack[k, :, 0]


def _integrate_many(geom: Geometry, vrig: VirtualRig, axis: str, lines) -> np.ndarray:
    """Noise-free camera signals (8-bit DN at exposure 1) of several 1-D patterns along
    one axis, before blur: (K, rows, cols) on the traced (padded) grid."""
    ph = vrig.photometry
    tables = [projector_profile(_emitted(lv, vrig), sigma=ph.projector_blur_px)
              for lv in lines]
    profs = np.ascontiguousarray(np.stack([t[0] for t in tables]))
    x_first = tables[0][1]
    inv = 1.0 / PROFILE_STEP_PX
    npx = geom.shape[0] * geom.shape[1]
    out = np.empty((len(lines), npx))
    c1, w1, c2, w2 = ((geom.cu1, geom.wu1, geom.cu2, geom.wu2) if axis == "u"
                      else (geom.cv1, geom.wv1, geom.cv2, geom.wv2))
    _k.accumulate_many(c1, w1, geom.n1, profs, x_first, inv, out)
    if geom.edge_pixels.size:
        o2 = np.empty((len(lines), geom.edge_pixels.size))
        _k.accumulate_many(c2, w2, geom.n2, profs, x_first, inv, o2)
        out[:, geom.edge_pixels] = o2
    out += geom.ambient
    return out.reshape((len(lines),) + geom.shape)


def _integrate(geom: Geometry, vrig: VirtualRig, axis: str, levels: np.ndarray) -> np.ndarray:
    """Noise-free camera signal (8-bit DN at exposure 1), (rows, cols), before blur."""
    return _integrate_many(geom, vrig, axis, [levels])[0]


def _blur_kernel(sigma: float) -> np.ndarray:
    """Normalised sampled Gaussian, radius ceil(4 sigma) (the camera's defocus PSF)."""
    r = _blur_pad(sigma)
    x = np.arange(-r, r + 1, dtype=float)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def _sensor(signal_dn8: np.ndarray, vrig: VirtualRig, exposure: float,
            rng: np.random.Generator, pad: int) -> np.ndarray:
    """Camera: defocus, exposure, shot + read noise, quantisation, saturation.

    ``signal_dn8`` covers the image grown by ``pad`` pixels per side (cropped here after
    the blur, so the blur sees the scene beyond the sensor's edge).
    """
    import cv2

    ph = vrig.photometry
    scale = exposure * ph.full_well_e / 255.0          # 8-bit DN -> electrons
    if ph.camera_blur_px > 0:
        k = _blur_kernel(ph.camera_blur_px)
        s = cv2.sepFilter2D(np.asarray(signal_dn8, dtype=np.float64), cv2.CV_64F, k,
                            k * scale, borderType=cv2.BORDER_REPLICATE)
    else:
        s = np.asarray(signal_dn8, dtype=np.float64) * scale
    if pad:
        s = s[pad:-pad, pad:-pad]
    normal = rng.standard_normal(s.shape, dtype=np.float32)
    full = ph.full_scale_dn
    out = np.empty(s.shape, dtype=np.uint8 if ph.bit_depth == 8 else np.uint16)
    _k.sensor_counts(s, normal, float(ph.read_noise_e), full / ph.full_well_e, full, out)
    if ph.bit_depth == 12:  # MSB-aligned, top bits replicated: 4095 -> 65535
        return (out << 4) | (out >> 8)
    return out


def render_images(geom: Geometry, vrig: VirtualRig, axis: str, levels: np.ndarray, *,
                  exposure: float, rng: np.random.Generator) -> np.ndarray:
    """One camera image of a 1-D projector pattern ``levels`` along ``axis``."""
    return _sensor(_integrate(geom, vrig, axis, levels), vrig, exposure, rng, geom.pad)


def render_scan(vrig: VirtualRig, scene, groups, *, white: bool = True, black: bool = True,
                exposures: Sequence[float] = (1.0,), seed: int = 0,
                progress: Callable | None = None,
                geometry: Geometry | None = None) -> tuple[Scan, Truth]:
    """Render a scan of ``scene`` with the virtual rig.

    Parameters
    ----------
    vrig : VirtualRig
    scene : a scene of :mod:`telefringe.simulate.scenes`.
    groups : sequence of PhaseGroup / GrayGroup (image names are ignored).
    white, black : bool
        Also capture a full-on and a full-off frame (at the first exposure).
    exposures : sequence of float
        Relative exposure times; each group is repeated once per exposure with its
        ``exposure`` field multiplied (an HDR set).
    seed : int
        Seeds the camera noise.
    progress : callable ``progress(done, total)``, optional.
    geometry : Geometry, optional
        ``trace_geometry(vrig, scene)`` computed before (repeated scans of one scene with
        other noise reuse it; it must come from this rig and scene).

    Returns
    -------
    scan : telefringe.scan.Scan
        Images uint8 (bit_depth 8) or uint16, ``max_value`` the stored saturation value.
    truth : Truth
    """
    groups = tuple(groups)
    if not groups:
        raise ValueError("groups is empty: give at least one pattern group")
    exposures = tuple(float(e) for e in exposures)
    if not exposures or not all(np.isfinite(e) and e > 0 for e in exposures):
        raise ValueError(f"exposures must be positive numbers, got {exposures!r}")
    if len(set(exposures)) != len(exposures):
        raise ValueError("exposures must differ from each other")
    for g in groups:
        if not isinstance(g, PhaseGroup | GrayGroup):
            raise ValueError(f"unsupported group {g!r}")
    out_groups = []
    for g in groups:
        for e in exposures:
            out_groups.append(replace(g, exposure=g.exposure * e, images=()))
    n_images = sum(g.count for g in out_groups) + int(white) + int(black)
    total = n_images + 4
    done = [0]

    def tick(n=1):
        done[0] += n
        if progress is not None:
            progress(done[0], total)

    geom = trace_geometry(vrig, scene) if geometry is None else geometry
    tick(4)
    rng = np.random.default_rng(seed)
    stacks = []
    cache: tuple = (None, None)      # (group key, signals): HDR repeats reuse the signals
    for g in out_groups:
        if cache[0] != g.key:
            lines = [_line(g, vrig, k) for k in range(g.count)]
            cache = (g.key, _integrate_many(geom, vrig, g.axis, lines))
        imgs = []
        for k in range(g.count):
            imgs.append(_sensor(cache[1][k], vrig, g.exposure, rng, geom.pad))
            tick()
        stacks.append(np.stack(imgs))
    cache = (None, None)
    w_img = b_img = None
    flat = [lv for want, lv in ((white, "white"), (black, "black")) if want]
    if flat:
        sig = _integrate_many(geom, vrig, "u", [_line(None, vrig, None, level=lv)
                                                for lv in flat])
        imgs = {}
        for lv, s in zip(flat, sig, strict=True):
            imgs[lv] = _sensor(s, vrig, exposures[0], rng, geom.pad)
            tick()
        w_img, b_img = imgs.get("white"), imgs.get("black")
    proj = vrig.projector.intrinsics
    man = ScanManifest(projector_width=proj.width, projector_height=proj.height,
                       groups=tuple(out_groups), white=None, black=None)
    scan = Scan(manifest=man, stacks=tuple(stacks), white=w_img, black=b_img,
                max_value=vrig.photometry.max_value, source=f"virtual rig {vrig.name!r}",
                meta={"simulated": True, "rig": vrig.name, "seed": int(seed),
                      "scene": geom.truth.features.get("type", type(scene).__name__)})
    return scan, geom.truth
