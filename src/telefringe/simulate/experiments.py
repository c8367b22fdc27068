"""The paper's experiments (its Tables 3 and 4), re-run on the virtual rig.

Everything here goes through the same pipeline a user's captures go through: the
virtual rig renders images; the images are decoded, the rig is calibrated from the
rendered calibration set (it never sees the true geometry), scans are reconstructed with
the *calibrated* rig and measured; only then is the result compared with the truth.

- Table 3: the 9 x 11 circle plate raised by a stage to Z = -1, -0.5, 0.5, 1 mm: mean
  distance between neighbouring marker centres along X and Y (measured in 3D), the
  plate's Z (distance of its fitted plane from the reference plane), their absolute
  errors and the standard deviations of the distances.
- Table 4: a BGA (0.8 mm pitch, 0.45 mm balls) scanned with HDR: fitted centre distances
  of adjacent balls, plus what the paper did not report (apex heights, coplanarity,
  missing balls).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from telefringe.devices.rig import Rig
from telefringe.simulate.presets import HDR_EXPOSURES, VirtualRig, get_preset

__all__ = [
    "PAPER_TABLE3",
    "PAPER_TABLE4",
    "PlateRow",
    "BallPair",
    "BGAResult",
    "PaperResult",
    "bin_camera",
    "paper_rig",
    "unbin_rig",
    "bga_window",
    "run_calibration",
    "run_plate",
    "run_bga",
    "run_paper",
]

#: Table 3 of the paper: position -> (mean X, mean Y, Z, |err X|, |err Y|, |err Z|,
#: std X, std Y), mm.
PAPER_TABLE3 = {
    -1.0: (2.997, 3.002, -1.008, 0.003, 0.002, 0.008, 0.004, 0.005),
    -0.5: (2.998, 3.001, -0.505, 0.002, 0.001, 0.005, 0.003, 0.004),
    0.5: (2.998, 3.001, 0.504, 0.002, 0.001, 0.004, 0.004, 0.004),
    1.0: (2.997, 3.001, 1.007, 0.003, 0.001, 0.007, 0.004, 0.004),
}
#: Table 4 of the paper: five adjacent-ball centre distances (mm) and their errors.
PAPER_TABLE4 = ((0.804, 0.004), (0.806, 0.006), (0.795, -0.005), (0.802, 0.002),
                (0.803, 0.003))

Progress = Callable[[str, int, int], None]


def _noop(stage: str, done: int, total: int) -> None:
    del stage, done, total


def bin_camera(vrig: VirtualRig, factor: int) -> VirtualRig:
    """The same rig with its camera's pixels binned ``factor`` x ``factor``.

    Geometry is unchanged: the binned pixel b covers the fine pixels
    ``[factor b, factor b + factor - 1]``, so its centre sits at fine coordinate
    ``factor b + (factor - 1) / 2``. Distortion coefficients live on the sensor plane in
    mm and do not change. Photometry per (bigger) pixel is kept as it is.
    """
    if int(factor) < 1:
        raise ValueError(f"factor must be >= 1, got {factor!r}")
    f = int(factor)
    if f == 1:
        return vrig
    k = vrig.camera.intrinsics
    intr = replace(k, du=k.du * f, dv=k.dv * f, u0=(k.u0 - (f - 1) / 2.0) / f,
                   v0=(k.v0 - (f - 1) / 2.0) / f, width=k.width // f, height=k.height // f)
    cam = vrig.camera.with_(intrinsics=intr)
    return replace(vrig, name=f"{vrig.name}/bin{f}", rig=Rig(cam, vrig.projector))


def unbin_rig(rig, factor: int, *, col0: int = 0, row0: int = 0, width: int | None = None,
              height: int | None = None) -> Rig:
    """A rig whose camera is ``rig``'s camera read at full resolution (the inverse of
    :func:`bin_camera`), optionally only a window of it (a region of interest: pixel
    (u, v) of the window is full-resolution pixel (u + col0, v + row0)).

    Exact for a calibrated rig too: binning changes only the pixel pitch and where
    pixel centres sit on the same sensor.
    """
    f = int(factor)
    k = rig.camera.intrinsics
    full_w, full_h = k.width * f, k.height * f
    w = full_w - col0 if width is None else int(width)
    h = full_h - row0 if height is None else int(height)
    if not (0 <= col0 and 0 <= row0 and col0 + w <= full_w and row0 + h <= full_h):
        raise ValueError("the window is not inside the full-resolution sensor")
    intr = replace(k, du=k.du / f, dv=k.dv / f, u0=k.u0 * f + (f - 1) / 2.0 - col0,
                   v0=k.v0 * f + (f - 1) / 2.0 - row0, width=w, height=h)
    return Rig(rig.camera.with_(intrinsics=intr), rig.projector)


def bga_window(vrig: VirtualRig, *, centre=(15.0, 12.0), size: int = 720) -> tuple[int, int]:
    """(col0, row0) of a ``size`` x ``size`` camera window centred on the BGA."""
    u, v = vrig.camera.project(np.array([centre[0], centre[1], 0.0]))
    k = vrig.camera.intrinsics
    col0 = int(np.clip(round(float(u) - size / 2), 0, k.width - size))
    row0 = int(np.clip(round(float(v) - size / 2), 0, k.height - size))
    return col0, row0


def paper_rig(*, quick: bool) -> VirtualRig:
    """The rig of the paper's experiments: the ``paper`` preset, with its camera binned
    2 x 2 (640 x 512) in quick mode."""
    vrig = get_preset("paper")
    return bin_camera(vrig, 2) if quick else vrig


# --------------------------------------------------------------------------- results
@dataclass(frozen=True)
class PlateRow:
    """One row of Table 3 (mm), with the truth it is compared with.

    ``distances_x`` / ``distances_y`` hold every neighbour distance (for histograms).
    """

    position: float
    mean_x: float
    mean_y: float
    z: float
    err_x: float
    err_y: float
    err_z: float
    std_x: float
    std_y: float
    n_x: int
    n_y: int
    sigma_z: float
    distances_x: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))
    distances_y: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))


@dataclass(frozen=True)
class BallPair:
    """The fitted centre distance of two adjacent balls (mm) against the truth."""

    a: tuple[int, int]
    b: tuple[int, int]
    distance: float
    truth: float

    @property
    def error(self) -> float:
        return self.distance - self.truth


@dataclass(frozen=True)
class BGAResult:
    """Table 4 and beyond: the BGA measured with HDR against the truth (mm).

    pairs : five adjacent pairs spread over the chip (as the paper reports).
    pitch_error_max : largest |error| over every measured adjacent pair.
    n_pairs : number of adjacent pairs measured.
    apex_rms_error : RMS of (measured - true) apex height above the substrate.
    apex_max_error : largest |error| of it.
    coplanarity, coplanarity_truth : JEDEC seating-plane coplanarity.
    n_present, n_found : balls in the scene, balls found (at their true positions).
    missing_truth, missing_reported : grid positions (row, col).
    not_measured_reported : ((row, col), reason) of balls seen but not measured.
    valid_fraction_balls : fraction of lit ball pixels with a valid 3-D point.
    """

    pairs: tuple[BallPair, ...]
    pitch_error_max: float
    n_pairs: int
    apex_rms_error: float
    apex_max_error: float
    coplanarity: float
    coplanarity_truth: float
    n_present: int
    n_found: int
    missing_truth: tuple[tuple[int, int], ...]
    missing_reported: tuple[tuple[int, int], ...]
    valid_fraction_balls: float
    measurement: object = field(repr=False, default=None)
    not_measured_reported: tuple = ()


@dataclass(frozen=True)
class PaperResult:
    """Everything ``telefringe paper`` reports."""

    rig_name: str
    quick: bool
    calibration: object
    plate: tuple[PlateRow, ...]
    bga: BGAResult
    timings: dict


# --------------------------------------------------------------------------- stages
def run_calibration(vrig: VirtualRig, *, n_poses: int, seed: int = 0,
                    progress: Progress = _noop, decode_options: dict | None = None):
    """Render a calibration set with the virtual rig and calibrate from its images.

    ``decode_options`` go to :func:`telefringe.decode.decode` (e.g.
    ``{"gamma_correction": False}``). Returns the
    :class:`telefringe.calibrate.RigCalibration`.
    """
    from telefringe.calibration.from_scans import calibrate_from_scans
    from telefringe.simulate.calibration import (
        calibration_manifest,
        iter_calibration_set,
        simulate_calibration_poses,
    )

    poses = simulate_calibration_poses(vrig, n_poses=n_poses, seed=seed)
    man = calibration_manifest(vrig, poses)

    def scans():
        for done, (name, scan, _truth, _pose) in enumerate(
                iter_calibration_set(vrig, poses, seed=seed), start=1):
            progress("calibration", done, len(poses))
            yield name, scan

    return calibrate_from_scans(scans(), man.target, man.camera_pixel_size,
                                man.projector_pixel_size, man.reference_pose,
                                projector_side=man.projector_side,
                                decode_options=decode_options)


def run_plate(vrig: VirtualRig, rig: Rig, position: float, *, seed: int = 0) -> PlateRow:
    """Scan the circle plate raised to Z = ``position`` mm and measure it (Table 3 row)."""
    from telefringe.metrology import measure_plate
    from telefringe.reconstruction.pipeline import reconstruct_scan
    from telefringe.simulate.render import default_groups, render_scan
    from telefringe.simulate.scenes import plate_at_z
    from telefringe.targets.circle_grid import detect_circle_grid

    target = vrig.target
    scan, truth = render_scan(vrig, plate_at_z(position, target=target), default_groups(vrig),
                              seed=seed)
    rec = reconstruct_scan(scan, rig, with_height_map=False)
    det = detect_circle_grid(rec.texture, rows=target.rows, cols=target.cols,
                             dark=target.circles == "dark-on-light")
    if not det:
        raise RuntimeError(f"plate at Z = {position} mm: grid not found ({det.reason})")
    m = measure_plate(rec.cloud, det.centers, rows=target.rows, cols=target.cols,
                      pitch_mm=target.pitch_mm, seed=seed, camera=rig.camera,
                      marker_diameter_mm=target.diameter_mm)
    sp = m.spacing
    dx = np.asarray(sp.dist_x, dtype=float).ravel()
    dy = np.asarray(sp.dist_y, dtype=float).ravel()
    dx, dy = dx[np.isfinite(dx)], dy[np.isfinite(dy)]
    pitch = target.pitch_mm
    z = float(m.z.distance)
    return PlateRow(position=float(position), mean_x=float(dx.mean()), mean_y=float(dy.mean()),
                    z=z, err_x=abs(float(dx.mean()) - pitch), err_y=abs(float(dy.mean()) - pitch),
                    err_z=abs(z - float(position)), std_x=float(dx.std(ddof=1)),
                    std_y=float(dy.std(ddof=1)), n_x=int(dx.size), n_y=int(dy.size),
                    sigma_z=float(getattr(m.z, "sigma", np.nan)),
                    distances_x=dx, distances_y=dy)


def _five_pairs(meas, rows: int, cols: int) -> list[tuple[tuple[int, int], tuple[int, int]]]:
    """Five adjacent pairs spread over the chip (corners and centre), both measured."""
    found = np.asarray(meas.found)
    wanted = [(0, 0), (0, cols - 2), (rows // 2, cols // 2), (rows - 1, 0), (rows - 2, cols - 1)]
    pairs = []
    for k, (i, j) in enumerate(wanted):
        horizontal = k % 2 == 0
        # walk inward until both balls of the pair were found
        for step in range(max(rows, cols)):
            ii = min(max(i + (step if i < rows // 2 else -step), 0), rows - 1)
            jj = min(max(j + (step if j < cols // 2 else -step), 0), cols - 1)
            a = (ii, jj)
            b = (ii, jj + 1) if horizontal else (ii + 1, jj)
            if b[0] < rows and b[1] < cols and found[a] and found[b]:
                pairs.append((a, b))
                break
    return pairs


def run_bga(vrig: VirtualRig, rig: Rig, *, seed: int = 0, hdr: bool = True) -> BGAResult:
    """Scan the default BGA (HDR unless ``hdr`` is False), measure it, compare with truth."""
    from telefringe.metrology import (
        BGANominal,
        BGAOptions,
        measure_bga,
        seating_plane_coplanarity,
    )
    from telefringe.metrology import Plane as _Plane
    from telefringe.reconstruction.pipeline import reconstruct_scan
    from telefringe.simulate.render import default_groups, render_scan
    from telefringe.simulate.scenes import default_bga

    bga = default_bga(seed)
    exposures = HDR_EXPOSURES if hdr else (1.0,)
    scan, truth = render_scan(vrig, bga, default_groups(vrig), exposures=exposures, seed=seed)
    rec = reconstruct_scan(scan, rig, with_height_map=False)
    # the design: every grid position populated; absent balls must be reported missing
    nominal = BGANominal(rows=bga.rows, cols=bga.cols, pitch_mm=bga.pitch,
                         ball_diameter_mm=bga.ball_diameter)
    # balls located by their specular highlights in the HDR radiance image (the offset
    # of highlight from ball centre is common to all balls: telecentric, collimated),
    # made from every phase image (the decoder's radiance uses one group: ~2.4x noisier)
    # caps: the nominal ball radius (the inspector's assumption: spheres of the nominal
    # diameter), the camera's point spread modelled (its variance estimated from the
    # caps), points within 2.5 px of the highlight (whose light the point spread carries
    # into them, beyond first order) and tilted more than 60 deg dropped; see measure_bga
    meas = measure_bga(rec.cloud, nominal, image=rec.radiance, options=BGAOptions(seed=seed))

    # the truth, indexed like the measurement
    true_centres = bga.centres_world()
    true_height = bga.ball_height + np.asarray(bga.height_offsets)
    idx = np.asarray(meas.index, dtype=int)
    err_h = np.asarray(meas.height) - true_height[idx[:, 0], idx[:, 1]]
    # every adjacent pair measured: in-plane centre distance vs truth (exactly the pitch
    # in the scene, since the substrate is the plane Z = 0)
    by_index = {(int(i), int(j)): n for n, (i, j) in enumerate(idx)}
    all_err = []
    for (i, j), n in by_index.items():
        for di, dj in ((0, 1), (1, 0)):
            other = by_index.get((i + di, j + dj))
            if other is None:
                continue
            d = float(np.linalg.norm(meas.position[other] - meas.position[n]))
            t = float(np.linalg.norm(true_centres[i + di, j + dj, :2] - true_centres[i, j, :2]))
            all_err.append(d - t)
    all_err = np.asarray(all_err)
    pairs = []
    for a, b in _five_pairs(meas, bga.rows, bga.cols):
        d = float(np.linalg.norm(meas.position[by_index[b]] - meas.position[by_index[a]]))
        t = float(np.linalg.norm(true_centres[b][:2] - true_centres[a][:2]))
        pairs.append(BallPair(a=a, b=b, distance=d, truth=t))
    present = bga.present()
    apex_true = bga.apexes_world()[present]
    cog = np.array([bga.origin[0] + (bga.cols - 1) * bga.pitch / 2,
                    bga.origin[1] + (bga.rows - 1) * bga.pitch / 2])
    cop_truth = seating_plane_coplanarity(apex_true, cog, reference=_Plane.horizontal(0.0))
    lit_balls = truth.lit & (truth.part == 2) if truth.part is not None else truth.lit
    valid = rec.cloud.mask & lit_balls
    frac = float(valid.sum() / max(int(lit_balls.sum()), 1))
    return BGAResult(
        pairs=tuple(pairs), pitch_error_max=float(np.max(np.abs(all_err))),
        n_pairs=int(all_err.size), apex_rms_error=float(np.sqrt(np.mean(err_h ** 2))),
        apex_max_error=float(np.max(np.abs(err_h))),
        coplanarity=float(meas.coplanarity.value), coplanarity_truth=float(cop_truth.value),
        n_present=int(present.sum()), n_found=int(meas.n_balls),
        missing_truth=tuple(tuple(int(x) for x in m) for m in bga.missing),
        missing_reported=tuple(tuple(int(x) for x in m) for m in meas.missing),
        valid_fraction_balls=frac, measurement=meas,
        not_measured_reported=tuple(meas.not_measured))


def run_paper(*, quick: bool = False, seed: int = 0, n_poses: int | None = None,
              positions: Sequence[float] = (-1.0, -0.5, 0.5, 1.0),
              progress: Progress = _noop) -> PaperResult:
    """Re-run the paper's experiments on the virtual rig.

    Parameters
    ----------
    quick : bool
        Camera binned 2 x 2 (640 x 512) and 8 calibration poses instead of 12.
    seed : int, seeds poses, scenes and noise.
    n_poses : int, optional, calibration poses (default 12, or 8 when quick).
    positions : plate positions along Z, mm (Table 3).
    progress : callable ``progress(stage, done, total)``.
    """
    vrig = paper_rig(quick=quick)
    n_poses = int(n_poses if n_poses is not None else (8 if quick else 12))
    timings = {}
    t0 = time.perf_counter()
    # quick mode decodes the calibration poses without the gamma fit (the slowest part of
    # decoding; four steps leave little gamma error and the fit around each marker
    # averages it); the measured scans always use the full pipeline
    calib = run_calibration(vrig, n_poses=n_poses, seed=seed, progress=progress,
                            decode_options={"gamma_correction": False} if quick else None)
    timings["calibration_s"] = time.perf_counter() - t0
    rows = []
    t0 = time.perf_counter()
    for k, z in enumerate(positions):
        rows.append(run_plate(vrig, calib.rig, float(z), seed=seed + 101 + k))
        progress("plate", k + 1, len(positions))
    timings["plate_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    if quick:
        # solder balls are ~7 binned pixels wide: read the BGA at full resolution in a
        # window around it (a region of interest), with the calibrated camera unbinned
        from telefringe.simulate.presets import crop_camera

        full = get_preset("paper")
        col0, row0 = bga_window(full)
        vrig_bga = crop_camera(full, col0=col0, row0=row0, width=720, height=720)
        rig_bga = unbin_rig(calib.rig, 2, col0=col0, row0=row0, width=720, height=720)
        bga = run_bga(vrig_bga, rig_bga, seed=seed)
    else:
        bga = run_bga(vrig, calib.rig, seed=seed)
    progress("bga", 1, 1)
    timings["bga_s"] = time.perf_counter() - t0
    return PaperResult(rig_name=vrig.name, quick=bool(quick), calibration=calib,
                       plate=tuple(rows), bga=bga, timings=timings)
