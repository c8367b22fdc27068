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
    assert doc["format"] == RIG_FORMAT and doc["version"] == 2


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
    (lambda d: d.update(version=3), "version"),
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


# --------------------------------------------------------------------------- version 2
def _pinhole(rng, *, size=(1280, 1024), rotvec=(0.0, 0.0, 0.0), t=(0.0, 0.0, 0.0)):
    from telefringe.devices.pinhole import PinholeDevice, PinholeIntrinsics
    from telefringe.geometry.so3 import rotation_from_rotvec

    k = PinholeIntrinsics(fx=1700 + 100 * rng.random(), fy=1700 + 100 * rng.random(),
                          cx=size[0] / 2 + rng.normal(), cy=size[1] / 2 + rng.normal(),
                          k1=-0.07, k2=-0.18, p1=2.3e-4, p2=5.5e-4, k3=1.8,
                          width=size[0], height=size[1])
    return PinholeDevice(k, rotation_from_rotvec(rotvec), np.asarray(t, dtype=float))


def _same_device(a, b):
    assert a.model == b.model and a.intrinsics == b.intrinsics
    np.testing.assert_allclose(b.R_dev_world, a.R_dev_world, atol=1e-15)
    np.testing.assert_array_equal(b.t_dev, a.t_dev)


def _as_v1(doc):
    """A version 1 document as telefringe wrote it before version 2 (telecentric devices
    without "model", lists [camera, projector] in the report)."""
    v1 = copy.deepcopy(doc)
    v1["version"] = 1
    del v1["cameras"], v1["models"]
    v1["model"] = "telecentric (in words)"
    for dev in ("camera", "projector"):
        del v1[dev]["model"]
    rep = v1["calibration"]
    rep["principal_point_weak"] = [rep["principal_point_weak"][d] for d in ("camera",
                                                                            "projector")]
    for p in rep["poses"]:
        p["rms_px"] = [p["rms_px"]["camera"], p["rms_px"]["projector"]]
    return v1


def test_version_1_files_still_load(calib):
    doc = rig_to_json(calib)
    back = rig_from_json(json.loads(json.dumps(_as_v1(doc))))
    for dev in ("camera", "projector"):
        _same_device(getattr(calib.rig, dev), getattr(back.rig, dev))
    for name in ("parameters", "covariance", "rms_per_pose", "residuals_projector"):
        np.testing.assert_array_equal(getattr(back, name), getattr(calib, name), err_msg=name)
    assert back.principal_point_weak == calib.principal_point_weak
    assert back.mirror == calib.mirror
    # a version 1 file cannot hold a pinhole device, and its report keeps its own layout
    bad = _as_v1(doc)
    bad["projector"]["model"] = "pinhole"
    with pytest.raises(InputError, match="projector.model.*needs version 2"):
        rig_from_json(bad)
    bad = _as_v1(doc)
    bad["calibration"]["poses"][0]["rms_px"] = {"camera": 0.1, "projector": 0.1}
    with pytest.raises(InputError, match=r"poses\[0\].rms_px"):
        rig_from_json(bad)


def test_pinhole_rig_round_trip_and_its_mirror(tmp_path):
    from telefringe.devices.rig import Rig
    from telefringe.io.rig_json import MIRROR_PINHOLE

    rng = np.random.default_rng(1)
    rig = Rig(_pinhole(rng), _pinhole(rng, size=(1920, 1080), rotvec=(0.01, 0.09, -0.004),
                                      t=(-108.2, -5.2, -15.7)))
    path = save_rig(tmp_path / "rig.json", rig, source={"imported_from": "x.yml"})
    doc = json.loads(path.read_text())
    assert doc["version"] == 2 and doc["camera"]["model"] == "pinhole"
    assert set(doc["camera"]) >= {"fx", "fy", "cx", "cy", "distortion", "t_mm"}
    assert len(doc["projector"]["t_mm"]) == 3 and doc["source"]["imported_from"] == "x.yml"
    assert "calibration" not in doc
    back = load_rig(path)
    _same_device(rig.camera, back.camera)
    _same_device(rig.projector, back.projector)
    assert back.mirror == MIRROR_PINHOLE
    assert back.parameter_names[0] == "camera.fx" and len(back.parameter_names) == 30
    np.testing.assert_array_equal(back.parameters[:9], rig.camera.to_params()[:9])


