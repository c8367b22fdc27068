"""The whole step: scan -> decoded projector coordinates -> cloud -> height map."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from telefringe.devices.rig import Rig
from telefringe.fringes.images import radiance_image, scan_radiance
from telefringe.fringes.scan import PhaseGroup
from telefringe.reconstruction import telecentric
from telefringe.reconstruction._rig import as_rig as _as_rig
from telefringe.reconstruction.cloud import PointCloud, TriangulationError
from telefringe.reconstruction.heightmap import HeightMap, height_map

__all__ = ["Reconstruction", "reconstruct_scan", "reconstruct_stereo_scans", "triangulate"]


def triangulate(rig, coords, *, max_residual: float | None = 1.0,
                max_sigma_z: float | None = None, use_v_p: bool = True,
                check_bounds: bool = True) -> PointCloud:
    """Triangulate decoded projector coordinates with any camera + projector rig.

    The telecentric fast path (:func:`telefringe.reconstruction.telecentric.triangulate`)
    when both devices are telecentric, else the generic path
    (:func:`telefringe.reconstruction.generic.triangulate`); both solve the same equations
    (tested to agree within 1e-9 mm) and take the same arguments. ``coords`` as there:
    ``u_p`` (rows, cols) projector px per camera pixel (and ``v_p``, ``mask``,
    ``sigma_u_p``, ``sigma_v_p``). Returns a :class:`PointCloud` (mm).
    """
    rig = _as_rig(rig)
    fast = (rig.projector is not None and rig.camera.model == "telecentric"
            and rig.projector.model == "telecentric")
    if fast:
        fn = telecentric.triangulate
    else:  # imported here: a telecentric rig's command need not load it
        from telefringe.reconstruction import generic

        fn = generic.triangulate
    return fn(rig, coords, max_residual=max_residual, max_sigma_z=max_sigma_z,
              use_v_p=use_v_p, check_bounds=check_bounds)


def _check_sizes(scan, rig: Rig, camera_name: str = "camera") -> None:
    """Raise :class:`TriangulationError` when the scan's image or projector size does not
    fit the rig's devices (where they declare a size)."""
    shape = tuple(int(n) for n in scan.stacks[0].shape[1:])
    size = rig.cameras[camera_name].image_size
    label = "camera" if camera_name == "camera" else f"camera {camera_name!r}"
    if size is not None and (size[1], size[0]) != shape:
        raise TriangulationError(
            f"the scan's images are {shape[1]} x {shape[0]} (width x height) but the rig's "
            f"{label} is {size[0]} x {size[1]}: the rig does not belong to this scan")
    psize = None if rig.projector is None else rig.projector.image_size
    man = scan.manifest
    if psize is not None and (man.projector_width, man.projector_height) != tuple(psize):
        raise TriangulationError(
            f"the scan's patterns are for a {man.projector_width} x {man.projector_height} "
            f"projector but the rig's projector is {psize[0]} x {psize[1]}: use the rig.json "
            "of the rig that took this scan")


@dataclass(frozen=True, eq=False)
class Reconstruction:
    """What :func:`reconstruct_scan` makes of one scan.

    Attributes
    ----------
    coords : telefringe.decode.ProjectorCoordinates
    cloud : PointCloud
    height : HeightMap or None
    texture : (rows, cols) ndarray of float32, the fringe-free camera image (white frame
        or mean of a phase group), for marker detection and display.
    radiance : (rows, cols) ndarray of float32 or None, brightness per unit exposure
        (DN at exposure 1) from the mean of every phase image (:func:`scan_radiance`; HDR:
        the longest unsaturated exposure), or the decoder's background when the scan has
        no phase images; for locating specular highlights (BGA).
    """

    coords: object
    cloud: PointCloud
    height: HeightMap | None
    texture: np.ndarray
    radiance: np.ndarray | None = None
    coords_2: object = None  #: the second camera's coordinates (two-camera rigs)
    #: the StereoMatch (two-camera rigs: the matched sub-pixels of the second camera, for
    #: :func:`telefringe.reconstruction.stereo.match_noise`)
    match: object = None



