"""measure_bga reports what it could not measure: balls seen but not fitted (with the
reason), a failed point-spread solve, and leaves the caller's arrays alone."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from test_metrology import bga_cloud

import telefringe.metrology.bga.psf as psf
from telefringe.io.bga_csv import write_bga_csv
from telefringe.io.figures.bga_png import _bga_map_figure
from telefringe.io.jsonable import write_json
from telefringe.io.reports import bga_summary
from telefringe.metrology import (
    NOT_MEASURED_REASONS,
    BGANominal,
    BGAOptions,
    MetrologyError,
    PSFSolveWarning,
    SphereFit,
    measure_bga,
)
from telefringe.reconstruction.cloud import PointCloud

NOM = BGANominal(rows=6, cols=7, pitch_mm=0.8, ball_diameter_mm=0.45)
TRUE_MISSING = {(2, 3), (0, 0)}


def _ball_pixels(cloud, apex, ij, radius):
    """Pixels within ``radius`` mm (in x, y) of ball ij's apex."""
    x, y = np.nan_to_num(cloud.x), np.nan_to_num(cloud.y)
    a = apex[ij]
    return np.hypot(x - a[0], y - a[1]) < radius


def _spoiled_cloud():
    """The synthetic BGA with three balls spoiled: (1, 1) keeps only a few pixels (region
    too small), (3, 5) loses its cap top (too few cap points), (4, 2) and (4, 3) are joined
    by a ridge (one region too large for a ball)."""
    cloud, present, offs, apex = bga_cloud()
    xyz = np.array(cloud.xyz)
    sig = np.array(cloud.sigma_z)
    small = _ball_pixels(cloud, apex, (1, 1), 0.225) & ~_ball_pixels(cloud, apex, (1, 1), 0.05)
    xyz[small] = np.nan
    top = _ball_pixels(cloud, apex, (3, 5), 0.16)
    xyz[top] = np.nan
    a, b = apex[4, 2], apex[4, 3]
    x, y = np.nan_to_num(cloud.x), np.nan_to_num(cloud.y)
    t = np.clip(((x - a[0]) * (b[0] - a[0]) + (y - a[1]) * (b[1] - a[1]))
                / np.sum((b[:2] - a[:2]) ** 2), 0, 1)
    ridge = np.hypot(x - (a[0] + t * (b[0] - a[0])), y - (a[1] + t * (b[1] - a[1]))) < 0.05
    xyz[ridge, 2] = np.maximum(xyz[ridge, 2], a[2] - 0.1)
    return PointCloud.from_xyz(xyz, sigma_z=sig), present


@pytest.mark.parametrize("cap_model", ["psf", "free"])
def test_balls_seen_but_not_fitted_are_not_measured_not_missing(cap_model):
    cloud, present = _spoiled_cloud()
    m = measure_bga(cloud, NOM, options=BGAOptions(cap_model=cap_model))
    nm = dict(m.not_measured)
    assert nm == {(1, 1): "region_too_small", (3, 5): "too_few_points",
                  (4, 2): "region_too_large", (4, 3): "region_too_large"}
    assert set(m.missing) == TRUE_MISSING
    for ij in nm:
        assert not m.found[ij]
    # every other present ball is measured
    expect = present.copy()
    for ij in nm:
        expect[ij] = False
    assert np.array_equal(m.found, expect)
    assert all(r in NOT_MEASURED_REASONS for r in nm.values())


def test_positions_outside_the_view_are_not_in_view():
    """The nominal grid is 6 x 7 but the cloud ends before the last column of balls (the
    populated map places the balls seen on the grid)."""
    cloud, present, offs, apex = bga_cloud()
    x = np.nan_to_num(cloud.x, nan=np.inf)
    cut = x < float(np.min(apex[:, 6, 0])) - 0.4  # half a pitch before the last column
    xyz = np.where(cut[..., None], cloud.xyz, np.nan)
    nom = BGANominal(rows=6, cols=7, pitch_mm=0.8, ball_diameter_mm=0.45, present=present)
    m = measure_bga(PointCloud.from_xyz(xyz, sigma_z=np.array(cloud.sigma_z)), nom)
    assert dict(m.not_measured) == {(i, 6): "not_in_view" for i in range(6)}
    assert m.missing == ()  # the two absent balls are not populated in this map
    assert m.n_balls == present[:, :6].sum()


