"""The calibration report: reprojection residual plots of a calibration (matplotlib, Agg
backend)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["write_calibration_report"]


def write_calibration_report(folder, calib) -> list[str]:
    """Residual plots (PNG) of a calibration into an existing ``folder``.

    Parameters
    ----------
    folder : path-like, an existing folder (the command writes into a temporary one that
        appears complete or not at all).
    calib : telefringe.calibration.calibrate.RigCalibration

    Returns
    -------
    list of str
        The file names written: ``residuals_{camera,projector}.png`` (quiver plots of the
        reprojection residuals over each image, exaggerated),
        ``histogram_{camera,projector}.png`` and ``rms_per_pose.png``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder = Path(folder)
    names = []
    devices = dict(calib.rig.cameras)
    if calib.rig.projector is not None:
        devices["projector"] = calib.rig.projector
    for dev, device in devices.items():
        obs = getattr(calib, f"{dev}_observations", None)
        res = getattr(calib, f"residuals_{dev}", None)
        if obs is None or res is None:
            continue
        size = device.image_size
        ok = np.all(np.isfinite(res), axis=2) & np.all(np.isfinite(obs), axis=2)
        o, r = obs[ok], res[ok]
        fig, ax = plt.subplots(figsize=(8, 6.5))
        if r.size:
            scale = float(np.percentile(np.hypot(r[:, 0], r[:, 1]), 95)) or 1.0
            q = ax.quiver(o[:, 0], o[:, 1], r[:, 0], r[:, 1], np.hypot(r[:, 0], r[:, 1]),
                          angles="xy", scale_units="xy", scale=scale / (0.04 * size[0]),
                          cmap="viridis")
            fig.colorbar(q, ax=ax, label="residual length (px)")
        ax.set_xlim(0, size[0])
        ax.set_ylim(size[1], 0)
        ax.set_aspect("equal")
        ax.set_xlabel("u (px)")
        ax.set_ylabel("v (px)")
        ax.set_title(f"{dev}: reprojection residuals (predicted - observed), exaggerated; "
                     f"RMS {getattr(calib, 'rms_' + dev):.4f} px", fontsize=9)
        fname = f"residuals_{dev}.png"
        fig.savefig(folder / fname, dpi=110, bbox_inches="tight")
        plt.close(fig)
        names.append(fname)
        fig, axs = plt.subplots(1, 2, figsize=(9, 3.5))
        for k, (ax, lab) in enumerate(zip(axs, ("du", "dv"), strict=True)):
            if r.size:
                ax.hist(r[:, k], bins=40, color="tab:blue")
            ax.set_xlabel(f"{lab} (px)")
        axs[0].set_ylabel("count")
        fig.suptitle(f"{dev}: residual distribution")
        fname = f"histogram_{dev}.png"
        fig.savefig(folder / fname, dpi=110, bbox_inches="tight")
        plt.close(fig)
        names.append(fname)
    fig, ax = plt.subplots(figsize=(max(6, 0.5 * len(calib.pose_names) + 2), 3.5))
    x = np.arange(len(calib.pose_names))
    per_pose = np.asarray(calib.rms_per_pose).reshape(len(calib.pose_names), -1)
    width = 0.8 / max(per_pose.shape[1], 1)
    for j, dev in enumerate(list(devices)[:per_pose.shape[1]]):
        ax.bar(x + (j - (per_pose.shape[1] - 1) / 2) * width, per_pose[:, j], width,
               label=dev)
    ax.set_xticks(x, calib.pose_names, rotation=60, fontsize=8)
    ax.set_ylabel("RMS reprojection error (px)")
    ax.legend()
    fig.savefig(folder / "rms_per_pose.png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    names.append("rms_per_pose.png")
    return names
