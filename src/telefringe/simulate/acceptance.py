"""The acceptance test of VDI/VDE 2634 Part 2 on the virtual rig: its measuring volume,
artefacts sized from it, and their positions.

The rig's measuring volume is the largest box (axis-parallel in the world frame) whose
every point is seen by the camera (by both cameras of a stereo rig) and lit by the
projector, x-y over the fields of view
and z over the depth of field (``VirtualRig.depth_of_field_mm``, centred on z = 0);
L0 is its space diagonal. The artefacts follow the guideline's proportions as they are
commonly summarised (docs/acceptance.md says which were checked): a test sphere of
diameter 0.1 L0 (the lower end of 0.1-0.2 L0, so that a single view's cap stays within
the depth of field), a ball bar of centre distance 0.3 L0 (rounded up to 0.1 mm) with
two such spheres, a plane 0.5 L0 long (rounded up) and 0.2 L0 wide. The positions:

- sphere (10): the centre of the volume at its top and bottom height, its four corners
  and the middles of its four sides, alternately high and low;
- ball bar (7): along the four space diagonals of the volume the sphere centres can
  span, along x, along y, and along x again nearer one side;
- plane (6): horizontal along x and along y, then tilted (rising along its length) along
  both horizontal diagonals, along x and along y, the tilt using 80 % of the depth of
  field (at most 20 deg).

Every artefact stays inside the volume: spheres between their equator at its bottom and
their top at its top; the plane's corners inside it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from telefringe.simulate.presets import VirtualRig
from telefringe.simulate.scenes import FreeSpheres, RectPlate

__all__ = ["MeasuringVolume", "AcceptanceArtefacts", "AcceptancePosition",
           "measuring_volume", "acceptance_artefacts", "acceptance_positions",
           "iter_acceptance_scans", "U_CERTIFICATE_MM"]

#: Standard uncertainty written into the virtual certificate for every calibrated value
#: (mm): the virtual artefacts are exact, a real certificate of a ceramic sphere, ball bar
#: or optical flat states about this much.
U_CERTIFICATE_MM = 0.0002


@dataclass(frozen=True)
class MeasuringVolume:
    """An axis-parallel box of the world frame, mm."""

    x0: float
    x1: float
    y0: float
    y1: float
    z0: float
    z1: float

    @property
    def size(self) -> np.ndarray:
        return np.array([self.x1 - self.x0, self.y1 - self.y0, self.z1 - self.z0])

    @property
    def centre(self) -> np.ndarray:
        return np.array([(self.x0 + self.x1) / 2, (self.y0 + self.y1) / 2,
                         (self.z0 + self.z1) / 2])

    @property
    def L0(self) -> float:
        """The space diagonal, mm."""
        return float(np.linalg.norm(self.size))


@dataclass(frozen=True)
class AcceptanceArtefacts:
    """The virtual artefacts' true sizes, mm (also their certificate values)."""

    L0: float
    sphere_diameter: float
    bar_distance: float
    plane_length: float
    plane_width: float


@dataclass(frozen=True, eq=False)
class AcceptancePosition:
    """One scan of the test: ``name`` (e.g. "sphere_03"), ``artefact`` ("sphere",
    "ball_bar" or "plane"), the ``scene`` and a short ``description``."""

    name: str
    artefact: str
    scene: object
    description: str


def _ceil_to(x: float, step: float) -> float:
    return round(float(np.ceil(x / step - 1e-9) * step), 9)