def test_exports_show_not_measured_and_missing(tmp_path):
    cloud, _ = _spoiled_cloud()
    m = measure_bga(cloud, NOM)
    with open(write_bga_csv(tmp_path / "b.csv", m), newline="") as f:
        rows = list(csv.DictReader(f))
    status = {(int(r["row"]), int(r["col"])): (r["status"], r["reason"]) for r in rows}
    for ij, why in m.not_measured:
        assert status[ij] == ("not_measured", why)
    for ij in TRUE_MISSING:
        assert status[ij] == ("missing", "")
    assert sum(s == "ok" for s, _ in status.values()) == m.n_balls
    noise = {(int(r["row"]), int(r["col"])): float(r["sigma_height_noise_mm"]) for r in rows
             if r["status"] == "ok"}
    for k, ij in enumerate(map(tuple, m.index)):
        assert abs(noise[ij] - m.sigma_height_noise[k]) < 5e-7  # printed to 1e-6 mm
    js = json.loads(write_json(tmp_path / "b.json", bga_summary(m)).read_text())
    sc = m.coplanarity.sigma
    assert js["sigma_coplanarity_mm"] == (pytest.approx(sc) if np.isfinite(sc) else None)
    assert js["coplanarity_alternatives_mm"][0] == pytest.approx(m.coplanarity.value)
    assert js["package_rocks"] == m.coplanarity.rocks
    assert len(js["balls"]["sigma_height_noise_mm"]) == m.n_balls
    assert js["balls_not_measured"] == 4
    assert {tuple(d["index"]): d["reason"] for d in js["not_measured"]} == dict(m.not_measured)
    assert sorted(map(tuple, js["missing"])) == sorted(TRUE_MISSING)
    labels = [t.get_text() for t in _bga_map_figure(m).axes[0].get_legend().get_texts()]
    assert "not measured (4)" in labels and "missing (2)" in labels


def test_failed_point_spread_solve_warns_and_gives_nan(monkeypatch):
    cloud, present, offs, apex = bga_cloud(psf_s2=4e-4, seed=4)

    def singular(fits, npar):
        return np.zeros((npar, npar)), np.zeros(npar), 0.0, 0

    monkeypatch.setattr(psf, "_reduced_system", singular)
    with pytest.warns(PSFSolveWarning, match="could not be estimated"):
        m = measure_bga(cloud, NOM)
    assert np.isnan(m.psf_variance) and np.isnan(m.sigma_psf_variance)
    # the caps are still fitted (without the correction), every present ball measured
    assert np.array_equal(m.found, present) and np.all(np.isfinite(m.height))
    assert m.psf_balls == 10 and m.psf_converged is False


def test_point_spread_solve_reports_its_convergence(monkeypatch):
    cloud, present, offs, apex = bga_cloud(psf_s2=4e-4, seed=4)
    m = measure_bga(cloud, NOM)
    assert m.psf_converged is True and m.psf_balls == 10  # every 4th of the 40 balls
    real = psf._fit_caps_smoothed

    def one_round(*args, **kw):
        return real(*args, **{**kw, "rounds": 1})

    monkeypatch.setattr("telefringe.metrology.bga.measure._fit_caps_smoothed", one_round)
    with pytest.warns(psf.PSFConvergenceWarning, match="did not converge in 1 round"):
        m1 = measure_bga(cloud, NOM)
    assert m1.psf_converged is False and np.isfinite(m1.psf_variance)
    js = bga_summary(m1)
    assert js["psf_converged"] is False and js["psf_balls"] == 10


def test_options_are_explicit_and_validated():
    cloud, *_ = bga_cloud()
    with pytest.raises(MetrologyError, match="cap_model"):
        BGAOptions(cap_model="spline")
    with pytest.raises(MetrologyError, match="always weights"):
        BGAOptions(weighted=False)
    with pytest.raises(MetrologyError, match="max_view_angle_deg"):
        BGAOptions(max_view_angle_deg=0)
    with pytest.raises(MetrologyError, match="edge_px"):
        BGAOptions(edge_px=-1)
    assert BGAOptions().view_angle_deg == 60.0
    assert BGAOptions(cap_model="free").view_angle_deg is None
    assert BGAOptions(max_view_angle_deg=None).view_angle_deg is None
    with pytest.raises(MetrologyError, match="projector"):
        measure_bga(cloud, NOM, projector=object(), options=BGAOptions(cap_model="free"))
    with pytest.raises(MetrologyError, match="projector"):
        measure_bga(cloud, NOM, projector=object())  # no image: the term is not used
    with pytest.raises(MetrologyError, match="highlight_px"):
        measure_bga(cloud, NOM, options=BGAOptions(highlight_px=2.0))


def test_callers_arrays_are_neither_changed_nor_made_read_only():
    cloud, present, offs, apex = bga_cloud(sigma=0.004, seed=3)
    img = np.full(cloud.shape, 10.0) + np.random.default_rng(0).normal(0, 0.5, cloud.shape)
    img_before = img.copy()
    pres = present.copy()
    nom = BGANominal(rows=6, cols=7, pitch_mm=0.8, ball_diameter_mm=0.45, present=pres)
    m = measure_bga(cloud, nom, image=img)
    assert img.flags.writeable and np.array_equal(img, img_before)
    assert pres.flags.writeable and not nom.present.flags.writeable
    assert not m.height.flags.writeable and not m.found.flags.writeable
    c = np.array([1.0, 2.0, 3.0])
    cov = np.eye(4)
    inl = np.ones(5, dtype=bool)
    f = SphereFit(c, 1.0, 0.0, 0.0, 5, 5, inl, cov)
    assert c.flags.writeable and cov.flags.writeable and inl.flags.writeable
    assert not f.centre.flags.writeable
    c[0] = 9.0  # the result keeps its own copy
    assert f.centre[0] == 1.0
