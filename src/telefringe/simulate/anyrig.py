"""The done-means experiments of any rig (issue 11): calibrate a virtual rig from rendered
poses, then measure a held-out plate, a step gauge and a sphere with it, and compare each
error with its predicted uncertainty.

Predicted uncertainties
-----------------------
- Noise: the per-pixel ``sigma_line`` of the triangulation (from the decoder's phase
  uncertainty), along the true plate normal (``sigma_n``); for a fitted quantity (plane
  offset, step height, sphere radius), the standard deviation over repeated scans of the
  same scene with other camera noise (Monte Carlo), or the fit's own covariance.
- Calibration: the rig's parameters are drawn from the adjustment's covariance and the
  same decoded scan is triangulated again with each draw; the spread of the measured
  quantity is its calibration uncertainty (the world frame, the target at the reference
  pose, is exact by definition).

Units: mm (reported in um by the benchmark), px.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from telefringe.devices.rig import Rig
from telefringe.simulate.presets import VirtualRig
from telefringe.simulate.scenes import TiltedPlane, default_sphere, default_steps

__all__ = ["AnyrigResult", "SceneFigures", "calibrate_virtual", "sample_rigs", "scan_scene",
           "run_anyrig", "held_out_plane"]


def _noop(stage: str, done: int, total: int) -> None:
    del stage, done, total


def calibrate_virtual(vrig: VirtualRig, *, n_poses: int = 12, seed: int = 0,
                      progress: Callable = _noop):
    """Render a calibration set of ``vrig`` (every camera) and calibrate it from the images
    as ``telefringe calibrate`` does (models, pixel sizes and side from the manifest).
    Returns the :class:`~telefringe.calibration.rig.RigCalibration`."""
    from telefringe.calibration.from_scans import calibrate_from_scans
    from telefringe.simulate.calibration import (
        calibration_manifest,
        iter_calibration_set,
        simulate_calibration_poses,
    )

    poses = simulate_calibration_poses(vrig, n_poses=n_poses, seed=seed)
    man = calibration_manifest(vrig, poses)
    cams = vrig.camera_names
    gens = {c: iter_calibration_set(vrig, poses, seed=seed,
                                    camera=c if len(cams) > 1 else None) for c in cams}

    def scans():
        for k in range(len(poses)):
            got = {c: next(gens[c]) for c in cams}
            progress("calibration", k + 1, len(poses))
            name = got[cams[0]][0]
            if len(cams) == 1:
                yield name, got[cams[0]][1]
            else:
                yield name, {c: got[c][1] for c in cams}

    return calibrate_from_scans(scans(), man.target, man.camera_pixel_size,
                                man.projector_pixel_size, man.reference_pose,
                                projector_side=man.projector_side, models=man.models,
                                pixel_sizes=man.pixel_sizes)


def sample_rigs(calib, n: int, *, seed: int = 0) -> list[Rig]:
    """``n`` rigs whose parameters are drawn from the calibration's covariance (fixed
    parameters kept). Each device's parameters are its ``to_params()`` (rotation
    perturbations at zero), so a draw is ``device.from_params(parameters + delta)``."""
    names = calib.device_names
    rig = calib.rig
    devs = [rig.cameras[d] if d != "projector" else rig.projector for d in names]
    p0 = np.asarray(calib.parameters, dtype=float)
    cov = np.asarray(calib.covariance, dtype=float)
    free = np.isfinite(np.diag(cov))
    C = cov[np.ix_(free, free)]
    w, V = np.linalg.eigh(0.5 * (C + C.T))
    L = V * np.sqrt(np.clip(w, 0.0, None))
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(int(n)):
        p = p0.copy()
        p[free] += L @ rng.standard_normal(L.shape[1])
        o = 0
        new = []
        for d in devs:
            k = len(d.param_names)
            new.append(d.from_params(p[o:o + k]))
            o += k
        cams = {nm: dv for nm, dv in zip(names, new, strict=True) if nm != "projector"}
        proj = new[names.index("projector")] if "projector" in names else None
        out.append(Rig(cameras=cams, projector=proj))
    return out


def scan_scene(vrig: VirtualRig, scene, *, seed: int = 0, geometries: dict | None = None):
    """Render ``scene`` with every camera of ``vrig``: ({camera: Scan}, {camera: Truth}).
    ``geometries`` (a dict, filled on first use) lets repeated scans reuse the traced
    geometry (only the noise differs between seeds)."""
    from telefringe.simulate.render import default_groups, render_scan, trace_geometry

    groups = default_groups(vrig)
    scans, truths = {}, {}
    for ci, cam in enumerate(vrig.camera_names):
        view = vrig.for_camera(cam) if len(vrig.camera_names) > 1 else vrig
        geom = None
        if geometries is not None:
            geom = geometries.get(cam)
            if geom is None:
                geom = geometries[cam] = trace_geometry(view, scene)
        scans[cam], truths[cam] = render_scan(view, scene, groups,
                                              seed=int(seed) * 7919 + ci, geometry=geom)
    return scans, truths


def _decode_all(scans: dict, calib, noise=None) -> dict:
    """Decode each camera's scan with the calibration's projector nonlinearity and the
    camera's noise model (``noise``; the decoder's default when None)."""
    from telefringe.fringes.decode import decode

    kw = {"noise": noise}
    pe = getattr(calib, "phase_errors", None) or None
    if pe:
        kw["phase_errors"] = pe
    return {c: decode(s, **kw) for c, s in scans.items()}


def _triangulate(rig: Rig, coords: dict):
    if len(rig.cameras) > 1:
        from telefringe.reconstruction.stereo import triangulate_stereo

        names = rig.camera_names
        return triangulate_stereo(rig, coords[names[0]], coords[names[1]])
    from telefringe.reconstruction.pipeline import triangulate

    return triangulate(rig, coords[rig.camera_names[0]])


def _triangulate_with_noise(rig: Rig, coords: dict):
    """(cloud, StereoNoise or None): a two-camera rig's match with its noise split
    (:func:`telefringe.reconstruction.stereo.match_noise`; the cloud is
    :func:`_triangulate`'s), None for one camera."""
    if len(rig.cameras) > 1:
        from telefringe.reconstruction.stereo import match_noise, match_stereo

        names = rig.camera_names
        c1, c2 = coords[names[0]], coords[names[1]]
        m = match_stereo(rig, c1, c2)
        return m.cloud, match_noise(rig, c1, c2, m)
    return _triangulate(rig, coords), None


def held_out_plane(vrig: VirtualRig) -> TiltedPlane:
    """A matte plane tilted 7 deg, 0.8 mm above the reference plate's centre: a pose no
    calibration set holds."""
    t = vrig.target
    centre = np.array([(t.cols - 1) * t.pitch_mm / 2, (t.rows - 1) * t.pitch_mm / 2, 0.8])
    a = np.radians(7.0)
    normal = np.array([np.sin(a) * np.cos(0.6), np.sin(a) * np.sin(0.6), np.cos(a)])
    return TiltedPlane(normal=normal, point=centre)


@dataclass(frozen=True)
class SceneFigures:
    """One measured quantity and its uncertainties (mm).

    Attributes
    ----------
    name : str; value, truth : float; error : value - truth.
    sigma_noise : float, from repeated scans or the fit; sigma_cal : float, from the
        calibration's covariance; sigma_pred : their quadrature sum.
    sigma_pixel : float, the median per-pixel uncertainty along the surface normal.
    """

    name: str
    value: float
    truth: float
    sigma_noise: float
    sigma_cal: float
    sigma_pixel: float

    @property
    def error(self) -> float:
        return self.value - self.truth

    @property
    def sigma_pred(self) -> float:
        return float(np.hypot(self.sigma_noise, self.sigma_cal))

    @property
    def z_score(self) -> float:
        """error / sigma_pred."""
        return self.error / self.sigma_pred if self.sigma_pred > 0 else float("inf")

    @property
    def of_pixel_sigma(self) -> float:
        """|error| / sigma_pixel: the systematic error in units of the per-pixel noise."""
        return abs(self.error) / self.sigma_pixel


@dataclass(frozen=True)
class AnyrigResult:
    """Figures of one rig (see :func:`run_anyrig`).

    Attributes
    ----------
    rig : str; n_poses : int; rms : dict device -> reprojection RMS (px).
    plane_bias : SceneFigures, the held-out plane's mean signed distance from the truth.
    sigma_ratio : float, RMS of the Monte Carlo per-pixel std over the RMS of the
        predicted per-pixel sigma (along the plane normal), on pixels valid in every
        repeat; n_mc : int.
    steps : list of SceneFigures (step heights); sphere : SceneFigures (radius) or None.
    sphere_centre : list of SceneFigures, the sphere centre's x, y, z (world, mm).
    plane_fit_sigma : (predicted, predicted for independent points, spread) mm: the
        standard uncertainty of the held-out plane's fitted height at its true point, as
        ``fit_plane`` predicts it (mean over the scans; a two-camera rig's with the
        matches' correlated noise) and as the points were independent, and the std of
        that height over the scans.
    """

    rig: str
    n_poses: int
    rms: dict
    plane_bias: SceneFigures
    sigma_ratio: float
    n_mc: int
    steps: list = field(default_factory=list)
    sphere: SceneFigures | None = None
    mirror: str = ""
    sphere_centre: list = field(default_factory=list)
    plane_fit_sigma: tuple = ()


def _plane_errors(cloud, plane: TiltedPlane):
    """Signed distances (n,) of the valid points from the true plane, and the per-pixel
    sigma along its normal (n,), and the valid mask."""
    m = cloud.mask
    n = plane.normal
    e = (cloud.xyz[m] - plane.point) @ n
    d = cloud.directions
    dn = np.abs(d @ n) if d.ndim == 1 else np.abs(d[m] @ n)
    return e, cloud.sigma_line[m] * dn, m


def _sphere_options(rig: Rig, scans: dict):
    """measure_sphere's point-spread options for a rig (a function of the rig measuring):
    the first camera's brightness (the scan's mean level), for two cameras the second's
    too, and the scan's finest fringe periods; a rig without a projector fits the points
    as they are."""
    from telefringe.fringes.images import scan_radiance
    from telefringe.metrology.spheres import finest_fringe_periods

    if len(rig.cameras) not in (1, 2) or rig.projector is None:
        return lambda r: {}
    names = rig.camera_names
    scan = scans[names[0]]
    kw = {"image": scan_radiance(scan), "fringe_periods": finest_fringe_periods(scan.manifest)}
    if len(names) == 2:
        kw["image_2"] = scan_radiance(scans[names[1]])
    return lambda r: {"rig": r, **kw}


def run_anyrig(vrig: VirtualRig, *, n_poses: int = 12, seed: int = 0, n_mc: int = 8,
               n_cal: int = 24, scenes: tuple[str, ...] = ("plane", "steps", "sphere"),
               progress: Callable = _noop) -> AnyrigResult:
    """Calibrate ``vrig`` from ``n_poses`` rendered poses and measure with it.

    Plane: ``n_mc`` scans of :func:`held_out_plane` with other noise; the bias is the mean
    signed distance from the truth over the pixels of the first scan (``sigma_noise`` its
    spread over the scans, ``sigma_cal`` over ``n_cal`` rigs drawn from the covariance);
    ``sigma_ratio`` compares the per-pixel spread over the scans with the predicted
    ``sigma_line`` along the normal. Steps (``default_steps``) and sphere
    (``default_sphere``): one scan each; their noise uncertainty from the fits (a
    two-camera rig's with the matches' correlated noise).
    """
    from telefringe.metrology.planes import fit_plane
    from telefringe.metrology.spheres import measure_sphere
    from telefringe.metrology.steps import measure_steps

    calib = calibrate_virtual(vrig, n_poses=n_poses, seed=seed, progress=progress)
    rigs = sample_rigs(calib, n_cal, seed=seed + 1)
    rms = {d: float(r.rms) for d, r in calib.devices.items()}

    # the camera's noise, as a user would give it after measuring it (photon transfer):
    # the decoder's per-pixel sigma then describes this camera
    noise = vrig.photometry.noise_model()
    plane = held_out_plane(vrig)
    geoms: dict = {}
    biases, es, sig, masks = [], [], [], []
    fit_h, fit_s, fit_si = [], [], []
    coords0 = None
    for k in range(max(int(n_mc), 2)):
        scans, _ = scan_scene(vrig, plane, seed=seed + 101 + k, geometries=geoms)
        coords = _decode_all(scans, calib, noise)
        if coords0 is None:
            coords0 = coords
        cloud, pnoise = _triangulate_with_noise(calib.rig, coords)
        fc = fit_plane(cloud, noise=pnoise)
        fit_h.append(float(fc.distance(plane.point)))
        fit_s.append(fc.sigma_at(plane.point))
        fit_si.append(fit_plane(cloud).sigma_at(plane.point) if pnoise is not None
                      else fit_s[-1])
        e, s, m = _plane_errors(cloud, plane)
        full_e = np.full(m.shape, np.nan)
        full_e[m] = e
        full_s = np.full(m.shape, np.nan)
        full_s[m] = s
        es.append(full_e)
        sig.append(full_s)
        masks.append(m)
        biases.append(float(np.mean(e)))
        progress("plane", k + 1, n_mc)
    common = np.logical_and.reduce(masks)
    E = np.array([e[common] for e in es])
    S = np.array([s[common] for s in sig])
    emp = np.sqrt(np.mean(np.var(E, axis=0, ddof=1)))
    pred = np.sqrt(np.mean(S ** 2))
    cal_b = []
    for r in rigs:
        e, _, _ = _plane_errors(_triangulate(r, coords0), plane)
        cal_b.append(float(np.mean(e)))
    plane_fig = SceneFigures("plane offset", biases[0], 0.0, float(np.std(biases, ddof=1)),
                             float(np.std(cal_b, ddof=1)), float(np.nanmedian(sig[0])))

    steps_figs = []
    if "steps" in scenes:
        gauge = default_steps()
        scans, _ = scan_scene(vrig, gauge, seed=seed + 301)
        coords = _decode_all(scans, calib, noise)
        # two cameras: the matches' correlated noise in the levels' fit (as 'measure steps')
        cloud, pnoise = _triangulate_with_noise(calib.rig, coords)
        meas = measure_steps(cloud, noise=pnoise)
        truth = np.diff(np.concatenate([[0.0], gauge.blocks[:, 5]]))
        cal = np.array([measure_steps(_triangulate(r, coords)).step_heights for r in rigs])
        sz = float(np.nanmedian(cloud.sigma_line[cloud.mask]))
        k = min(len(truth), len(meas.step_heights))
        for j in range(k):
            steps_figs.append(SceneFigures(
                f"step {j + 1}", float(meas.step_heights[j]), float(truth[j]),
                float(meas.sigma_steps[j]),
                float(np.std(cal[:, j], ddof=1)) if cal.shape[1] > j else float("nan"), sz))
        progress("steps", 1, 1)
    sphere_fig = None
    centre_figs: list = []
    if "sphere" in scenes:
        sph = default_sphere()
        scans, _ = scan_scene(vrig, sph, seed=seed + 401)
        coords = _decode_all(scans, calib, noise)
        cloud, snoise = _triangulate_with_noise(calib.rig, coords)
        kw = _sphere_options(calib.rig, scans)
        opts = kw(calib.rig)
        if snoise is not None and "rig" in opts:  # the fit's covariance with it
            opts["noise"] = snoise
        fit = measure_sphere(cloud, **opts).sphere
        cal = np.array([[*f.centre, f.radius] for f in
                        (measure_sphere(_triangulate(r, coords), **kw(r)).sphere
                         for r in rigs)])
        sz = float(np.nanmedian(cloud.sigma_line[cloud.mask]))
        sphere_fig = SceneFigures("sphere radius", float(fit.radius), float(sph.radius),
                                  float(np.sqrt(fit.covariance[3, 3])),
                                  float(np.std(cal[:, 3], ddof=1)), sz)
        centre_figs = [SceneFigures(f"sphere centre {ax}", float(fit.centre[k]),
                                    float(sph.center[k]),
                                    float(np.sqrt(fit.covariance[k, k])),
                                    float(np.std(cal[:, k], ddof=1)), sz)
                       for k, ax in enumerate("xyz")]
        progress("sphere", 1, 1)
    return AnyrigResult(rig=vrig.name, n_poses=n_poses, rms=rms, plane_bias=plane_fig,
                        sigma_ratio=float(emp / pred), n_mc=int(n_mc), steps=steps_figs,
                        sphere=sphere_fig, mirror=calib.mirror, sphere_centre=centre_figs,
                        plane_fit_sigma=(float(np.sqrt(np.mean(np.square(fit_s)))),
                                         float(np.sqrt(np.mean(np.square(fit_si)))),
                                         float(np.std(fit_h, ddof=1))))
