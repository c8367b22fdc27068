"""Virtual rig presets: a true telecentric camera + projector and their photometry.

``paper``
    After Tables 1 and 2 of the paper (NOTES.md): camera 1280 x 1024, 5.2 um pixels,
    m = 0.1597; projector 800 x 600, 13.7 um pixels, m = 0.11733; principal points and
    rotations from the tables. The paper's rotations are re-expressed in our world frame
    (z toward the camera): ``R_ours = R_paper @ Ry(pi)``, so the camera looks down
    (``R[2] ~ (0, 0, -1)``), the grid's x runs to the right and y up in the camera image,
    and the camera and projector axes are 25.7 deg apart. Translations put the 9 x 11
    plate (reference pose = world frame) in the middle of both fields of view. The
    tables' distortion coefficients are implausible for telecentric lenses (NOTES.md), so
    distortion is chosen to move the image corners by about 1.5-3.5 px on both devices.
``fast``
    The same geometry with a 4 x 4 binned camera (320 x 256, 20.8 um pixels) and a 2 x 2
    binned projector (400 x 300, 27.4 um pixels), for tests: the same plate fits and the
    default fringe ladder still has >= 6 projector pixels per period.
``mixed``
    The paper's telecentric camera with a pinhole projector, the rig most telecentric
    profilometers use (Li & Zhang 2015): the projector is the paper's 800 x 600 panel
    (13.7 um) behind a 20 mm lens focused 150 mm away, at the plate centre, along the paper
    projector's axis (25.7 deg from the camera's), so it lights about 71 x 53 mm
    there (the camera's whole field, tilted); mild barrel distortion (k1 = -0.06).
``macro``
    A pinhole camera and a pinhole projector (Zhang & Huang 2006): a 1280 x 1024 camera
    with 4.8 um pixels behind a 25 mm lens (f/11) 200 mm from the plate, field 43 x 34 mm,
    depth of field about 12 mm (circle of confusion 2 pixels); a 1280 x 800 DLP panel
    (7.6 um mirrors) behind a 28 mm lens, 200 mm away on the other side (it lights about
    60 x 37 mm): 25 deg between the axes, baseline about 87 mm. Distortion as in
    C-mount lenses of this class (k1 = -0.15: about 2 px at the camera's corners).
``stereo``
    Two of the ``macro`` cameras at +-15 deg about a ``macro`` projector in the middle
    (30 deg between the cameras, baseline about 104 mm): the layout of most commercial
    and open structured-light scanners. Pinhole cameras because that is what such
    scanners use, and because a pinhole pair calibrated from a flat target has no mirror
    ambiguity (a telecentric pair does: it would need a side given by the user); the
    telecentric models are exercised by ``paper`` and ``mixed``. The projector only
    codes the phase; its calibration is optional.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from telefringe.devices.pinhole import PinholeDevice, PinholeIntrinsics
from telefringe.devices.rig import Rig
from telefringe.devices.telecentric import Intrinsics, TelecentricDevice
from telefringe.geometry.so3 import rotation_from_rotvec
from telefringe.targets.grid import CircleGridTarget

__all__ = ["Photometry", "VirtualRig", "get_preset", "crop_camera", "PRESETS", "PAPER_TARGET",
           "HDR_EXPOSURES", "bin_camera_any"]

#: The calibration plate of the paper: 9 x 11 dark circles, pitch 3 mm, diameter 1.5 mm.
PAPER_TARGET = CircleGridTarget(rows=9, cols=11, pitch_mm=3.0, diameter_mm=1.5)

#: Relative exposure times of the default HDR set: the dim flanks of the BGA balls valid at
#: the first (>= 99.5 % of lit ball pixels), their highlights unsaturated at the last.
HDR_EXPOSURES = (4.0, 0.6, 0.1)


@dataclass(frozen=True)
class Photometry:
    """Radiometry and sensor of the virtual rig.

    Attributes
    ----------
    gamma : float
        Projector response exponent (not compensated): a pattern level ``p`` in [0, 1]
        emits ``black_level + (1 - black_level) * p**gamma``.
    black_level : float
        Light the projector emits for level 0, relative to full white.
    projector_bit_depth : int
        Bit depth of the projector's pattern levels (8).
    ambient : float
        Uniform room light, relative to the projector's full white (reaches shadows).
    dn_per_radiance : float
        Camera signal, in 8-bit DN at exposure 1, of an albedo-1 Lambertian surface lit at
        normal incidence by the projector's full white. With the default 250, the light
        area of the plate (albedo 0.9, 28 deg incidence) reads about 200 DN.
    full_well_e : float
        Electrons at saturation (the 8-bit full scale): sets shot noise. 13000 e- gives
        about 2 DN standard deviation at 200 DN (with read noise and quantisation).
    read_noise_e : float
        Read noise, electrons RMS.
    bit_depth : int
        Camera output: 8 (uint8), 12 (stored in uint16, MSB-aligned with the top bits
        replicated below, so full scale is 65535) or 16 (uint16).
    camera_blur_px : float
        Camera defocus: Gaussian sigma in camera pixels (discrete normalised kernel on
        the pixel-integrated image; 0 disables).
    projector_blur_px : float
        Projector defocus: Gaussian sigma in projector pixels, convolved exactly with
        the projector's square pixels (fill factor 1).
    supersample : int
        Camera integration over the square pixel: at least ``supersample`` x
        ``supersample`` midpoint rays on pixels that straddle an edge (and on every
        pixel when ``smooth_gauss`` is 0).
    edge_supersample : int
        Midpoint rays per pixel side on pixels that straddle an edge (marker, ball,
        shadow, step wall, silhouette), traced exactly (the larger of this and
        ``supersample`` is used).
    smooth_gauss : int
        Pixels that see one smooth surface patch integrate with the 2 x 2
        Gauss-Legendre rule (2, exact for cubics), the centre only (1) or the
        ``supersample`` midpoint grid (0).
    specular_sigma_deg : float
        Width (Gaussian sigma, deg) of the specular lobe around the mirror direction
        (surface roughness and the illumination aperture together).
    """

    gamma: float = 2.2
    black_level: float = 0.02
    projector_bit_depth: int = 8
    ambient: float = 0.01
    dn_per_radiance: float = 250.0
    full_well_e: float = 13000.0
    read_noise_e: float = 10.0
    bit_depth: int = 8
    camera_blur_px: float = 0.5
    projector_blur_px: float = 0.6
    supersample: int = 3
    edge_supersample: int = 7
    smooth_gauss: int = 2
    specular_sigma_deg: float = 8.0

    def __post_init__(self):
        for name in ("gamma", "dn_per_radiance", "full_well_e"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"Photometry.{name} must be finite and > 0, got {v!r}")
        for name in ("black_level", "ambient", "read_noise_e", "camera_blur_px",
                     "projector_blur_px"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"Photometry.{name} must be finite and >= 0, got {v!r}")
        if self.black_level >= 1:
            raise ValueError("Photometry.black_level must be < 1")
        if self.bit_depth not in (8, 12, 16):
            raise ValueError(f"Photometry.bit_depth must be 8, 12 or 16, got {self.bit_depth!r}")
        if self.projector_bit_depth not in (8, 10, 12, 16):
            raise ValueError("Photometry.projector_bit_depth must be 8, 10, 12 or 16")
        if int(self.supersample) < 1:
            raise ValueError("Photometry.supersample must be >= 1")
        if int(self.edge_supersample) < 0:
            raise ValueError("Photometry.edge_supersample must be >= 0")
        if self.smooth_gauss not in (0, 1, 2):
            raise ValueError("Photometry.smooth_gauss must be 0, 1 or 2")
        if not (np.isfinite(self.specular_sigma_deg) and self.specular_sigma_deg > 0):
            raise ValueError("Photometry.specular_sigma_deg must be > 0")

    def noise_model(self):
        """The camera's noise as the decoder models it
        (:class:`telefringe.fringes.phase.NoiseModel`, in DN of the stored images): read
        noise and shot noise from ``read_noise_e`` and ``full_well_e``, quantisation of
        integer images. What a user would measure on a real camera (photon transfer)."""
        from telefringe.fringes.phase import NoiseModel

        dn_per_e = 255.0 / self.full_well_e
        return NoiseModel(read_noise=self.read_noise_e * dn_per_e,
                          gain=dn_per_e).scaled(self.max_value / 255.0)

    @property
    def max_value(self) -> float:
        """The camera's saturation value as stored (255, 65535)."""
        return 255.0 if self.bit_depth == 8 else 65535.0

    @property
    def full_scale_dn(self) -> float:
        """Largest raw level of the camera's ADC (255, 4095, 65535)."""
        return float(2 ** self.bit_depth - 1)


