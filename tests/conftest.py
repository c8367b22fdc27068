"""Shared test helpers."""

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
