"""Two-camera stereo (reconstruction/stereo.py): a synthetic pair (render-free: a plane seen
by both cameras, each pixel's projector coordinates from the projector model), for two
pinhole and two telecentric cameras; sigma against Monte Carlo; flags."""

from __future__ import annotations

import numpy as np
import pytest
from anyrig_rigs import Coords, rig_of, stereo_rig_of, stereo_truth

from telefringe.reconstruction.cloud import (
    FLAG_INCONSISTENT,
    FLAG_NO_PHASE,
    FLAG_OUTSIDE,
    TriangulationError,
)
from telefringe.reconstruction.heightmap import height_map
from telefringe.reconstruction.stereo import match_stereo, triangulate_stereo

# The match interpolates the second camera's phase map bilinearly: on this plane (a
# smooth projective map over 64 px) that leaves 1.0e-5 mm (pinhole pair) and 1.5e-5 mm
# (telecentric pair) at worst; the bounds are twice that, and 400 times below the
# points' sigma_z at 0.05 px of phase noise.
BOUND = {"pp": 2.5e-5, "tt": 3.0e-5}


@pytest.mark.parametrize("kind", ["pp", "tt"])
@pytest.mark.parametrize("axes", ["u", "uv"])
def test_synthetic_pair(kind, axes):
    rig = stereo_rig_of(kind)
    X1, (u1, v1), (u2, v2) = stereo_truth(rig)
    uv = axes == "uv"
    m = match_stereo(rig, Coords(u1, v1 if uv else None), Coords(u2, v2 if uv else None))
    cl = m.cloud
    # every pixel is either matched or seen outside the second camera's view
    assert cl.count > 0.8 * u1.size
    assert np.all((cl.flags == 0) | (cl.flags == FLAG_OUTSIDE))
    err = np.linalg.norm(cl.xyz - X1, axis=-1)
    assert np.nanmax(err) < BOUND[kind]
    # the matched sub-pixel of the second camera sees the same point
    cam2 = rig.cameras["camera_2"]
    pu, pv = cam2.project(X1)
    good = cl.mask
    assert np.max(np.hypot(m.u2[good] - pu[good], m.v2[good] - pv[good])) < 1e-3
    # OUTSIDE only where the point is out of the second camera's image
    h, w = u2.shape
    out = (cl.flags == FLAG_OUTSIDE)
    near_edge = (pu < 0.5) | (pu > w - 1.5) | (pv < 0.5) | (pv > h - 1.5)
    assert np.all(near_edge[out])
    if uv:
        assert np.nanmax(cl.residual[good]) < 1e-3
    else:
        assert cl.residual is None
    # the cloud's lines are the first camera's: per pixel for a pinhole one
    assert cl.directions.shape == ((3,) if kind == "tt" else u1.shape + (3,))
    hm = height_map(cl)
    assert np.isfinite(hm.z).sum() > 0.5 * u1.size


@pytest.mark.parametrize("kind", ["pp", "tt"])
def test_sigma_matches_monte_carlo(kind):
    """sigma_z within 10 % of the spread of Monte Carlo matches (independent noise on
    both cameras' u_p and v_p maps)."""
    shape = (16, 24)
    rig = stereo_rig_of(kind, shape)
    _, (u1, v1), (u2, v2) = stereo_truth(rig, shape)
    rng = np.random.default_rng(8)
    su, sv = 0.05, 0.1
    n_mc = 120
    for uv in (False, True):
        zs, sig = [], []
        for _ in range(n_mc):
            c1 = Coords(u1 + rng.normal(0, su, shape),
                        v1 + rng.normal(0, sv, shape) if uv else None, None,
                        np.full(shape, su), np.full(shape, sv))
            c2 = Coords(u2 + rng.normal(0, su, shape),
                        v2 + rng.normal(0, sv, shape) if uv else None, None,
                        np.full(shape, su), np.full(shape, sv))
            cl = triangulate_stereo(rig, c1, c2, max_residual=None)
            zs.append(cl.z)
            sig.append(cl.sigma_z)
        zs = np.array(zs)
        sig = np.array(sig)
        keep = np.all(np.isfinite(zs), axis=0)
        assert keep.sum() > 0.6 * u1.size
        mc = zs[:, keep].std(axis=0, ddof=1)
        pred = np.nanmean(sig[:, keep], axis=0)
        # per pixel a std of 120 samples scatters by 6.5 %: the mean of the squared ratio
        # over ~300 pixels by well under 1 %
        ratio = np.sqrt(np.mean((mc / pred) ** 2))
        assert abs(ratio - 1.0) < 0.10, (uv, ratio)


def test_flags_and_errors():
    rig = stereo_rig_of("pp")
    X1, (u1, v1), (u2, v2) = stereo_truth(rig)
    u1 = u1.copy()
    v2 = v2.copy()
    mask1 = np.ones(u1.shape, dtype=bool)
    mask1[0, :3] = False
    u1[1, 5] = np.nan
    u2 = u2.copy()
    u2[:, :] = np.where(np.arange(u2.shape[1]) < 20, np.nan, u2)  # a hole in camera 2
    v2 += 5.0  # the second camera's v_p off by 5 px: inconsistent everywhere
    cl = triangulate_stereo(rig, Coords(u1, v1, mask1), Coords(u2, v2), use_v_p=False)
    assert np.all(cl.flags[0, :3] == FLAG_NO_PHASE)
    assert cl.flags[1, 5] == FLAG_NO_PHASE
    assert np.all(cl.flags[cl.flags != FLAG_NO_PHASE] & (FLAG_INCONSISTENT | FLAG_OUTSIDE))
    assert cl.count == 0
    # without the check, the points are where they were
    cl = triangulate_stereo(rig, Coords(u1, v1, mask1), Coords(u2, v2), use_v_p=False,
                            max_residual=None)
    assert cl.count > 0.3 * u1.size
    assert np.nanmax(np.linalg.norm(cl.xyz - X1, axis=-1)) < BOUND["pp"]
    with pytest.raises(TriangulationError, match="two cameras"):
        triangulate_stereo(rig_of("pp"), Coords(u1), Coords(u2))
    with pytest.raises(TriangulationError, match="share no projector axis"):
        triangulate_stereo(rig, Coords(u1), Coords(None, v2))
    with pytest.raises(TriangulationError, match="expected"):
        triangulate_stereo(rig, Coords(u1[:10]), Coords(u2))