@dataclass(frozen=True, eq=False)
class VirtualRig:
    """A virtual rig: the true devices (world = reference target frame) and photometry.

    Attributes
    ----------
    name : str
    rig : telefringe.devices.rig.Rig
        True camera and projector; the world frame is the calibration target at its
        reference pose (x along columns, y along rows, z toward the camera).
    photometry : Photometry
    target : CircleGridTarget
        The calibration plate the rig is calibrated with.
    depth_of_field_mm : float
        Usable depth around z = 0 (the scene should stay within +- half of it).
    calibration_tilt_deg : float
        Largest plate tilt of a simulated calibration set (a pinhole device needs
        larger tilts than a telecentric one to see its focal length).
    """

    name: str
    rig: Rig
    photometry: Photometry = field(default_factory=Photometry)
    target: CircleGridTarget = PAPER_TARGET
    depth_of_field_mm: float = 5.0
    calibration_tilt_deg: float = 15.0

    @property
    def camera(self):
        """The reference (first) camera: the one the renderer renders."""
        return self.rig.camera

    @property
    def projector(self):
        return self.rig.projector

    @property
    def camera_names(self) -> tuple[str, ...]:
        return self.rig.camera_names

    def for_camera(self, name: str) -> VirtualRig:
        """The rig seen by its camera ``name`` (that camera first, the others dropped):
        what the renderer renders for that camera."""
        from dataclasses import replace

        if name not in self.rig.cameras:
            raise ValueError(f"no camera {name!r} in rig {self.name!r} (cameras: "
                             f"{', '.join(self.rig.camera_names)})")
        if name == self.rig.camera_names[0] and len(self.rig.cameras) == 1:
            return self
        return replace(self, rig=Rig(cameras={name: self.rig.cameras[name]},
                                     projector=self.rig.projector))

    def with_photometry(self, **changes) -> VirtualRig:
        """A copy whose photometry has some fields replaced."""
        from dataclasses import replace

        return replace(self, photometry=replace(self.photometry, **changes))


