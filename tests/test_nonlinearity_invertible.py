"""``PhaseErrorModel.invertible`` is a proof, not a sample: a model it passes can be
inverted everywhere (the decoder's table never fails), a model that dips below a monotonic
mapping between sample points is refused."""

from __future__ import annotations

import numpy as np

from telefringe.fringes.nonlinearity import PhaseErrorModel

#: Learned by the decoder from the tilted plane of a tiny acceptance scan (6 % of the
#: circle covered): the old 64-samples-per-period check passed it, and its inversion then
#: raised "phase error model is not invertible" inside `telefringe accept`.
_LEARNED_ON_A_TINY_PLANE = PhaseErrorModel(
    1, (4, 12, 20, 24), np.array([-0.00131648, 0.00358584, -0.00644912, 0.00519531]),
    np.array([-0.06604705, -0.01836919, -0.03520623, 0.01680904]))


def _fine_min(model, n=2 ** 21):
    return float(np.min(1.0 + model.slope(np.linspace(-np.pi, np.pi, n, endpoint=False))))


def test_a_model_that_dips_between_samples_is_not_invertible():
    m = _LEARNED_ON_A_TINY_PLANE
    grid = np.linspace(-np.pi, np.pi, 64 * max(m.harmonics), endpoint=False)
    assert np.min(1.0 + m.slope(grid)) > 0  # what the sampled check saw
    assert _fine_min(m) < 0  # what is there
    assert not m.invertible


def test_invertible_models_invert_everywhere_and_the_rest_are_not_monotonic():
    rng = np.random.default_rng(7)
    seen = {True: 0, False: 0}
    for _ in range(60):
        harm = tuple(sorted(rng.choice(np.arange(1, 13), size=3, replace=False).tolist()))
        a, b = rng.normal(size=3), rng.normal(size=3)
        # scale so that the slope's amplitude bound sits near 1: both outcomes occur
        scale = rng.uniform(0.6, 1.6) / np.sum(np.array(harm) * np.hypot(a, b))
        m = PhaseErrorModel(1, harm, a * scale, b * scale)
        ok = m.invertible
        seen[ok] += 1
        if ok:
            assert _fine_min(m, 2 ** 16) > 0
            g, err = m.correction_table(4096)  # raised on non-invertible models
            assert np.all(np.isfinite(g)) and np.isfinite(err)
        else:
            # refused only when not monotonic or too close to it to prove at 2^22 points
            assert _fine_min(m, 2 ** 18) < 1e-3
    assert seen[True] >= 10 and seen[False] >= 10
