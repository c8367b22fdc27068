"""The acceptance test's page of plots: the residual map of every position (radial
residuals on the spheres, normal distances on the plane) and the characteristics per
position against the MPE (matplotlib, drawn off-screen)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from telefringe.io.atomic import atomic_file

__all__ = ["write_acceptance_figure"]


def _crop(m: np.ndarray, pad: int = 3) -> np.ndarray:
    rows, cols = np.nonzero(np.isfinite(m))
    if rows.size == 0:
        return m[:1, :1]
    r0, r1 = max(rows.min() - pad, 0), min(rows.max() + pad + 1, m.shape[0])
    c0, c1 = max(cols.min() - pad, 0), min(cols.max() + pad + 1, m.shape[1])
    return m[r0:r1, c0:c1]


def write_acceptance_figure(path, result, *, title: str = "", force: bool = False) -> Path:
    """Write the page of plots (PNG) of an acceptance test.

    Parameters
    ----------
    path : path-like, the PNG to write (atomically).
    result : telefringe.metrology.acceptance.AcceptanceResult
    title : a line above the page.

    Returns
    -------
    Path of the file written.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    positions = list(result.positions)
    ncols = 6
    nmaps = len(positions)
    nrows = -(-nmaps // ncols) + 1
    fig = Figure(figsize=(2.6 * ncols, 2.4 * nrows + 0.6), layout="constrained")
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(nrows, ncols)
    maps = [p.residual_map() * 1000.0 for p in positions]  # um
    finite = np.concatenate([m[np.isfinite(m)] for m in maps]) if maps else np.zeros(1)
    lim = float(np.percentile(np.abs(finite), 99.5)) if finite.size else 1.0
    lim = lim or 1.0
    im = None
    for k, (p, m) in enumerate(zip(positions, maps, strict=True)):
        ax = fig.add_subplot(grid[k // ncols, k % ncols])
        im = ax.imshow(_crop(m), cmap="RdBu_r", vmin=-lim, vmax=lim, interpolation="nearest")
        t = p.test
        if p.kind == "sphere":
            label = (f"PF {t.PF * 1e3:.1f}  PS {t.PS * 1e3:+.1f} um\n"
                     f"cap {t.cap_half_angle_deg:.0f} deg")
        elif p.kind == "ball_bar":
            label = f"SD {t.SD * 1e3:+.1f} um\nL {t.distance:.4f} mm"
        else:
            label = f"F {t.F * 1e3:.1f} um"
        ax.set_title(f"{p.name}\n{label}", fontsize=7)
        ax.set_xticks([])
        ax.set_yticks([])
    if im is not None:
        fig.colorbar(im, ax=fig.axes, shrink=0.5, label="residual (um)")
    ax = fig.add_subplot(grid[nrows - 1, :])
    xs, labels, x = [], [], 0
    for q, qr in result.quantities.items():
        vals = np.asarray(qr.values) * 1e3
        pos = np.arange(x, x + vals.size)
        ax.bar(pos, vals, yerr=np.asarray(qr.U) * 1e3, capsize=2, label=q)
        if qr.mpe is not None:
            for s in ((1, -1) if q in ("PS", "SD") else (1,)):
                ax.plot([pos[0] - 0.4, pos[-1] + 0.4], [s * qr.mpe * 1e3] * 2, "k--", lw=0.8)
        xs += list(pos)
        labels += [f"{q} {i}" for i in range(vals.size)]
        x += vals.size + 1
    ax.axhline(0.0, color="0.5", lw=0.5)
    ax.set_xticks(xs, labels, rotation=90, fontsize=6)
    ax.set_ylabel("um (bars: U, k = 2; dashed: MPE)")
    ax.legend(fontsize=7, ncols=4)
    verdict = f"  verdict: {result.verdict}" if result.verdict else ""
    fig.suptitle((title + "  " if title else "") + "VDI/VDE 2634-2 acceptance test" + verdict,
                 fontsize=10)
    path = Path(path)
    with atomic_file(path, force=force) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    return path