# Paper rotations (Tables 1 and 2), axis-angle, in the paper's world frame.
_ROTVEC_CAM_PAPER = (-0.09134, 0.16807, -3.04052)
_ROTVEC_PROJ_PAPER = (-0.78604, 0.06802, -3.10345)


def _paper_rotations() -> tuple[np.ndarray, np.ndarray]:
    flip = rotation_from_rotvec([0.0, np.pi, 0.0])
    return (rotation_from_rotvec(_ROTVEC_CAM_PAPER) @ flip,
            rotation_from_rotvec(_ROTVEC_PROJ_PAPER) @ flip)


def _centred_device(intr: Intrinsics, R: np.ndarray, point_world) -> TelecentricDevice:
    """A device with rotation R whose undistorted image of ``point_world`` is the image
    centre."""
    point = np.asarray(point_world, dtype=float)
    uc = (intr.width - 1) / 2.0
    vc = (intr.height - 1) / 2.0
    tx = (uc - intr.u0) * intr.du / intr.m - R[0] @ point
    ty = (vc - intr.v0) * intr.dv / intr.m - R[1] @ point
    return TelecentricDevice(intr, R, np.array([tx, ty]))


def _plate_centre(target: CircleGridTarget) -> np.ndarray:
    return np.array([(target.cols - 1) * target.pitch_mm / 2.0,
                     (target.rows - 1) * target.pitch_mm / 2.0, 0.0])


def _paper() -> VirtualRig:
    Rc, Rp = _paper_rotations()
    cam = Intrinsics(m=0.1597, du=0.0052, dv=0.0052, u0=474.9241, v0=513.0791,
                     k1=1.5e-4, s1=-2e-5, s2=3e-5, width=1280, height=1024)
    proj = Intrinsics(m=0.11733, du=0.0137, dv=0.0137, u0=460.3254, v0=468.2354,
                      k1=7e-5, s1=1e-5, s2=-2e-5, width=800, height=600)
    centre = _plate_centre(PAPER_TARGET)
    rig = Rig(_centred_device(cam, Rc, centre), _centred_device(proj, Rp, centre))
    return VirtualRig(name="paper", rig=rig)