def measuring_volume(vrig: VirtualRig, *, margin: float = 0.03, n: int = 121
                     ) -> MeasuringVolume:
    """The rig's measuring volume (see the module notes).

    ``margin``: share of each image's width and height left out at its borders. The
    box is found on an ``n`` x ``n`` grid over the camera's field at z = 0.
    """
    cam, proj = vrig.camera, vrig.projector
    dof = float(vrig.depth_of_field_mm)
    zs = (-dof / 2, 0.0, dof / 2)
    w, h = cam.image_size
    uu = np.array([0, w - 1, w - 1, 0, (w - 1) / 2, (w - 1) / 2, 0, w - 1], dtype=float)
    vv = np.array([0, 0, h - 1, h - 1, 0, h - 1, (h - 1) / 2, (h - 1) / 2], dtype=float)
    o, d = cam.backproject(uu, vv)
    # a telecentric camera shares its direction, a pinhole camera its origin
    o, d = np.broadcast_arrays(o, d)
    foot = o - (o[:, 2] / d[:, 2])[:, None] * d  # on z = 0
    lo, hi = foot[:, :2].min(axis=0), foot[:, :2].max(axis=0)
    xs = np.linspace(lo[0], hi[0], n)
    ys = np.linspace(lo[1], hi[1], n)
    X, Y = np.meshgrid(xs, ys)
    ok = np.ones(X.shape, dtype=bool)
    for dev in (*vrig.rig.cameras.values(), proj):  # every camera (stereo: both)
        dw, dh = dev.image_size
        for z in zs:
            u, v = dev.project(np.stack([X, Y, np.full_like(X, z)], axis=-1))
            ok &= ((u >= margin * dw) & (u <= (1 - margin) * dw - 1)
                   & (v >= margin * dh) & (v <= (1 - margin) * dh - 1))
    if not ok.any():
        raise ValueError(f"{vrig.name}: no point is seen by the camera and lit by the "
                         "projector over the whole depth of field")
    rows, cols = np.nonzero(ok)
    r0, r1, c0, c1 = rows.min(), rows.max(), cols.min(), cols.max()
    # shrink the bounding box, one grid step at a time on the side with most holes
    while True:
        sub = ok[r0:r1 + 1, c0:c1 + 1]
        if sub.all():
            break
        holes = {"r0": (~sub[0]).sum(), "r1": (~sub[-1]).sum(), "c0": (~sub[:, 0]).sum(),
                 "c1": (~sub[:, -1]).sum()}
        side = max(holes, key=holes.get)
        if side == "r0":
            r0 += 1
        elif side == "r1":
            r1 -= 1
        elif side == "c0":
            c0 += 1
        else:
            c1 -= 1
        if r0 >= r1 or c0 >= c1:
            raise ValueError(f"{vrig.name}: the measuring volume is empty")
    return MeasuringVolume(float(xs[c0]), float(xs[c1]), float(ys[r0]), float(ys[r1]),
                           -dof / 2, dof / 2)


