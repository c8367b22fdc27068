"""The first stages of a BGA inspection: the substrate plane, one region per ball, and
each ball's cap points."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from telefringe.metrology._common import MetrologyError, _components
from telefringe.metrology.planes import PlaneFit, fit_plane
from telefringe.reconstruction.cloud import PointCloud


class Segmentation(NamedTuple):
    """Substrate and ball regions of a BGA cloud.

    substrate : PlaneFit.   height : (rows, cols) mm above it, NaN where invalid.
    above : (rows, cols) bool, pixels above the ball threshold.   labels : (rows, cols)
    int, their connected regions (0: none), ``n_labels`` of them.   px_mm : float, the
    cloud's point spacing (NaN when unknown).   footprint_px : float, a ball's expected
    footprint in pixels (0 when unknown).   substrate_pixels : (k,) int, flat indices of the
    pixels whose points the substrate plane was fitted on (its inliers).
    """

    substrate: PlaneFit
    height: np.ndarray
    above: np.ndarray
    labels: np.ndarray
    n_labels: int
    px_mm: float
    footprint_px: float
    substrate_pixels: np.ndarray | None = None


class Candidate(NamedTuple):
    """One region standing above the substrate.

    slice : the region's bounding box (2 slices).   region : bool mask in that box.
    reason : None when the region is a ball's cap, else why it is not measured (a key of
    :data:`telefringe.metrology.bga.result.NOT_MEASURED_REASONS`).
    points, sigma : (m, 3), (m,) the cap points and their ``sigma_line`` (None when
    ``reason``).   gradient : (m, 3) brightness-gradient terms (zeros without them).
    view : (m, 3) unit vectors from each point toward the camera (along its pixel's
    line of sight: the same for every point of a telecentric camera).
    pixels : (m,) int, flat (row-major) index of each cap point's pixel in the cloud.
    """

    slice: tuple
    region: np.ndarray
    reason: str | None
    points: np.ndarray | None = None
    sigma: np.ndarray | None = None
    gradient: np.ndarray | None = None
    view: np.ndarray | None = None
    pixels: np.ndarray | None = None


def _sigma_weights(cloud: PointCloud, sel: np.ndarray):
    """1 / sigma_z^2 of the selected points, or None when some are unknown."""
    s = cloud.sigma_z[sel]
    return 1.0 / s**2 if np.all(np.isfinite(s) & (s > 0)) else None


def _substrate_fit(cloud: PointCloud, sel: np.ndarray, seed: int, noise):
    """The robust plane of the selected points (its weights 1 / sigma_z^2 when every
    sigma is known), and the flat indices of its inliers' pixels. With ``noise`` (a
    two-camera match's StereoNoise) the plane's covariance is the sandwich of the
    points' correlated noise (:func:`fit_plane`); the plane is the same."""
    if noise is None:
        plane = fit_plane(cloud.xyz[sel], weights=_sigma_weights(cloud, sel), robust=True,
                          seed=seed)
    else:
        from dataclasses import replace

        if _sigma_weights(cloud, sel) is None:
            raise MetrologyError("the substrate's points lack a sigma_z: no covariance "
                                 "with the stereo noise")
        # the same points and weights (fit_plane weights a PointCloud's by 1 / sigma_z^2)
        plane = fit_plane(replace(cloud, mask=sel), robust=True, seed=seed, noise=noise)
    return plane, np.flatnonzero(sel.reshape(-1))[np.asarray(plane.inliers, dtype=bool)]


