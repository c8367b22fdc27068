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


def _camera_scan(u_p, v_p, *, width=800, height=600, periods=(1, 8, 64)):
    """A render-free scan: each camera pixel shows the fringes at its projector pixel
    (u_p, v_p), 8 bit, with a dark level and contrast a real camera would have."""
    from telefringe.fringes.patterns import fringe_intensity, pattern_groups
    from telefringe.fringes.scan import Scan, ScanManifest

    groups = pattern_groups(steps=4, periods=periods, axes=("u", "v"))
    stacks = []
    for g in groups:
        x, length = (u_p, width) if g.axis == "u" else (v_p, height)
        imgs = [20.0 + 200.0 * fringe_intensity(x, periods=g.periods, steps=g.steps, k=k,
                                                length=length) for k in range(g.steps)]
        stacks.append(np.round(np.nan_to_num(np.array(imgs), nan=20.0)).astype(np.uint8))
    man = ScanManifest(projector_width=width, projector_height=height, groups=groups)
    return Scan(manifest=man, stacks=tuple(stacks), max_value=255.0)


def test_cli_two_cameras(tmp_path):
    """telefringe reconstruct LEFT --second RIGHT --rig rig.json (v2, two pinhole cameras)
    writes the usual outputs on the first camera's grid; a rig that does not fit the scans
    and a one-camera rig are refused in one line, exit 2, nothing written."""
    import json

    from telefringe.cli import main
    from telefringe.io.points_npz import load_points
    from telefringe.io.rig_json import bare_rig_json
    from telefringe.io.scan_json import write_scan

    rig = stereo_rig_of("pp")
    X1, (u1, v1), (u2, v2) = stereo_truth(rig)
    write_scan(tmp_path / "left", _camera_scan(u1, v1))
    write_scan(tmp_path / "right", _camera_scan(u2, v2))
    (tmp_path / "rig.json").write_text(json.dumps(bare_rig_json(rig)))
    out = tmp_path / "out"
    code = main(["reconstruct", str(tmp_path / "left"), "--second", str(tmp_path / "right"),
                 "--rig", str(tmp_path / "rig.json"), "-o", str(out), "--no-gamma-correction"])
    assert code == 0
    names = {p.name for p in out.iterdir()}
    assert {"points.npz", "cloud.ply", "heightmap.tif", "summary.json"} <= names
    cloud = load_points(out / "points.npz").cloud
    xyz = cloud.xyz
    assert xyz.shape == u1.shape + (3,)
    err = np.linalg.norm(xyz - X1, axis=-1)
    good = np.isfinite(err)
    assert good.sum() > 0.7 * u1.size
    # 8-bit fringes of 64 periods on 800 px: the decoded u_p scatters (quantisation), which
    # sigma_z carries (median 1.3 um here); every point lies within 3 of its sigma_z of the
    # truth (measured: 0.66 at worst, median error 0.22 um)
    sz = cloud.sigma_z
    assert np.all(err[good] < 3 * sz[good])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["second_scan"].endswith("right")
    # a rig whose second camera is another size: one line, exit 2, nothing written
    from dataclasses import replace

    from telefringe.devices.rig import Rig

    c2 = rig.cameras["camera_2"]
    small = type(c2)(replace(c2.intrinsics, width=32, height=24), c2.R_dev_world, c2.t_dev)
    bad = Rig(cameras={"camera": rig.camera, "camera_2": small}, projector=rig.projector)
    (tmp_path / "bad.json").write_text(json.dumps(bare_rig_json(bad)))
    for rj in ("bad.json",):
        code = main(["reconstruct", str(tmp_path / "left"), "--second",
                     str(tmp_path / "right"), "--rig", str(tmp_path / rj), "-o",
                     str(tmp_path / "no")])
        assert code == 2 and not (tmp_path / "no").exists()
    code = main(["reconstruct", str(tmp_path / "left"), "--rig", str(tmp_path / "rig.json"),
                 "-o", str(tmp_path / "no"), "--search-mm", "5"])
    assert code == 2 and not (tmp_path / "no").exists()
    one = Rig(rig.camera, rig.projector)
    (tmp_path / "one.json").write_text(json.dumps(bare_rig_json(one)))
    code = main(["reconstruct", str(tmp_path / "left"), "--second", str(tmp_path / "right"),
                 "--rig", str(tmp_path / "one.json"), "-o", str(tmp_path / "no")])
    assert code == 2 and not (tmp_path / "no").exists()


def test_occlusion_edge_is_flagged_not_matched():
    """A step of 1.5 mm seen by two pinhole cameras: where the second camera's cell holds
    both sides of an occlusion edge, its interpolated phase belongs to no surface; those
    matches are flagged inconsistent, and every point kept lies on the step."""
    from anyrig_rigs import step_hits

    rig = stereo_rig_of("pp")
    cams = list(rig.cameras.values())
    X1 = step_hits(cams[0], u_shape := (48, 64))
    X2 = step_hits(cams[1], u_shape)
    u1, v1 = rig.projector.project(X1)
    u2, v2 = rig.projector.project(X2)
    cl = triangulate_stereo(rig, Coords(u1), Coords(u2))
    err = np.linalg.norm(cl.xyz - X1, axis=-1)
    assert cl.count > 0.6 * u1.size
    # the bilinear interpolation on either side of the edge: as on the plane
    assert np.nanmax(err) < 1e-4, np.nanmax(err)
    assert np.count_nonzero(cl.flags & FLAG_INCONSISTENT) > 0
