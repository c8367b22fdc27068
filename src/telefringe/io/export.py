"""BGA exports: a CSV with one row per grid position, a PNG map coloured by apex height and
the JSON summary (see docs/formats.md). Every other format has its own module in
:mod:`telefringe.io`.

Every writer writes atomically (temporary name, then rename) and refuses to replace an
existing file unless ``force``.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from telefringe.io.atomic import atomic_file
from telefringe.io.jsonable import number_or_none as _f
from telefringe.io.jsonable import to_jsonable
from telefringe.io.reports import plane_summary

__all__ = [
    "write_bga_csv",
    "write_bga_png",
    "bga_summary",
]


def _figure(figsize):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=100)
    FigureCanvasAgg(fig)
    return fig


# --------------------------------------------------------------------------------------
# BGA
# --------------------------------------------------------------------------------------
_BGA_COLUMNS = ("row", "col", "status", "x_mm", "y_mm", "z_mm", "apex_x_mm", "apex_y_mm",
                "apex_z_mm", "height_mm", "sigma_height_mm", "diameter_mm", "pos_x_mm",
                "pos_y_mm", "dx_mm", "dy_mm", "coplanarity_mm", "seating_contact", "fit_rms_mm",
                "n_points", "reason")


def write_bga_csv(path, m, *, force: bool = False) -> Path:
    """One row per grid position of a :class:`telefringe.metrology.BGAMeasurement`.

    ``status`` is ``ok``, ``not_measured`` (a ball is seen there but could not be
    measured: ``reason`` says why, see
    :data:`telefringe.metrology.bga.result.NOT_MEASURED_REASONS`), ``missing`` (populated
    position where no ball is seen) or ``unexpected`` (a ball where the nominal grid has
    none); positions that are empty as they should be are left out. Columns: grid
    ``row``, ``col``; sphere centre ``x/y/z_mm`` and apex
    ``apex_*_mm`` (world); ``height_mm`` (apex above the substrate plane) and its
    ``sigma_height_mm``; ``diameter_mm``; ``pos_*_mm`` (centre in the grid frame) and
    ``dx/dy_mm`` (its offset from the nominal position); ``coplanarity_mm`` (distance of the
    apex from the JEDEC seating plane); ``seating_contact`` (1 for the balls the package
    rests on); ``fit_rms_mm``; ``n_points``; ``reason`` (empty unless not measured).
    """
    pitch = m.nominal.pitch_mm
    contacts = set(int(k) for k in m.coplanarity.contacts)
    by_pos = {(int(i), int(j)): k for k, (i, j) in enumerate(m.index)}
    unexpected = set(m.unexpected)
    populated = m.nominal.populated()
    not_measured = dict(m.not_measured)
    blank = [""] * (len(_BGA_COLUMNS) - 4)
    rows = []
    for i in range(m.nominal.rows):
        for j in range(m.nominal.cols):
            k = by_pos.get((i, j))
            if k is None:
                if (i, j) in not_measured:
                    rows.append([i, j, "not_measured", *blank, not_measured[(i, j)]])
                elif populated[i, j]:
                    rows.append([i, j, "missing", *blank, ""])
                continue
            status = "unexpected" if (i, j) in unexpected else "ok"
            c, a = m.centre[k], m.apex[k]
            px, py = m.position[k]
            rows.append([i, j, status, *(f"{v:.6f}" for v in c), *(f"{v:.6f}" for v in a),
                         f"{m.height[k]:.6f}", f"{m.sigma_height[k]:.6f}",
                         f"{m.diameter[k]:.6f}", f"{px:.6f}", f"{py:.6f}",
                         f"{px - j * pitch:.6f}", f"{py - i * pitch:.6f}",
                         f"{m.coplanarity.distances[k]:.6f}", int(k in contacts),
                         f"{m.rms[k]:.6f}", int(m.n_points[k]), ""])
    path = Path(path)
    with atomic_file(path, force=force) as tmp, open(tmp, "w", newline="") as f:
        wr = csv.writer(f)
        wr.writerow(_BGA_COLUMNS)
        wr.writerows(rows)
    return path


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


def bga_summary(m) -> dict:
    """A :class:`telefringe.metrology.BGAMeasurement` (per-ball arrays included)."""
    fin = np.concatenate([np.asarray(m.pitch_x)[np.isfinite(m.pitch_x)],
                          np.asarray(m.pitch_y)[np.isfinite(m.pitch_y)]])
    nom = m.nominal
    return {
        "nominal": {"rows": int(nom.rows), "cols": int(nom.cols), "pitch_mm": _f(nom.pitch_mm),
                    "ball_diameter_mm": _f(nom.ball_diameter_mm)},
        "balls_found": int(m.n_balls), "missing": [list(x) for x in m.missing],
        "balls_not_measured": len(m.not_measured),
        "not_measured": [{"index": [int(i), int(j)], "reason": why}
                         for (i, j), why in m.not_measured],
        "unexpected": [list(x) for x in m.unexpected],
        "coplanarity_mm": _f(m.coplanarity.value),
        "seating_contacts": [list(map(int, m.index[k])) for k in m.coplanarity.contacts],
        "height_mean_mm": _f(np.mean(m.height)), "height_min_mm": _f(np.min(m.height)),
        "height_max_mm": _f(np.max(m.height)),
        "diameter_mean_mm": (_f(np.nanmean(m.diameter)) if np.any(np.isfinite(m.diameter))
                             else None),
        "diameters_measured": int(np.count_nonzero(np.isfinite(m.diameter))),
        "pitch_mean_mm": _f(np.mean(fin)) if fin.size else None,
        "pitch_std_mm": _f(np.std(fin, ddof=1)) if fin.size > 1 else None,
        "pitch_error_max_mm": _f(m.pitch_error_max),
        "grid_angle_deg": _f(m.grid_angle_deg),
        "psf_variance_mm2": _f(m.psf_variance), "sigma_psf_variance_mm2": _f(m.sigma_psf_variance),
        "psf_balls": int(m.psf_balls), "psf_converged": m.psf_converged,
        "substrate": plane_summary(m.substrate),
        "balls": {"index": to_jsonable(m.index), "height_mm": to_jsonable(m.height),
                  "sigma_height_mm": to_jsonable(m.sigma_height),
                  "diameter_mm": to_jsonable(m.diameter), "centre_mm": to_jsonable(m.centre),
                  "apex_mm": to_jsonable(m.apex)},
    }
