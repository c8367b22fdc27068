"""measure_bga: the BGA inspection as a sequence of stages, and its options."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from telefringe.metrology._common import MetrologyError, _tangent_basis
from telefringe.metrology.bga.caps import CapFit, _apex_sigma, fit_caps_alone
from telefringe.metrology.bga.coplanarity import seating_plane_coplanarity
from telefringe.metrology.bga.grid import _claim_positions, _grid_local, _register_grid
from telefringe.metrology.bga.highlights import _fit_along_line, _refine_by_highlights
from telefringe.metrology.bga.nominal import BGANominal
from telefringe.metrology.bga.psf import (
    _brightness_gradient_terms,
    _fit_caps_smoothed,
    shared_direction,
)
from telefringe.metrology.bga.result import BGAMeasurement
from telefringe.metrology.bga.segment import cap_candidates, segment
from telefringe.reconstruction.cloud import PointCloud

CAP_MODELS = ("psf", "free", "fixed")
#: Per-ball error of the apex heights of the point-spread cap model fitted with an image,
#: in camera pixels (on the object): an error that varies from ball to ball but not with
#: the noise, so it is not in the noise propagation (``sigma_height_noise``). Its cause
#: is not found: the caps fitted without the image, or by the other cap models, show it
#: too (and larger), so it lies in the rendered scans' imaging of a cap (pixel footprint,
#: point spread beyond first order) rather than in one fit. Measured on the virtual
#: paper rig (telecentric, 14 px balls, 32.8 um per pixel on the object), 200 px
#: windows of 6 x 6 balls, four scenes (default_bga seeds 1, 2, 5, 6 at centres offset
#: by 0.1-0.5 mm, so other heights and other sub-pixel phases) x two noise seeds (11,
#: 12), 136 balls x 2: mean(e^2) = 1.185 um^2 against the truth, mean(sigma_noise^2)
#: = 0.607 um^2, so sigma_model = sqrt(1.185 - 0.607) = 0.760 um = 0.023 px (from the
#: seed pairs alone: 0.85 um; the per-scene values 0.77-0.93 um; the common part of the
#: error -0.05 to -0.13 um, so per ball). It is assumed to scale with the pixel.
#: Not measured for the other cap models or without an image (NaN there).
SIGMA_HEIGHT_MODEL_PX = 0.023
#: Coverage factor of the seating triangles' distance from the centre of gravity.
COG_K = 4.0


@dataclass(frozen=True)
class BGAOptions:
    """Options of :func:`measure_bga` (every one is used by the cap model it allows).

    Attributes
    ----------
    cap_model : {"psf", "free", "fixed"}
        How each ball's cap is fitted:

        - ``"psf"`` (default): a sphere of the nominal radius seen through a model of the
          camera's point spread. A pixel measures the spread-averaged surface, which on a
          convex cap lies deeper than the surface (by s^2 lap(z) / 2, growing as the cap
          tilts away), and where the brightness varies the average is taken off-centre
          (by s^2 grad(ln I), with an ``image``). The spread's variance s^2 (one camera,
          so one value for every ball) is estimated from the caps themselves (reported as
          ``psf_variance``), and so is the depth change per pixel of that shift at
          constant projector coordinate unless a ``projector`` gives it. Every point is
          weighted by 1 / sigma_r^2 (its ``sigma_line`` projected on the radius). Needs
          the nominal diameter to hold; diameters are not reported.
        - ``"free"``: a robust sphere fit per ball, its radius free when the cap
          determines it (0.7 D < diameter < 1.4 D and sigma_radius < 5 % D; else the
          nominal radius and no diameter reported).
        - ``"fixed"``: a robust sphere of the nominal radius per ball (an assumption: the
          balls are spheres of the nominal diameter); diameters are not reported.
    weighted : bool, optional
        ``"free"``/``"fixed"``: weight each cap point by 1 / sigma_r^2 (default False).
        ``"psf"`` always weights: True or None only.
    max_view_angle_deg : float or None or "auto"
        Drop cap points whose surface is tilted more than this from facing the camera
        (None: keep all). "auto" (default): 60 for ``"psf"``, None otherwise.
    min_height : float, optional, mm
        Pixels this far above the substrate form the ball regions (default 0.2 D).
    min_fraction : float
        Regions smaller than this fraction of a ball's footprint are too small to fit
        (reported as not measured where they sit on the grid).
    edge_px : int, optional
        Shrink each region by this many pixels (silhouette pixels mix ball and
        substrate). Default 1 when a ball is at least 10 pixels wide, else 0 (on small
        balls the points are too few to spare).
    cap_min_height : float, optional, mm
        Keep cap points higher than this above the substrate (default 0.3 D, above the
        shadowed flank).
    highlight_px : float, optional
        Drop cap points within this many pixels of the brightest pixel of ``image`` (the
        camera's point spread carries the highlight's phase into them, beyond the first
        order of the point-spread model); 0 keeps them. Default 2.5 when a ball is at
        least 10 pixels wide (the highlight of the paper rig's balls, ~1 px sigma, has
        fallen to the diffuse level there), else 0. Used only with an ``image``.
    substrate_margin : float, optional, mm
        The substrate plane is refitted on points farther than this (default D / 2) from
        every ball region (next to a ball the substrate's points are biased by its
        shadow edge and the light of its flank spread by the camera); 0 keeps the first
        fit on all points.
    seed : int, seeds the robust substrate fit.
    """

    cap_model: str = "psf"
    weighted: bool | None = None
    max_view_angle_deg: float | str | None = "auto"
    min_height: float | None = None
    min_fraction: float = 0.2
    edge_px: int | None = None
    cap_min_height: float | None = None
    highlight_px: float | None = None
    substrate_margin: float | None = None
    seed: int = 0

    def __post_init__(self):
        if self.cap_model not in CAP_MODELS:
            raise MetrologyError(f"cap_model must be one of {CAP_MODELS}, got "
                                 f"{self.cap_model!r}")
        if self.cap_model == "psf" and self.weighted is False:
            raise MetrologyError("cap_model 'psf' always weights the points: weighted=False "
                                 "needs cap_model 'free' or 'fixed'")
        a = self.max_view_angle_deg
        if not (a is None or a == "auto" or (isinstance(a, (int, float))
                                             and 0 < float(a) <= 90)):
            raise MetrologyError(f"max_view_angle_deg must be in (0, 90], None or 'auto', "
                                 f"got {a!r}")
        for name in ("min_height", "cap_min_height", "highlight_px", "substrate_margin"):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and v >= 0):
                raise MetrologyError(f"{name} must be >= 0 (or None), got {v!r}")
        if not (np.isfinite(self.min_fraction) and 0 <= self.min_fraction < 1):
            raise MetrologyError(f"min_fraction must be in [0, 1), got {self.min_fraction!r}")
        if self.edge_px is not None and int(self.edge_px) != self.edge_px or (
                self.edge_px is not None and self.edge_px < 0):
            raise MetrologyError(f"edge_px must be an integer >= 0, got {self.edge_px!r}")

    @property
    def view_angle_deg(self) -> float | None:
        """The view-angle cut in use (deg; None: none)."""
        if self.max_view_angle_deg == "auto":
            return 60.0 if self.cap_model == "psf" else None
        return None if self.max_view_angle_deg is None else float(self.max_view_angle_deg)


def measure_bga(cloud: PointCloud, nominal: BGANominal, *, image=None, projector=None,
                options: BGAOptions | None = None, noise=None) -> BGAMeasurement:
    """Inspect a ball grid array from its point cloud.

    Stages: the substrate plane is fitted robustly and pixels above it form one region
    per ball (:func:`.segment.segment`); each region's cap points are selected
    (:func:`.segment.cap_candidates`) and fitted with a sphere (``options.cap_model``:
    :func:`.psf._fit_caps_smoothed` or :func:`.caps.fit_caps_alone`); with an ``image``
    the centres are refined by their specular highlights
    (:func:`.highlights._refine_by_highlights`), and with the point-spread model the
    centre is then held on its highlight's camera line and only its depth along it
    refitted. The apex is the sphere's point farthest from the substrate. Balls are
    registered on the nominal grid (its rotation and offset found from the balls
    themselves), which gives the pitch between neighbours, the positions where a ball is
    seen but could not be measured (``not_measured``, with the reason), the missing
    balls (nothing seen) and the JEDEC seating-plane coplanarity (see
    :func:`seating_plane_coplanarity`).

    Parameters
    ----------
    cloud : PointCloud (organised, camera pixel grid; mm).
    nominal : BGANominal.
    image : (rows, cols) array_like, optional
        An unsaturated image of the scene in the camera's pixels (e.g. the HDR radiance
        of the decoder's background,
        :attr:`telefringe.reconstruction.pipeline.Reconstruction.radiance`). When
        given, each ball's position on the substrate comes from its specular highlight
        (Gaussian fit, ~0.01 px), offset by the median (highlight - cap centre) of all
        balls: with a telecentric camera and projector every ball shows its highlight at
        the same place, so the pitch is measured about 5x better than from the cap fits
        alone. The highlight's 3-D point is where its camera line meets the ball's fitted
        sphere. Balls without a clear highlight keep their cap centres. With the
        point-spread model the image also gives the brightness-gradient terms.
        With a pinhole camera (a cloud whose pixels have their own viewing directions,
        :attr:`PointCloud.directions` (rows, cols, 3)) each ball is seen from another
        direction, so there is no common offset: the highlights do not move the
        centres (``refined`` False); the cap fits, their view-angle cut and the
        point-spread model use each point's own viewing direction.
    projector : TelecentricDevice, optional
        The (calibrated) projector, for the brightness-gradient term of the point-spread
        model (u fringes only; without it the term's geometric factor is estimated,
        which also absorbs the v fringes' share). Needs ``cap_model="psf"``, an
        ``image`` and a telecentric camera (one viewing direction).
    options : BGAOptions, optional (default ``BGAOptions()``).
    noise : StereoNoise, optional, a cloud matched by two cameras: the matches' noise
        split into its independent parts on the cloud's grid
        (:func:`telefringe.reconstruction.stereo.match_noise`). Neighbouring matches
        share the second camera's pixels, so a cap's points are correlated and a fit that
        treats them as independent understates the apex's and the centre's noise. With
        it, each ball's cap fit (every cap model, and the depth along the highlight's
        line) and the substrate plane take the sandwich of their points' exact
        covariance (:mod:`telefringe.metrology.bga.stereo`), so ``sigma_height_noise``,
        ``sigma_centre``, the pitch's and the coplanarity's noise figures hold it; the
        fits themselves are the same. Between balls: their caps (and the substrate's
        points) share no pixel of the second camera unless matched within two pixels of
        each other there, which a resolved BGA's are not; each ball's sandwich is then
        the whole of its noise and the balls are independent. Where some do share a
        pixel a :class:`~telefringe.metrology.bga.stereo.StereoCorrelationWarning` says
        so (the pitch and coplanarity figures leave that correlation out). With cap
        model "psf" the common point-spread parameters' covariance (their part of every
        height, and ``sigma_psf_variance``) is the sandwich of their Schur-reduced solve
        (:func:`.stereo.theta_sandwich`).

    Returns
    -------
    BGAMeasurement

    Raises
    ------
    MetrologyError
        No ball, no ball that could be fitted, a grid that does not fit the nominal one,
        an image of the wrong shape, or a ``projector`` or ``highlight_px`` that would
        not be used (no image, or a cap model without the point-spread term), or a
        ``projector`` with a pinhole camera; ``noise`` of another grid or not covering a
        fitted point.

    Warns
    -----
    PSFSolveWarning
        The point-spread variance could not be estimated (``psf_variance`` NaN).
    PSFConvergenceWarning
        Its Gauss-Newton rounds ended before it converged (``psf_converged`` False).
    StereoCorrelationWarning
        With ``noise``: two balls (or a ball and the substrate) share second-camera
        pixels.
    """
    opt = BGAOptions() if options is None else options
    if cloud.count < 10:
        raise MetrologyError(f"the cloud has {cloud.count} valid points: no BGA")
    if image is not None and np.shape(image) != cloud.shape:
        raise MetrologyError(f"image has shape {np.shape(image)}, the cloud {cloud.shape}")
    if projector is not None and (opt.cap_model != "psf" or image is None):
        raise MetrologyError("a projector is used only by cap_model 'psf' with an image")
    if opt.highlight_px is not None and image is None:
        raise MetrologyError("highlight_px is used only with an image")
    image_arr = None if image is None else np.array(image, dtype=np.float64)
    D = float(nominal.ball_diameter_mm)
    if noise is not None and np.shape(noise.var_own) != cloud.shape:
        raise MetrologyError(f"noise has shape {np.shape(noise.var_own)}, the cloud "
                             f"{cloud.shape}")
    seg = segment(cloud, D, min_height=opt.min_height, substrate_margin=opt.substrate_margin,
                  seed=opt.seed, noise=noise)
    big = bool(np.isfinite(seg.px_mm) and D / seg.px_mm >= 10.0)
    edge_px = (1 if big else 0) if opt.edge_px is None else int(opt.edge_px)
    highlight_px = (2.5 if big else 0.0) if opt.highlight_px is None else opt.highlight_px
    gradient, grad_known = None, True
    if opt.cap_model == "psf" and image_arr is not None and np.isfinite(seg.px_mm):
        gradient, grad_known = _brightness_gradient_terms(cloud, image_arr, projector,
                                                          seg.px_mm)
    cands = cap_candidates(cloud, seg, D, image=image_arr, gradient=gradient,
                           min_fraction=opt.min_fraction, edge_px=edge_px,
                           cap_min_height=opt.cap_min_height, highlight_px=highlight_px)
    caps, cov_theta, s2, psf_run, solved = _fit_caps(cands, cloud, D, opt,
                                                     free_gradient=not grad_known,
                                                     with_index=noise is not None)
    if noise is not None:
        caps = _with_stereo_noise(caps, cands, cloud, noise, seg)
        if cov_theta is not None and np.all(np.isfinite(cov_theta)):
            from telefringe.metrology.bga.stereo import noise_at, theta_sandwich

            used = [k for k in solved if caps[k].fit is not None]
            cov_theta = theta_sandwich(
                [caps[k] for k in used],
                [noise_at(cloud, noise, cands[k].pixels[caps[k].index]) for k in used],
                D / 2)
            s2 = (s2[0], float(np.sqrt(cov_theta[0, 0])))
    ok = [k for k, c in enumerate(caps) if c.fit is not None]
    if not caps:
        thr = (f"{0.2 * D:.3g} mm (a fifth of the diameter)" if opt.min_height is None
               else f"{float(opt.min_height):.3g} mm (min_height)")
        raise MetrologyError(
            f"no ball found: no region of ball size stands {thr} above the substrate plane "
            "(is this a BGA, its balls toward the camera, of this diameter?)")
    if not ok:
        why = sorted({c.reason for c in caps})
        raise MetrologyError(f"no ball could be fitted ({', '.join(why)})")
    balls = _centres_and_apexes(cloud, seg, image_arr, [cands[k] for k in ok],
                                [caps[k] for k in ok], cov_theta, opt.cap_model, noise)
    failed = [(cands[k], caps[k].reason) for k in range(len(cands)) if caps[k].fit is None]
    model = (SIGMA_HEIGHT_MODEL_PX * seg.px_mm if opt.cap_model == "psf" and image is not None
             else np.nan)
    return _on_the_grid(cloud, seg, nominal, balls, failed, s2, psf_run, float(model))


def _fit_caps(cands, cloud: PointCloud, D: float, opt: BGAOptions, *, free_gradient: bool,
              with_index: bool = False):
    """Stage: one CapFit per candidate (those with a reason stay unfitted), the common
    point-spread parameters' covariance, (s^2, its sigma), (balls, converged) of their
    solve and the candidates it was solved on."""
    idx = [k for k, c in enumerate(cands) if c.reason is None]
    caps_in = [(cands[k].points, cands[k].sigma, cands[k].gradient) for k in idx]
    shared = shared_direction(cloud)
    # toward the camera: one vector for every point, or each point's own (pinhole)
    view = -shared if shared is not None else [cands[k].view for k in idx]
    s2 = (np.nan, np.nan)
    cov_theta = None
    psf_run = (0, None)
    solved = []
    if opt.cap_model == "psf":
        angle = opt.view_angle_deg
        res = _fit_caps_smoothed(caps_in, view, D / 2,
                                 max_view_angle_deg=90.0 if angle is None else angle,
                                 free_gradient=free_gradient, with_index=with_index)
        fits = [c if c.fit is None or c.fit.rms < 0.1 * D
                else CapFit(None, "fit_rms_too_large") for c in res.caps]
        s2 = (float(res.theta[0]), float(np.sqrt(res.cov_theta[0, 0])))
        cov_theta = res.cov_theta
        psf_run = (res.n_balls, res.converged)
        solved = [idx[int(t)] for t in res.sub] if res.sub is not None else []
    else:
        fits = fit_caps_alone(caps_in, view, D, weighted=bool(opt.weighted),
                              max_view_angle_deg=opt.view_angle_deg,
                              fixed_radius=opt.cap_model == "fixed")
    out = [CapFit(None, c.reason) for c in cands]
    for k, f in zip(idx, fits, strict=True):
        out[k] = f
    return out, cov_theta, s2, psf_run, solved


def _with_stereo_noise(caps, cands, cloud, noise, seg):
    """Stage (two cameras): each fitted cap's covariance the sandwich of its points'
    correlated noise (:func:`.stereo.sphere_sandwich`); a StereoCorrelationWarning when
    balls, or a ball and the substrate, share second-camera pixels."""
    import warnings

    from telefringe.metrology.bga.stereo import (
        StereoCorrelationWarning,
        noise_at,
        shared_sources,
        sphere_sandwich,
    )

    out = list(caps)
    groups = []
    for k, c in enumerate(caps):
        if c.fit is None:
            continue
        parts = noise_at(cloud, noise, cands[k].pixels[c.index])
        cov = sphere_sandwich(c.points, c.weights, c.fit.centre, c.fit.radius,
                              bool(c.radius_free), parts)
        out[k] = c._replace(fit=replace(c.fit, covariance=cov))
        groups.append(parts[2])
    K = np.shape(noise.sources)[-1]
    groups.append(np.asarray(noise.sources).reshape(-1, K)[seg.substrate_pixels])
    between, with_sub = shared_sources(groups)
    if between or with_sub:
        warnings.warn(
            f"{between} pixel(s) of the second camera are read by the cap points of two "
            f"balls and {with_sub} by a cap's and the substrate's: their errors are "
            "correlated, which the pitch's and the coplanarity's noise figures leave out",
            StereoCorrelationWarning, stacklevel=3)
    return out


def _centres_and_apexes(cloud, seg, image, cands, caps, cov_theta, cap_model, noise=None):
    """Stage: centres (highlight-refined with an image), apexes, heights and their
    uncertainties of the fitted balls (``noise``: a two-camera match's, for the depth
    along the highlight's line)."""
    nrm = seg.substrate.normal
    fits = [c.fit for c in caps]
    centre = np.array([f.centre for f in fits])
    sig_c = np.array([f.sigma_centre for f in fits]).reshape(-1, 3)
    radius = np.array([f.radius for f in fits])
    refined = np.zeros(len(fits), dtype=bool)
    med = None
    regions = [(c.slice, c.region) for c in cands]
    d = shared_direction(cloud)
    if image is not None and d is not None:
        # (a pinhole camera sees each ball from another direction: the highlights'
        # common offset does not hold, the centres stay the cap fits')
        sig_top = np.array([_apex_sigma(f, nrm) for f in fits])
        centre, sig_c, refined, lines, med = _refine_by_highlights(
            cloud, image, regions, centre, sig_c, nrm, radius, sig_top)
    sig_top = np.array([_apex_sigma(f, nrm) for f in fits])
    if cap_model == "psf" and image is not None and med is not None:
        # every ball's centre lies on its highlight's camera line shifted by the common
        # offset: fit the one remaining unknown, the depth along that line
        for k in np.flatnonzero(refined):
            res = _fit_along_line(caps[k].points, caps[k].weights,
                                  lines[k] - (med if med.ndim == 1 else med[k]), d,
                                  radius[k], centre[k])
            if res is not None:
                centre[k], s_t = res
                if noise is not None:
                    from telefringe.metrology.bga.stereo import line_sandwich, noise_at

                    s_t = line_sandwich(caps[k].points, caps[k].weights, centre[k],
                                        radius[k], d,
                                        noise_at(cloud, noise, cands[k].pixels[caps[k].index]))
                sig_top[k] = s_t * abs(float(d @ nrm))
    if cov_theta is not None and np.all(np.isfinite(cov_theta)):
        # the estimated spread parameters are common to every ball: their uncertainty
        # moves every apex together
        for k in range(len(fits)):
            gk = nrm @ caps[k].dcentre_dtheta  # d height / d theta
            sig_top[k] = np.hypot(sig_top[k], np.sqrt(max(float(gk @ cov_theta @ gk), 0.0)))
    apex = centre + radius[:, None] * nrm
    substrate = seg.substrate
    height = apex @ nrm - substrate.offset
    sig_h = np.array([np.hypot(st, substrate.sigma_at(a))
                      for st, a in zip(sig_top, apex, strict=True)])
    return dict(fits=fits, centre=centre, sig_c=sig_c, radius=radius, refined=refined,
                apex=apex, height=height, sig_h=sig_h,
                free=np.array([c.radius_free for c in caps], dtype=bool))


def _unseen_positions(cloud, seg, T, pitch, theta, origin_local, rows, cols, D):
    """Grid positions with valid points on fewer than a quarter of a ball's footprint
    within D / 2 of their nominal place (on the substrate plane)."""
    from telefringe.metrology.bga._kernels import footprint_counts

    # (one compiled pass over the cloud: as _grid_local(xyz[mask] @ T.T, ...) / pitch,
    # rounded, within D / 2 of the position)
    counts = footprint_counts(np.ascontiguousarray(cloud.xyz, dtype=np.float64),
                              np.ascontiguousarray(cloud.mask),
                              np.ascontiguousarray(T, dtype=np.float64),
                              float(np.cos(theta)), float(np.sin(theta)),
                              np.asarray(origin_local, dtype=np.float64), float(pitch),
                              int(rows), int(cols), float(D) / 2)
    need = max(0.25 * seg.footprint_px, 1.0)
    return [(int(i), int(j)) for i, j in np.argwhere(counts < need)], counts


def _on_the_grid(cloud, seg, nominal: BGANominal, b: dict, failed, s2,
                 psf_run, sigma_model: float) -> BGAMeasurement:
    """Stage: grid registration, not-measured and missing positions, pitch and
    coplanarity."""
    substrate = seg.substrate
    nrm = substrate.normal
    pitch = float(nominal.pitch_mm)
    fits = b["fits"]
    T = _tangent_basis(nrm)
    pos = b["centre"] @ T.T
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
    # positions where a region is seen but no ball could be measured
    not_measured = {}
    for cand, reason in failed:
        pts = cloud.xyz[cand.slice][cand.region & cloud.mask[cand.slice]]
        for ij in _claim_positions(pts @ T.T, pitch, theta, origin_local, rows, cols):
            if not found[ij] and ij not in not_measured:
                not_measured[ij] = reason
    # a populated position with neither a ball nor a view of the substrate around it
    # cannot be called missing (outside the field of view, or invalid there)
    unseen, _ = _unseen_positions(cloud, seg, T, pitch, theta, origin_local, rows, cols,
                                  float(nominal.ball_diameter_mm))
    for ij in unseen:
        if populated[ij] and not found[ij] and ij not in not_measured:
            not_measured[ij] = "not_in_view"
    not_measured = tuple(sorted(not_measured.items()))
    seen = found.copy()
    for ij, _ in not_measured:
        seen[ij] = True
    missing = tuple((int(i), int(j)) for i, j in np.argwhere(populated & ~seen))
    unexpected = tuple((int(i), int(j)) for i, j in np.argwhere(~populated & found))
    local = _grid_local(pos[sel], theta, origin_local)
    grid_xy = np.full((rows, cols, 2), np.nan)
    grid_xy[found] = local
    px = np.linalg.norm(np.diff(grid_xy, axis=1), axis=2)
    py = np.linalg.norm(np.diff(grid_xy, axis=0), axis=2)
    errs = np.concatenate([px[np.isfinite(px)], py[np.isfinite(py)]]) - pitch
    # centre of gravity: given, or the centre of the nominal grid
    if nominal.centre_of_gravity is not None:
        cog = np.asarray(nominal.centre_of_gravity, dtype=np.float64)
    else:
        c_, s_ = np.cos(theta), np.sin(theta)
        mid_local = np.array([(cols - 1) / 2.0, (rows - 1) / 2.0]) * pitch + origin_local
        mid_plane = np.array([[c_, -s_], [s_, c_]]) @ mid_local  # rotate back by theta
        cog = mid_plane[0] * T[0] + mid_plane[1] * T[1] + substrate.offset * nrm
    apex = b["apex"]
    # the centre of gravity is known relative to the balls only as well as their
    # in-plane positions: a seating triangle within K of their sigma of it is one the
    # package may rest on (on a point-symmetric grid the centre often lies on an edge
    # of two seating triangles; the worst of them is reported, see Coplanarity)
    sig_noise = b["sig_h"][sel]
    sig_h = sig_noise if np.isnan(sigma_model) else np.hypot(sig_noise, sigma_model)
    sig_c = b["sig_c"][sel]
    sig_plane = np.sqrt(np.mean(np.sum((sig_c[:, None, :] * T[None]) ** 2, axis=2)))
    cop = seating_plane_coplanarity(apex[sel], cog, reference=substrate.plane,
                                    cog_tolerance=COG_K * float(sig_plane),
                                    sigma_heights=sig_h)
    radius = b["radius"]
    return BGAMeasurement(
        index=np.argwhere(found), centre=b["centre"][sel],
        sigma_centre=b["sig_c"][sel], refined=b["refined"][sel],
        apex=apex[sel], height=b["height"][sel], sigma_height=sig_h,
        sigma_height_noise=sig_noise, sigma_height_model=sigma_model,
        diameter=np.where(b["free"][sel], 2.0 * radius[sel], np.nan),
        position=local,
        rms=np.array([fits[k].rms for k in sel]),
        n_points=np.array([fits[k].n_inliers for k in sel], dtype=np.int64),
        substrate=substrate, found=found, missing=missing, unexpected=unexpected,
        pitch_x=px, pitch_y=py,
        pitch_error_max=float(np.max(np.abs(errs))) if errs.size else np.nan,
        coplanarity=cop, grid_angle_deg=float(np.degrees(theta)), nominal=nominal,
        psf_variance=float(s2[0]), sigma_psf_variance=float(s2[1]),
        not_measured=not_measured, psf_balls=int(psf_run[0]), psf_converged=psf_run[1])
