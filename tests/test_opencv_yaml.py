"""OpenCV calibration files in and out (io/opencv_yaml.py, `telefringe rig import-opencv |
export-opencv`): the names of OpenCV's stereo_calib sample and SLMaster's, checked against
cv2.projectPoints; round trip to 1e-12; every bad input refused in one line, exit 2,
nothing written."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from telefringe.cli import main
from telefringe.devices.pinhole import PinholeDevice, PinholeIntrinsics
from telefringe.devices.rig import Rig
from telefringe.geometry.so3 import rotation_from_rotvec
from telefringe.io.errors import InputError
from telefringe.io.opencv_yaml import opencv_rig_text, read_opencv_rig, write_opencv_rig
from telefringe.io.rig_json import load_rig

REAL = Path(__file__).resolve().parents[1] / ".." / "shared" / "realdata" / \
    "slmaster_mono_relief" / "caliInfo.yml"


def write_fs(path, nodes: dict, *, header="%YAML:1.0"):
    """An OpenCV FileStorage YAML file with the given matrices (as OpenCV writes them)."""
    fs = cv2.FileStorage(".yml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY
                         | cv2.FILE_STORAGE_FORMAT_YAML)
    for k, v in nodes.items():
        fs.write(k, np.asarray(v, dtype=float))
    text = fs.releaseAndGetString()
    Path(path).write_text(text.replace("%YAML 1.2", header, 1))
    return Path(path)


def K(fx=1750.0, fy=1749.0, cx=640.0, cy=512.0):
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])


D5 = np.array([[-0.07, -0.18, 2.3e-4, 5.5e-4, 1.8]])
R_LP = rotation_from_rotvec([0.005, 0.09, 0.01])
T_LP = np.array([[-108.2], [-5.2], [-15.7]])


def slmaster_nodes(**changes):
    nodes = {"M1": K(), "D1": D5, "S": [[1280.0], [1024.0]], "M4": K(2500, 2499, 990, 547),
             "D4": D5 * 0.5, "Rlp": R_LP, "Tlp": T_LP}
    nodes.update(changes)
    return {k: v for k, v in nodes.items() if v is not None}


# --------------------------------------------------------------------------- the names
def test_slmaster_camera_projector_projects_as_opencv(tmp_path):
    f = write_fs(tmp_path / "cal.yml", slmaster_nodes())
    imp = read_opencv_rig(f, projector_size="1920x1080")
    rig = imp.rig
    assert rig.camera_names == ("camera",) and rig.projector.image_size == (1920, 1080)
    assert rig.camera.image_size == (1280, 1024) and imp.sizes == {
        "camera": "S", "projector": "--projector-size"}
    np.testing.assert_array_equal(rig.camera.R_dev_world, np.eye(3))  # world = camera frame
    rng = np.random.default_rng(0)
    X = np.column_stack([rng.uniform(-100, 100, 50), rng.uniform(-80, 80, 50),
                         rng.uniform(600, 800, 50)])
    for dev, (M, D, R, T) in ((rig.camera, (K(), D5, np.eye(3), np.zeros(3))),
                              (rig.projector, (K(2500, 2499, 990, 547), D5 * 0.5, R_LP, T_LP))):
        want, _ = cv2.projectPoints(X, cv2.Rodrigues(R)[0], np.asarray(T, float), M, D)
        got = np.stack(dev.project(X), axis=-1)
        np.testing.assert_allclose(got, want.reshape(-1, 2), rtol=0, atol=1e-9)


def test_stereo_calib_two_files_and_extra_nodes(tmp_path):
    """OpenCV's stereo_calib writes intrinsics.yml (M1 D1 M2 D2) and extrinsics.yml (R T
    and the rectification R1 R2 P1 P2 Q); no sizes."""
    R = rotation_from_rotvec([0.0, -0.2, 0.01])
    intr = write_fs(tmp_path / "intrinsics.yml", {"M1": K(), "D1": D5, "M2": K(1760, 1758),
                                                  "D2": D5[:, :4]})
    extr = write_fs(tmp_path / "extrinsics.yml", {"R": R, "T": [[-90.0], [0.5], [4.0]],
                                                  "R1": np.eye(3), "Q": np.eye(4)})
    with pytest.raises(InputError, match="camera's image size.*--camera-size"):
        read_opencv_rig([intr, extr])
    imp = read_opencv_rig([intr, extr], camera_size=(1280, 1024))
    rig = imp.rig
    assert rig.camera_names == ("camera", "camera_2") and rig.projector is None
    assert rig.cameras["camera_2"].image_size == (1280, 1024)
    assert "camera's" in imp.sizes["camera_2"]
    np.testing.assert_allclose(rig.cameras["camera_2"].R_dev_world, R, atol=1e-15)
    np.testing.assert_array_equal(rig.cameras["camera_2"].t_dev, [-90.0, 0.5, 4.0])
    assert rig.cameras["camera_2"].intrinsics.k3 == 0.0  # 4 coefficients: k3 = 0
    assert imp.unused == ("Q", "R1")
    # SLMaster's names for the same pose: equal is fine, different is refused
    write_fs(tmp_path / "lr.yml", {"Rlr": R, "Tlr": [[-90.0], [0.5], [4.0]]})
    read_opencv_rig([intr, extr, tmp_path / "lr.yml"], camera_size="1280x1024")
    write_fs(tmp_path / "lr.yml", {"Rlr": R, "Tlr": [[-91.0], [0.5], [4.0]]})
    with pytest.raises(InputError, match="differ"):
        read_opencv_rig([intr, extr, tmp_path / "lr.yml"], camera_size="1280x1024")
    # and the same node in two files with two values
    write_fs(tmp_path / "other.yml", {"M1": K(1751.0)})
    with pytest.raises(InputError, match="M1 differs from M1"):
        read_opencv_rig([intr, tmp_path / "other.yml", extr], camera_size="1280x1024")


def test_units_scale_the_translations(tmp_path):
    f = write_fs(tmp_path / "cal.yml", slmaster_nodes(Tlp=T_LP / 1000.0))
    rig = read_opencv_rig(f, projector_size="1920x1080", unit="m").rig
    np.testing.assert_allclose(rig.projector.t_dev, T_LP.ravel(), rtol=1e-15)


@pytest.mark.parametrize("D, ok", [
    (np.zeros((1, 4)), True),
    (np.zeros((5, 1)), True),
    (np.r_[D5.ravel(), 0, 0, 0], True),            # rational model, its terms 0
    (np.r_[D5.ravel(), 0.01, 0, 0], False),        # k4 != 0
    (np.r_[D5.ravel(), np.zeros(7)], True),
    (np.r_[D5.ravel(), np.zeros(7), 0, 1e-3], False),  # tilted sensor (ty)
    (np.zeros(6), False),                          # a length OpenCV does not define
    (np.zeros((2, 5)), False),
])
def test_distortion_lengths(tmp_path, D, ok):
    f = write_fs(tmp_path / "cal.yml", slmaster_nodes(D4=np.atleast_2d(D)))
    if ok:
        dev = read_opencv_rig(f, projector_size="1920x1080").rig.projector
        d = np.ravel(D)
        np.testing.assert_array_equal(dev.intrinsics.distortion, np.r_[d[:5], np.zeros(5)][:5])
    else:
        with pytest.raises(InputError, match=r"D4 (has|must hold)") as exc:
            read_opencv_rig(f, projector_size="1920x1080")
        assert "\n" not in str(exc.value)


@pytest.mark.parametrize("changes, options, match", [
    ({"M1": None}, {}, "M1 .* is missing"),
    ({"D1": None}, {}, "D1 missing"),
    ({"Rlp": None}, {}, "Rlp missing"),
    ({"M4": None, "D4": None, "Rlp": None, "Tlp": None}, {}, "holds one camera"),
    ({"Rlp": R_LP * 1.01}, {}, "Rlp is not a rotation"),
    ({"Rlp": R_LP @ np.diag([1.0, 1.0, -1.0])}, {}, "Rlp is not a rotation.*reflection"),
    ({"Rlp": np.diag([1.0, 1.0, 1e300])}, {}, "Rlp is not a rotation"),
    ({"Rlp": [[0.0, 0.0, 1e300]]}, {}, "Rlp is not a rotation vector"),
    ({"Tlp": [[1.0, 2.0]]}, {}, "Tlp must be a translation"),
    ({"M4": K()[:2]}, {}, "M4 must be a 3 x 3"),
    ({"M1": K() + np.array([[0, 3.0, 0], [0, 0, 0], [0, 0, 0]])}, {}, "skew"),
    ({"M1": K(fx=-5.0)}, {}, "fx, fy > 0"),
    ({"M1": K() * 2}, {}, "is not a camera matrix"),
    ({"M1": K(cx=1500.0)}, {}, "outside the 1280x1024 image"),
    ({"D1": [[np.nan, 0, 0, 0, 0]]}, {}, "not a finite number"),
    ({"S": [[1280.5], [1024.0]]}, {}, "S must be an image size"),
    ({}, {"camera_size": "1024x1280"}, "S says the camera is 1280x1024"),
    ({"M2": K()}, {}, "D2 missing"),
    ({"T": [[1.0], [0.0], [0.0]]}, {}, "M2, D2 missing"),
    ({}, {"projector_size": "1920by1080"}, "--projector-size must be WIDTHxHEIGHT"),
    ({}, {"unit": "furlong"}, "unit must be one of"),
])
def test_bad_files_are_refused_in_one_line(tmp_path, changes, options, match):
    f = write_fs(tmp_path / "cal.yml", slmaster_nodes(**changes))
    options = {"projector_size": "1920x1080", **options}
    with pytest.raises(InputError, match=match) as exc:
        read_opencv_rig(f, **options)
    msg = str(exc.value)
    assert "\n" not in msg
    assert msg.startswith(str(f)) or msg.startswith(("--", "unit")), msg


def test_unreadable_files(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_opencv_rig(tmp_path / "none.yml")
    bad = tmp_path / "bad.yml"
    bad.write_text("%YAML:1.0\n---\nM1: [1, 2\n")
    with pytest.raises(InputError, match="not a readable OpenCV FileStorage file") as exc:
        read_opencv_rig(bad)
    assert "\n" not in str(exc.value)
    (tmp_path / "empty.yml").write_text("")
    with pytest.raises(InputError, match="empty"):
        read_opencv_rig(tmp_path / "empty.yml")


# --------------------------------------------------------------------------- round trip
def _device(draw, size, pose):
    f = draw(st.floats(300, 5000))
    k = PinholeIntrinsics(
        fx=f, fy=f * draw(st.floats(0.98, 1.02)), cx=draw(st.floats(0.3, 0.7)) * size[0],
        cy=draw(st.floats(0.3, 0.7)) * size[1], k1=draw(st.floats(-0.3, 0.3)),
        k2=draw(st.floats(-0.5, 0.5)), p1=draw(st.floats(-1e-3, 1e-3)),
        p2=draw(st.floats(-1e-3, 1e-3)), k3=draw(st.floats(-2, 2)),
        width=size[0], height=size[1])
    return PinholeDevice(k, *pose)


@st.composite
def rigs(draw):
    def pose():
        rv = [draw(st.floats(-np.pi / 2, np.pi / 2)) for _ in range(3)]
        t = [draw(st.floats(-500, 500)) for _ in range(3)]
        return rotation_from_rotvec(rv), np.array(t)

    cams = {"camera": _device(draw, (1280, 1024), pose())}
    if draw(st.booleans()):
        cams["camera_2"] = _device(draw, (2448, 2048), pose())
    proj = _device(draw, (1920, 1080), pose()) if (len(cams) == 1 or draw(st.booleans())) \
        else None
    return Rig(cameras=cams, projector=proj)


def _relative(dev, ref):
    R = dev.R_dev_world @ ref.R_dev_world.T
    return R, dev.t_dev - R @ ref.t_dev


@settings(max_examples=60, deadline=None)
@given(rig=rigs())
def test_round_trip_to_1e_12(rig, tmp_path_factory):
    path = tmp_path_factory.mktemp("rt") / "cal.yml"
    path.write_text(opencv_rig_text(rig))
    back = read_opencv_rig(path).rig  # sizes from S, S2, S4: no option needed
    assert back.camera_names == rig.camera_names
    assert (back.projector is None) == (rig.projector is None)
    pairs = [(rig.cameras[n], back.cameras[n]) for n in rig.cameras]
    if rig.projector is not None:
        pairs.append((rig.projector, back.projector))
    for a, b in pairs:
        ka, kb = a.intrinsics, b.intrinsics
        assert (ka.width, ka.height) == (kb.width, kb.height)
        va = np.array([getattr(ka, n) for n in ("fx", "fy", "cx", "cy", "k1", "k2", "p1",
                                                  "p2", "k3")])
        vb = np.array([getattr(kb, n) for n in ("fx", "fy", "cx", "cy", "k1", "k2", "p1",
                                                  "p2", "k3")])
        np.testing.assert_allclose(vb, va, rtol=1e-12, atol=1e-15)
        Ra, ta = _relative(a, rig.camera)
        Rb, tb = _relative(b, back.camera)
        np.testing.assert_allclose(Rb, Ra, rtol=0, atol=1e-12)
        np.testing.assert_allclose(tb, ta, rtol=0, atol=1e-12 * max(1.0, np.abs(ta).max()))


# --------------------------------------------------------------------------- command line
def test_cli_import_then_export(tmp_path, capsys):
    src = write_fs(tmp_path / "cal.yml", slmaster_nodes())
    rig_json = tmp_path / "rig.json"
    assert main(["rig", "import-opencv", str(src), "--projector-size", "1920x1080", "-o",
                 str(rig_json)]) == 0
    doc = json.loads(rig_json.read_text())
    assert doc["version"] == 2 and doc["projector"]["model"] == "pinhole"
    assert doc["source"]["imported_from"] == [str(src)] and "calibration" not in doc
    assert "first camera" in doc["world_frame"]["definition"]
    calib = load_rig(rig_json)
    assert calib.mirror == "none: a pinhole device fixes it"
    out = tmp_path / "back.yml"
    assert main(["rig", "export-opencv", str(rig_json), "-o", str(out)]) == 0
    assert "M1 D1 S M4 D4 S4 Rlp Tlp" in " ".join(capsys.readouterr().out.split())
    again = read_opencv_rig(out).rig
    np.testing.assert_allclose(again.projector.R_dev_world, R_LP, atol=1e-15)
    np.testing.assert_allclose(again.projector.t_dev, T_LP.ravel(), rtol=1e-15)
    # existing outputs are refused without --force
    before = out.read_bytes()
    assert main(["rig", "export-opencv", str(rig_json), "-o", str(out)]) == 2
    assert out.read_bytes() == before
    assert main(["rig", "export-opencv", str(rig_json), "-o", str(out), "--force"]) == 0


def test_cli_refuses_bad_input_and_writes_nothing(tmp_path, capsys):
    src = write_fs(tmp_path / "cal.yml", slmaster_nodes(Rlp=R_LP * 1.1))
    out = tmp_path / "rig.json"
    assert main(["rig", "import-opencv", str(src), "--projector-size", "1920x1080", "-o",
                 str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "Rlp is not a rotation" in err and len(err.splitlines()) == 1
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["cal.yml"]


def test_cli_export_refuses_a_telecentric_rig(tmp_path, capsys):
    from test_calibrate import paper_like_rig

    from telefringe.io.rig_json import save_rig

    rig_json = save_rig(tmp_path / "rig.json", paper_like_rig())
    out = tmp_path / "x.yml"
    assert main(["rig", "export-opencv", str(rig_json), "-o", str(out)]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "telecentric" in err and "pinhole" in err and str(rig_json) in err
    assert not out.exists()
    with pytest.raises(InputError, match="camera is telecentric"):
        write_opencv_rig(out, paper_like_rig())


@pytest.mark.skipif(not REAL.is_file(), reason="../shared/realdata is not present")
def test_the_real_slmaster_calibration(tmp_path):
    with pytest.raises(InputError, match="--projector-size"):
        read_opencv_rig(REAL)
    imp = read_opencv_rig(REAL, projector_size="1920x1080")
    fs = cv2.FileStorage(str(REAL), cv2.FILE_STORAGE_READ)
    M1, M4 = fs.getNode("M1").mat(), fs.getNode("M4").mat()
    Rlp, Tlp = fs.getNode("Rlp").mat(), fs.getNode("Tlp").mat()
    cam, proj = imp.rig.camera, imp.rig.projector
    np.testing.assert_array_equal(cam.intrinsics.camera_matrix, M1)
    np.testing.assert_array_equal(proj.intrinsics.camera_matrix, M4)
    np.testing.assert_array_equal(proj.intrinsics.distortion, fs.getNode("D4").mat().ravel())
    np.testing.assert_allclose(proj.R_dev_world, Rlp, atol=1e-15)
    np.testing.assert_array_equal(proj.t_dev, Tlp.ravel())
    assert cam.image_size == (1280, 1024) and imp.unused == ()
    # the projector sits about 11 cm to the camera's right
    assert 100 < proj.centre_world[0] < 115


@pytest.mark.skipif(not REAL.is_file(), reason="../shared/realdata is not present")
def test_the_help_example_runs_as_written(tmp_path, monkeypatch):
    """`telefringe rig import-opencv --help`'s example, run from the repository (its output
    sent to a temporary folder), then export-opencv's."""
    import shlex

    from telefringe.cli.rig import _IMPORT_EXAMPLE

    args = shlex.split(_IMPORT_EXAMPLE)
    assert args[:3] == ["telefringe", "rig", "import-opencv"] and args[-2] == "-o"
    monkeypatch.chdir(Path(__file__).resolve().parents[1])
    out = tmp_path / args[-1]
    assert main([*args[1:-1], str(out)]) == 0
    assert load_rig(out).projector.image_size == (1920, 1080)
    assert main(["rig", "export-opencv", str(out), "-o", str(tmp_path / "relief_cal.yml")]) == 0


