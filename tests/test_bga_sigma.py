"""The BGA apex-height uncertainty against the truth: normalised errors pooled over seeds,
tested with a two-sided band from their sampling error (independent pixel noise).

Here sigma_height holds (pooled RMS 0.96-1.09 for the cap models). On rendered scans
the normalised apex error against the truth is 1.37 (test_reconstruct_virtual, paper
rig) to 1.5-1.7 (the 160 px window of test_measure_bga_cli, 36 whole balls), yet the
scatter of each ball's height over 4 noise seeds is 0.99 sigma_height there: sigma is a
right repeatability, and the rest is a per-ball error of the cap model that does not
change with the noise (0.94 um RMS over the balls). It needs a model term, not a larger
noise sigma; it is not in sigma_height, so it is not tested here."""

from __future__ import annotations

import numpy as np
import pytest
from test_metrology import bga_cloud

from telefringe.metrology import BGANominal, BGAOptions, measure_bga

NOM = BGANominal(rows=6, cols=7, pitch_mm=0.8, ball_diameter_mm=0.45)
SEEDS = range(10, 16)  # 6 clouds x 40 balls = 240 normalised errors


def _pooled_z(make, options):
    z = []
    for seed in SEEDS:
        cloud, present, offs = make(seed)
        m = measure_bga(cloud, NOM, options=options)
        assert np.array_equal(m.found, present)
        z.append((m.height - (0.35 + offs)[present]) / m.sigma_height)
    return np.concatenate(z), m


def _independent(seed):
    cloud, present, offs, _ = bga_cloud(seed=seed)
    return cloud, present, offs


@pytest.mark.parametrize(("cap_model", "weighted", "model_term"), [
    ("psf", None, 0.0),
    ("fixed", True, 0.0),
    # the unweighted free fit takes the radial noise (sigma_z cos(tilt)) as uniform:
    # its covariance is slightly low for the apex, which the untilted top points
    # decide (measured 1.086 over these seeds)
    ("free", False, 0.1),
])
def test_apex_sigma_matches_the_scatter(cap_model, weighted, model_term):
    z, m = _pooled_z(_independent, BGAOptions(cap_model=cap_model, weighted=weighted))
    rms = float(np.sqrt(np.mean(z**2)))
    # 4 standard errors of an RMS of n standard normal values: 4 / sqrt(2 n)
    assert abs(rms - 1.0) < 4 / np.sqrt(2 * z.size) + model_term, rms
