"""Fig. 4-style histograms of the paper re-run (matplotlib, Agg backend)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from telefringe.io.atomic import atomic_file

__all__ = ["write_spacing_histograms"]


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