def _fast() -> VirtualRig:
    Rc, Rp = _paper_rotations()
    # binned pixels: centre of binned pixel b covers fine pixels [4b, 4b + 3]
    cam = Intrinsics(m=0.1597, du=0.0208, dv=0.0208, u0=(474.9241 + 0.5) / 4 - 0.5,
                     v0=(513.0791 + 0.5) / 4 - 0.5, k1=6e-4, s1=-8e-5, s2=1.2e-4,
                     width=320, height=256)
    proj = Intrinsics(m=0.11733, du=0.0274, dv=0.0274, u0=(460.3254 + 0.5) / 2 - 0.5,
                      v0=(468.2354 + 0.5) / 2 - 0.5, k1=1.4e-4, s1=2e-5, s2=-4e-5,
                      width=400, height=300)
    centre = _plate_centre(PAPER_TARGET)
    rig = Rig(_centred_device(cam, Rc, centre), _centred_device(proj, Rp, centre))
    return VirtualRig(name="fast", rig=rig)


def _look_at(centre_world, target_world, x_hint) -> np.ndarray:
    """R_dev_world of a device at ``centre_world`` whose optical axis (+z) points at
    ``target_world``, its x axis (+u) as close to ``x_hint`` as the axis allows."""
    z = np.asarray(target_world, dtype=float) - np.asarray(centre_world, dtype=float)
    z /= np.linalg.norm(z)
    x = np.asarray(x_hint, dtype=float)
    x = x - (x @ z) * z
    x /= np.linalg.norm(x)
    return np.array([x, np.cross(z, x), z])


def _pinhole_at(intr: PinholeIntrinsics, centre_world, target_world, x_hint) -> PinholeDevice:
    R = _look_at(centre_world, target_world, x_hint)
    return PinholeDevice(intr, R, -R @ np.asarray(centre_world, dtype=float))


def _tilted(axis_down, angle_deg: float, about) -> np.ndarray:
    """``axis_down`` rotated by ``angle_deg`` about ``about`` (unit vectors, world)."""
    a = np.asarray(about, dtype=float)
    return rotation_from_rotvec(np.radians(angle_deg) * a / np.linalg.norm(a)) @ axis_down


def _mixed() -> VirtualRig:
    Rc, Rp = _paper_rotations()
    cam = Intrinsics(m=0.1597, du=0.0052, dv=0.0052, u0=474.9241, v0=513.0791,
                     k1=1.5e-4, s1=-2e-5, s2=3e-5, width=1280, height=1024)
    centre = _plate_centre(PAPER_TARGET)
    f_px = (20.0 * 150.0 / 130.0) / 0.0137  # 20 mm lens focused at 150 mm
    proj = PinholeIntrinsics(fx=f_px, fy=f_px, cx=407.3, cy=318.6, k1=-0.06, k2=0.03,
                             p1=1.5e-4, p2=-1e-4, width=800, height=600)
    projector = _pinhole_at(proj, centre - 150.0 * Rp[2], centre, Rp[0])
    rig = Rig(_centred_device(cam, Rc, centre), projector)
    return VirtualRig(name="mixed", rig=rig)


# pinhole-equivalent focal lengths: a lens of focal length f focused at distance d has its
# image plane at f d / (d - f) (thin lens)
_MACRO_CAMERA = PinholeIntrinsics(fx=(25.0 * 200 / 175) / 0.0048,
                                  fy=(25.0 * 200 / 175) / 0.0048, cx=645.2, cy=506.7,
                                  k1=-0.15, k2=0.2, p1=3e-4, p2=-2e-4, width=1280,
                                  height=1024)
_MACRO_PROJECTOR = PinholeIntrinsics(fx=(28.0 * 200 / 172) / 0.0076,
                                     fy=(28.0 * 200 / 172) / 0.0076, cx=636.4, cy=412.8,
                                     k1=-0.05, k2=0.04, p1=1e-4, p2=1e-4, width=1280,
                                     height=800)


def _macro() -> VirtualRig:
    centre = _plate_centre(PAPER_TARGET)
    down = np.array([0.0, 0.0, -1.0])
    # the camera 12.5 deg to one side of the vertical, the projector 12.5 deg to the other
    cam_axis = _tilted(down, 12.5, (0.0, 1.0, 0.0))
    proj_axis = _tilted(down, -12.5, (0.0, 1.0, 0.0))
    cam = _pinhole_at(_MACRO_CAMERA, centre - 200.0 * cam_axis, centre, (1.0, 0.0, 0.0))
    proj = _pinhole_at(_MACRO_PROJECTOR, centre - 200.0 * proj_axis, centre, (1.0, 0.0, 0.0))
    return VirtualRig(name="macro", rig=Rig(cam, proj), depth_of_field_mm=12.0,
                      calibration_tilt_deg=22.0)


