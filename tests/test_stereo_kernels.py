"""The compiled stereo matcher (reconstruction/_stereo_kernels.py) against the NumPy
reference of reconstruction/stereo.py: the same flags pixel for pixel, and the same points,
sigmas, residuals and matched sub-pixels to the iterations' tolerance, on render-free
pairs that exercise every branch (noise, holes in either camera, a mask, an occlusion
step, one or both axes, no sigmas, sigma_z and residual limits; pinhole and telecentric)."""

from __future__ import annotations

import numpy as np
import pytest
from anyrig_rigs import Coords, step_hits, stereo_rig_of, stereo_truth

from telefringe.reconstruction.cloud import FLAG_INCONSISTENT, FLAG_OUTSIDE, TriangulationError
from telefringe.reconstruction.stereo import match_stereo

# Both paths run the same iterations; per pixel the compiled one stops its Gauss-Newton
# steps when that pixel converged (the reference when the whole chunk did), which moves a
# point by at most the 1e-12 relative step tolerance (measured: 1.1e-12 mm). The bounds
# are far above that and far below any sigma (um).
TOL_MM = 1e-9
TOL_PX = 1e-8


def _same(a, b):
    ca, cb = a.cloud, b.cloud
    np.testing.assert_array_equal(ca.flags, cb.flags)
    np.testing.assert_array_equal(ca.mask, cb.mask)
    np.testing.assert_allclose(cb.xyz, ca.xyz, rtol=0, atol=TOL_MM, equal_nan=True)
    np.testing.assert_allclose(cb.sigma_line, ca.sigma_line, rtol=1e-9, equal_nan=True)
    assert (ca.residual is None) == (cb.residual is None)
    if ca.residual is not None:
        np.testing.assert_allclose(cb.residual, ca.residual, rtol=0, atol=TOL_PX,
                                   equal_nan=True)
    np.testing.assert_allclose(b.u2, a.u2, rtol=0, atol=TOL_PX, equal_nan=True)
    np.testing.assert_allclose(b.v2, a.v2, rtol=0, atol=TOL_PX, equal_nan=True)
    np.testing.assert_array_equal(np.asarray(ca.directions).shape,
                                  np.asarray(cb.directions).shape)


def _both(rig, c1, c2, **kw):
    a = match_stereo(rig, c1, c2, engine="numpy", **kw)
    b = match_stereo(rig, c1, c2, engine="compiled", **kw)
    _same(a, b)
    return a, b


@pytest.mark.parametrize("kind", ["pp", "tt"])
def test_compiled_matches_reference(kind):
    rig = stereo_rig_of(kind)
    _, (u1, v1), (u2, v2) = stereo_truth(rig)
    sh = u1.shape
    rng = np.random.default_rng(3)
    s = np.full(sh, 0.05)
    n1 = Coords(u1 + rng.normal(0, 0.05, sh), v1 + rng.normal(0, 0.05, sh), None, s, 2 * s)
    u2h = u2 + rng.normal(0, 0.05, sh)
    u2h[10:20, 30:36] = np.nan  # a hole in the second camera: crossings at its edges
    n2 = Coords(u2h, v2 + rng.normal(0, 0.05, sh), None, s, 2 * s)
    mask = np.ones(sh, dtype=bool)
    mask[5, :7] = False
    n1m = Coords(n1.u_p, n1.v_p, mask, s, 2 * s)
    a, _ = _both(rig, n1m, n2)  # both axes, combined
    assert a.cloud.count > 0.6 * u1.size
    assert np.any(a.cloud.flags == FLAG_OUTSIDE)
    a, _ = _both(rig, n1, n2, use_v_p=False, max_residual=0.2)  # v_p checks only
    assert np.any(a.cloud.flags & FLAG_INCONSISTENT)
    _both(rig, Coords(n1.u_p), Coords(n2.u_p))  # one axis, no sigmas
    _both(rig, Coords(None, n1.v_p, None, None, s), Coords(None, n2.v_p, None, None, s))
    a, _ = _both(rig, n1, n2, max_sigma_z=np.nanmedian(a.cloud.sigma_z), search_mm=30.0)
    assert a.cloud.count > 0


def test_compiled_matches_reference_at_occlusions():
    """A step of 1.5 mm: cells of the second camera across its occlusion edge."""
    rig = stereo_rig_of("pp")
    cams = list(rig.cameras.values())
    sh = (48, 64)
    X1 = step_hits(cams[0], sh)
    X2 = step_hits(cams[1], sh)
    u1, v1 = rig.projector.project(X1)
    u2, v2 = rig.projector.project(X2)
    a, _ = _both(rig, Coords(u1, v1), Coords(u2, v2))
    assert np.any(a.cloud.flags & FLAG_INCONSISTENT)
    assert a.cloud.count > 0.5 * u1.size


def test_engine_argument():
    rig = stereo_rig_of("pp")
    _, (u1, _), (u2, _) = stereo_truth(rig)
    with pytest.raises(TriangulationError, match="engine"):
        match_stereo(rig, Coords(u1), Coords(u2), engine="fast")
