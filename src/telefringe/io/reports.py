"""Compact summaries of results: JSON-ready dicts without per-point arrays (the BGA's
keeps its per-ball arrays)."""

from __future__ import annotations

import numpy as np

from telefringe.io.jsonable import number_or_none as _f
from telefringe.io.jsonable import to_jsonable

__all__ = ["bga_summary", "cloud_summary", "plane_summary", "plate_summary", "sphere_summary",
           "steps_summary", "paper_result_to_json", "uncertainty_summary"]

#: The unit of each quantity of a measurement's ``uncertainty`` (mm unless listed).
_UNCERTAINTY_UNITS = {"tilt_deg": "deg"}


def uncertainty_summary(unc) -> dict | None:
    """A measurement's ``uncertainty`` (dict of
    :class:`telefringe.metrology.uncertainty.Uncertainty`) as JSON: per quantity its
    ``value``, ``u_noise``, ``u_calibration``, combined ``u``, expanded ``U`` (same shape
    as the value; mm, or deg for ``tilt_deg``), ``k`` and ``unit``. None stays None."""
    if unc is None:
        return None
    return {name: {"value": to_jsonable(q.value), "u_noise": to_jsonable(q.u_noise),
                   "u_calibration": to_jsonable(q.u_calibration), "u": to_jsonable(q.u),
                   "U": to_jsonable(q.U), "k": _f(q.k),
                   "unit": _UNCERTAINTY_UNITS.get(name, "mm")}
            for name, q in unc.items()}


def _with_uncertainty(out: dict, m) -> dict:
    unc = getattr(m, "uncertainty", None)
    out["uncertainty"] = uncertainty_summary(unc)
    out["uncertainty_includes_calibration"] = unc is not None
    return out


def cloud_summary(cloud) -> dict:
    """Counts and uncertainty figures of a point cloud."""
    from telefringe.reconstruction.cloud import (
        FLAG_INCONSISTENT,
        FLAG_NO_PHASE,
        FLAG_NOT_CONVERGED,
        FLAG_OUTSIDE,
        FLAG_UNCERTAIN,
    )

    fl = np.asarray(cloud.flags)
    sz = np.asarray(cloud.sigma_z)[np.asarray(cloud.mask)]
    out = {
        "pixels": int(fl.size), "valid": int(cloud.count),
        "valid_fraction": _f(cloud.count / max(fl.size, 1)),
        "invalid": {name: int(np.count_nonzero(fl & bit)) for name, bit in (
            ("no_phase", FLAG_NO_PHASE), ("inconsistent", FLAG_INCONSISTENT),
            ("outside_projector", FLAG_OUTSIDE), ("not_converged", FLAG_NOT_CONVERGED),
            ("uncertain", FLAG_UNCERTAIN))},
        "sigma_z_median_mm": _f(np.median(sz)) if sz.size and np.isfinite(sz).all() else None,
        "sigma_z_p95_mm": (_f(np.percentile(sz, 95)) if sz.size and np.isfinite(sz).all()
                           else None),
    }
    if cloud.residual is not None:
        r = np.asarray(cloud.residual)[np.asarray(cloud.mask)]
        r = r[np.isfinite(r)]
        out["residual_median_px"] = _f(np.median(r)) if r.size else None
        out["residual_p99_px"] = _f(np.percentile(r, 99)) if r.size else None
    return out


def plane_summary(p) -> dict:
    """A :class:`telefringe.metrology.PlaneFit` without its per-point arrays."""
    return {"normal": to_jsonable(p.normal), "offset_mm": _f(p.offset),
            "centroid_mm": to_jsonable(p.centroid), "rms_mm": _f(p.rms),
            "flatness_mm": _f(p.flatness), "tilt_deg": _f(p.tilt_deg),
            "n_points": int(p.n_points), "n_inliers": int(p.n_inliers),
            "sigma_offset_mm": _f(p.sigma_offset)}


def plate_summary(m) -> dict:
    """A :class:`telefringe.metrology.PlateMeasurement` as in the paper's Table 3."""
    sp = m.spacing
    return _with_uncertainty({
        "z_mm": _f(m.z.distance), "sigma_z_mm": _f(m.z.sigma),
        "angle_to_reference_deg": _f(m.z.angle_deg),
        "plane": plane_summary(m.plane),
        "spacing": {
            "nominal_mm": _f(sp.nominal_mm),
            "mean_x_mm": _f(sp.mean_x), "mean_y_mm": _f(sp.mean_y),
            "abs_err_x_mm": _f(sp.abs_err_x), "abs_err_y_mm": _f(sp.abs_err_y),
            "std_x_mm": _f(sp.std_x), "std_y_mm": _f(sp.std_y),
            "rms_err_x_mm": _f(sp.rms_err_x), "rms_err_y_mm": _f(sp.rms_err_y),
            "n_x": int(sp.n_x), "n_y": int(sp.n_y),
            "dist_x_mm": to_jsonable(sp.dist_x), "dist_y_mm": to_jsonable(sp.dist_y),
        },
        "markers": {"measured": int(np.count_nonzero(m.centres.valid)),
                    "centres_mm": to_jsonable(m.centres.xyz),
                    "sigma_mm": to_jsonable(m.centres.sigma_xyz)},
    }, m)


