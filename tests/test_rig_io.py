"""rig.json: round trip, validation of broken files, atomic no-clobber writing."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_calibrate import (
    CAM_PIX,
    CAM_SIZE,
    PROJ_PIX,
    PROJ_SIZE,
    grid_points,
    observe,
    paper_like_rig,
    side_of,
    target_poses,
)

from telefringe.calibration.rig import calibrate_rig
from telefringe.io.errors import InputError
from telefringe.io.rig_json import RIG_FORMAT, load_rig, rig_from_json, rig_to_json, save_rig


@pytest.fixture(scope="module")
def calib():
    rng = np.random.default_rng(8)
    rig = paper_like_rig()
    P = grid_points(5, 6, pitch=5.0)
    Rs, Ts = target_poses(6, rng, tilt_deg=15.0, centre=(12.5, 10.0, 0.0))
    cam, proj = observe(rig, P, Rs, Ts, rng)
    cam[2, 3] = np.nan  # a marker not seen
    cam[4, 7] += (0.5, 0.5)  # an outlier
    return calibrate_rig(P, cam, proj, camera_pixel_size=CAM_PIX, projector_pixel_size=PROJ_PIX,
                         camera_size=CAM_SIZE, projector_size=PROJ_SIZE, grid_shape=(5, 6),
                         pose_names=[f"p{i}" for i in range(6)], projector_side=side_of(rig),
                         principal_point="fixed")


def test_round_trip(tmp_path, calib):
    path = save_rig(tmp_path / "rig.json", calib)
    back = load_rig(path)
    for dev in ("camera", "projector"):
        a, b = getattr(calib.rig, dev), getattr(back.rig, dev)
        assert a.intrinsics == b.intrinsics
        np.testing.assert_allclose(b.R_dev_world, a.R_dev_world, atol=1e-15)
        np.testing.assert_array_equal(b.t_dev, a.t_dev)
    for name in ("parameters", "covariance", "std", "residuals_camera", "residuals_projector",
                 "camera_observations", "projector_observations", "rms_per_pose", "used",
                 "t_world_target", "points_target"):
        np.testing.assert_array_equal(getattr(back, name), getattr(calib, name), err_msg=name)
    np.testing.assert_allclose(back.R_world_target, calib.R_world_target, atol=1e-15)
    for name in ("pose_names", "reference_pose", "grid_shape", "outliers", "warnings",
                 "mirror", "principal_point", "principal_point_weak", "rms_camera",
                 "rms_projector", "sigma_camera", "sigma_projector"):
        assert getattr(back, name) == getattr(calib, name), name
    assert any(o.marker == (1, 1) and o.pose == "p4" for o in back.outliers)
    assert np.isnan(back.covariance[1, 1])  # the fixed principal point
    # a RigCalibration stands for its Rig
    assert back.camera is back.rig.camera and back.projector is back.rig.projector
    doc = json.loads(path.read_text())
    assert doc["format"] == RIG_FORMAT and doc["version"] == 1


def test_no_clobber_without_force(tmp_path, calib):
    path = save_rig(tmp_path / "rig.json", calib)
    before = path.read_text()
    with pytest.raises(InputError, match="already exists"):
        save_rig(path, calib)
    assert path.read_text() == before
    save_rig(path, calib, force=True)
    assert [p.name for p in tmp_path.iterdir()] == ["rig.json"]


def test_devices_only(calib):
    doc = rig_to_json(calib)
    del doc["calibration"]
    back = rig_from_json(doc)
    assert back.rig.camera.intrinsics == calib.rig.camera.intrinsics
    assert back.pose_names == () and np.isnan(back.rms_camera)


@pytest.mark.parametrize("edit, key", [
    (lambda d: d.update(version=2), "version"),
    (lambda d: d.update(format="other"), "format"),
    (lambda d: d["camera"].pop("m"), "camera.m"),
    (lambda d: d["camera"].update(m=float("nan")), "camera.m"),
    (lambda d: d["projector"].update(m=-1.0), "projector.m"),
    (lambda d: d["projector"]["distortion"].update(k1="x"), "projector.distortion.k1"),
    (lambda d: d["camera"].update(rotation_vector=[0, 1]), "camera.rotation_vector"),
    (lambda d: d["camera"].update(width=0), "camera.width"),
    (lambda d: d["camera"].update(pixel_size_mm=[0.005, float("inf")]),
     "camera.pixel_size_mm[1]"),
    (lambda d: d.pop("world_frame"), "world_frame"),
    (lambda d: d["calibration"]["parameters"]["covariance"].pop(), "covariance"),
    (lambda d: d["calibration"]["parameters"]["values"].__setitem__(0, float("nan")), "values"),
    (lambda d: d["calibration"]["poses"][1].update(used="yes"), "poses[1].used"),
    (lambda d: d["calibration"]["observations"].pop("camera"), "observations.camera"),
    (lambda d: d["calibration"].update(grid_shape=[4, 6]), "grid_shape"),
    (lambda d: d["world_frame"].update(reference_pose="nope"), "reference_pose"),
])
def test_broken_files_name_the_key(tmp_path, calib, edit, key):
    doc = copy.deepcopy(rig_to_json(calib))
    edit(doc)
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(doc))  # NaN / Infinity written as JSON constants
    with pytest.raises(InputError) as exc:
        load_rig(path)
    msg = str(exc.value)
    assert str(path) in msg and key in msg


def test_unreadable_files(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_rig(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{ not json")
    with pytest.raises(InputError, match="malformed JSON"):
        load_rig(bad)
    with pytest.raises(InputError, match="folder"):
        load_rig(tmp_path)


def _leaves(doc, path=()):
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _leaves(v, path + (k,))
    elif isinstance(doc, list) and doc and not isinstance(doc[0], list | dict):
        yield path
    elif isinstance(doc, list):
        for i, v in enumerate(doc[:3]):
            yield from _leaves(v, path + (i,))
    else:
        yield path


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_any_corruption_is_refused_cleanly(calib, data):
    """Replace any leaf with a hostile value: the loader returns a rig or raises
    InputError, nothing else."""
    doc = copy.deepcopy(rig_to_json(calib))
    paths = list(_leaves(doc))
    path = data.draw(st.sampled_from(paths))
    value = data.draw(st.sampled_from([None, float("nan"), float("inf"), -1, 0, "x", [], {},
                                       True, [1.0], 1e308]))
    node = doc
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value
    try:
        out = rig_from_json(json.loads(json.dumps(doc), parse_constant=lambda s: float("nan")))
    except InputError:
        return
    assert np.all(np.isfinite(out.rig.camera.R_dev_world))
