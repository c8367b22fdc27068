"""Time the calibration of 12 poses of the paper rig at full resolution.

Renders the virtual rig's 12-pose calibration set and decodes it first (not timed:
rendering is the simulator's, decoding the decoder's), then times what calibration
itself does: circle-grid detection, projector observations (the phase fit around each
circle), the camera's and the projector's own calibrations and the joint adjustment.
Also prints the accuracy against the rig's truth.

    .venv/bin/python benchmarks/calibrate.py [--gamma]
"""

from __future__ import annotations

import sys
import time

import numpy as np

from telefringe.calibration.rig import calibrate_rig
from telefringe.fringes.decode import decode
from telefringe.fringes.images import fringe_free_image
from telefringe.simulate.calibration import (
    iter_calibration_set,
    projector_side,
    simulate_calibration_poses,
)
from telefringe.simulate.presets import get_preset
from telefringe.targets.circle_grid import detect_circle_grid
from telefringe.targets.observations import projector_observations


def main() -> None:
    gamma = "--gamma" in sys.argv
    vrig = get_preset("paper")
    poses = simulate_calibration_poses(vrig, n_poses=12, seed=0)
    T = vrig.target
    r, c = np.mgrid[0:T.rows, 0:T.cols]
    P = np.stack([c.ravel() * T.pitch_mm, r.ravel() * T.pitch_mm, np.zeros(r.size)], 1)
    # warm the compiled kernels (numba caches them on disk after the first run)
    t0 = time.perf_counter()
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:200, 0:200]
    img = 200 - 150 * (((xx - 100) ** 2 + (yy - 100) ** 2) < 400) + rng.normal(0, 1, xx.shape)
    projector_observations(xx * 1.0, yy * 1.0, np.ones(xx.shape, bool), np.array([[100.0, 100]]),
                           marker_radius_px=20.0)
    detect_circle_grid(img, rows=2, cols=2)
    warm = time.perf_counter() - t0
    t_render = t_decode = t_detect = t_proj = 0.0
    names, cam, proj, feats = [], [], [], []
    it = iter(iter_calibration_set(vrig, poses, seed=0))
    while True:
        t0 = time.perf_counter()
        try:
            name, scan, truth, _pose = next(it)
        except StopIteration:
            break
        t1 = time.perf_counter()
        det = detect_circle_grid(fringe_free_image(scan), rows=T.rows, cols=T.cols)
        t2 = time.perf_counter()
        t_render += t1 - t0
        t_detect += t2 - t1
        if not det:
            print(f"  {name}: skipped ({det.reason})")
            continue
        coords = decode(scan, gamma_correction=gamma)
        t3 = time.perf_counter()
        po = projector_observations(coords.u_p, coords.v_p, coords.mask, det)
        t4 = time.perf_counter()
        t_decode += t3 - t2
        t_proj += t4 - t3
        names.append(name)
        cam.append(np.where(det.found[:, None], det.centers, np.nan))
        proj.append(po.uv)
        feats.append(truth.features)
    k = vrig.rig
    t0 = time.perf_counter()
    cal = calibrate_rig(P, np.array(cam), np.array(proj),
                        camera_pixel_size=(k.camera.intrinsics.du, k.camera.intrinsics.dv),
                        projector_pixel_size=(k.projector.intrinsics.du,
                                              k.projector.intrinsics.dv),
                        camera_size=(k.camera.intrinsics.width, k.camera.intrinsics.height),
                        projector_size=(k.projector.intrinsics.width,
                                        k.projector.intrinsics.height),
                        pose_names=names, grid_shape=(T.rows, T.cols),
                        projector_side=projector_side(vrig))
    t_adj = time.perf_counter() - t0
    ec = np.concatenate([c_ - f["circle_centres_px"] for c_, f in zip(cam, feats, strict=True)])
    ep = np.concatenate([p_ - f["circle_centres_proj_px"] for p_, f in zip(proj, feats,
                                                                            strict=True)])
    ec, ep = ec[np.all(np.isfinite(ec), 1)], ep[np.all(np.isfinite(ep), 1)]
    print(f"paper rig, {len(poses)} poses ({len(names)} with the grid found), 1280 x 1024, "
          f"decode gamma_correction={gamma}")
    print(f"  not timed: render {t_render:.1f} s, decode {t_decode:.1f} s, "
          f"kernel warm-up {warm:.1f} s")
    print(f"  detection            {t_detect:6.2f} s")
    print(f"  projector obs.       {t_proj:6.2f} s")
    print(f"  devices + joint adj. {t_adj:6.2f} s")
    print(f"  calibration total    {t_detect + t_proj + t_adj:6.2f} s  (aim < 20 s)")
    print(f"  circle centre error RMS: camera {np.sqrt(np.mean(np.sum(ec**2, 1))):.4f} px, "
          f"projector {np.sqrt(np.mean(np.sum(ep**2, 1))):.4f} projector px")
    print(f"  reprojection RMS: camera {cal.rms_camera:.4f} px, projector "
          f"{cal.rms_projector:.4f} px; outliers {len(cal.outliers)}")


if __name__ == "__main__":
    main()
