"""``bga.png``: the map of a BGA measurement, balls coloured by apex height, the seating
contacts, missing and not-measured balls marked (matplotlib, drawn off-screen)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from telefringe.io.atomic import atomic_file

__all__ = ["write_bga_png"]


def _figure(figsize):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=100)
    FigureCanvasAgg(fig)
    return fig


# --------------------------------------------------------------------------------------
# BGA
# --------------------------------------------------------------------------------------


def write_bga_png(path, m, *, title: str | None = None, force: bool = False) -> Path:
    """A map of the balls on the grid, coloured by apex height (mm); balls seen but not
    measured are orange hollow squares, missing balls red crosses, the seating-plane
    contacts are circled (drawn by ``_bga_map_figure``)."""
    fig = _bga_map_figure(m, title=title)
    path = Path(path)
    with atomic_file(path, force=force) as tmp:
        fig.savefig(tmp, format="png")
    return path


def _bga_map_figure(m, *, title: str | None = None):
    """The matplotlib figure of :func:`write_bga_png` (one axes, a legend entry per
    marker kind shown)."""
    rows, cols = m.nominal.rows, m.nominal.cols
    width_in = 7.5
    plot_in = 5.6  # about the axes' width
    fig = _figure((width_in, max(3.0, plot_in * (rows + 1) / (cols + 1)) + 1.6))
    ax = fig.add_subplot(1, 1, 1)
    pitch = m.nominal.pitch_mm
    x = m.index[:, 1] * pitch
    y = m.index[:, 0] * pitch
    # marker diameter: the nominal ball diameter at the plot's scale (points)
    pt_per_mm = plot_in * 72.0 / ((cols + 1) * pitch)
    size = (min(m.nominal.ball_diameter_mm, 0.9 * pitch) * pt_per_mm) ** 2
    sc = ax.scatter(x, y, c=m.height, cmap="viridis", s=size, marker="o", edgecolors="none")
    if len(m.coplanarity.contacts):
        k = m.coplanarity.contacts
        ax.scatter(x[k], y[k], s=size * 1.6, facecolors="none", edgecolors="k",
                   linewidths=1.2, label="seating-plane contacts")
    if m.not_measured:
        nm = np.array([ij for ij, _ in m.not_measured])
        ax.scatter(nm[:, 1] * pitch, nm[:, 0] * pitch, marker="s", facecolors="none",
                   edgecolors="tab:orange", linewidths=1.5, s=size * 0.8,
                   label=f"not measured ({len(m.not_measured)})")
    if m.missing:
        mi = np.array(m.missing)
        ax.scatter(mi[:, 1] * pitch, mi[:, 0] * pitch, marker="x", c="red", s=size * 0.6,
                   label=f"missing ({len(m.missing)})")
    ax.set_aspect("equal")
    ax.set_xlim(-pitch, cols * pitch)
    ax.set_ylim(-pitch, rows * pitch)
    ax.set_xlabel("column x' (mm)")
    ax.set_ylabel("row y' (mm)")
    ax.set_title(title or f"BGA: {m.n_balls} balls, coplanarity "
                 f"{m.coplanarity.value * 1000:.1f} um")
    cb = fig.colorbar(sc, ax=ax, shrink=0.9)
    cb.set_label("apex height above substrate (mm)")
    if len(m.coplanarity.contacts) or m.missing or m.not_measured:
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=2,
                  fontsize="small", frameon=False, markerscale=0.5)
    fig.tight_layout()
    return fig
