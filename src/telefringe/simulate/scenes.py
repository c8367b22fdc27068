"""Analytic scenes for the virtual rig, with exact ray intersection and ground truth.

Every scene is a frozen dataclass with

- ``intersect(origins, direction) -> Hits``: first intersection of rays with the scene:
  ``origins`` (N, 3) mm and unit directions, one (3,) for parallel rays (a telecentric
  device) or one per ray (N, 3) (rays from a pinhole device's centre).
  Rays must start outside the scene (the renderer starts them 500 mm away); only hits
  with ``t > 0`` count; a ray whose origin holds NaN hits nothing.
- ``features() -> dict``: the scene's ground-truth features (JSON-friendly values or
  arrays): circle centres, step heights, sphere centre and radius, ball apexes, ...
- ``z_range() -> (zmin, zmax)``: heights the surface spans (world mm).

Surfaces are two-sided: the returned normal faces the incoming ray. Shading (which side
the projector lights) is the renderer's business.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from telefringe.geometry.so3 import rotation_from_rotvec
from telefringe.simulate import _kernels as _k
from telefringe.targets.grid import CircleGridTarget

__all__ = [
    "Hits",
    "CirclePlate",
    "StepGauge",
    "Sphere",
    "BGA",
    "TiltedPlane",
    "HeightField",
    "FreeSpheres",
    "RectPlate",
    "plate_at_z",
    "plate_from_target",
    "default_steps",
    "default_sphere",
    "default_bga",
    "tilted_plane",
    "SCENE_NAMES",
    "make_scene",
    "rotation_xyz_deg",
]



@dataclass(frozen=True, eq=False)
class Hits:
    """First hits of N rays.

    Attributes
    ----------
    t : (N,) ndarray of float
        Distance along the ray to the hit, mm; ``inf`` where the ray hits nothing.
    normal : (N, 3) ndarray of float
        Unit surface normal (world), facing the incoming ray; 0 where no hit.
    albedo : (N,) ndarray of float
        Lambertian albedo in [0, 1]; 0 where no hit.
    specular : (N,) ndarray of float
        Peak specular reflectance relative to a white Lambertian surface (0: matte).
    part : (N,) ndarray of int
        Which surface was hit (scene specific, >= 0); -1 where no hit. Pixels whose
        sub-samples hit different parts straddle an edge.
    """

    t: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray
    specular: np.ndarray
    part: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        """(N,) bool, the ray hit something."""
        return np.isfinite(self.t)


def _check_rays(origins, direction):
    """Validated origins (N, 3) and per-ray unit directions (N, 3), contiguous floats
    (a single direction (3,) is repeated for every ray)."""
    o = np.ascontiguousarray(origins, dtype=float)
    d = np.asarray(direction, dtype=float)
    if o.ndim != 2 or o.shape[1] != 3:
        raise ValueError(f"origins must have shape (N, 3), got {o.shape}")
    if d.shape == (3,):
        if not np.all(np.isfinite(d)) or abs(np.linalg.norm(d) - 1) > 1e-9:
            raise ValueError("direction must be a finite unit (3,) vector")
        return o, np.ascontiguousarray(np.broadcast_to(d, o.shape))
    if d.shape != o.shape:
        raise ValueError(f"direction must have shape (3,) or {o.shape}, got {d.shape}")
    ok = np.isfinite(o[:, 0])
    if not (np.all(np.isfinite(d[ok]))
            and np.all(np.abs(np.linalg.norm(d[ok], axis=1) - 1) <= 1e-9)):
        raise ValueError("directions must be finite unit vectors (one per ray)")
    return o, np.ascontiguousarray(np.where(ok[:, None], d, 0.0))


def _face_ray(normal, d):
    """Flip normals to face the incoming rays (``d`` (N, 3))."""
    s = np.where(np.einsum("ij,ij->i", normal, d) > 0, -1.0, 1.0)
    return normal * s[:, None]


def _frozen_array(a, shape=None, name="array"):
    a = np.array(a, dtype=float)
    if shape is not None and a.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite")
    a.setflags(write=False)
    return a


def _check_rotation(R, name):
    R = _frozen_array(R, (3, 3), name)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-9) or np.linalg.det(R) < 0:
        raise ValueError(f"{name} must be a proper rotation")
    return R


# --------------------------------------------------------------------------- circle plate
@dataclass(frozen=True, eq=False)
class CirclePlate:
    """A flat plate with a grid of dark circles (the calibration target), at any pose.

    In the target frame the plate is Z = 0, circle (i, j) (row i, column j) is centred
    at ``(j * pitch, i * pitch, 0)``; the plate extends ``margin`` beyond the outer
    circle centres. Parts: 0 plate, 1 marker.

    Attributes
    ----------
    R_world_target : (3, 3) rotation, target -> world.
    t_world_target : (3,) mm, the target origin (circle (0, 0)) in the world.
    rows, cols : int.  pitch, diameter, margin : float, mm.
    albedo, marker_albedo : float, Lambertian albedo of the plate and of the circles.
    """

    R_world_target: np.ndarray = field(default_factory=lambda: np.eye(3))
    t_world_target: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rows: int = 9
    cols: int = 11
    pitch: float = 3.0
    diameter: float = 1.5
    margin: float = 3.0
    albedo: float = 0.9
    marker_albedo: float = 0.15

    def __post_init__(self):
        object.__setattr__(self, "R_world_target",
                           _check_rotation(self.R_world_target, "R_world_target"))
        object.__setattr__(self, "t_world_target",
                           _frozen_array(self.t_world_target, (3,), "t_world_target"))
        if self.rows < 1 or self.cols < 1:
            raise ValueError("rows and cols must be >= 1")
        if not 0 < self.diameter < self.pitch:
            raise ValueError("need 0 < diameter < pitch")
        if self.margin < self.diameter / 2:
            raise ValueError("margin must be at least the circle radius")

    @property
    def R_world_scene(self):
        return self.R_world_target

    @property
    def t_world_scene(self):
        return self.t_world_target

    def intersect(self, origins, direction) -> Hits:
        o, d = _check_rays(origins, direction)
        return Hits(*_k.plate_intersect(o, d, self.R_world_target, self.t_world_target,
                                        int(self.rows), int(self.cols), float(self.pitch),
                                        float(self.diameter) / 2, float(self.margin),
                                        float(self.albedo), float(self.marker_albedo)))

    def circle_centres_world(self) -> np.ndarray:
        """Circle centres (rows * cols, 3) in world mm, row-major (row, col)."""
        r, c = np.mgrid[0:self.rows, 0:self.cols]
        pts = np.stack([c.ravel() * self.pitch, r.ravel() * self.pitch, np.zeros(r.size)], 1)
        return pts @ self.R_world_target.T + self.t_world_target

    def z_range(self) -> tuple[float, float]:
        x1 = (self.cols - 1) * self.pitch + self.margin
        y1 = (self.rows - 1) * self.pitch + self.margin
        xs, ys = np.meshgrid([-self.margin, x1], [-self.margin, y1])
        pts = np.stack([xs.ravel(), ys.ravel(), np.zeros(4)], 1) @ self.R_world_target.T
        z = pts[:, 2] + self.t_world_target[2]
        return float(z.min()), float(z.max())

    def features(self) -> dict:
        n = self.R_world_target[:, 2]
        return {
            "type": "circle-plate",
            "rows": int(self.rows), "cols": int(self.cols), "pitch_mm": float(self.pitch),
            "diameter_mm": float(self.diameter),
            "R_world_target": self.R_world_target.copy(),
            "t_world_target": self.t_world_target.copy(),
            "circle_centres_world": self.circle_centres_world(),
            "plane_normal": n.copy(),
            "plane_offset_mm": float(n @ self.t_world_target),
        }


def plate_from_target(target: CircleGridTarget, R_world_target=None, t_world_target=None,
                      **kw) -> CirclePlate:
    """A :class:`CirclePlate` with the geometry of a :class:`CircleGridTarget`."""
    return CirclePlate(R_world_target=np.eye(3) if R_world_target is None else R_world_target,
                       t_world_target=np.zeros(3) if t_world_target is None else t_world_target,
                       rows=target.rows, cols=target.cols, pitch=target.pitch_mm,
                       diameter=target.diameter_mm, **kw)


def plate_at_z(z: float = 0.0, *, target: CircleGridTarget | None = None, **kw) -> CirclePlate:
    """The calibration plate at its reference orientation, raised by ``z`` mm (a stage move
    along world Z, as in Table 3 of the paper)."""
    from telefringe.simulate.presets import PAPER_TARGET

    return plate_from_target(target or PAPER_TARGET, np.eye(3), np.array([0.0, 0.0, float(z)]),
                             **kw)


# --------------------------------------------------------------------------- step gauge
@dataclass(frozen=True, eq=False)
class StepGauge:
    """Rectangular blocks standing on a base plate (Z = 0 of the scene frame).

    Parts: 0 the base plate, k + 1 block k (any of its faces).

    Attributes
    ----------
    blocks : (n, 6) array of float, mm: ``(xmin, xmax, ymin, ymax, zmin, zmax)`` per block
        in the scene frame (usually ``zmin = 0``).
    base : (4,) ``(xmin, xmax, ymin, ymax)`` of the base plate, mm.
    R_world_scene, t_world_scene : pose of the scene frame in the world.
    albedo, base_albedo : float.
    """

    blocks: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    base: tuple[float, float, float, float] = (-10.0, 40.0, -8.0, 32.0)
    R_world_scene: np.ndarray = field(default_factory=lambda: np.eye(3))
    t_world_scene: np.ndarray = field(default_factory=lambda: np.zeros(3))
    albedo: float = 0.75
    base_albedo: float = 0.75

    def __post_init__(self):
        b = np.array(self.blocks, dtype=float).reshape(-1, 6)
        if np.any(b[:, 1] <= b[:, 0]) or np.any(b[:, 3] <= b[:, 2]) or np.any(b[:, 5] <= b[:, 4]):
            raise ValueError("every block needs min < max on each axis")
        object.__setattr__(self, "blocks", _frozen_array(b, b.shape, "blocks"))
        object.__setattr__(self, "R_world_scene",
                           _check_rotation(self.R_world_scene, "R_world_scene"))
        object.__setattr__(self, "t_world_scene",
                           _frozen_array(self.t_world_scene, (3,), "t_world_scene"))

    def intersect(self, origins, direction) -> Hits:
        o, d = _check_rays(origins, direction)
        return Hits(*_k.boxes_intersect(o, d, self.R_world_scene, self.t_world_scene,
                                        self.blocks, np.asarray(self.base, dtype=float),
                                        float(self.albedo), float(self.base_albedo)))

    def z_range(self) -> tuple[float, float]:
        zs = [0.0] + list(self.blocks[:, 4]) + list(self.blocks[:, 5])
        return float(min(zs)) + float(self.t_world_scene[2]), \
            float(max(zs)) + float(self.t_world_scene[2])

    def features(self) -> dict:
        tops = self.blocks[:, 5]
        return {
            "type": "step-gauge",
            "blocks": self.blocks.copy(),
            "base": list(map(float, self.base)),
            "R_world_scene": self.R_world_scene.copy(),
            "t_world_scene": self.t_world_scene.copy(),
            "top_heights_mm": tops.copy(),
            "step_heights_mm": np.diff(np.concatenate([[0.0], tops])),
        }


def default_steps(*, heights=(0.5, 1.0, 1.5, 2.0), width: float = 5.0,
                  centre=(15.0, 12.0), length: float = 16.0) -> StepGauge:
    """A staircase of blocks rising toward +x (toward the projector side of the presets),
    centred at ``centre`` (x, y) mm on a base plate at Z = 0. Each block is ``width``
    wide in x; its wall on the -x side shadows the step below."""
    heights = np.asarray(heights, dtype=float)
    n = len(heights)
    xs = centre[0] - n * width / 2 + width * np.arange(n)
    y0, y1 = centre[1] - length / 2, centre[1] + length / 2
    blocks = np.array([[x, x + width, y0, y1, 0.0, h] for x, h in zip(xs, heights, strict=True)])
    return StepGauge(blocks=blocks)


# --------------------------------------------------------------------------- sphere
@dataclass(frozen=True, eq=False)
class Sphere:
    """A matte sphere on a plane Z = ``plane_z`` (world). Parts: 0 plane, 1 sphere.

    The part of the sphere below the plane is hidden (a sphere sunk into the plane is a
    spherical cap).
    """

    center: np.ndarray = field(default_factory=lambda: np.array([15.0, 12.0, 0.5]))
    radius: float = 3.0
    plane_z: float = 0.0
    albedo: float = 0.8
    plane_albedo: float = 0.6
    plane_half_size: float = 40.0

    def __post_init__(self):
        object.__setattr__(self, "center", _frozen_array(self.center, (3,), "center"))
        if not self.radius > 0:
            raise ValueError("radius must be > 0")

    def intersect(self, origins, direction) -> Hits:
        o, d = _check_rays(origins, direction)
        return Hits(*_k.sphere_intersect(o, d, self.center, float(self.radius),
                                         float(self.plane_z), float(self.plane_half_size),
                                         float(self.albedo), float(self.plane_albedo)))

    def z_range(self) -> tuple[float, float]:
        return float(self.plane_z), float(max(self.plane_z, self.center[2] + self.radius))

    def features(self) -> dict:
        return {"type": "sphere", "center_world": self.center.copy(),
                "radius_mm": float(self.radius), "plane_z_mm": float(self.plane_z)}


def default_sphere() -> Sphere:
    """A 3 mm radius matte sphere whose top is 3.5 mm above the plane, centred in view."""
    return Sphere()


# --------------------------------------------------------------------------- BGA
@dataclass(frozen=True, eq=False)
class BGA:
    """A ball grid array: spherical-cap solder balls on a flat substrate (Z = 0, world).

    Ball (i, j) sits at ``origin + (j * pitch, i * pitch)``; it is a sphere of diameter
    ``ball_diameter`` whose apex is at height ``ball_height + height_offsets[i, j]``
    (so the sphere centre is ``radius`` below the apex); the part below Z = 0 is hidden.
    Balls listed in ``missing`` are absent. Parts: 0 substrate, 1 board beyond the chip,
    2 balls.

    Attributes
    ----------
    rows, cols : int.  pitch, ball_diameter, ball_height : float, mm.
    origin : (2,) mm, centre of ball (0, 0) in world x, y.
    height_offsets : (rows, cols) mm, known perturbation of each apex height.
    missing : tuple of (i, j).
    ball_albedo, ball_specular : float, diffuse albedo and peak specular reflectance
        (relative to white Lambertian) of the solder.
    substrate_albedo, board_albedo : float.
    chip_margin : float, mm, substrate beyond the outer ball centres.
    """

    rows: int = 24
    cols: int = 24
    pitch: float = 0.8
    ball_diameter: float = 0.45
    ball_height: float = 0.35
    origin: np.ndarray = field(default_factory=lambda: np.array([5.8, 2.8]))
    height_offsets: np.ndarray | None = None
    missing: tuple[tuple[int, int], ...] = ()
    ball_albedo: float = 0.25
    ball_specular: float = 6.0
    substrate_albedo: float = 0.3
    board_albedo: float = 0.5
    chip_margin: float = 1.0

    def __post_init__(self):
        object.__setattr__(self, "origin", _frozen_array(self.origin, (2,), "origin"))
        off = (np.zeros((self.rows, self.cols)) if self.height_offsets is None
               else self.height_offsets)
        object.__setattr__(self, "height_offsets",
                           _frozen_array(off, (self.rows, self.cols), "height_offsets"))
        miss = tuple(sorted({(int(i), int(j)) for i, j in self.missing}))
        for i, j in miss:
            if not (0 <= i < self.rows and 0 <= j < self.cols):
                raise ValueError(f"missing ball {(i, j)} is outside the grid")
        object.__setattr__(self, "missing", miss)
        r = self.ball_diameter / 2
        h = self.ball_height + self.height_offsets
        if not 0 < self.ball_diameter < self.pitch:
            raise ValueError("need 0 < ball_diameter < pitch")
        if np.any(h <= 0) or np.any(h > self.ball_diameter):
            raise ValueError(f"apex heights must be in (0, {self.ball_diameter}] mm")
        del r

    @property
    def radius(self) -> float:
        return self.ball_diameter / 2

    def present(self) -> np.ndarray:
        """(rows, cols) bool, True where a ball is."""
        p = np.ones((self.rows, self.cols), dtype=bool)
        for i, j in self.missing:
            p[i, j] = False
        return p

    def apexes_world(self) -> np.ndarray:
        """(rows, cols, 3) apex of each grid position (also where missing), world mm."""
        i, j = np.mgrid[0:self.rows, 0:self.cols]
        return np.stack([self.origin[0] + j * self.pitch, self.origin[1] + i * self.pitch,
                         self.ball_height + self.height_offsets], axis=-1)

    def centres_world(self) -> np.ndarray:
        """(rows, cols, 3) sphere centres, world mm."""
        c = self.apexes_world()
        c[..., 2] -= self.radius
        return c

    def intersect(self, origins, direction) -> Hits:
        o, d = _check_rays(origins, direction)
        r = self.radius
        hmax = float(np.max(self.ball_height + self.height_offsets))
        # every ball a ray can meet has its centre within reach (x-y) of the ray's point
        # at mid-height: the cap's radius plus the ray's x-y travel over half the height
        slope = np.hypot(d[:, 0], d[:, 1]) / np.maximum(np.abs(d[:, 2]), 1e-12)
        half_span = 0.5 * hmax * (float(np.max(slope)) if len(slope) else 0.0)
        reach = 1.0001 * (r + half_span) + 1e-9
        chip = np.array([self.origin[0] - self.chip_margin,
                         self.origin[0] + (self.cols - 1) * self.pitch + self.chip_margin,
                         self.origin[1] - self.chip_margin,
                         self.origin[1] + (self.rows - 1) * self.pitch + self.chip_margin])
        centre_z = np.ascontiguousarray(self.centres_world()[..., 2])
        return Hits(*_k.bga_intersect(o, d, self.origin, float(self.pitch), centre_z,
                                      self.present(), float(r), chip, float(reach),
                                      hmax / 2,
                                      float(self.substrate_albedo), float(self.board_albedo),
                                      float(self.ball_albedo), float(self.ball_specular)))

    def z_range(self) -> tuple[float, float]:
        return 0.0, float(np.max(self.ball_height + self.height_offsets))

    def features(self) -> dict:
        present = self.present()
        return {
            "type": "bga",
            "rows": int(self.rows), "cols": int(self.cols), "pitch_mm": float(self.pitch),
            "ball_diameter_mm": float(self.ball_diameter),
            "ball_height_mm": float(self.ball_height),
            "substrate_z_mm": 0.0,
            "apexes_world": self.apexes_world()[present],
            "centres_world": self.centres_world()[present],
            "ball_index": np.argwhere(present),
            "height_offsets_mm": self.height_offsets.copy(),
            "missing": [list(m) for m in self.missing],
        }


def default_bga(seed: int = 0, *, rows: int = 24, cols: int = 24, n_missing: int = 4,
                height_sigma: float = 0.005, centre=(15.0, 12.0)) -> BGA:
    """A 24 x 24 BGA at 0.8 mm pitch centred at ``centre``, with ``n_missing`` balls
    missing and apex heights perturbed: N(0, height_sigma) everywhere plus two known
    outliers (+0.03 mm and -0.04 mm). All random choices come from ``seed``."""
    rng = np.random.default_rng(seed)
    off = rng.normal(0.0, height_sigma, size=(rows, cols))
    flat = rng.choice(rows * cols, size=n_missing + 2, replace=False)
    missing = tuple((int(k // cols), int(k % cols)) for k in flat[:n_missing])
    hi, lo = flat[n_missing], flat[n_missing + 1]
    off[hi // cols, hi % cols] = 0.03
    off[lo // cols, lo % cols] = -0.04
    pitch = 0.8
    origin = np.array([centre[0] - (cols - 1) * pitch / 2, centre[1] - (rows - 1) * pitch / 2])
    return BGA(rows=rows, cols=cols, pitch=pitch, origin=origin, height_offsets=off,
               missing=missing)


# --------------------------------------------------------------------------- tilted plane
@dataclass(frozen=True, eq=False)
class TiltedPlane:
    """An infinite matte plane through ``point`` with unit ``normal`` (world). Part 0."""

    normal: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    point: np.ndarray = field(default_factory=lambda: np.array([15.0, 12.0, 0.0]))
    albedo: float = 0.8

    def __post_init__(self):
        n = np.array(self.normal, dtype=float)
        if n.shape != (3,) or not np.all(np.isfinite(n)) or np.linalg.norm(n) == 0:
            raise ValueError("normal must be a finite non-zero (3,) vector")
        n = n / np.linalg.norm(n)
        if n[2] < 0:
            n = -n
        object.__setattr__(self, "normal", _frozen_array(n, (3,), "normal"))
        object.__setattr__(self, "point", _frozen_array(self.point, (3,), "point"))

    def intersect(self, origins, direction) -> Hits:
        o, d = _check_rays(origins, direction)
        return Hits(*_k.plane_intersect(o, d, self.normal, self.point, float(self.albedo)))

    def height_at(self, x, y):
        """Z of the plane at world (x, y) mm (arrays broadcast)."""
        n, p = self.normal, self.point
        return p[2] - (n[0] * (np.asarray(x) - p[0]) + n[1] * (np.asarray(y) - p[1])) / n[2]

    def z_range(self, half_size: float = 25.0) -> tuple[float, float]:
        slope = np.hypot(self.normal[0], self.normal[1]) / self.normal[2]
        return (float(self.point[2] - slope * half_size * np.sqrt(2)),
                float(self.point[2] + slope * half_size * np.sqrt(2)))

    def features(self) -> dict:
        return {"type": "tilted-plane", "normal": self.normal.copy(),
                "point_world": self.point.copy(),
                "offset_mm": float(self.normal @ self.point),
                "tilt_deg": float(np.degrees(np.arccos(self.normal[2])))}


def tilted_plane(tilt_deg: float = 10.0, *, azimuth_deg: float = 30.0, z0: float = 0.0,
                 centre=(15.0, 12.0)) -> TiltedPlane:
    """A plane tilted by ``tilt_deg`` from horizontal, its normal leaning toward azimuth
    ``azimuth_deg`` (from +x toward +y), at height ``z0`` above ``centre``."""
    t, a = np.radians(tilt_deg), np.radians(azimuth_deg)
    n = np.array([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)])
    return TiltedPlane(normal=n, point=np.array([centre[0], centre[1], z0]))


# --------------------------------------------------------------------------- height field
@dataclass(frozen=True, eq=False)
class HeightField:
    """A surface Z = h(x, y) given on a regular grid, bilinear between samples.

    Sample ``z[i, j]`` is at world ``x = origin[0] + j * pixel_size``,
    ``y = origin[1] + i * pixel_size``. Outside the grid there is nothing. Part 0.

    Intersection marches along each ray in steps of ``pixel_size / 4`` in x-y (and at
    most 1/8 of the height range in z), then refines the first sign change by bisection
    to 1e-9 mm: features narrower than a quarter sample along the ray can be missed.
    """

    z: np.ndarray
    pixel_size: float
    origin: np.ndarray = field(default_factory=lambda: np.zeros(2))
    albedo: float = 0.8

    def __post_init__(self):
        z = _frozen_array(self.z, None, "z")
        if z.ndim != 2 or min(z.shape) < 2:
            raise ValueError("z must be a 2-D array with at least 2 x 2 samples")
        object.__setattr__(self, "z", z)
        object.__setattr__(self, "origin", _frozen_array(self.origin, (2,), "origin"))
        if not self.pixel_size > 0:
            raise ValueError("pixel_size must be > 0")

    def height_at(self, x, y):
        """Bilinear height at world (x, y) (arrays broadcast); NaN outside the grid."""
        from telefringe.simulate._kernels import heightfield_eval

        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        xb, yb = np.broadcast_arrays(x, y)
        h, _, _ = heightfield_eval(self.z, float(self.pixel_size), float(self.origin[0]),
                                   float(self.origin[1]), xb.ravel(), yb.ravel())
        return h.reshape(xb.shape)

    def intersect(self, origins, direction) -> Hits:
        from telefringe.simulate._kernels import heightfield_intersect

        o, d = _check_rays(origins, direction)
        n = len(o)
        t, normal = heightfield_intersect(self.z, float(self.pixel_size),
                                          float(self.origin[0]), float(self.origin[1]),
                                          np.ascontiguousarray(o), d)
        hit = np.isfinite(t)
        normal = _face_ray(normal, d)
        return Hits(t=t, normal=np.where(hit[:, None], normal, 0.0),
                    albedo=np.where(hit, self.albedo, 0.0), specular=np.zeros(n),
                    part=np.where(hit, 0, -1).astype(np.int32))

    def z_range(self) -> tuple[float, float]:
        return float(self.z.min()), float(self.z.max())

    def features(self) -> dict:
        return {"type": "height-field", "pixel_size_mm": float(self.pixel_size),
                "origin_world": self.origin.copy(), "z": self.z.copy()}


# --------------------------------------------------------------------------- acceptance artefacts
@dataclass(frozen=True, eq=False)
class FreeSpheres:
    """Matte spheres with nothing behind them: the test sphere (one) or the two spheres
    of a ball bar, as in an acceptance test (VDI/VDE 2634 Part 2). Part k is sphere k.

    The stands and the ball bar's rod are not modelled: pixels beside the spheres see
    nothing (no light returns), so each sphere is its own region of the image. Spheres
    may shadow each other.

    Attributes
    ----------
    centres : (n, 3) mm, world.   radii : (n,) mm.   albedo : float.
    """

    centres: np.ndarray = field(default_factory=lambda: np.array([[15.0, 12.0, 0.0]]))
    radii: np.ndarray = field(default_factory=lambda: np.array([3.0]))
    albedo: float = 0.8

    def __post_init__(self):
        c = np.array(self.centres, dtype=float).reshape(-1, 3)
        r = np.array(self.radii, dtype=float).reshape(-1)
        if r.shape != (c.shape[0],) or c.shape[0] < 1:
            raise ValueError("need one radius per centre, and at least one sphere")
        if not np.all(r > 0):
            raise ValueError("radii must be > 0")
        object.__setattr__(self, "centres", _frozen_array(c, c.shape, "centres"))
        object.__setattr__(self, "radii", _frozen_array(r, r.shape, "radii"))

    def intersect(self, origins, direction) -> Hits:
        o, d = _check_rays(origins, direction)
        n = o.shape[0]
        dd = np.broadcast_to(d, o.shape)  # one direction per ray (parallel rays share it)
        t = np.full(n, np.inf)
        part = np.full(n, -1, dtype=np.int32)
        for k, (c, r) in enumerate(zip(self.centres, self.radii, strict=True)):
            oc = o - c
            b = np.einsum("ij,ij->i", oc, dd)
            disc = b * b - (np.einsum("ij,ij->i", oc, oc) - r * r)
            with np.errstate(invalid="ignore"):
                tk = -b - np.sqrt(np.where(disc >= 0, disc, np.nan))
            closer = np.isfinite(tk) & (tk > 0) & (tk < t)
            t[closer] = tk[closer]
            part[closer] = k
        hit = part >= 0
        normal = np.zeros((n, 3))
        if hit.any():
            p = o[hit] + t[hit, None] * dd[hit]
            nrm = (p - self.centres[part[hit]]) / self.radii[part[hit], None]
            # facing the incoming ray
            normal[hit] = nrm * np.where(np.einsum("ij,ij->i", nrm, dd[hit]) > 0, -1.0,
                                         1.0)[:, None]
        return Hits(t=t, normal=normal, albedo=np.where(hit, float(self.albedo), 0.0),
                    specular=np.zeros(n), part=part)

    def z_range(self) -> tuple[float, float]:
        return (float(np.min(self.centres[:, 2] - self.radii)),
                float(np.max(self.centres[:, 2] + self.radii)))

    def features(self) -> dict:
        f = {"type": "free-spheres", "centres_world": self.centres.copy(),
             "radii_mm": self.radii.copy()}
        if len(self.radii) == 2:
            f["centre_distance_mm"] = float(np.linalg.norm(self.centres[1] - self.centres[0]))
        return f


@dataclass(frozen=True, eq=False)
class RectPlate:
    """A flat matte rectangle with nothing behind it (the flatness standard of an
    acceptance test). Part 0.

    In its own frame the plate is ``|x| <= length / 2``, ``|y| <= width / 2``, ``z = 0``;
    ``R_world_scene`` (3, 3) turns that frame into the world and ``t_world_scene`` (3,)
    (mm) is the plate's centre. The plate is ideally flat and has no thickness (its
    edges are not seen).
    """

    length: float = 20.0
    width: float = 8.0
    R_world_scene: np.ndarray = field(default_factory=lambda: np.eye(3))
    t_world_scene: np.ndarray = field(default_factory=lambda: np.array([15.0, 12.0, 0.0]))
    albedo: float = 0.8

    def __post_init__(self):
        if not (self.length > 0 and self.width > 0):
            raise ValueError("length and width must be > 0")
        object.__setattr__(self, "R_world_scene",
                           _check_rotation(self.R_world_scene, "R_world_scene"))
        object.__setattr__(self, "t_world_scene",
                           _frozen_array(self.t_world_scene, (3,), "t_world_scene"))

    @property
    def normal(self) -> np.ndarray:
        """(3,) unit normal, world, with a non-negative z component."""
        n = self.R_world_scene[:, 2]
        return n if n[2] >= 0 else -n

    def corners(self) -> np.ndarray:
        """(4, 3) corners, world mm."""
        a, b = self.length / 2, self.width / 2
        loc = np.array([[-a, -b, 0.0], [a, -b, 0.0], [a, b, 0.0], [-a, b, 0.0]])
        return loc @ self.R_world_scene.T + self.t_world_scene

    def intersect(self, origins, direction) -> Hits:
        o, d = _check_rays(origins, direction)
        n_rays = o.shape[0]
        R, c = self.R_world_scene, self.t_world_scene
        nz = R[:, 2]
        dd = np.broadcast_to(d, o.shape)  # one direction per ray (parallel rays share it)
        den = dd @ nz
        t = np.full(n_rays, np.inf)
        with np.errstate(invalid="ignore", divide="ignore"):
            tt = np.where(np.abs(den) > 1e-12, ((c - o) @ nz) / np.where(den == 0, 1.0, den),
                          np.nan)
            q = (o + tt[:, None] * dd - c) @ R[:, :2]
            ok = (np.isfinite(tt) & (tt > 0) & (np.abs(q[:, 0]) <= self.length / 2)
                  & (np.abs(q[:, 1]) <= self.width / 2))
        t[ok] = tt[ok]
        hit = np.isfinite(t)
        facing = np.where(den > 0, -1.0, 1.0)[:, None] * nz
        normal = np.where(hit[:, None], facing, 0.0)
        return Hits(t=t, normal=normal, albedo=np.where(hit, float(self.albedo), 0.0),
                    specular=np.zeros(n_rays), part=np.where(hit, 0, -1).astype(np.int32))

    def z_range(self) -> tuple[float, float]:
        z = self.corners()[:, 2]
        return float(z.min()), float(z.max())

    def features(self) -> dict:
        n = self.normal
        return {"type": "rect-plate", "length_mm": float(self.length),
                "width_mm": float(self.width), "R_world_scene": self.R_world_scene.copy(),
                "t_world_scene": self.t_world_scene.copy(), "plane_normal": n.copy(),
                "plane_offset_mm": float(n @ self.t_world_scene),
                "corners_world": self.corners()}


# --------------------------------------------------------------------------- by name
SCENE_NAMES = ("plate", "steps", "sphere", "bga", "tilted-plane")


def make_scene(name: str, *, z: float = 0.0, seed: int = 0):
    """A default scene by name (the CLI's ``--scene``), raised by ``z`` mm.

    ``plate``: the calibration plate at Z = z; ``steps``: :func:`default_steps`;
    ``sphere``: :func:`default_sphere`; ``bga``: :func:`default_bga` (``seed``);
    ``tilted-plane``: :func:`tilted_plane` tilted by 6 deg (+-2 mm over the field).
    """
    if name == "plate":
        return plate_at_z(z)
    if name == "steps":
        s = default_steps()
        return StepGauge(blocks=s.blocks, base=s.base, t_world_scene=np.array([0.0, 0.0, z]))
    if name == "sphere":
        c = np.array([15.0, 12.0, 0.5 + z])
        return Sphere(center=c, plane_z=z)
    if name == "bga":
        b = default_bga(seed)
        if z != 0.0:
            raise ValueError("the BGA scene sits at Z = 0 (no --z)")
        return b
    if name == "tilted-plane":
        return tilted_plane(6.0, z0=z)
    raise ValueError(f"unknown scene {name!r}; known: {', '.join(SCENE_NAMES)}")


def rotation_xyz_deg(rx: float, ry: float, rz: float) -> np.ndarray:
    """``Rz(rz) @ Ry(ry) @ Rx(rx)`` (degrees): a vector turns about x first, then y, then z."""
    return (rotation_from_rotvec([0, 0, np.radians(rz)])
            @ rotation_from_rotvec([0, np.radians(ry), 0])
            @ rotation_from_rotvec([np.radians(rx), 0, 0]))