def test_two_cameras_of_any_models_without_projector(calib, tmp_path):
    from telefringe.devices.rig import Rig

    rng = np.random.default_rng(2)
    rig = Rig(cameras={"camera": calib.rig.camera,
                       "camera_2": _pinhole(rng, rotvec=(0.0, -0.2, 0.0), t=(90.0, 0, 5))},
              projector=None)
    back = load_rig(save_rig(tmp_path / "rig.json", rig))
    assert back.rig.camera_names == ("camera", "camera_2") and back.projector is None
    _same_device(rig.cameras["camera_2"], back.rig.cameras["camera_2"])
    _same_device(rig.camera, back.camera)
    assert back.mirror.startswith("none")
    # a single camera needs a projector
    doc = bare_doc = json.loads((tmp_path / "rig.json").read_text())
    del doc["camera_2"], doc["cameras"]
    with pytest.raises(InputError, match="'projector' is missing"):
        rig_from_json(bare_doc)


def test_mixed_rig_report_round_trip(calib):
    """A calibration report of a telecentric camera with a pinhole projector keeps every
    entry, with the parameter names of the devices."""
    import dataclasses

    from telefringe.devices.rig import Rig
    from telefringe.io.rig_json import rig_parameter_names_of

    rng = np.random.default_rng(3)
    rig = Rig(calib.rig.camera, _pinhole(rng, size=(800, 600), rotvec=(0.3, 0.0, 0.1),
                                          t=(1.0, 2.0, 150.0)))
    names = rig_parameter_names_of(rig)
    n = len(names)
    A = rng.normal(size=(n, n))
    cov = A @ A.T
    cov[2, :] = cov[:, 2] = np.nan  # a fixed parameter
    mixed = dataclasses.replace(calib, rig=rig, parameter_names=names,
                                parameters=np.concatenate([rig.camera.to_params(),
                                                           rig.projector.to_params()]),
                                covariance=cov, std=np.sqrt(np.diag(cov)),
                                mirror="none: a pinhole device fixes it")
    doc = json.loads(json.dumps(rig_to_json(mixed)))
    assert doc["calibration"]["parameters"]["names"][-15:] == [
        f"projector.{p}" for p in rig.projector.param_names]
    back = rig_from_json(doc)
    _same_device(rig.projector, back.projector)
    for name in ("parameters", "covariance", "std", "residuals_projector", "rms_per_pose",
                 "projector_observations"):
        np.testing.assert_array_equal(getattr(back, name), getattr(mixed, name), err_msg=name)
    assert back.parameter_names == names and back.mirror == mixed.mirror
    # names of the wrong model (telecentric names for the pinhole projector) are refused
    bad = copy.deepcopy(doc)
    bad["calibration"]["parameters"]["names"] = list(rig_to_json(calib)["calibration"][
        "parameters"]["names"]) + ["projector.x"] * 4
    with pytest.raises(InputError, match="projector's parameters must be"):
        rig_from_json(bad)


