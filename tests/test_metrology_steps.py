"""Step gauges: parallel levels fitted jointly."""

from __future__ import annotations

import numpy as np
import pytest
from test_metrology import camera_grid, cloud_from

from telefringe.metrology import MetrologyError, measure_steps


# --- steps ------------------------------------------------------------------------------
def test_step_heights():
    shape = (200, 300)
    x, y = camera_grid(shape, pixel=0.05, origin=(0.0, 10.0))
    level = np.clip((x // 3.0).astype(int), 0, 4)
    tops = np.array([0.0, 0.5, 1.0, 1.5, 2.0])
    tilt = 0.004 * x - 0.002 * y
    z = tops[level] + tilt
    sigma = 0.003
    cloud = cloud_from(x, y, z, sigma=sigma, seed=9)
    m = measure_steps(cloud)
    assert len(m.heights) == 5
    n_true = np.array([-0.004, 0.002, 1.0]) / np.linalg.norm([-0.004, 0.002, 1.0])
    true_h = tops * n_true[2]
    assert np.all(np.abs(m.heights - true_h) < 4 * m.sigma_heights + 1e-12)
    assert np.all(np.abs(m.step_heights - np.diff(true_h)) < 4 * m.sigma_steps)
    assert np.all(m.sigma_steps < 1e-3) and np.all(m.sigma_steps > 0)
    assert np.allclose(m.rms, sigma, rtol=0.2)
    assert np.allclose(m.normal, n_true, atol=1e-4)
    assert set(np.unique(m.labels)) == {-1, 0, 1, 2, 3, 4}
    flat = cloud_from(x, y, tilt, sigma=sigma)
    with pytest.raises(MetrologyError, match="no step"):
        measure_steps(flat)