def segment(cloud: PointCloud, D: float, *, min_height: float | None,
            substrate_margin: float | None, seed: int, noise=None) -> Segmentation:
    """Substrate plane and ball regions.

    The substrate is fitted robustly (the balls are outliers; on every third row and
    column of a cloud of more than 200 000 points); pixels more than ``min_height``
    (default 0.2 D) above it form connected regions; the substrate is then refitted on
    the points farther than ``substrate_margin`` (default D / 2) from every region.
    ``noise``: a two-camera match's StereoNoise, for the plane's covariance.
    """
    from telefringe.metrology.bga._kernels import heights, row_steps, within_taxicab

    xyz = np.ascontiguousarray(cloud.xyz, dtype=np.float64)
    mask = np.ascontiguousarray(cloud.mask)
    k = 3 if cloud.count > 200_000 else 1
    sub_sel = np.zeros(cloud.shape, dtype=bool)
    sub_sel[::k, ::k] = True
    sub_sel &= cloud.mask
    substrate, sub_px = _substrate_fit(cloud, sub_sel, seed, noise)
    h = np.empty(cloud.shape)
    heights(xyz, mask, substrate.normal, substrate.offset, h)
    thr = 0.2 * D if min_height is None else float(min_height)
    above = np.nan_to_num(h, nan=-np.inf) > thr
    labels, n_lab = _components(above)
    if n_lab == 0:
        raise MetrologyError(f"no ball: nothing stands {thr:.3g} mm above the substrate")
    # expected footprint of a ball in pixels (from the cloud's point spacing)
    step = row_steps(xyz)  # the finite ones
    px_mm = float(np.median(step)) if step.size else np.nan
    foot = np.pi * (D / 2) ** 2 / px_mm**2 if np.isfinite(px_mm) else 0.0
    margin = 0.5 * D if substrate_margin is None else float(substrate_margin)
    if margin > 0 and np.isfinite(px_mm):
        # refit the substrate away from the balls: next to a ball the substrate's points
        # are biased (its shadow edge and its flank's light, spread by the camera)
        # (as ndimage.binary_dilation(above, iterations=...), in one compiled pass)
        near = within_taxicab(above, max(int(np.ceil(margin / px_mm)), 1))
        far = cloud.mask & ~near
        if cloud.count > 200_000:  # every second row and column is plenty
            far[1::2, :] = False
            far[:, 1::2] = False
        if np.count_nonzero(far) >= max(100, 0.01 * cloud.count):
            substrate, sub_px = _substrate_fit(cloud, far, seed, noise)
            heights(xyz, mask, substrate.normal, substrate.offset, h)
    return Segmentation(substrate, h, above, labels, int(n_lab), px_mm, float(foot),
                        sub_px)


def cap_candidates(cloud: PointCloud, seg: Segmentation, D: float, *, image, gradient,
                   min_fraction: float, edge_px: int, cap_min_height: float | None,
                   highlight_px: float) -> list[Candidate]:
    """Each region's cap points, or why the region is not a measurable ball.

    Regions smaller than ``min_fraction`` of a ball's footprint (at least 8 pixels) are
    ``region_too_small`` (those under 3 pixels are ignored: single outliers); regions
    wider than 2 D or larger than three footprints ``region_too_large``. A region is
    shrunk by ``edge_px`` pixels, its points below ``cap_min_height`` (default 0.3 D)
    above the substrate and within ``highlight_px`` of the brightest pixel of ``image``
    are dropped; fewer than 10 left is ``too_few_points``.
    """
    from scipy import ndimage

    from telefringe.metrology.bga._kernels import eroded_taxicab

    labels, px_mm, foot = seg.labels, seg.px_mm, seg.footprint_px
    sizes = np.bincount(labels.ravel(), minlength=seg.n_labels + 1)
    slices = ndimage.find_objects(labels)
    cap_thr = 0.3 * D if cap_min_height is None else float(cap_min_height)
    dirs = np.asarray(cloud.directions, dtype=np.float64)
    out = []
    for lab in range(1, seg.n_labels + 1):
        sl = slices[lab - 1]
        region = labels[sl] == lab
        if sizes[lab] < max(min_fraction * foot, 8):
            if sizes[lab] >= 3:
                out.append(Candidate(sl, region, "region_too_small"))
            continue
        # a ball is compact: no wider than twice its diameter, no larger than 3 footprints
        if np.isfinite(px_mm) and (max(sl[0].stop - sl[0].start, sl[1].stop - sl[1].start)
                                   > 2.0 * D / px_mm + 2 or sizes[lab] > 3.0 * foot + 10):
            out.append(Candidate(sl, region, "region_too_large"))
            continue
        reg = region
        if edge_px > 0:  # (as ndimage.binary_erosion(reg, iterations=edge_px))
            reg = eroded_taxicab(reg, int(edge_px))
        sel = reg & (np.nan_to_num(seg.height[sl], nan=-np.inf) > cap_thr)
        if image is not None and highlight_px > 0:
            # pixels near the specular highlight: the camera's point spread mixes the
            # highlight's (far brighter) light, and so its phase, into them
            sub_img = np.where(region, image[sl], -np.inf)
            pi, pj = np.unravel_index(int(np.argmax(sub_img)), sub_img.shape)
            vv, uu = np.mgrid[0:sub_img.shape[0], 0:sub_img.shape[1]]
            sel &= np.hypot(vv - pi, uu - pj) > highlight_px
        pts = cloud.xyz[sl][sel]
        if pts.shape[0] < 10:
            out.append(Candidate(sl, region, "too_few_points"))
            continue
        grad = np.zeros((pts.shape[0], 3)) if gradient is None else gradient[sl][sel]
        view = (np.broadcast_to(-dirs, pts.shape).copy() if dirs.ndim == 1
                else -dirs[sl][sel])
        rr, cc = np.nonzero(sel)  # row-major, as cloud.xyz[sl][sel]
        pixels = (rr + sl[0].start) * cloud.shape[1] + (cc + sl[1].start)
        out.append(Candidate(sl, region, None, pts, cloud.sigma_line[sl][sel], grad, view,
                             pixels))
    return out
