"""measure_bga: the BGA inspection as a sequence of stages."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from telefringe.metrology._common import MetrologyError, _components, _tangent_basis
from telefringe.metrology.bga.caps import _apex_sigma, _fit_cap
from telefringe.metrology.bga.coplanarity import seating_plane_coplanarity
from telefringe.metrology.bga.grid import _register_grid
from telefringe.metrology.bga.highlights import _fit_along_line, _refine_by_highlights
from telefringe.metrology.bga.nominal import BGANominal
from telefringe.metrology.bga.psf import _brightness_gradient_terms, _fit_caps_smoothed
from telefringe.metrology.bga.result import BGAMeasurement
from telefringe.metrology.planes import fit_plane
from telefringe.reconstruction.reconstruct import PointCloud


def _sigma_weights(cloud: PointCloud, sel: np.ndarray):
    """1 / sigma_z^2 of the selected points, or None when some are unknown."""
    s = cloud.sigma_z[sel]
    return 1.0 / s**2 if np.all(np.isfinite(s) & (s > 0)) else None


def measure_bga(cloud: PointCloud, nominal: BGANominal, *, image=None,
                min_height: float | None = None, min_fraction: float = 0.2,
                edge_px: int | None = None, cap_min_height: float | None = None,
                weighted: bool = False, max_view_angle_deg: float | None = None,
                highlight_px: float | None = None, fixed_radius: bool = False,
                psf_model: bool = True, projector=None, substrate_margin: float | None = None,
                seed: int = 0) -> BGAMeasurement:
    """Inspect a ball grid array from its point cloud.

    Steps: the substrate plane is fitted robustly (the balls are outliers); pixels more
    than ``min_height`` (default 0.2 ball diameters) above it form connected regions,
    one per ball (regions smaller than ``min_fraction`` of a ball's footprint are
    ignored, and so are regions too large or too wide for one ball); the substrate is
    refitted away from them (``substrate_margin``). Each region, shrunk
    by ``edge_px`` pixels (silhouette pixels mix ball and
    substrate; default 1 when a ball is at least 10 pixels wide, else 0: on small balls
    the points are too few to spare), keeping points higher than ``cap_min_height``
    (default 0.3 ball diameters, above the shadowed flank) and away from the highlight
    (``highlight_px``), is fitted with a sphere: by default (``psf_model``) of the
    nominal radius, through a model of the camera's point spread, weighted by each
    point's uncertainty (else robust, free radius when the cap determines it); with an
    ``image``, the centre is then held on its highlight's camera line and only its depth
    along it refitted. The apex is
    the sphere's point farthest from the substrate. Balls are then registered on the
    nominal grid (its rotation and offset found from the balls themselves), which gives
    the missing balls, the pitch between neighbours and the JEDEC seating-plane
    coplanarity (see :func:`seating_plane_coplanarity`).

    Parameters
    ----------
    cloud : PointCloud.   nominal : BGANominal.
    image : (rows, cols) array_like, optional
        An unsaturated image of the scene in the camera's pixels (e.g. the HDR radiance
        of the decoder's background, :attr:`telefringe.reconstruct.Reconstruction.radiance`).
        When given, each ball's position on the substrate comes from its specular
        highlight (Gaussian fit, ~0.01 px), offset by the median (highlight - cap centre)
        of all balls: with a telecentric camera and projector every ball shows its
        highlight at the same place, so the pitch is measured about 5x better than from
        the cap fits alone. The highlight's 3-D point is where its camera line meets the
        ball's fitted sphere (so the depth noise of the few points at the highlight does
        not leak onto the substrate through the tilt of the viewing direction). Balls
        without a clear highlight keep their cap centres.
    weighted : bool
        Weight each cap point by 1 / sigma_r^2 (its ``sigma_line`` projected on the
        sphere's radius).
    max_view_angle_deg : float, optional
        Drop cap points whose surface is tilted more than this from facing the camera.
    highlight_px : float, optional
        Drop cap points within this many pixels of the brightest pixel of ``image`` (the
        camera's point spread carries the highlight's phase into them, beyond the first
        order of ``psf_model``); 0 keeps them. Default 2.5 when a ball is at least 10
        pixels wide (the highlight of the paper rig's balls, ~1 px sigma, has fallen to
        the diffuse level there), else 0.
    fixed_radius : bool
        Fit every cap with the nominal radius (an assumption: the balls are spheres of
        the nominal diameter); the diameter is then not reported.
    psf_model : bool
        Fit the caps with the nominal radius and a model of the camera's point spread:
        a pixel measures the spread-averaged surface, which on a convex cap lies deeper
        than the surface (by s^2 lap(z) / 2, growing as the cap tilts away), and where
        the brightness varies the average is taken off-centre (by s^2 grad(ln I), with
        ``image``). The spread's variance s^2 (one camera, so one value for every ball)
        is estimated from the caps themselves (reported as ``psf_variance``), and so is
        the depth change per pixel of that shift at constant projector coordinate unless
        ``projector`` gives it; points tilted more than ``max_view_angle_deg`` (default
        60) from facing the camera are dropped, every point is weighted by
        1 / sigma_r^2. Needs the nominal diameter to hold (the radius is not fitted).
    projector : TelecentricDevice, optional
        The (calibrated) projector: gives the projector coordinate of each point and its
        rate along the camera line, for the brightness-gradient term of ``psf_model``
        (u fringes only; without it the term's geometric factor is estimated, which also
        absorbs the v fringes' share).
    substrate_margin : float, optional
        The substrate plane is refitted on points farther than this (mm, default D / 2)
        from every ball region (next to a ball the substrate's points are biased by its
        shadow edge and the light of its flank spread by the camera); 0 keeps the first
        fit on all points.
    seed : seeds the robust substrate fit.

    Returns
    -------
    BGAMeasurement
    """
    from scipy import ndimage

    if cloud.count < 10:
        raise MetrologyError(f"the cloud has {cloud.count} valid points: no BGA")
    if image is not None and np.shape(image) != cloud.shape:
        raise MetrologyError(f"image has shape {np.shape(image)}, the cloud {cloud.shape}")
    D = float(nominal.ball_diameter_mm)
    pitch = float(nominal.pitch_mm)
    # a first substrate plane, to find the balls (0.2 D above it): on every third row and
    # column of a large cloud (it is refitted on all the points away from the balls)
    k = 3 if cloud.count > 200_000 else 1
    sub_sel = np.zeros(cloud.shape, dtype=bool)
    sub_sel[::k, ::k] = True
    sub_sel &= cloud.mask
    substrate = fit_plane(cloud.xyz[sub_sel], weights=_sigma_weights(cloud, sub_sel),
                          robust=True, seed=seed)
    nrm = substrate.normal
    h = np.where(cloud.mask, cloud.xyz @ nrm - substrate.offset, np.nan)
    thr = 0.2 * D if min_height is None else float(min_height)
    cap_thr = 0.3 * D if cap_min_height is None else float(cap_min_height)
    above = np.nan_to_num(h, nan=-np.inf) > thr
    labels, n_lab = _components(above)
    if n_lab == 0:
        raise MetrologyError(f"no ball: nothing stands {thr:.3g} mm above the substrate")
    # expected footprint of a ball in pixels (from the cloud's point spacing)
    pts_all = cloud.xyz
    step = np.linalg.norm(np.diff(pts_all[:, :, :2], axis=1), axis=2)
    px_mm = float(np.nanmedian(step)) if np.any(np.isfinite(step)) else np.nan
    foot = np.pi * (D / 2) ** 2 / px_mm**2 if np.isfinite(px_mm) else 0.0
    if edge_px is None:
        edge_px = 1 if (np.isfinite(px_mm) and D / px_mm >= 10.0) else 0
    if highlight_px is None:
        highlight_px = 2.5 if (np.isfinite(px_mm) and D / px_mm >= 10.0) else 0.0
    margin = 0.5 * D if substrate_margin is None else float(substrate_margin)
    if margin > 0 and np.isfinite(px_mm):
        # refit the substrate away from the balls: next to a ball the substrate's points
        # are biased (its shadow edge and its flank's light, spread by the camera)
        near = ndimage.binary_dilation(above, iterations=max(int(np.ceil(margin / px_mm)), 1))
        far = cloud.mask & ~near
        if cloud.count > 200_000:  # every second row and column is plenty
            far[1::2, :] = False
            far[:, 1::2] = False
        if np.count_nonzero(far) >= max(100, 0.01 * cloud.count):
            substrate = fit_plane(cloud.xyz[far], weights=_sigma_weights(cloud, far),
                                  robust=True, seed=seed)
            nrm = substrate.normal
            h = np.where(cloud.mask, cloud.xyz @ nrm - substrate.offset, np.nan)
    sizes = np.bincount(labels.ravel(), minlength=n_lab + 1)
    slices = ndimage.find_objects(labels)
    bgrad, grad_known = None, True
    if psf_model and image is not None and np.isfinite(px_mm):
        bgrad, grad_known = _brightness_gradient_terms(cloud, np.asarray(image, np.float64),
                                                       projector, px_mm)
    fits = []
    regions = []
    free_r = []
    caps = []
    view = -np.asarray(cloud.direction, dtype=np.float64)
    image_arr = None if image is None else np.asarray(image, dtype=np.float64)
    for lab in range(1, n_lab + 1):
        if sizes[lab] < max(min_fraction * foot, 8):
            continue
        sl = slices[lab - 1]
        # a ball is compact: no wider than twice its diameter, no larger than 3 footprints
        if np.isfinite(px_mm) and (max(sl[0].stop - sl[0].start, sl[1].stop - sl[1].start)
                                   > 2.0 * D / px_mm + 2 or sizes[lab] > 3.0 * foot + 10):
            continue
        reg = labels[sl] == lab
        if edge_px > 0:
            reg = ndimage.binary_erosion(reg, iterations=int(edge_px))
        hh = h[sl]
        sel = reg & (np.nan_to_num(hh, nan=-np.inf) > cap_thr)
        if image_arr is not None and highlight_px > 0:
            # pixels near the specular highlight: the camera's point spread mixes the
            # highlight's (far brighter) light, and so its phase, into them
            sub_img = np.where(labels[sl] == lab, image_arr[sl], -np.inf)
            pi, pj = np.unravel_index(int(np.argmax(sub_img)), sub_img.shape)
            vv, uu = np.mgrid[0:sub_img.shape[0], 0:sub_img.shape[1]]
            sel &= np.hypot(vv - pi, uu - pj) > highlight_px
        pts = cloud.xyz[sl][sel]
        sig = cloud.sigma_line[sl][sel]
        if pts.shape[0] < 10:
            continue
        if psf_model:
            caps.append((pts, sig, np.zeros((pts.shape[0], 3)) if bgrad is None
                         else bgrad[sl][sel]))
            regions.append((sl, labels[sl] == lab))
            continue
        try:
            f = _fit_cap(pts, sig, view, D, weighted=weighted,
                         max_view_angle_deg=max_view_angle_deg, fixed_radius=fixed_radius)
        except MetrologyError:
            continue
        if f is None:
            continue
        f, free = f
        fits.append(f)
        free_r.append(free)
        regions.append((sl, labels[sl] == lab))
    smoothing = (np.nan, np.nan)
    if psf_model:
        all_fits, all_data, theta, cov_theta = _fit_caps_smoothed(
            caps, view, D / 2, max_view_angle_deg=(60.0 if max_view_angle_deg is None
                                                   else float(max_view_angle_deg)),
            free_gradient=not grad_known)
        smoothing = (float(theta[0]), float(np.sqrt(cov_theta[0, 0])))
        keep = [k for k, f in enumerate(all_fits) if f is not None and f.rms < 0.1 * D]
        fits = [all_fits[k] for k in keep]
        cap_data = [all_data[k] for k in keep]
        regions = [regions[k] for k in keep]
        free_r = [False] * len(fits)
    if not fits:
        raise MetrologyError("no ball could be fitted")
    centre = np.array([f.centre for f in fits])
    sig_c = np.array([f.sigma_centre for f in fits]).reshape(-1, 3)
    radius = np.array([f.radius for f in fits])
    refined = np.zeros(len(fits), dtype=bool)
    med = None
    if image is not None:
        sig_top = np.array([_apex_sigma(f, nrm) for f in fits])
        centre, sig_c, refined, lines, med = _refine_by_highlights(
            cloud, np.asarray(image, np.float64), regions, centre, sig_c, nrm, radius,
            sig_top)
    sig_top = np.array([_apex_sigma(f, nrm) for f in fits])
    if psf_model and image is not None and med is not None:
        # every ball's centre lies on its highlight's camera line shifted by the common
        # offset: fit the one remaining unknown, the depth along that line
        d = np.asarray(cloud.direction, dtype=np.float64)
        for k in np.flatnonzero(refined):
            res = _fit_along_line(cap_data[k][0], cap_data[k][1], lines[k] - med, d,
                                  radius[k], centre[k])
            if res is not None:
                centre[k], s_t = res
                sig_top[k] = s_t * abs(float(d @ nrm))
    if psf_model and np.all(np.isfinite(cov_theta)):
        # the estimated spread parameters are common to every ball: their uncertainty
        # moves every apex together
        for k in range(len(fits)):
            gk = nrm @ cap_data[k][2]  # d height / d theta
            sig_top[k] = np.hypot(sig_top[k], np.sqrt(max(float(gk @ cov_theta @ gk), 0.0)))
    apex = centre + radius[:, None] * nrm
    height = apex @ nrm - substrate.offset
    sig_h = np.array([np.hypot(st, substrate.sigma_at(a))
                      for st, a in zip(sig_top, apex, strict=True)])
    T = _tangent_basis(nrm)
    pos = centre @ T.T
    if nominal.rows is None:
        # the grid is the span of the balls found
        _, _, _, span = _register_grid(pos, pitch, None, None, None)
        nominal = replace(nominal, rows=int(span[1]), cols=int(span[0]))
    populated = nominal.populated()
    rows, cols = int(nominal.rows), int(nominal.cols)
    idx, theta, origin_local, _ = _register_grid(pos, pitch, rows, cols, populated)
    # keep one ball per grid position (the one with the most points), drop off-grid blobs
    order = sorted(range(len(fits)), key=lambda k: -fits[k].n_inliers)
    taken = np.full((rows, cols), -1, dtype=np.int64)
    for k in order:
        i, j = idx[k]
        if i >= 0 and taken[i, j] < 0:
            taken[i, j] = k
    sel = taken[taken >= 0]  # row-major grid order
    found = taken >= 0
    missing = tuple((int(i), int(j)) for i, j in np.argwhere(populated & ~found))
    unexpected = tuple((int(i), int(j)) for i, j in np.argwhere(~populated & found))
    c_, s_ = np.cos(theta), np.sin(theta)
    local = pos[sel] @ np.array([[c_, -s_], [s_, c_]]) - origin_local
    grid_xyz = np.full((rows, cols, 2), np.nan)
    grid_xyz[found] = local
    px = np.linalg.norm(np.diff(grid_xyz, axis=1), axis=2)
    py = np.linalg.norm(np.diff(grid_xyz, axis=0), axis=2)
    errs = np.concatenate([px[np.isfinite(px)], py[np.isfinite(py)]]) - pitch
    # centre of gravity: given, or the centre of the nominal grid
    if nominal.centre_of_gravity is not None:
        cog = np.asarray(nominal.centre_of_gravity, dtype=np.float64)
    else:
        mid_local = np.array([(cols - 1) / 2.0, (rows - 1) / 2.0]) * pitch + origin_local
        mid_plane = np.array([[c_, -s_], [s_, c_]]) @ mid_local  # rotate back by theta
        cog = (mid_plane[0] * T[0] + mid_plane[1] * T[1]
               + substrate.offset * nrm)
    cop = seating_plane_coplanarity(apex[sel], cog, reference=substrate.plane)
    return BGAMeasurement(
        index=np.argwhere(found), centre=centre[sel],
        sigma_centre=sig_c[sel], refined=refined[sel],
        apex=apex[sel], height=height[sel],
        sigma_height=sig_h[sel],
        diameter=np.where(np.asarray(free_r)[sel], 2.0 * radius[sel], np.nan),
        position=local,
        rms=np.array([fits[k].rms for k in sel]),
        n_points=np.array([fits[k].n_inliers for k in sel], dtype=np.int64),
        substrate=substrate, found=found, missing=missing, unexpected=unexpected,
        pitch_x=px, pitch_y=py,
        pitch_error_max=float(np.max(np.abs(errs))) if errs.size else np.nan,
        coplanarity=cop, grid_angle_deg=float(np.degrees(theta)), nominal=nominal,
        psf_variance=float(smoothing[0]), sigma_psf_variance=float(smoothing[1]))
