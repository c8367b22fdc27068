"""Shared test helpers."""

import numpy as np
import pytest

from telefringe.fringes.phase import NoiseModel


def _rig_noise(vrig) -> NoiseModel:
    """The virtual rig's camera noise in DN (8 bit): shot noise of ``full_well_e`` electrons
    at 255 DN and read noise (quantisation is added by the decoder's noise model)."""
    ph = vrig.photometry
    return NoiseModel(read_noise=ph.read_noise_e * 255 / ph.full_well_e,
                      gain=255 / ph.full_well_e)


@pytest.fixture(scope="session")
def rig_noise():
    """``rig_noise(vrig) -> NoiseModel``: the camera noise of a virtual rig, in DN."""
    return _rig_noise


def _jacobian_error(problem, x, rel_step: float = 1e-6) -> float:
    """Largest error of ``problem.jacobian(x)`` against central differences of
    ``problem.residuals`` (step ``rel_step`` of each parameter, at least of 1e-3), relative
    to each column's largest entry."""
    J = problem.jacobian(x).toarray()
    num = np.empty_like(J)
    for j in range(x.size):
        h = rel_step * max(abs(x[j]), 1e-3)
        xp, xm = x.copy(), x.copy()
        xp[j] += h
        xm[j] -= h
        num[:, j] = (problem.residuals(xp) - problem.residuals(xm)) / (2 * h)
    scale = np.maximum(np.abs(num).max(axis=0), 1e-12)
    return float(np.max(np.abs(J - num) / scale))


@pytest.fixture(scope="session")
def jacobian_error():
    """``jacobian_error(problem, x, rel_step=1e-6) -> float``: a bundle problem's analytic
    Jacobian against finite differences (relative to each column's scale)."""
    return _jacobian_error
