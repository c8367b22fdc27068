"""The gamma fit's non-convergence is no longer silent (fringes/nonlinearity.py): a
RuntimeWarning and a line in :attr:`PhaseErrorFit.warnings`."""

import warnings

import numpy as np
import pytest

from telefringe.fringes.nonlinearity import fit_phase_errors
from telefringe.fringes.phase import wrapped_phase


def _tiny_ladder(seed, width, n=3000, sigma=0.01):
    """Measured phases of the 1, 8, 64 ladder (4 steps, gamma 2.2) on a tiny plane: the
    projector x within ``width`` of its range (the 1-period phase covers 2 of 36 bins)."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.4, 0.4 + width, n)
    out = []
    for p in (1, 8, 64):
        phi = 2 * np.pi * p * x
        d = 2 * np.pi * np.arange(4)[:, None] / 4
        imgs = (0.5 + 0.5 * np.cos(phi[None] + d)) ** 2.2 + rng.normal(0, sigma, (4, n))
        out.append(wrapped_phase(imgs, steps=4).phase)
    return out


def test_a_fit_that_does_not_converge_warns():
    """On this tiny plane Gauss-Newton contracts slowly (0.7-1 per step; its 5 steps ended
    0.49 standard errors short, which used to pass silently, then warned); it now goes on
    with Newton's method and converges within its steps. Held to one step
    (``iterations=0``), the fit has not converged (the step moved a coefficient by 2.9
    standard errors): it says so."""
    ph = _tiny_ladder(2, 0.02)
    with pytest.warns(RuntimeWarning, match=r"without meeting a convergence test") as rec:
        fit = fit_phase_errors(ph, [1, 8, 64], steps=[4, 4, 4], iterations=0)
    notes = [w for w in fit.warnings if w.endswith("(not converged)")]
    assert notes and "Gauss-Newton took its 1 steps" in notes[-1], fit.warnings
    # the warning is about the fit that gave the result (the last refit), not the earlier
    # passes it started from (those stay in ``warnings``)
    (msg,) = [str(r.message) for r in rec if r.category is RuntimeWarning]
    assert msg.count("Gauss-Newton took") == 1 and msg.endswith(notes[-1]), msg
    # with the default steps (and with more) the result's fit converges: no warning (an
    # earlier pass's note may stay in ``warnings``), the same harmonics
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        default = fit_phase_errors(ph, [1, 8, 64], steps=[4, 4, 4])
        more = fit_phase_errors(ph, [1, 8, 64], steps=[4, 4, 4], iterations=12)
    assert [m.harmonics for m in more.models] == [m.harmonics for m in default.models]
    assert more.models[2].harmonics == fit.models[2].harmonics


def test_a_converged_fit_on_the_same_tiny_plane_is_silent():
    """Other noise on the same tiny plane: the result's fit converges within its steps,
    no warning (the finest group's gamma harmonic 4 is learned)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit = fit_phase_errors(_tiny_ladder(0, 0.02), [1, 8, 64], steps=[4, 4, 4])
    assert 4 in fit.models[2].harmonics
