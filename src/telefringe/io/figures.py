"""Figures of the paper re-run (matplotlib, Agg backend) and its JSON report."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from telefringe.io.atomic import atomic_file

__all__ = ["write_spacing_histograms", "paper_result_to_json"]


def write_spacing_histograms(path, rows, *, pitch_mm: float, force: bool = True) -> Path:
    """Fig. 4-style histograms of neighbour distances, one column per plate position.

    Parameters
    ----------
    path : output PNG.
    rows : sequence of :class:`telefringe.simulate.experiments.PlateRow`.
    pitch_mm : the nominal pitch (drawn as a line).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = list(rows)
    fig, axes = plt.subplots(2, len(rows), figsize=(3.2 * len(rows), 5.2), squeeze=False,
                             constrained_layout=True)
    for k, row in enumerate(rows):
        for a, (name, d) in enumerate((("X", row.distances_x), ("Y", row.distances_y))):
            ax = axes[a, k]
            err_um = (np.asarray(d) - pitch_mm) * 1000.0
            ax.hist(err_um, bins=15, color="#3b75af", edgecolor="white")
            ax.axvline(0.0, color="k", lw=0.8)
            ax.set_title(f"Z = {row.position:+.1f} mm, along {name}", fontsize=9)
            ax.set_xlabel(f"distance - {pitch_mm:g} mm (um)", fontsize=8)
            ax.tick_params(labelsize=7)
            label = f"mean {np.mean(err_um):+.2f} um\nstd {np.std(err_um, ddof=1):.2f} um"
            ax.text(0.02, 0.95, label, transform=ax.transAxes, va="top", fontsize=7)
    fig.suptitle("Neighbour distances of the 9 x 11 plate markers (virtual rig)", fontsize=10)
    path = Path(path)
    with atomic_file(path, force=force) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path


def paper_result_to_json(result) -> dict:
    """A JSON-able summary of :class:`telefringe.simulate.experiments.PaperResult`."""
    from telefringe.simulate.experiments import PAPER_TABLE3, PAPER_TABLE4

    cal = result.calibration
    plate = []
    for r in result.plate:
        paper = PAPER_TABLE3.get(r.position)
        plate.append({
            "position_mm": r.position, "mean_x_mm": r.mean_x, "mean_y_mm": r.mean_y,
            "z_mm": r.z, "abs_err_x_mm": r.err_x, "abs_err_y_mm": r.err_y,
            "abs_err_z_mm": r.err_z, "std_x_mm": r.std_x, "std_y_mm": r.std_y,
            "n_x": r.n_x, "n_y": r.n_y, "sigma_z_mm": r.sigma_z,
            "paper": None if paper is None else dict(zip(
                ("mean_x_mm", "mean_y_mm", "z_mm", "abs_err_x_mm", "abs_err_y_mm",
                 "abs_err_z_mm", "std_x_mm", "std_y_mm"), paper, strict=True)),
        })
    b = result.bga
    return {
        "rig": result.rig_name, "quick": result.quick,
        "calibration": {"rms_camera_px": float(cal.rms_camera),
                        "rms_projector_px": float(cal.rms_projector),
                        "poses_used": int(np.count_nonzero(cal.used)),
                        "warnings": list(cal.warnings)},
        "table3": plate,
        "table4": {
            "pairs": [{"a": list(p.a), "b": list(p.b), "distance_mm": p.distance,
                       "truth_mm": p.truth, "error_mm": p.error} for p in b.pairs],
            "paper_pairs": [{"distance_mm": d, "error_mm": e} for d, e in PAPER_TABLE4],
            "pitch_error_max_mm": b.pitch_error_max, "n_pairs": b.n_pairs,
            "apex_rms_error_mm": b.apex_rms_error, "apex_max_error_mm": b.apex_max_error,
            "coplanarity_mm": b.coplanarity, "coplanarity_truth_mm": b.coplanarity_truth,
            "n_present": b.n_present, "n_found": b.n_found,
            "missing_truth": [list(m) for m in b.missing_truth],
            "missing_reported": [list(m) for m in b.missing_reported],
            "valid_fraction_ball_pixels": b.valid_fraction_balls,
        },
        "timings_s": {k: float(v) for k, v in result.timings.items()},
    }