def test_world_frame_toward_the_camera(tmp_path):
    """--world toward-camera: the same rig turned 180 deg about the camera's x axis, so
    that z (heights) points toward the camera; projections unchanged, export unchanged."""
    f = write_fs(tmp_path / "cal.yml", slmaster_nodes())
    cam_frame = read_opencv_rig(f, projector_size="1920x1080").rig
    imp = read_opencv_rig(f, projector_size="1920x1080", world="toward-camera")
    np.testing.assert_array_equal(imp.rig.camera.R_dev_world, np.diag([1.0, -1.0, -1.0]))
    assert "toward the camera" in imp.world_definition
    X = np.array([[10.0, -20.0, 700.0], [-50.0, 40.0, 760.0]])  # camera frame, mm
    Xw = X * [1.0, -1.0, -1.0]
    assert np.all(Xw[:, 2] < 0)  # in front of the camera = negative z: heights grow toward it
    for a, b in ((cam_frame.camera, imp.rig.camera), (cam_frame.projector, imp.rig.projector)):
        np.testing.assert_allclose(np.stack(b.project(Xw)), np.stack(a.project(X)), atol=1e-9)
    assert opencv_rig_text(imp.rig) == opencv_rig_text(cam_frame)
    with pytest.raises(InputError, match="world must be one of"):
        read_opencv_rig(f, projector_size="1920x1080", world="up")
    out = tmp_path / "rig.json"
    assert main(["rig", "import-opencv", str(f), "--projector-size", "1920x1080", "--world",
                 "toward-camera", "-o", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert "toward the camera" in doc["world_frame"]["definition"]
    np.testing.assert_allclose(load_rig(out).camera.R_dev_world, np.diag([1.0, -1.0, -1.0]),
                               atol=1e-15)


@settings(max_examples=80, deadline=None)
@given(data=st.data())
def test_any_corrupted_node_is_refused_cleanly(data, tmp_path_factory):
    """Replace any node by a matrix of any small shape and hostile values: the reader
    returns a rig of valid devices or raises InputError, nothing else."""
    nodes = slmaster_nodes(M2=K(1760.0, 1758.0), D2=D5, R=np.eye(3), T=[[-90.0], [0], [0]])
    key = data.draw(st.sampled_from(sorted(nodes)))
    shape = (data.draw(st.integers(1, 4)), data.draw(st.integers(1, 4)))
    values = data.draw(st.lists(st.sampled_from([0.0, 1.0, -1.0, 1e-300, 1e300, np.nan,
                                                 np.inf, 1280.0, 0.5]),
                                min_size=shape[0] * shape[1], max_size=shape[0] * shape[1]))
    nodes[key] = np.array(values).reshape(shape)
    f = write_fs(tmp_path_factory.mktemp("fz") / "cal.yml", nodes)
    try:
        rig = read_opencv_rig(f, projector_size="1920x1080").rig
    except InputError as exc:
        assert "\n" not in str(exc)
        return
    for dev in [*rig.cameras.values(), rig.projector]:
        k = dev.intrinsics
        assert k.fx > 0 and k.fy > 0 and np.all(np.isfinite(dev.t_dev))
        np.testing.assert_allclose(dev.R_dev_world @ dev.R_dev_world.T, np.eye(3), atol=1e-9)