@pytest.mark.parametrize("edit, key", [
    (lambda d: d["projector"].update(model="fisheye"), "projector.model"),
    (lambda d: d["camera"].pop("model"), "camera.model"),
    (lambda d: d["projector"].pop("fx"), "projector.fx"),
    (lambda d: d["projector"].update(fy=0.0), "projector.fy"),
    (lambda d: d["projector"].update(t_mm=[1.0, 2.0]), "projector.t_mm"),
    (lambda d: d["projector"]["distortion"].pop("k3"), "projector.distortion.k3"),
    (lambda d: d.update(cameras=["camera", "cam2"]), "cameras"),
    (lambda d: d.update(cameras=["camera", "camera_2"]), "camera_2"),
])
def test_broken_v2_files_name_the_key(tmp_path, edit, key):
    from telefringe.devices.rig import Rig
    from telefringe.io.rig_json import bare_rig_json

    rng = np.random.default_rng(4)
    doc = bare_rig_json(Rig(_pinhole(rng), _pinhole(rng, t=(100.0, 0.0, 0.0))))
    edit(doc)
    with pytest.raises(InputError) as exc:
        rig_from_json(json.loads(json.dumps(doc)), where="r.json")
    assert key in str(exc.value) and str(exc.value).startswith("r.json:")


@settings(max_examples=40, deadline=None)
@given(data=st.data())
def test_any_corruption_of_a_pinhole_rig_is_refused_cleanly(data):
    from telefringe.devices.rig import Rig
    from telefringe.io.rig_json import bare_rig_json

    rng = np.random.default_rng(5)
    doc = bare_rig_json(Rig(cameras={"camera": _pinhole(rng),
                                     "camera_2": _pinhole(rng, t=(80.0, 0.0, 0.0))},
                            projector=_pinhole(rng, t=(40.0, 0.0, 0.0))))
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
    for dev in out.rig.cameras.values():
        assert np.all(np.isfinite(dev.R_dev_world)) and np.all(np.isfinite(dev.t_dev))


def test_every_device_report_round_trips(calib):
    """A calibration of two cameras and a projector keeps each device's report (its
    DeviceReport in RigCalibration.devices), camera_2 included."""
    import dataclasses

    from telefringe.calibration import rig as calibration_rig
    from telefringe.devices.rig import Rig
    from telefringe.io.rig_json import rig_parameter_names_of

    DeviceReport = getattr(calibration_rig, "DeviceReport", None)
    if DeviceReport is None:
        pytest.skip("this RigCalibration keeps no per-device reports (DeviceReport)")
    rng = np.random.default_rng(6)
    rig = Rig(cameras={"camera": _pinhole(rng), "camera_2": _pinhole(rng, t=(80.0, 0, 0))},
              projector=calib.rig.projector)
    names = rig_parameter_names_of(rig)
    n, shape = len(names), calib.camera_observations.shape

    def report(model, seed):
        g = np.random.default_rng(seed)
        res = g.normal(size=shape)
        res[1, 2] = np.nan
        return DeviceReport(model=model, sigma=float(g.random()), observations=g.normal(
            size=shape), residuals=res, rms=float(g.random()),
            rms_per_pose=g.random(shape[0]), principal_point_weak=bool(seed % 2))

    reps = {"camera": report("pinhole", 1), "camera_2": report("pinhole", 2),
            "projector": report("telecentric", 3)}
    three = dataclasses.replace(calib, rig=rig, parameter_names=names,
                                parameters=rng.normal(size=n), covariance=np.eye(n),
                                std=np.ones(n), devices=reps)
    back = rig_from_json(json.loads(json.dumps(rig_to_json(three))))
    assert back.rig.camera_names == ("camera", "camera_2")
    assert back.mirror == "none: a pinhole device fixes it"
    for d, rep in reps.items():
        got = back.devices[d]
        for f in ("observations", "residuals", "rms_per_pose"):
            np.testing.assert_array_equal(getattr(got, f), getattr(rep, f), err_msg=f"{d}.{f}")
        assert (got.rms, got.sigma, got.principal_point_weak, got.model) == (
            rep.rms, rep.sigma, rep.principal_point_weak, rep.model)
    np.testing.assert_array_equal(back.rms_per_pose[:, 1], reps["projector"].rms_per_pose)
    assert back.sigma_projector == reps["projector"].sigma
