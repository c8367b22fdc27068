"""OpenCV calibration files (FileStorage YAML, XML or JSON) in and out of telefringe's rigs.

Two sets of names are read, as the tools that write them use them:

- **two cameras**, OpenCV's ``stereo_calib`` sample: ``M1``, ``D1`` (first camera),
  ``M2``, ``D2`` (second camera), ``R``, ``T`` with ``X2 = R X1 + T`` (SLMaster's
  ``Rlr``, ``Tlr`` are the same);
- **camera + projector**, SLMaster's: ``M1``, ``D1`` (camera), ``M4``, ``D4`` (projector),
  ``Rlp``, ``Tlp`` with ``X_projector = Rlp X_camera + Tlp``.

Both may be in one file (two cameras and a projector). ``M`` is OpenCV's camera matrix
``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (px), ``D`` its distortion coefficients in
OpenCV's order (4, 5, 8, 12 or 14 of them: k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4
[tx ty]]]]); telefringe's pinhole model has k1 k2 p1 p2 k3, so any further coefficient
must be zero. ``R`` is a rotation matrix (or a rotation vector), ``T`` a translation in
the file's length unit (mm unless told). Image sizes come from ``S`` ([width, height] of
the cameras, SLMaster's), ``S2`` and ``S4`` (the second camera's and the projector's,
telefringe's additions, which OpenCV tools ignore) or from the caller. The world frame of
the imported rig is the first camera's (``X_world = X_camera``).

The files are read with ``cv2.FileStorage``; this module checks everything and raises
:class:`~telefringe.io.errors.InputError` (one line naming the file and the matrix) for
anything missing or inconsistent.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from telefringe.devices.pinhole import PinholeDevice, PinholeIntrinsics
from telefringe.devices.rig import Rig
from telefringe.geometry.so3 import project_to_rotation, rotation_from_rotvec
from telefringe.io.atomic import atomic_file
from telefringe.io.errors import InputError

__all__ = ["OpenCVImport", "read_opencv_rig", "opencv_rig_text", "write_opencv_rig",
           "LENGTH_UNITS", "DISTORTION_NAMES", "WORLD_FRAMES"]

#: Millimetres per unit of the file's translations.
LENGTH_UNITS = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "um": 1e-3, "in": 25.4}
#: OpenCV's distortion coefficients, in its order (``distCoeffs`` of 14).
DISTORTION_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4",
                    "tx", "ty")
#: World frames of an imported rig, from the first camera's frame (x along its columns, y
#: along its rows, z along its view): ``X_world = F X_camera``.
WORLD_FRAMES = {
    "camera": (np.eye(3), "the first camera's frame: X_world = X_camera (x along its columns, "
                          "y along its rows, z the depth along its view)"),
    "toward-camera": (np.diag([1.0, -1.0, -1.0]),
                      "the first camera's frame turned 180 degrees about its x axis: "
                      "X_world = (X_c, -Y_c, -Z_c) (x along its columns, y up its image, z "
                      "toward the camera: heights positive toward the camera)"),
}
_D_LENGTHS = (4, 5, 8, 12, 14)
_ROTATION_TOL = 1e-6  # |R R^T - I| accepted (then made exactly orthonormal)
# what each device is called in files, and which nodes hold it
_CAMERA = ("M1", "D1")
_CAMERA_2 = ("M2", "D2")
_PROJECTOR = ("M4", "D4")
_USED = {"M1", "D1", "M2", "D2", "R", "T", "Rlr", "Tlr", "M4", "D4", "Rlp", "Tlp", "S", "S2",
         "S4"}


@dataclass(frozen=True)
class OpenCVImport:
    """What :func:`read_opencv_rig` made of OpenCV files.

    Attributes
    ----------
    rig : Rig, pinhole devices (mm): ``camera`` (and ``camera_2``) and the projector (or
        None), in the world frame asked for (:data:`WORLD_FRAMES`).
    names : str, which naming the files follow, in words.
    sizes : dict device -> where its image size came from (``"S"``, ``"--camera-size"``,
        ...).
    unused : tuple of str, the nodes of the files that were not needed (rectification
        R1 R2 P1 P2 Q, a colour camera M3, ...).
    """

    rig: Rig
    names: str
    sizes: dict
    unused: tuple[str, ...]
    world: str = "camera"

    @property
    def world_definition(self) -> str:
        """The world frame, in words."""
        return WORLD_FRAMES[self.world][1]

    def source(self, files) -> dict:
        """The ``source`` block of rig.json for this import of ``files``."""
        return {"imported_from": [str(f) for f in files], "format": "OpenCV FileStorage",
                "names": self.names, "image_sizes_from": dict(self.sizes),
                "world_frame": self.world_definition,
                "not_used": list(self.unused)}


# --------------------------------------------------------------------------- reading
def _read_nodes(path: Path) -> dict[str, np.ndarray]:
    """Every top-level node of an OpenCV FileStorage file as a float array (matrices as
    they are, sequences and numbers 1-D); nodes that are not numeric are skipped."""
    import cv2

    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise InputError(f"{path}: not found") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a folder, expected an OpenCV .yml/.xml file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read ({exc})") from None
    if not text.strip():
        raise InputError(f"{path}: is empty")
    try:
        fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (cv2.error, SystemError) as exc:
        cause = exc.__cause__ if isinstance(exc, SystemError) and exc.__cause__ else exc
        msg = " ".join(str(cause).split())
        msg = msg.split("error: ", 1)[-1]
        raise InputError(f"{path}: not a readable OpenCV FileStorage file ({msg})") from None
    if not fs.isOpened():
        raise InputError(f"{path}: not an OpenCV FileStorage file (YAML starting with "
                         "'%YAML', XML or JSON)")
    out = {}
    try:
        root = fs.root()
        for key in root.keys():
            node = fs.getNode(key)
            if node.isMap():
                m = node.mat()
                if m is not None:
                    out[key] = np.asarray(m, dtype=float)
            elif node.isSeq():
                vals = [node.at(i) for i in range(node.size())]
                if all(v.isReal() or v.isInt() for v in vals):
                    out[key] = np.array([v.real() for v in vals], dtype=float)
            elif node.isReal() or node.isInt():
                out[key] = np.array([node.real()], dtype=float)
    except (cv2.error, SystemError) as exc:
        raise InputError(f"{path}: cannot read its nodes ({' '.join(str(exc).split())})"
                         ) from None
    finally:
        fs.release()
    return out


def _merge(files) -> tuple[dict[str, np.ndarray], dict[str, Path]]:
    nodes: dict[str, np.ndarray] = {}
    where: dict[str, Path] = {}
    for f in files:
        f = Path(f)
        for key, val in _read_nodes(f).items():
            if key in nodes and (nodes[key].shape != val.shape
                                 or not np.array_equal(nodes[key], val)):
                raise InputError(f"{f}: {key} differs from {key} in {where[key]}")
            nodes[key], where[key] = val, f
    return nodes, where


class _Check:
    def __init__(self, nodes, where, label):
        self.nodes, self.where, self.label = nodes, where, label

    def fail(self, key, msg):
        raise InputError(f"{self.where.get(key, self.label)}: {key} {msg}")

    def finite(self, key) -> np.ndarray:
        a = self.nodes[key]
        if not np.all(np.isfinite(a)):
            self.fail(key, "holds a value that is not a finite number")
        return a

    def camera_matrix(self, key) -> tuple[float, float, float, float]:
        K = self.finite(key)
        if K.shape != (3, 3):
            self.fail(key, f"must be a 3 x 3 camera matrix, got {K.shape[0]} x "
                           f"{K.shape[1] if K.ndim > 1 else 1}")
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        if not (fx > 0 and fy > 0):
            self.fail(key, f"must have focal lengths fx, fy > 0, got {fx:g}, {fy:g}")
        if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
            self.fail(key, "is not a camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (its "
                           "lower part is not 0, 0, 0, 1)")
        if abs(K[0, 1]) > 1e-9 * fx:
            self.fail(key, f"has a skew of {K[0, 1]:g} px: telefringe's pinhole model has "
                           "none (OpenCV's calibrateCamera never estimates one)")
        return float(fx), float(fy), float(cx), float(cy)

    def distortion(self, key) -> dict[str, float]:
        D = self.finite(key)
        if D.ndim > 2 or (D.ndim == 2 and 1 not in D.shape) or D.size not in _D_LENGTHS:
            self.fail(key, f"must hold 4, 5, 8, 12 or 14 distortion coefficients (OpenCV's), "
                           f"got a {' x '.join(map(str, D.shape))} matrix")
        d = D.reshape(-1)
        extra = [(DISTORTION_NAMES[i], d[i]) for i in range(5, d.size) if d[i] != 0]
        if extra:
            listed = ", ".join(f"{n} = {v:g}" for n, v in extra)
            self.fail(key, f"has {d.size} coefficients with {listed}: telefringe's pinhole model "
                           "has k1 k2 p1 p2 k3 only (recalibrate without OpenCV's rational, "
                           "thin-prism or tilted models, or set them to 0 if they are)")
        full = np.zeros(5)
        full[:min(5, d.size)] = d[:5]
        return dict(zip(("k1", "k2", "p1", "p2", "k3"), map(float, full), strict=True))

    def rotation(self, key) -> np.ndarray:
        R = self.finite(key)
        if R.size == 3:
            if np.max(np.abs(R)) > 1e3:
                self.fail(key, f"is not a rotation vector (an angle of {np.max(np.abs(R)):.3g} "
                               "rad)")
            return rotation_from_rotvec(R.reshape(3))
        if R.shape != (3, 3):
            self.fail(key, "must be a 3 x 3 rotation matrix or a rotation vector of 3, got "
                           f"a {' x '.join(map(str, R.shape))} matrix")
        if np.max(np.abs(R)) > 1.0 + _ROTATION_TOL:
            self.fail(key, f"is not a rotation: it holds {np.max(np.abs(R)):.3g}, beyond 1")
        err = float(np.max(np.abs(R @ R.T - np.eye(3))))
        if err > _ROTATION_TOL or np.linalg.det(R) <= 0:
            what = (f"R R^T differs from I by {err:.2g}" if err > _ROTATION_TOL else
                    "its determinant is negative (a reflection)")
            self.fail(key, f"is not a rotation: {what}")
        return project_to_rotation(R) if err > 0 else R.copy()

    def translation(self, key, scale) -> np.ndarray:
        T = self.finite(key)
        if T.size != 3 or (T.ndim == 2 and 1 not in T.shape):
            self.fail(key, f"must be a translation of 3 values, got a "
                           f"{' x '.join(map(str, T.shape))} matrix")
        with np.errstate(over="ignore"):
            T = T.reshape(3) * scale
        if not np.all(np.isfinite(T)):
            self.fail(key, "is too large for a translation")
        return T

    def size(self, key) -> tuple[int, int]:
        S = self.finite(key).reshape(-1)
        if S.size != 2 or np.any(S != np.round(S)) or np.any(S <= 0) or np.any(S > 100_000):
            self.fail(key, f"must be an image size [width, height] of 2 positive integers, "
                           f"got {S.tolist()}")
        return int(S[0]), int(S[1])


def _parse_size(text, option) -> tuple[int, int] | None:
    if text is None:
        return None
    if isinstance(text, tuple | list):
        w, h = text
    else:
        parts = str(text).lower().replace(" ", "").split("x")
        try:
            w, h = (int(p) for p in parts)
        except ValueError:
            raise InputError(f"{option} must be WIDTHxHEIGHT in px, e.g. 1920x1080, got "
                             f"{text!r}") from None
    if not (0 < int(w) <= 100_000 and 0 < int(h) <= 100_000):
        raise InputError(f"{option} must be positive, got {w}x{h}")
    return int(w), int(h)


def read_opencv_rig(files, *, camera_size=None, camera_2_size=None, projector_size=None,
                    unit: str = "mm", world: str = "camera") -> OpenCVImport:
    """Read a rig from OpenCV calibration files (see the module notes for the names).

    Parameters
    ----------
    files : path-like or sequence of them (e.g. stereo_calib's intrinsics.yml and
        extrinsics.yml); their nodes are merged (a node in two files must be equal).
    camera_size, camera_2_size, projector_size : (width, height) px, or "WxH", or None.
        Used where the files hold no size (``S``, ``S2``, ``S4``); a size given both ways
        must agree. The second camera defaults to the first camera's size.
    unit : the length unit of the files' translations (``T``, ``Tlp``), one of
        :data:`LENGTH_UNITS`; converted to mm.
    world : the world frame, one of :data:`WORLD_FRAMES`: ``"camera"`` (the first
        camera's; Z is depth) or ``"toward-camera"`` (the same turned about x: z toward
        the camera, like the world frame of a telefringe calibration).

    Returns
    -------
    OpenCVImport

    Raises
    ------
    InputError
        A file missing or unreadable, a needed matrix missing (M1, D1, the rest of a
        second camera or of a projector), a matrix of the wrong shape, a camera matrix
        with skew, distortion coefficients the pinhole model lacks (nonzero), a ``R``
        that is not a rotation, an image size missing or disagreeing with an option.
    """
    files = [Path(files)] if isinstance(files, str | Path) else [Path(f) for f in files]
    if not files:
        raise InputError("no OpenCV file given")
    if unit not in LENGTH_UNITS:
        raise InputError(f"unit must be one of {', '.join(LENGTH_UNITS)}, got {unit!r}")
    if world not in WORLD_FRAMES:
        raise InputError(f"world must be one of {', '.join(WORLD_FRAMES)}, got {world!r}")
    scale = LENGTH_UNITS[unit]
    sizes_opt = {"camera": _parse_size(camera_size, "--camera-size"),
                 "camera_2": _parse_size(camera_2_size, "--camera-2-size"),
                 "projector": _parse_size(projector_size, "--projector-size")}
    nodes, where = _merge(files)
    label = files[0] if len(files) == 1 else ", ".join(map(str, files))
    chk = _Check(nodes, where, label)
    have = set(nodes)
    if "M1" not in have:
        raise InputError(f"{label}: M1 (the first camera's matrix) is missing; found "
                         f"{', '.join(sorted(have)) or 'no matrices'}")

    def need(keys, what):
        missing = [k for k in keys if k not in have]
        if missing:
            raise InputError(f"{label}: {', '.join(missing)} missing ({what})")

    need(["D1"], "the first camera's distortion; write zeros if it has none")
    pairs = [p for p in (("R", "T"), ("Rlr", "Tlr")) if have & set(p)]
    two = bool(have & {"M2", "D2"} or pairs)
    with_proj = bool(have & {"M4", "D4", "Rlp", "Tlp"})
    if two:
        need(["M2", "D2"], "a second camera needs M2 and D2 with R and T (X2 = R X1 + T)")
        if not pairs:
            need(["R", "T"], "the second camera's pose: X2 = R X1 + T")
        for p in pairs:
            need(p, "the second camera's pose: X2 = R X1 + T")
    if with_proj:
        need(["M4", "D4", "Rlp", "Tlp"], "a projector needs M4, D4, Rlp and Tlp "
                                         "(X_projector = Rlp X_camera + Tlp)")
    if not (two or with_proj):
        raise InputError(f"{label}: holds one camera (M1) and neither a second camera (M2, D2, "
                         "R, T) nor a projector (M4, D4, Rlp, Tlp)")

    sizes_from: dict[str, str] = {}

    def size_of(dev, key, fallback=None):
        opt = sizes_opt[dev]
        option = "--" + dev.replace("_", "-") + "-size"
        if key in have:
            s = chk.size(key)
            if opt is not None and opt != s:
                raise InputError(f"{where[key]}: {key} says the {dev} is {s[0]}x{s[1]} px but "
                                 f"{option} {opt[0]}x{opt[1]}")
            sizes_from[dev] = key
            return s
        if opt is not None:
            sizes_from[dev] = option
            return opt
        if fallback is not None:
            sizes_from[dev] = fallback[1]
            return fallback[0]
        raise InputError(f"{label}: the {dev}'s image size is not in the file (no {key}): "
                         f"give {option} WIDTHxHEIGHT, e.g. 1920x1080")

    def device(mkey, dkey, size, R, t, is_camera):
        fx, fy, cx, cy = chk.camera_matrix(mkey)
        dist = chk.distortion(dkey)
        w, h = size
        if is_camera and not (0 <= cx <= w and 0 <= cy <= h):
            chk.fail(mkey, f"puts the principal point ({cx:.1f}, {cy:.1f}) outside the "
                           f"{w}x{h} image: is the image size right (WIDTHxHEIGHT)?")
        return PinholeDevice(PinholeIntrinsics(fx, fy, cx, cy, **dist, width=w, height=h),
                             R, t)

    cam_size = size_of("camera", "S")
    cams = {"camera": device("M1", "D1", cam_size, np.eye(3), np.zeros(3), True)}
    if two:
        poses = [(chk.rotation(r), chk.translation(t, scale)) for r, t in pairs]
        if len(poses) == 2 and not (np.allclose(poses[0][0], poses[1][0], rtol=0, atol=1e-9)
                                    and np.allclose(poses[0][1], poses[1][1], rtol=0,
                                                    atol=1e-9 * scale)):
            raise InputError(f"{label}: R, T and Rlr, Tlr both give the second camera's pose "
                             "and they differ")
        size2 = size_of("camera_2", "S2", (cam_size, f"the camera's ({sizes_from['camera']})"))
        cams["camera_2"] = device("M2", "D2", size2, *poses[0], True)
    proj = None
    if with_proj:
        proj = device("M4", "D4", size_of("projector", "S4"), chk.rotation("Rlp"),
                      chk.translation("Tlp", scale), False)
    kinds = []
    if two:
        kinds.append("OpenCV stereo_calib (M1 D1 M2 D2 " + " ".join(pairs[0])
                     + ": X2 = R X1 + T)")
    if with_proj:
        kinds.append("SLMaster camera + projector (M1 D1 M4 D4 Rlp Tlp: X_projector = "
                     "Rlp X_camera + Tlp)")
    unused = tuple(sorted(have - _USED))
    F = WORLD_FRAMES[world][0]  # X_world = F X_camera, so X_dev = R F^T X_world + t
    if world != "camera":
        cams = {n: d.with_pose(d.R_dev_world @ F.T, d.t_dev) for n, d in cams.items()}
        if proj is not None:
            proj = proj.with_pose(proj.R_dev_world @ F.T, proj.t_dev)
    return OpenCVImport(Rig(cameras=cams, projector=proj), "; ".join(kinds) + f"; {unit}",
                        sizes_from, unused, world)


# --------------------------------------------------------------------------- writing
def _relative(dev, ref) -> tuple[np.ndarray, np.ndarray]:
    """``dev``'s pose in ``ref``'s frame: ``X_dev = R X_ref + T``."""
    R = dev.R_dev_world @ ref.R_dev_world.T
    return R, dev.t_dev - R @ ref.t_dev


def opencv_rig_text(rig: Rig, *, comment: str = "") -> str:
    """A rig of pinhole devices as OpenCV FileStorage YAML text (the names of
    :func:`read_opencv_rig`: M1 D1 S for the camera, M2 D2 R T S2 for ``camera_2``, M4 D4
    Rlp Tlp S4 for the projector; lengths in mm; poses relative to the first camera).

    Raises
    ------
    InputError
        A device that is not a pinhole one (a telecentric device has no camera matrix),
        cameras other than ``camera`` (and ``camera_2``).
    """
    import cv2

    names = tuple(rig.cameras)
    if names not in (("camera",), ("camera", "camera_2")):
        raise InputError(f"cameras {', '.join(names)}: OpenCV's names hold a camera and "
                         "optionally camera_2")
    devs = dict(rig.cameras)
    if rig.projector is not None:
        devs["projector"] = rig.projector
    for name, dev in devs.items():
        if getattr(dev, "model", None) != "pinhole":
            raise InputError(
                f"the {name} is {getattr(dev, 'model', type(dev).__name__)}: OpenCV's "
                "calibration files hold pinhole devices (a camera matrix and distortion); "
                "a telecentric device has no focal length or centre of projection and "
                "cannot be written in them")
        if dev.image_size is None:
            raise InputError(f"the {name} has no image size")
    if len(devs) < 2:
        raise InputError("the rig has one camera and no projector: nothing to triangulate "
                         "with")
    fs = cv2.FileStorage(".yml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY
                         | cv2.FILE_STORAGE_FORMAT_YAML)
    for line in ("written by telefringe: pinhole devices, OpenCV's model (K, distortion "
                 "k1 k2 p1 p2 k3); lengths in mm",
                 "M1 D1 S: camera; M2 D2 S2: second camera, X2 = R X1 + T; M4 D4 S4: "
                 "projector, X_projector = Rlp X_camera + Tlp; S* = [width, height] px",
                 *([comment] if comment else [])):
        fs.writeComment(line)
    cam = rig.camera

    def put(mkey, dkey, skey, dev):
        k = dev.intrinsics
        fs.write(mkey, k.camera_matrix)
        fs.write(dkey, np.array([k.distortion], dtype=float))
        fs.write(skey, np.array([[float(k.width)], [float(k.height)]]))

    put("M1", "D1", "S", cam)
    if "camera_2" in devs:
        put("M2", "D2", "S2", devs["camera_2"])
        R, T = _relative(devs["camera_2"], cam)
        fs.write("R", R)
        fs.write("T", T.reshape(3, 1))
    if rig.projector is not None:
        put("M4", "D4", "S4", rig.projector)
        R, T = _relative(rig.projector, cam)
        fs.write("Rlp", R)
        fs.write("Tlp", T.reshape(3, 1))
    return fs.releaseAndGetString()


def write_opencv_rig(path, rig: Rig, *, force: bool = False, comment: str = "") -> Path:
    """Write :func:`opencv_rig_text` to ``path`` (atomically; an existing file is replaced
    only with ``force``). Returns the path."""
    path = Path(path)
    text = opencv_rig_text(rig, comment=comment)
    with atomic_file(path, force=force) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")
    return path
