"""Small rigs of every mix for the triangulation and stereo tests (render-free).

World frame as a calibration's: the target plane z = 0, z toward the camera. Cameras are
small (48 x 64 px) so the tests stay cheap; the distortions are those of real lenses
(a few px at the corners of a full frame), scaled to these fields.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from telefringe.devices.pinhole import PinholeDevice, PinholeIntrinsics
from telefringe.devices.rig import Rig
from telefringe.devices.telecentric import Intrinsics, TelecentricDevice
from telefringe.geometry.so3 import rotation_from_rotvec

SHAPE = (48, 64)
DOWN = np.diag([1.0, -1.0, -1.0])  # device x = world x, y = -world y, z = -world z


@dataclass(frozen=True)
class Coords:
    u_p: np.ndarray | None
    v_p: np.ndarray | None = None
    mask: np.ndarray | None = None
    sigma_u_p: np.ndarray | None = None
    sigma_v_p: np.ndarray | None = None


def look_at(centre, target=(0.0, 0.0, 0.0), roll=0.0):
    """R_dev_world of a device at ``centre`` looking at ``target``, image v roughly along
    -world y."""
    z = np.asarray(target, float) - np.asarray(centre, float)
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x = -x / np.linalg.norm(x) if x[0] < 0 else x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return rotation_from_rotvec([0.0, 0.0, roll]) @ R


def telecentric_camera(shape=SHAPE, *, tilt=(0.01, -0.02, 0.03), t=(0.05, -0.02)):
    rows, cols = shape
    return TelecentricDevice(
        Intrinsics(m=1.0, du=0.06, dv=0.06, u0=(cols - 1) / 2 + 1.3, v0=(rows - 1) / 2 - 0.7,
                   k1=1e-3, s1=2e-4, s2=-1e-4, width=cols, height=rows),
        rotation_from_rotvec(list(tilt)) @ DOWN, np.array(t))


def telecentric_projector(angle_deg=25.0):
    a = np.radians(angle_deg)
    R = rotation_from_rotvec([0.0, 0.0, 0.05]) @ rotation_from_rotvec([0.0, -a, 0.0]) @ DOWN
    return TelecentricDevice(
        Intrinsics(m=0.5, du=0.0137, dv=0.0137, u0=400.0, v0=300.0, k1=3e-4, s1=5e-5,
                   s2=-8e-5, width=800, height=600), R, np.array([0.3, -0.2]))


def pinhole(centre, *, f, size, dist=(0.0, 0.0, 0.0, 0.0, 0.0), pp=(0.0, 0.0), roll=0.02,
            target=(0.0, 0.0, 0.0)):
    w, h = size
    R = look_at(centre, target, roll)
    intr = PinholeIntrinsics(fx=f, fy=f * 1.001, cx=(w - 1) / 2 + pp[0], cy=(h - 1) / 2 + pp[1],
                             k1=dist[0], k2=dist[1], p1=dist[2], p2=dist[3], k3=dist[4],
                             width=w, height=h)
    return PinholeDevice(intr, R, -R @ np.asarray(centre, float))


def pinhole_camera(shape=SHAPE, centre=(0.0, 0.0, 200.0)):
    """About 4 x 3 mm at 200 mm (a macro lens), barrel distortion of a few px at the
    corners of a full-size frame."""
    rows, cols = shape
    return pinhole(centre, f=cols * 200.0 / 4.0, size=(cols, rows),
                   dist=(-0.12, 0.3, 4e-4, -3e-4, 0.0), pp=(1.1, -0.6))


def pinhole_projector(centre=(80.0, 5.0, 190.0)):
    return pinhole(centre, f=800 * 210.0 / 12.0, size=(800, 600),
                   dist=(0.08, -0.2, -5e-4, 2e-4, 0.0), pp=(3.0, 40.0), roll=-0.03)


def rig_of(mix, shape=SHAPE) -> Rig:
    """``mix`` in tt (telecentric camera + telecentric projector), tp, pt, pp."""
    cam = telecentric_camera(shape) if mix[0] == "t" else pinhole_camera(shape)
    prj = telecentric_projector() if mix[1] == "t" else pinhole_projector()
    return Rig(cam, prj)


MIXES = ("tt", "tp", "pt", "pp")


def pixel_lines(cam, shape):
    """Every pixel's line of a (rows, cols) camera image: points o and unit directions d,
    each (rows, cols, 3) (mm; read-only broadcasts where the camera gives one for all)."""
    rows, cols = shape
    v, u = np.mgrid[0:rows, 0:cols].astype(float)
    o, d = cam.backproject(u, v)
    return np.broadcast_to(o, shape + (3,)), np.broadcast_to(d, shape + (3,))


def surface_truth(rig: Rig, shape=SHAPE, *, seed=0, depth=1.0):
    """True points on each camera pixel's line at random heights within +-depth mm of the
    plane z = 0, and their projector pixels (u_p, v_p)."""
    cam = rig.camera
    o, d = pixel_lines(cam, shape)
    rng = np.random.default_rng(seed)
    z = rng.uniform(-depth, depth, size=shape)
    s = (z - o[..., 2]) / d[..., 2]
    X = o + s[..., None] * d
    up, vp = rig.projector.project(X)
    return X, up, vp


def telecentric_camera_2(shape=SHAPE, angle_deg=-20.0):
    """A second telecentric camera, tilted about world y from the first."""
    rows, cols = shape
    a = np.radians(angle_deg)
    R = rotation_from_rotvec([0.0, -a, 0.0]) @ rotation_from_rotvec([0.01, 0.0, -0.02]) @ DOWN
    return TelecentricDevice(
        Intrinsics(m=1.0, du=0.06, dv=0.06, u0=(cols - 1) / 2 - 0.8, v0=(rows - 1) / 2 + 0.4,
                   k1=-8e-4, s1=-1e-4, s2=2e-4, width=cols, height=rows), R,
        np.array([-0.1, 0.05]))


def stereo_rig_of(kind, shape=SHAPE) -> Rig:
    """Two cameras (``pp``: pinhole, ``tt``: telecentric) and a projector."""
    if kind == "pp":
        c1 = pinhole_camera(shape)
        c2 = pinhole((-70.0, 3.0, 185.0), f=shape[1] * 200.0 / 4.0, size=(shape[1], shape[0]),
                     dist=(0.1, -0.2, -3e-4, 2e-4, 0.0), pp=(-0.7, 0.9), roll=-0.01)
        prj = pinhole_projector()
    else:
        c1 = telecentric_camera(shape)
        c2 = telecentric_camera_2(shape)
        prj = telecentric_projector()
    return Rig(cameras={"camera": c1, "camera_2": c2}, projector=prj)


def plane_hits(cam, shape, plane=(0.05, -0.03, 0.2)):
    """Points where each pixel's line meets the plane z = a x + b y + c (mm)."""
    a, b, c = plane
    o, d = pixel_lines(cam, shape)
    n = np.array([-a, -b, 1.0])
    s = (c - o @ n) / (d @ n)
    return o + s[..., None] * d