def sphere_summary(f, base=None, *, region: str | None = None, uncertainty=None,
                   spread=None) -> dict:
    """A :class:`telefringe.metrology.SphereFit` (and its base plane, which points were
    fitted: ``SphereMeasurement.region``, ``SphereMeasurement.uncertainty`` and the
    point-spread model it was fitted through, ``SphereMeasurement.spread``)."""
    out = {"centre_mm": to_jsonable(f.centre), "radius_mm": _f(f.radius),
           "diameter_mm": _f(f.diameter), "sigma_centre_mm": to_jsonable(f.sigma_centre),
           "sigma_radius_mm": _f(f.sigma_radius), "rms_mm": _f(f.rms),
           "form_error_mm": _f(f.form_error), "n_points": int(f.n_points),
           "n_inliers": int(f.n_inliers)}
    if base is not None:
        out["base_plane"] = plane_summary(base)
    if region is not None:
        out["fitted_points"] = region
    out["uncertainty"] = uncertainty_summary(uncertainty)
    out["uncertainty_includes_calibration"] = uncertainty is not None
    out["point_spread"] = None if spread is None else {
        "variance_px2": _f(spread.variance_px2),
        "sigma_variance_px2": _f(spread.sigma_variance_px2),
        "estimated": bool(spread.estimated), "max_view_deg": _f(spread.max_view_deg)}
    if spread is not None and getattr(spread, "cameras", 1) == 2:
        # two cameras: the second camera's variance (equal to the first's when shared)
        out["point_spread"].update({
            "cameras": 2, "shared": bool(spread.shared),
            "variance_2_px2": _f(spread.variance_2_px2),
            "sigma_variance_2_px2": _f(spread.sigma_variance_2_px2)})
    return out


def steps_summary(m) -> dict:
    """A :class:`telefringe.metrology.StepMeasurement` without the label image."""
    return _with_uncertainty({"levels": int(len(m.offsets)), "normal": to_jsonable(m.normal),
            "heights_mm": to_jsonable(m.heights),
            "sigma_heights_mm": to_jsonable(m.sigma_heights),
            "step_heights_mm": to_jsonable(m.step_heights),
            "sigma_steps_mm": to_jsonable(m.sigma_steps), "rms_mm": to_jsonable(m.rms),
            "n_points": to_jsonable(m.n_points)}, m)


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


def bga_summary(m) -> dict:
    """A :class:`telefringe.metrology.BGAMeasurement` (per-ball arrays included)."""
    fin = np.concatenate([np.asarray(m.pitch_x)[np.isfinite(m.pitch_x)],
                          np.asarray(m.pitch_y)[np.isfinite(m.pitch_y)]])
    nom = m.nominal
    return _with_uncertainty({
        "nominal": {"rows": int(nom.rows), "cols": int(nom.cols), "pitch_mm": _f(nom.pitch_mm),
                    "ball_diameter_mm": _f(nom.ball_diameter_mm)},
        "balls_found": int(m.n_balls), "missing": [list(x) for x in m.missing],
        "balls_not_measured": len(m.not_measured),
        "not_measured": [{"index": [int(i), int(j)], "reason": why}
                         for (i, j), why in m.not_measured],
        "unexpected": [list(x) for x in m.unexpected],
        "coplanarity_mm": _f(m.coplanarity.value),
        "sigma_coplanarity_mm": _f(m.coplanarity.sigma),
        "coplanarity_alternatives_mm": to_jsonable(m.coplanarity.alternatives),
        "package_rocks": bool(m.coplanarity.rocks),
        "seating_contacts": [list(map(int, m.index[k])) for k in m.coplanarity.contacts],
        "sigma_height_model_mm": _f(m.sigma_height_model),
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
                  "sigma_height_noise_mm": to_jsonable(m.sigma_height_noise),
                  "diameter_mm": to_jsonable(m.diameter), "centre_mm": to_jsonable(m.centre),
                  "apex_mm": to_jsonable(m.apex)},
    }, m)