def reconstruct_scan(scan, rig: Rig, *, max_residual: float | None = 1.0,
                     max_sigma_z: float | None = None, pixel_mm: float | None = None,
                     with_height_map: bool = True, **decode_options) -> Reconstruction:
    """Decode a scan and triangulate it with a rig (what ``telefringe reconstruct`` does).

    Parameters
    ----------
    scan : telefringe.scan.Scan
    rig : Rig
    max_residual, max_sigma_z : see :func:`triangulate`.
    pixel_mm : grid spacing of the height map (default: the camera's footprint).
    with_height_map : bool, resample the cloud on a regular XY grid.
    **decode_options : passed to :func:`telefringe.decode.decode` (``method``,
        ``gamma_correction``, ``min_modulation``, ``phase_errors``, ``noise``, ...).
        ``noise`` defaults to ``"auto"`` here: the camera noise behind sigma is the scan's
        calibrated one (scan.json ``meta.camera_noise``), else measured from the scan's own
        phase steps, else the decoder's typical camera (see
        :func:`telefringe.fringes.noise.resolve_noise`; the choice is in
        ``coords.noise``). A
        :class:`~telefringe.calibrate.RigCalibration` that learned the projector's
        nonlinearity (``phase_errors``) gives it to the decoder unless ``phase_errors`` is
        passed here (``phase_errors=None`` learns it from the scan instead).

    Raises
    ------
    TriangulationError
        When the scan's image size or projector size does not match the rig.
    telefringe.decode.DecodeError
        When the scan cannot be decoded.
    """
    from telefringe.fringes.decode import decode
    from telefringe.fringes.images import fringe_free_image

    learned = getattr(rig, "phase_errors", None)  # a RigCalibration's projector model
    if learned and "phase_errors" not in decode_options:
        decode_options = {**decode_options, "phase_errors": learned}
    decode_options = {"noise": "auto", **decode_options}
    rig = _as_rig(rig)
    if rig.projector is None:
        raise TriangulationError("the rig has no calibrated projector: a one-camera scan "
                                 "needs one (two cameras: reconstruct_stereo)")
    _check_sizes(scan, rig)
    coords = decode(scan, **decode_options)
    cloud = triangulate(rig, coords, max_residual=max_residual, max_sigma_z=max_sigma_z)
    hm = None
    if with_height_map and cloud.count >= 3:
        hm = height_map(cloud, pixel_mm=pixel_mm)
    texture = np.asarray(fringe_free_image(scan), dtype=np.float32)
    # no phase images (a Gray-code-only scan): the decoder's background; any other error
    # of scan_radiance is raised
    has_phase = any(isinstance(g, PhaseGroup) for g in scan.manifest.groups)
    radiance = scan_radiance(scan) if has_phase else radiance_image(coords)
    return Reconstruction(coords, cloud, hm, texture, radiance)


def reconstruct_stereo_scans(scan_1, scan_2, rig: Rig, *, max_residual: float | None = 1.0,
                             max_sigma_z: float | None = None, pixel_mm: float | None = None,
                             with_height_map: bool = True, search_mm: float | None = None,
                             **decode_options) -> Reconstruction:
    """Decode the scans of two cameras and match them (a two-camera rig).

    Parameters
    ----------
    scan_1, scan_2 : telefringe.scan.Scan, the same patterns seen by the rig's first and
        second camera (the cloud is on the first camera's pixel grid).
    rig : Rig with two cameras (a projector is optional; where the rig has one, the
        scans' projector size is checked against it).
    max_residual, max_sigma_z, search_mm : see
        :func:`telefringe.reconstruction.stereo.match_stereo`.
    pixel_mm, with_height_map, **decode_options : as for :func:`reconstruct_scan`.

    Returns
    -------
    Reconstruction
        ``coords`` the first camera's, ``coords_2`` the second's; texture and radiance of
        the first camera.

    Raises
    ------
    TriangulationError
        A rig with fewer than two cameras, or scans whose image or projector sizes do not
        match the rig's devices.
    telefringe.decode.DecodeError
        When a scan cannot be decoded.
    """
    from telefringe.fringes.decode import decode
    from telefringe.fringes.images import fringe_free_image
    from telefringe.reconstruction.stereo import match_stereo

    learned = getattr(rig, "phase_errors", None)
    if learned and "phase_errors" not in decode_options:
        decode_options = {**decode_options, "phase_errors": learned}
    decode_options = {"noise": "auto", **decode_options}
    rig = _as_rig(rig)
    names = rig.camera_names
    if len(names) < 2:
        raise TriangulationError(
            f"two scans need a rig with two cameras; this rig has one ({names[0]})")
    _check_sizes(scan_1, rig, names[0])
    _check_sizes(scan_2, rig, names[1])
    m1, m2 = scan_1.manifest, scan_2.manifest
    if (m1.projector_width, m1.projector_height) != (m2.projector_width,
                                                     m2.projector_height):
        raise TriangulationError(
            f"the two scans' patterns are for different projectors ({m1.projector_width} x "
            f"{m1.projector_height} and {m2.projector_width} x {m2.projector_height})")
    coords_1 = decode(scan_1, **decode_options)
    coords_2 = decode(scan_2, **decode_options)
    match = match_stereo(rig, coords_1, coords_2, max_residual=max_residual,
                         max_sigma_z=max_sigma_z, search_mm=search_mm)
    cloud = match.cloud
    hm = None
    if with_height_map and cloud.count >= 3:
        hm = height_map(cloud, pixel_mm=pixel_mm)
    texture = np.asarray(fringe_free_image(scan_1), dtype=np.float32)
    has_phase = any(isinstance(g, PhaseGroup) for g in m1.groups)
    radiance = scan_radiance(scan_1) if has_phase else radiance_image(coords_1)
    return Reconstruction(coords_1, cloud, hm, texture, radiance, coords_2, match)
