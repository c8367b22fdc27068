"""The real capture ``../shared/realdata/slmaster_mono_relief`` measured end to end.

Usage: python benchmarks/realdata_relief.py [--data DIR] [--figure docs/realdata_relief.png]

A pinhole camera (1280 x 1024) and a pinhole DLP projector (1920 x 1080) calibrated by
their owner with OpenCV (``caliInfo.yml``, SLMaster's names), vertical fringes only (12
steps, 32 periods, complementary Gray code) on a plaster relief tile about 0.73 m away.
Steps, all through telefringe's public API:

1. the rig: ``caliInfo.yml`` imported (:func:`telefringe.io.opencv_yaml.read_opencv_rig`;
   the projector's size from scan.json); the world frame is the camera's, so Z is depth;
2. the camera's noise measured from the scan itself
   (:func:`telefringe.fringes.noise.estimate_noise`, what ``telefringe reconstruct`` does
   by default): each pixel's 12 samples are fitted by ``A + B cos(phi + 2 pi k / 12)``
   and the projector's harmonics; the residual variance (9 degrees of freedom) against
   ``A`` gives read noise and gain, a
   :class:`~telefringe.fringes.phase.NoiseModel` of this camera (the default one describes
   another camera and understates this one's noise about 2x);
3. decode + generic triangulation (:func:`telefringe.reconstruction.pipeline.reconstruct_scan`
   with that noise model): u_P only, so each camera ray meets the projector's surface of
   constant u_P; sigma_z per point from the decoded phase's uncertainty;
4. checks without ground truth: the tile (the largest connected region of valid points)
   lies at Z about 695-774 mm (the owner's figure); no neighbouring pixels on the tile
   differ by a fringe period (60 projector px); the relief stands far above the noise
   (height over a smooth quadratic surface fitted to the whole tile, against sigma_z); the
   RMS residual of a smooth (quadratic) fit over a flat part of the tile against the RMS of
   its points' sigma_z.

Prints the figures and draws the README's picture (``--figure``). The test
``tests/test_realdata_relief.py`` runs the same function and checks its figures.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "realdata" / \
    "slmaster_mono_relief"
#: A flat part of the tile (camera rows, columns): plain plaster above the brow.
FLAT = (slice(400, 441), slice(470, 531))
#: The projector's fringe period of the scan (px): 1920 px / 32 periods.
PERIOD_PX = 60.0


@dataclass
class Relief:
    """What :func:`measure_relief` finds (arrays on the camera's pixel grid)."""

    rig: object
    noise: object
    cloud: object
    u_p: np.ndarray
    texture: np.ndarray
    tile: np.ndarray           # bool, the largest connected region of valid points
    z: np.ndarray              # mm, NaN off the tile
    relief: np.ndarray         # mm, height toward the camera above a quadratic surface
                               # fitted to the tile (minus Z's deviation from it)
    figures: dict


def _quadratic_residual(xyz):
    """Residual (n,) mm of z - a quadratic surface in x, y fitted by least squares."""
    x = xyz[:, 0] - xyz[:, 0].mean()
    y = xyz[:, 1] - xyz[:, 1].mean()
    A = np.column_stack([np.ones_like(x), x, y, x * x, x * y, y * y])
    coef = np.linalg.lstsq(A, xyz[:, 2], rcond=None)[0]
    return xyz[:, 2] - A @ coef


def measure_relief(folder=DATA) -> Relief:
    """Import the rig, measure the noise, reconstruct, and compute the figures (see the
    module notes). Raises InputError / DecodeError / TriangulationError like the CLI."""
    from scipy import ndimage

    from telefringe.fringes.noise import estimate_noise
    from telefringe.io.opencv_yaml import read_opencv_rig
    from telefringe.io.scan_json import read_scan
    from telefringe.reconstruction.pipeline import reconstruct_scan

    folder = Path(folder)
    scan = read_scan(folder)
    man = scan.manifest
    rig = read_opencv_rig(folder / "caliInfo.yml",
                          projector_size=(man.projector_width, man.projector_height)).rig
    est = estimate_noise(scan)
    noise = est.model
    rec = reconstruct_scan(scan, rig, noise=noise, with_height_map=False)
    default = reconstruct_scan(scan, rig, noise="default", with_height_map=False).cloud
    cloud = rec.cloud
    lab, n = ndimage.label(cloud.mask)
    if n == 0:
        raise ValueError(f"{folder}: no valid point")
    sizes = ndimage.sum(cloud.mask, lab, np.arange(1, n + 1))
    tile = lab == 1 + int(np.argmax(sizes))
    xyz = np.asarray(cloud.xyz)
    z = np.where(tile, xyz[..., 2], np.nan)
    sigma_z = np.asarray(cloud.sigma_z)
    u_p = np.asarray(rec.coords.u_p)
    # neighbours on the tile: the largest step of u_p and of Z, horizontally and vertically
    steps_u, steps_z = [], []
    for ax in (0, 1):
        both = np.logical_and(np.take(tile, range(tile.shape[ax] - 1), axis=ax),
                              np.take(tile, range(1, tile.shape[ax]), axis=ax))
        steps_u.append(np.abs(np.diff(u_p, axis=ax))[both])
        steps_z.append(np.abs(np.diff(xyz[..., 2], axis=ax))[both])
    steps_u = np.concatenate(steps_u)
    steps_z = np.concatenate(steps_z)
    # Z change of one fringe period along each pixel's ray: period * |dZ/du_p| =
    # period * sigma_z / sigma_u_p
    dz_du = sigma_z / np.asarray(rec.coords.sigma_u_p)
    period_z = PERIOD_PX * np.nanmedian(dz_du[tile])
    rel = -_quadratic_residual(xyz[tile])  # toward the camera: raised parts positive
    relief = np.full(tile.shape, np.nan)
    relief[tile] = rel
    flat = np.zeros_like(tile)
    flat[FLAT] = True
    flat &= tile
    res_flat = _quadratic_residual(xyz[flat])
    figures = {
        "valid_points": int(cloud.mask.sum()), "tile_points": int(tile.sum()),
        "noise_read_DN": noise.read_noise, "noise_gain_DN_per_DN": noise.gain,
        "noise_u_gain_DN_per_DN": float(np.sqrt(est.covariance[1, 1])),
        "noise_chi2_dof": float(est.chi2_dof), "noise_misfit": float(est.misfit),
        "noise_pixels": int(est.n_pixels),
        "z_p01_mm": float(np.percentile(z[tile], 1)),
        "z_p50_mm": float(np.percentile(z[tile], 50)),
        "z_p99_mm": float(np.percentile(z[tile], 99)),
        "z_min_mm": float(np.min(z[tile])), "z_max_mm": float(np.max(z[tile])),
        "sigma_z_median_mm": float(np.median(sigma_z[tile])),
        "neighbour_step_u_max_px": float(steps_u.max()),
        "neighbour_step_z_max_mm": float(steps_z.max()),
        "period_z_mm": float(period_z),
        "neighbour_pairs": int(steps_u.size),
        "neighbour_steps_over_half_period": int(np.sum(steps_u > PERIOD_PX / 2)),
        "relief_p01_mm": float(np.percentile(rel, 1)),
        "relief_p99_mm": float(np.percentile(rel, 99)),
        "flat_points": int(flat.sum()),
        "flat_rms_residual_mm": float(np.sqrt(np.mean(res_flat ** 2))),
        "flat_rms_sigma_z_mm": float(np.sqrt(np.mean(sigma_z[flat] ** 2))),
        "flat_rms_sigma_z_default_noise_mm": float(np.sqrt(np.mean(
            np.asarray(default.sigma_z)[flat] ** 2))),
    }
    return Relief(rig, noise, cloud, u_p, np.asarray(rec.texture), tile, z, relief, figures)


def draw(r: Relief, path) -> Path:
    """The README's picture: the camera image, the depth map and the relief of the tile."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows, cols = np.nonzero(r.tile)
    box = (slice(rows.min() - 8, rows.max() + 9), slice(cols.min() - 8, cols.max() + 9))
    f = r.figures
    fig, axes = plt.subplots(1, 3, figsize=(13.5, 4.6), constrained_layout=True)
    axes[0].imshow(r.texture[box], cmap="gray")
    axes[0].set_title("camera image (fringe-free)")
    im = axes[1].imshow(r.z[box], cmap="viridis")
    fig.colorbar(im, ax=axes[1], shrink=0.85, label="Z (mm)")
    axes[1].set_title(f"depth Z: {f['z_p01_mm']:.0f}-{f['z_p99_mm']:.0f} mm (1-99 %)")
    lim = max(abs(f["relief_p01_mm"]), abs(f["relief_p99_mm"]))
    im = axes[2].imshow(r.relief[box], cmap="RdBu_r", vmin=-lim, vmax=lim)
    fig.colorbar(im, ax=axes[2], shrink=0.85, label="mm")
    axes[2].set_title("relief: height toward the camera over a quadratic surface")
    y0, x0 = box[0].start, box[1].start
    for a in axes[1:]:
        a.add_patch(plt.Rectangle((FLAT[1].start - x0, FLAT[0].start - y0),
                                  FLAT[1].stop - FLAT[1].start, FLAT[0].stop - FLAT[0].start,
                                  fill=False, ec="k", lw=1.2))
    for a in axes:
        a.set_xticks([])
        a.set_yticks([])
    fig.suptitle(
        f"Real capture (SLMaster, pinhole camera + projector, OpenCV calibration): "
        f"flat part (box) residual {f['flat_rms_residual_mm'] * 1e3:.0f} um RMS, "
        f"sigma_z {f['flat_rms_sigma_z_mm'] * 1e3:.0f} um", fontsize=10)
    path = Path(path)
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--figure", type=Path, default=None,
                    help="write the README picture here (e.g. docs/realdata_relief.png)")
    args = ap.parse_args(argv)
    t0, c0 = time.perf_counter(), time.process_time()
    r = measure_relief(args.data)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    for key, val in r.figures.items():
        print(f"{key:36s} {val:.6g}" if isinstance(val, float) else f"{key:36s} {val}")
    print(f"time: {wall:.1f} s wall, {cpu:.1f} s CPU (shared machine: wall varies)")
    if args.figure:
        print(f"wrote {draw(r, args.figure)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