def acceptance_artefacts(volume: MeasuringVolume) -> AcceptanceArtefacts:
    """The artefacts' sizes for ``volume`` (see the module notes), mm."""
    L0 = volume.L0
    return AcceptanceArtefacts(L0=L0, sphere_diameter=_ceil_to(0.1 * L0, 0.01),
                               bar_distance=_ceil_to(0.3 * L0, 0.1),
                               plane_length=_ceil_to(0.5 * L0, 0.1),
                               plane_width=_ceil_to(0.2 * L0, 0.1))


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def acceptance_positions(vrig: VirtualRig, volume: MeasuringVolume | None = None
                         ) -> tuple[AcceptanceArtefacts, list[AcceptancePosition]]:
    """The artefacts and their 10 + 7 + 6 positions in ``vrig``'s measuring volume.

    Raises
    ------
    ValueError
        When the volume cannot hold an artefact at a position (e.g. a depth of field
        shallower than the test sphere's radius).
    """
    vol = measuring_volume(vrig) if volume is None else volume
    art = acceptance_artefacts(vol)
    r = art.sphere_diameter / 2
    size = vol.size
    if r > size[2]:
        raise ValueError(f"{vrig.name}: a depth of field of {size[2]:.3g} mm cannot hold the "
                         f"test sphere's cap (radius {r:.3g} mm = 0.05 L0)")
    # sphere centres: equator at the bottom of the volume, top at its top (5 % spare)
    spare = 0.05 * (size[2] - r)
    zlo, zhi = vol.z0 + spare, vol.z1 - r - spare
    inset = r * 1.1 + 0.02 * min(size[0], size[1])
    xa, xb = vol.x0 + inset, vol.x1 - inset
    ya, yb = vol.y0 + inset, vol.y1 - inset
    xc, yc = vol.centre[:2]
    if xa >= xb or ya >= yb:
        raise ValueError(f"{vrig.name}: the field is too small for the test sphere")
    out = []

    def sphere(name, c, desc, kind="sphere", centres=None):
        cs = np.atleast_2d(c if centres is None else centres)
        return AcceptancePosition(name, kind, FreeSpheres(centres=cs, radii=[r] * len(cs)),
                                  desc)

    spots = [((xc, yc, zhi), "centre, high"), ((xc, yc, zlo), "centre, low"),
             ((xa, ya, zlo), "corner -x -y, low"), ((xb, ya, zhi), "corner +x -y, high"),
             ((xb, yb, zlo), "corner +x +y, low"), ((xa, yb, zhi), "corner -x +y, high"),
             ((xc, ya, zhi), "side -y, high"), ((xb, yc, zlo), "side +x, low"),
             ((xc, yb, zhi), "side +y, high"), ((xa, yc, zlo), "side -x, low")]
    for k, (c, desc) in enumerate(spots):
        out.append(sphere(f"sphere_{k:02d}", c, desc))

    L = art.bar_distance
    dz = min(zhi - zlo, 0.9 * L)
    zm = (zlo + zhi) / 2
    diag = _unit([xb - xa, yb - ya])
    anti = _unit([-(xb - xa), yb - ya])
    bars = []
    for h, s, desc in ((diag, 1, "space diagonal 1"), (diag, -1, "space diagonal 2"),
                       (anti, 1, "space diagonal 3"), (anti, -1, "space diagonal 4")):
        hz = s * dz / L
        hh = np.sqrt(max(1 - hz * hz, 0.0))
        bars.append((np.array([h[0] * hh, h[1] * hh, hz]), (xc, yc, zm), desc))
    bars.append((np.array([1.0, 0, 0]), (xc, yc, zm), "along x"))
    bars.append((np.array([0, 1.0, 0]), (xc, yc, zm), "along y"))
    bars.append((np.array([1.0, 0, 0]), (xc, (ya + yc) / 2, zm), "along x, toward -y"))
    for k, (e, c, desc) in enumerate(bars):
        c = np.asarray(c, dtype=float)
        ends = np.array([c - L / 2 * e, c + L / 2 * e])
        if (ends[:, 0].min() < xa - 1e-9 or ends[:, 0].max() > xb + 1e-9
                or ends[:, 1].min() < ya - 1e-9 or ends[:, 1].max() > yb + 1e-9):
            raise ValueError(f"{vrig.name}: the ball bar ({L:.3g} mm = 0.3 L0) does not fit "
                             f"the field {desc}")
        out.append(sphere(f"ball_bar_{k:02d}", None, desc, "ball_bar", ends))

    Lp, Wp = art.plane_length, art.plane_width
    tilt = float(np.arcsin(min(0.8 * size[2] / Lp, np.sin(np.radians(20.0)))))
    planes = [((1.0, 0.0), 0.0, "horizontal, along x"), ((0.0, 1.0), 0.0, "horizontal, along y"),
              (tuple(diag), tilt, "tilted, along diagonal 1"),
              (tuple(anti), -tilt, "tilted, along diagonal 2"),
              ((1.0, 0.0), -tilt, "tilted, along x"), ((0.0, 1.0), tilt, "tilted, along y")]
    for k, (h, a, desc) in enumerate(planes):
        ex = np.array([h[0] * np.cos(a), h[1] * np.cos(a), np.sin(a)])
        ey = _unit(np.cross([0.0, 0.0, 1.0], [h[0], h[1], 0.0]))
        R = np.column_stack([ex, ey, np.cross(ex, ey)])
        plate = RectPlate(length=Lp, width=Wp, R_world_scene=R,
                          t_world_scene=vol.centre.copy(), albedo=0.8)
        cor = plate.corners()
        if (cor[:, 0].min() < vol.x0 or cor[:, 0].max() > vol.x1
                or cor[:, 1].min() < vol.y0 or cor[:, 1].max() > vol.y1
                or cor[:, 2].min() < vol.z0 - 1e-9 or cor[:, 2].max() > vol.z1 + 1e-9):
            raise ValueError(f"{vrig.name}: the plane ({Lp:.3g} mm = 0.5 L0) does not fit the "
                             f"measuring volume {desc}")
        out.append(AcceptancePosition(f"plane_{k:02d}", "plane", plate,
                                      f"{desc} ({np.degrees(abs(a)):.1f} deg)"))
    return art, out


def _seed(seed: int, k: int) -> int:
    return int(np.random.SeedSequence([int(seed), 2634, int(k)]).generate_state(1)[0])


def iter_acceptance_scans(vrig: VirtualRig, positions, *, seed: int = 0, groups=None,
                          progress: Callable | None = None, camera: str | None = None
                          ) -> Iterator[tuple]:
    """Render each position (bounded memory): yields ``(position, scan, truth)``.

    ``progress(done, total)`` counts scans. ``camera``: which camera of a two-camera rig
    sees the scans (``vrig.camera_names``; its noise is seeded apart from the other's);
    default the first.
    """
    from telefringe.simulate.render import default_groups, render_scan

    names = vrig.camera_names
    ci = 0 if camera is None else names.index(camera)
    view = vrig.for_camera(names[ci]) if len(names) > 1 else vrig
    if groups is None:
        groups = default_groups(view)
    for k, pos in enumerate(positions):
        scan, truth = render_scan(view, pos.scene, groups,
                                  seed=_seed(seed, k) + 1000003 * ci)
        if progress is not None:
            progress(k + 1, len(positions))
        yield pos, scan, truth
