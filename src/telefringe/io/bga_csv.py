"""``bga.csv``: one row per grid position of a BGA measurement (see docs/formats.md),
written atomically; an existing file is replaced only with ``force``."""

from __future__ import annotations

import csv
from pathlib import Path

from telefringe.io.atomic import atomic_file

__all__ = ["write_bga_csv"]


_BGA_COLUMNS = ("row", "col", "status", "x_mm", "y_mm", "z_mm", "apex_x_mm", "apex_y_mm",
                "apex_z_mm", "height_mm", "sigma_height_mm", "diameter_mm", "pos_x_mm",
                "pos_y_mm", "dx_mm", "dy_mm", "coplanarity_mm", "seating_contact", "fit_rms_mm",
                "n_points", "reason", "sigma_height_noise_mm",
                # with the calibration's uncertainty (measure bga --rig): the calibration
                # part of the height's, the combined u and the expanded U (k = 2) of the
                # height and of the position in the grid frame
                "u_cal_height_mm", "u_height_mm", "U_height_mm", "u_pos_x_mm", "u_pos_y_mm",
                "U_pos_x_mm", "U_pos_y_mm")
_N_UNC = 7


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
    rests on); ``fit_rms_mm``; ``n_points``; ``reason`` (empty unless not measured);
    ``sigma_height_noise_mm``, the part of ``sigma_height_mm`` from the pixels' noise (the
    rest is the cap model's, ``sigma_height_model`` of the measurement); when the
    measurement holds the calibration's uncertainty (``m.uncertainty``, see
    :func:`telefringe.metrology.uncertainty.bga_uncertainty`): ``u_cal_height_mm`` (the
    calibration's part), ``u_height_mm`` (combined standard uncertainty),
    ``U_height_mm`` (expanded, k = 2), ``u_pos_x/y_mm`` and ``U_pos_x/y_mm`` (of
    ``pos_*_mm``); these are empty otherwise.
    """
    unc = getattr(m, "uncertainty", None)
    pitch = m.nominal.pitch_mm
    contacts = set(int(k) for k in m.coplanarity.contacts)
    by_pos = {(int(i), int(j)): k for k, (i, j) in enumerate(m.index)}
    unexpected = set(m.unexpected)
    populated = m.nominal.populated()
    not_measured = dict(m.not_measured)
    blank = [""] * (len(_BGA_COLUMNS) - 5 - _N_UNC)
    more_blank = [""] * _N_UNC
    rows = []
    for i in range(m.nominal.rows):
        for j in range(m.nominal.cols):
            k = by_pos.get((i, j))
            if k is None:
                if (i, j) in not_measured:
                    rows.append([i, j, "not_measured", *blank, not_measured[(i, j)], "",
                                 *more_blank])
                elif populated[i, j]:
                    rows.append([i, j, "missing", *blank, "", "", *more_blank])
                continue
            status = "unexpected" if (i, j) in unexpected else "ok"
            c, a = m.centre[k], m.apex[k]
            px, py = m.position[k]
            rows.append([i, j, status, *(f"{v:.6f}" for v in c), *(f"{v:.6f}" for v in a),
                         f"{m.height[k]:.6f}", f"{m.sigma_height[k]:.6f}",
                         f"{m.diameter[k]:.6f}", f"{px:.6f}", f"{py:.6f}",
                         f"{px - j * pitch:.6f}", f"{py - i * pitch:.6f}",
                         f"{m.coplanarity.distances[k]:.6f}", int(k in contacts),
                         f"{m.rms[k]:.6f}", int(m.n_points[k]), "",
                         f"{m.sigma_height_noise[k]:.6f}", *_unc_cells(unc, k)])
    path = Path(path)
    with atomic_file(path, force=force) as tmp, open(tmp, "w", newline="") as f:
        wr = csv.writer(f)
        wr.writerow(_BGA_COLUMNS)
        wr.writerows(rows)
    return path


def _unc_cells(unc, k: int) -> list:
    """The uncertainty columns of ball ``k`` (empty without ``unc``)."""
    if unc is None:
        return [""] * _N_UNC
    h, p = unc["height"], unc["position"]
    return [f"{h.u_calibration[k]:.6f}", f"{h.u[k]:.6f}", f"{h.U[k]:.6f}",
            f"{p.u[k, 0]:.6f}", f"{p.u[k, 1]:.6f}", f"{p.U[k, 0]:.6f}", f"{p.U[k, 1]:.6f}"]