def stereo_truth(rig: Rig, shape=SHAPE, plane=(0.05, -0.03, 0.2)):
    """The plane seen by both cameras: the first camera's true points, and each camera's
    projector coordinates (u_p, v_p)."""
    cams = list(rig.cameras.values())
    X1 = plane_hits(cams[0], shape, plane)
    X2 = plane_hits(cams[1], shape, plane)
    return X1, rig.projector.project(X1), rig.projector.project(X2)


def step_hits(cam, shape, h=1.5):
    """Where each pixel's line first meets a step: the plane z = h for x < 0, z = 0 for
    x >= 0 and the wall x = 0 between them (mm); the camera's occlusions are exact."""
    o, d = pixel_lines(cam, shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        s_up = (h - o[..., 2]) / d[..., 2]
        s_lo = -o[..., 2] / d[..., 2]
        s_wall = -o[..., 0] / d[..., 0]
        x_up = o[..., 0] + s_up * d[..., 0]
        x_lo = o[..., 0] + s_lo * d[..., 0]
        z_wall = o[..., 2] + s_wall * d[..., 2]
        cand = np.stack([np.where(x_up < 0, s_up, np.inf), np.where(x_lo >= 0, s_lo, np.inf),
                         np.where((z_wall >= 0) & (z_wall <= h), s_wall, np.inf)])
    s = cand.min(axis=0)
    return o + s[..., None] * d


def noisy_coords(u, v, s, rng=None):
    """Coords of (rows, cols) projector coordinates u, v (px; NaN: no hit), their sigma s
    (px) everywhere, with Gaussian noise of that sigma added where ``rng`` is given."""
    shape = u.shape

    def noisy(a):
        return a if rng is None else a + rng.normal(0, s, shape)

    mask = np.isfinite(u) & np.isfinite(v)
    return Coords(noisy(u), noisy(v), mask, np.full(shape, s), np.full(shape, s))


def var_ratio_tol(n_runs, k=3.0):
    """k sigma of the ratio of a sample variance of n_runs Gaussian draws to the true."""
    return k * np.sqrt(2.0 / (n_runs - 1))


def ball_hits(cam, shape, centres, r):
    """Where each pixel's line first meets a BGA: spheres of radius ``r`` (mm) at
    ``centres`` (n, 3) on the substrate z = 0 (mm); the camera's occlusions are exact."""
    o, d = pixel_lines(cam, shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -o[..., 2] / d[..., 2]  # the substrate
        for c in np.asarray(centres, dtype=np.float64):
            oc = o - c
            b = np.sum(d * oc, axis=-1)
            disc = b * b - (np.sum(oc * oc, axis=-1) - r * r)
            t = np.where(disc >= 0, -b - np.sqrt(np.where(disc >= 0, disc, 0.0)), np.inf)
            s = np.minimum(s, t)
    return o + s[..., None] * d


def write_stereo_scan(tmp, scene, *, seed=3, binning=8):
    """The "stereo" preset (binned ``binning``) scans ``scene``: writes the scan folders
    ``tmp/s0/camera`` and ``tmp/s0/camera_2``, the true (bare) ``tmp/rig.json``, and the
    folder ``reconstruct --second`` makes of them, ``tmp/one`` (no gamma correction, no
    PLY). Returns (scans by camera name, the loaded rig.json)."""
    import json

    from telefringe.cli.reconstruct import reconstruct_to_folder
    from telefringe.io.rig_json import bare_rig_json, load_rig
    from telefringe.io.scan_json import write_scan
    from telefringe.simulate.anyrig import scan_scene
    from telefringe.simulate.presets import bin_camera_any, get_preset

    vrig = bin_camera_any(get_preset("stereo"), binning)
    scans, _ = scan_scene(vrig, scene, seed=seed)
    names = vrig.rig.camera_names
    assert names == ("camera", "camera_2")
    (tmp / "s0").mkdir()
    for n in names:
        write_scan(tmp / "s0" / n, scans[n])
    (tmp / "rig.json").write_text(json.dumps(bare_rig_json(vrig.rig)))
    cal = load_rig(tmp / "rig.json")
    reconstruct_to_folder(tmp / "s0" / names[0], cal, tmp / "one",
                          second=tmp / "s0" / names[1], ply=False, gamma_correction=False,
                          read=lambda f: scans[f.name])
    return scans, cal