def _stereo() -> VirtualRig:
    centre = _plate_centre(PAPER_TARGET)
    down = np.array([0.0, 0.0, -1.0])
    cams = {}
    for name, ang in (("camera", 15.0), ("camera_2", -15.0)):
        axis = _tilted(down, ang, (0.0, 1.0, 0.0))
        cams[name] = _pinhole_at(_MACRO_CAMERA, centre - 200.0 * axis, centre,
                                 (1.0, 0.0, 0.0))
    proj = _pinhole_at(_MACRO_PROJECTOR, centre - 200.0 * down + np.array([0.0, 0.0, 0.0]),
                       centre, (1.0, 0.0, 0.0))
    return VirtualRig(name="stereo", rig=Rig(cameras=cams, projector=proj),
                      depth_of_field_mm=12.0, calibration_tilt_deg=22.0)


PRESETS = {"paper": _paper, "fast": _fast, "mixed": _mixed, "macro": _macro,
           "stereo": _stereo}


def bin_camera_any(vrig: VirtualRig, factor: int) -> VirtualRig:
    """The rig with every camera's pixels binned ``factor`` x ``factor`` (either model):
    the binned pixel b covers fine pixels ``[factor b, factor b + factor - 1]``; the
    geometry is unchanged. For small, fast test rigs."""
    from dataclasses import replace

    f = int(factor)
    if f < 1:
        raise ValueError(f"factor must be >= 1, got {factor!r}")
    if f == 1:
        return vrig
    cams = {}
    for name, cam in vrig.rig.cameras.items():
        k = cam.intrinsics
        if cam.model == "telecentric":
            intr = replace(k, du=k.du * f, dv=k.dv * f, u0=(k.u0 - (f - 1) / 2.0) / f,
                           v0=(k.v0 - (f - 1) / 2.0) / f, width=k.width // f,
                           height=k.height // f)
        else:
            intr = replace(k, fx=k.fx / f, fy=k.fy / f, cx=(k.cx - (f - 1) / 2.0) / f,
                           cy=(k.cy - (f - 1) / 2.0) / f, width=k.width // f,
                           height=k.height // f)
        cams[name] = cam.with_pose(cam.R_dev_world, cam.t_dev).__class__(
            intr, cam.R_dev_world, cam.t_dev)
    return replace(vrig, name=f"{vrig.name}/bin{f}",
                   rig=Rig(cameras=cams, projector=vrig.projector))


def crop_camera(vrig: VirtualRig, *, col0: int, row0: int, width: int, height: int
                ) -> VirtualRig:
    """The same rig with only a window of the camera's sensor read out (a region of
    interest): pixel (u, v) of the crop is pixel (u + col0, v + row0) of the full camera,
    so geometry, distortion and photometry are unchanged. Handy for fast tests at full
    resolution."""
    from dataclasses import replace

    k = vrig.camera.intrinsics
    if not (0 <= col0 and 0 <= row0 and width >= 1 and height >= 1
            and col0 + width <= k.width and row0 + height <= k.height):
        raise ValueError(f"window {width} x {height} at ({col0}, {row0}) is not inside the "
                         f"{k.width} x {k.height} camera")
    cam = vrig.camera
    if cam.model == "telecentric":
        intr = replace(k, u0=k.u0 - col0, v0=k.v0 - row0, width=int(width),
                       height=int(height))
        cam = cam.with_(intrinsics=intr)
    else:  # pinhole: the principal point moves with the window
        intr = replace(k, cx=k.cx - col0, cy=k.cy - row0, width=int(width),
                       height=int(height))
        cam = cam.__class__(intr, cam.R_dev_world, cam.t_dev)
    return replace(vrig, name=f"{vrig.name}[{col0}:{col0 + width},{row0}:{row0 + height}]",
                   rig=Rig(cam, vrig.projector))


def get_preset(name: str) -> VirtualRig:
    """The virtual rig called ``name`` (see :data:`PRESETS`: "paper", "fast", "mixed",
    "macro", "stereo").

    Raises
    ------
    ValueError
        For an unknown name (the message lists the known ones).
    """
    try:
        make = PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown rig preset {name!r}; known: {', '.join(PRESETS)}") from None
    return make()
