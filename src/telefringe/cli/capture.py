"""`telefringe capture`: scans and calibration sets straight from a camera and a projector,
every frame verified; the display latency; the devices each driver finds."""

from __future__ import annotations

import contextlib
import math
import sys
from pathlib import Path

import typer

from telefringe.cli._common import detail, err_console, info, progress_bar

__all__ = ["register"]

_CAMERA_HELP = ("Camera as DRIVER[:ADDRESS]: sim, aravis:IP, pylon:SERIAL, gentl:FILE.cti "
                "(see `telefringe capture devices`).")
_PROJECTOR_HELP = ("Projector as DRIVER[:SPEC]: sim[:preset=fast,...], window:WxH+X+Y, "
                   "lightcrafter.")


# --------------------------------------------------------------------------- helpers
def _fail(msg: str, code: int = 1):
    """One line on stderr, then exit (device and capture failures: 1)."""
    from rich.markup import escape

    err_console.print(f"[bold red]error:[/bold red] {escape(msg)}", soft_wrap=True)
    raise typer.Exit(code)


@contextlib.contextmanager
def _errors():
    """Map acquisition errors to the command line's endings: an unknown or missing driver
    is a user error (exit 2), a device or capture failure exit 1; one line each."""
    from telefringe.acquisition.base import AcquisitionError, DriverUnavailable
    from telefringe.io.errors import InputError

    try:
        yield
    except DriverUnavailable as exc:
        raise InputError(str(exc)) from None
    except AcquisitionError as exc:
        _fail(str(exc))


def _open_pair(camera: str, projector: str, stack: contextlib.ExitStack):
    from telefringe.acquisition.base import open_camera, open_projector

    proj = stack.enter_context(open_projector(projector))
    cam = stack.enter_context(open_camera(camera, projector=proj))
    return cam, proj


def _parse_exposures(text: str) -> list[float]:
    from telefringe.io.errors import InputError

    try:
        vals = [float(x) for x in text.replace(" ", "").split(",") if x]
    except ValueError:
        raise InputError(f"--exposures: expected numbers separated by commas, got {text!r}") \
            from None
    if not vals or any(not (math.isfinite(v) and v > 0) for v in vals):
        raise InputError(f"--exposures: relative exposures must be positive, got {text!r}")
    if len(set(vals)) != len(vals):
        raise InputError(f"--exposures: relative exposures must differ, got {text!r}")
    return vals


def _parse_roi(text: str | None):
    from telefringe.io.errors import InputError

    if not text:
        return None
    try:
        size, _, rest = text.partition("+")
        w, h = (int(v) for v in size.lower().split("x"))
        x, y = (int(v) for v in rest.split("+"))
    except ValueError:
        raise InputError(f"--roi: expected WIDTHxHEIGHT+X+Y (pixels), got {text!r}") from None
    if w < 1 or h < 1 or x < 0 or y < 0:
        raise InputError(f"--roi: expected WIDTHxHEIGHT+X+Y with positive sizes, got {text!r}")
    return (x, y, w, h)


def _pattern_groups(*, width, height, steps, periods, axes, gray, complementary):
    from telefringe.cli.patterns import _parse_axes, _parse_periods
    from telefringe.fringes.decode import DecodeError, choose_method
    from telefringe.fringes.patterns import pattern_groups
    from telefringe.io.errors import InputError

    per = _parse_periods(periods)
    ax = _parse_axes(axes)
    if steps < 3:
        raise InputError(f"--steps must be >= 3, got {steps}")
    if gray and not 1 <= gray <= 16:
        raise InputError(f"--gray must be 1..16 bits, got {gray}")
    if gray and 2 ** gray not in per:
        raise InputError(f"--gray {gray} fixes the order of the group with {2 ** gray} periods;"
                         f" add {2 ** gray} to --periods")
    for a in ax:
        length = width if a == "u" else height
        if any(2 * p > length for p in per):
            raise InputError(f"--periods {periods}: at most {length // 2} periods fit the "
                             f"projector's {length} pixels along {a}")
        try:
            choose_method(per, length=length, gray_bits=gray or None)
        except DecodeError as exc:
            raise InputError(f"--periods {periods}: {exc}") from None
    return pattern_groups(steps=steps, periods=per, axes=ax, gray_bits=gray or None,
                          complementary=complementary)


def _latency_for(cam, proj, latency: float | None, latency_file: Path | None):
    from telefringe.acquisition.capture import LatencyUsed
    from telefringe.acquisition.latency import load_latency, pair_key
    from telefringe.io.errors import InputError

    if latency is not None:
        if not (math.isfinite(latency) and 0 <= latency < 10):
            raise InputError(f"--latency must be 0..10 s, got {latency}")
        return LatencyUsed(float(latency), "option")
    entry = load_latency(pair_key(cam.info, proj.info), latency_file)
    if entry is not None:
        return LatencyUsed(float(entry["latency_s"]), "measured")
    return None


def _base_exposure(exposure: float | None, proj) -> float:
    from telefringe.io.errors import InputError

    if exposure is None:
        period = proj.info.period_s
        return 2 * period if period > 0 else 0.02
    if not (math.isfinite(exposure) and 1e-6 <= exposure <= 10):
        raise InputError(f"--exposure must be 1e-6..10 s, got {exposure}")
    return float(exposure)


def _policy(retries: int):
    from telefringe.acquisition.sequence import Policy
    from telefringe.io.errors import InputError

    if not 0 <= retries <= 20:
        raise InputError(f"--retries must be 0..20, got {retries}")
    return Policy(frame_retries=retries, group_rounds=max(1, min(retries, 3)))


def _summary(block: dict) -> None:
    detail(f"camera {block['camera']['model']} ({block['camera']['serial']}), projector "
           f"{block['projector']['model']} ({block['projector']['serial']})")
    for w in block["warnings"]:
        err_console.print(f"[yellow]warning:[/yellow] {w}", soft_wrap=True)
    for e in block["events"]:
        detail(e)


# --------------------------------------------------------------------------- scan
def scan_cmd(
    out: Path = typer.Argument(..., help="New scan folder (images + scan.json)."),
    camera: str = typer.Option(..., "--camera", help=_CAMERA_HELP),
    projector: str = typer.Option(..., "--projector", help=_PROJECTOR_HELP),
    steps: int = typer.Option(4, "--steps", help="Phase steps per group (>= 3; >= 4 lets "
                              "every frame's phase step be checked)."),
    periods: str = typer.Option("1,8,64", "--periods",
                                help="Period counts of the ladder, comma separated."),
    axes: str = typer.Option("u,v", "--axes", help="u (vertical fringes), v or u,v."),
    gray: int = typer.Option(0, "--gray", help="Also a Gray code with this many bits (its "
                             "phase group has 2**bits periods); 0: none."),
    complementary: bool = typer.Option(True, "--complementary/--plain",
                                       help="Complementary Gray code (one more image)."),
    white_black: bool = typer.Option(True, "--white-black/--no-white-black",
                                     help="Add full-on and full-off frames."),
    exposure: float = typer.Option(None, "--exposure", help="Base exposure, seconds "
                                   "(default: two refresh periods)."),
    exposures: str = typer.Option("1", "--exposures", help="Relative exposures for HDR, "
                                  "e.g. 4,0.6,0.1 (each a pass over the patterns)."),
    whole_periods: bool = typer.Option(True, "--whole-periods/--any-exposure",
                                       help="Round exposures to whole refresh periods."),
    mode: str = typer.Option("streamed", "--mode", help="streamed (show, wait, software "
                             "trigger) or sequenced (the projector triggers the camera)."),
    latency: float = typer.Option(None, "--latency", help="Display latency, seconds "
                                  "(default: the one `telefringe capture latency` kept)."),
    latency_file: Path = typer.Option(None, "--latency-file", envvar="TELEFRINGE_LATENCY_FILE",
                                      help="Where measured latencies are kept."),
    pixel_format: str = typer.Option("Mono8", "--pixel-format",
                                     help="Mono8, Mono10, Mono12 or Mono16."),
    gain: float = typer.Option(0.0, "--gain", help="Camera gain, dB."),
    roi: str = typer.Option(None, "--roi", help="Camera region WIDTHxHEIGHT+X+Y."),
    retries: int = typer.Option(3, "--retries", help="Re-shoots per frame before giving up."),
    force: bool = typer.Option(False, "--force", help="Replace an existing folder."),
):
    """Capture a scan: show each pattern, grab, verify every frame (status, ids,
    saturation, modulation, phase steps), re-shoot what fails, write the scan folder with
    its provenance (scan.json's `capture` block).

    Example: telefringe capture scan sim_scan --camera sim --projector sim:preset=fast
    --periods 1,8,64 --exposures 1
    """
    from telefringe.acquisition.capture import capture_scan
    from telefringe.io.atomic import check_can_write
    from telefringe.io.errors import InputError
    from telefringe.io.scan_json import write_scan

    check_can_write(out, force=force)
    exps = _parse_exposures(exposures)
    roi_t = _parse_roi(roi)
    if mode not in ("streamed", "sequenced"):
        raise InputError(f"--mode must be streamed or sequenced, got {mode!r}")
    policy = _policy(retries)
    with _errors(), contextlib.ExitStack() as stack:
        cam, proj = _open_pair(camera, projector, stack)
        groups = _pattern_groups(width=proj.info.width, height=proj.info.height, steps=steps,
                                 periods=periods, axes=axes, gray=gray,
                                 complementary=complementary)
        lat = _latency_for(cam, proj, latency, latency_file)
        base = _base_exposure(exposure, proj)
        n = sum(g.count for g in groups) * len(exps) + 2 * white_black
        with progress_bar(f"capturing {n} frames", n) as advance:
            res = capture_scan(cam, proj, groups=groups, white_black=white_black,
                               exposure_s=base, exposures=exps, mode=mode, latency=lat,
                               pixel_format=pixel_format, gain_db=gain, roi=roi_t,
                               whole_periods=whole_periods, policy=policy, progress=advance)
        write_scan(out, res.scan, force=force, capture=res.capture)
    _summary(res.capture)
    lat_used = res.capture["latency"]
    info(f"wrote {out}: {len(res.capture['frames'])} frames verified, "
         f"{res.capture['retries']} re-shot; waited {lat_used['wait_periods']} refresh "
         f"period(s) after each flip (latency {lat_used['latency_s'] * 1e3:.1f} ms, "
         f"{lat_used['source']})")


# --------------------------------------------------------------------------- calibration
def _coverage(centres, shape, cells: int = 4) -> float:
    """Fraction of a cells x cells grid over the image holding a detected marker."""
    import numpy as np

    rows, cols = shape
    hit = np.zeros((cells, cells), dtype=bool)
    for c in centres:
        ok = np.all(np.isfinite(c), axis=1)
        iu = np.clip((c[ok, 0] / cols * cells).astype(int), 0, cells - 1)
        iv = np.clip((c[ok, 1] / rows * cells).astype(int), 0, cells - 1)
        hit[iv, iu] = True
    return float(hit.mean())


def _tilt(det, ref=None) -> tuple[float, float]:
    """Tilt of the plate from the reference pose (deg) and the azimuth of its tilt axis in
    the image (deg), from the foreshortening of the detected lattice relative to the
    reference's (an orthographic view of a square grid; a rough guide for the user)."""
    import numpy as np

    L = np.asarray(det.lattice, dtype=float)
    if not np.all(np.isfinite(L)):
        return float("nan"), float("nan")
    if ref is not None and np.all(np.isfinite(ref.lattice)):
        L = L @ np.linalg.inv(np.asarray(ref.lattice, dtype=float))
    U, s, _ = np.linalg.svd(L)
    tilt = float(np.degrees(np.arccos(np.clip(s[1] / s[0], 0.0, 1.0))))
    axis = float(np.degrees(np.arctan2(U[1, 0], U[0, 0]))) % 180.0
    return tilt, axis


_MODELS = ("telecentric", "pinhole")
_SIDES = ("left", "right", "top", "bottom")


def _device_models(vrig, camera_model, projector_model, camera_pixel_size,
                   projector_pixel_size, projector_side):
    """calibration.json's device models, pixel sizes (mm, telecentric devices only) and
    projector side: as given, else the sim rig's, else telecentric (calibration.json's
    default). Raises InputError on a bad or missing value."""
    from telefringe.io.errors import InputError

    devices = {"camera": (camera_model, camera_pixel_size),
               "projector": (projector_model, projector_pixel_size)}
    models, sizes = {}, {}
    for name, (model, size) in devices.items():
        dev = None if vrig is None else (vrig.rig.camera if name == "camera"
                                          else vrig.projector)
        model = model or (dev.model if dev is not None else "telecentric")
        if model not in _MODELS:
            raise InputError(f"--{name}-model must be telecentric or pinhole, got {model!r}")
        models[name] = model
        if model == "pinhole":
            if size is not None:
                raise InputError(f"--{name}-pixel-size is for a telecentric {name}; a pinhole "
                                 f"{name}'s scale comes from its focal length")
            continue
        if size is None and dev is not None and dev.model == "telecentric":
            size = float(dev.intrinsics.du)
        if size is None:
            raise InputError(f"give --{name}-pixel-size (mm): calibration.json needs it for "
                             f"a telecentric {name} (or --{name}-model pinhole)")
        if not (math.isfinite(size) and size > 0):
            raise InputError(f"--{name}-pixel-size must be > 0 mm, got {size}")
        sizes[name] = (float(size), float(size))
    side = projector_side
    if side is None and vrig is not None:
        from telefringe.simulate.calibration import projector_side as rig_side

        side = rig_side(vrig)
    if side is not None and side not in _SIDES:
        raise InputError(f"--projector-side must be one of {', '.join(_SIDES)}, got {side!r}")
    return models, sizes, side


def calibration_cmd(
    out: Path = typer.Argument(..., help="New calibration-set folder."),
    camera: str = typer.Option(..., "--camera", help=_CAMERA_HELP),
    projector: str = typer.Option(..., "--projector", help=_PROJECTOR_HELP),
    poses: int = typer.Option(8, "--poses", help="Plate poses (the first is the reference)."),
    rows: int = typer.Option(None, "--rows", help="Circle rows of the plate (sim: its own)."),
    cols: int = typer.Option(None, "--cols", help="Circle columns of the plate."),
    pitch: float = typer.Option(None, "--pitch", help="Circle pitch, mm."),
    diameter: float = typer.Option(None, "--diameter", help="Circle diameter, mm."),
    camera_model: str = typer.Option(None, "--camera-model",
                                     help="telecentric or pinhole (sim: its rig's; else "
                                          "telecentric). calibrate then fits this model."),
    projector_model: str = typer.Option(None, "--projector-model",
                                        help="telecentric or pinhole (sim: its rig's; else "
                                             "telecentric)."),
    camera_pixel_size: float = typer.Option(None, "--camera-pixel-size",
                                            help="Camera pixel size, mm (telecentric only)."),
    projector_pixel_size: float = typer.Option(None, "--projector-pixel-size",
                                               help="Projector pixel size, mm (telecentric "
                                                    "only)."),
    projector_side: str = typer.Option(None, "--projector-side",
                                       help="Where the projector is seen from the camera: "
                                            "left, right, top or bottom (sim: its rig's); a "
                                            "telecentric pair needs it to calibrate (the "
                                            "shadow of an upright pin falls away from the "
                                            "projector)."),
    steps: int = typer.Option(4, "--steps", help="Phase steps per group."),
    periods: str = typer.Option("1,8,64", "--periods", help="Period counts of the ladder."),
    axes: str = typer.Option("u,v", "--axes", help="u, v or u,v."),
    exposure: float = typer.Option(None, "--exposure", help="Exposure, seconds."),
    latency: float = typer.Option(None, "--latency", help="Display latency, seconds."),
    latency_file: Path = typer.Option(None, "--latency-file", envvar="TELEFRINGE_LATENCY_FILE",
                                      help="Where measured latencies are kept."),
    pixel_format: str = typer.Option("Mono8", "--pixel-format", help="Camera pixel format."),
    retries: int = typer.Option(3, "--retries", help="Re-shoots per frame before giving up."),
    force: bool = typer.Option(False, "--force", help="Replace an existing folder."),
):
    """Capture a calibration set: before each pose, wait for Enter (type q to stop),
    capture a verified scan of the circle plate, show whether the grid was found and how
    well the poses so far cover the field and the tilts; write the poses and
    calibration.json (each device's model, pixel sizes of the telecentric ones, the
    projector's side where known). With the sim driver the virtual plate moves to its next
    pose and the devices' models and side come from its rig.

    Example: printf '\\n\\n\\n\\n' | telefringe capture calibration sim_cal --camera sim
    --projector sim:preset=fast,scene=calibration,poses=5 --poses 4

    A pinhole camera and projector: ... --camera-model pinhole --projector-model pinhole
    """
    import numpy as np

    from telefringe.acquisition.capture import capture_scan
    from telefringe.calibration.manifest import CalibrationSetManifest
    from telefringe.io.atomic import atomic_dir, check_can_write
    from telefringe.io.calibration_json import write_calibration_manifest
    from telefringe.io.errors import InputError
    from telefringe.io.scan_json import write_scan
    from telefringe.targets.circle_grid import detect_circle_grid
    from telefringe.targets.grid import CircleGridTarget

    check_can_write(out, force=force)
    if not 3 <= poses <= 200:
        raise InputError(f"--poses must be 3..200, got {poses}")
    policy = _policy(retries)
    with _errors(), contextlib.ExitStack() as stack:
        cam, proj = _open_pair(camera, projector, stack)
        sim_poses = getattr(cam, "n_poses", None)
        vrig = getattr(getattr(cam, "rig", None), "vrig", None)
        if sim_poses is not None:
            if sim_poses < poses:
                raise InputError(f"the sim plate has {sim_poses} poses; give "
                                 f"--projector sim:scene=calibration,poses={poses} (or more)")
        t = vrig.target if vrig is not None else None
        try:
            target = CircleGridTarget(rows=rows or (t.rows if t else 9),
                                      cols=cols or (t.cols if t else 11),
                                      pitch_mm=pitch or (t.pitch_mm if t else 3.0),
                                      diameter_mm=diameter or (t.diameter_mm if t else 1.5))
        except ValueError as exc:
            raise InputError(f"target: {exc}") from None
        models, sizes, side = _device_models(vrig, camera_model, projector_model,
                                             camera_pixel_size, projector_pixel_size,
                                             projector_side)
        groups = _pattern_groups(width=proj.info.width, height=proj.info.height, steps=steps,
                                 periods=periods, axes=axes, gray=0, complementary=True)
        lat = _latency_for(cam, proj, latency, latency_file)
        base = _base_exposure(exposure, proj)
        names = []
        centres = []
        tilts = []
        ref_det = None
        with atomic_dir(out, force=force) as tmp:
            k = 0
            sim_k = 0               # the sim "user" moves the plate at every Enter
            while k < poses:
                info(f"pose {k + 1}/{poses}: place the plate"
                     + (" (reference: flat, in the middle of the field)" if k == 0 else "")
                     + ", then press Enter (q: stop)")
                line = sys.stdin.readline()
                if line == "" or line.strip().lower() in ("q", "quit"):
                    _fail(f"stopped at pose {k + 1} of {poses}: nothing was written", 130
                          if line else 1)
                if sim_poses is not None:
                    if sim_k >= sim_poses:
                        _fail(f"the sim plate has no pose left after {sim_poses}: "
                              f"nothing was written")
                    cam.move_to_pose(sim_k)
                    sim_k += 1
                n = sum(g.count for g in groups) + 2
                with progress_bar(f"pose {k + 1}: capturing {n} frames", n) as advance:
                    res = capture_scan(cam, proj, groups=groups, white_black=True,
                                       exposure_s=base, mode="streamed", latency=lat,
                                       pixel_format=pixel_format, policy=policy,
                                       progress=advance)
                det = detect_circle_grid(res.scan.white.astype(float), rows=target.rows,
                                         cols=target.cols, dark=target.circles.startswith("dark"))
                if not det:
                    info(f"  grid NOT found ({det.reason}): move the plate and press Enter to "
                         f"take pose {k + 1} again")
                    continue
                name = f"pose_{k:02d}"
                write_scan(tmp / name, res.scan, capture=res.capture)
                names.append(name)
                centres.append(det.centers)
                if k == 0:
                    ref_det = det
                    _summary(res.capture)
                tilt, axis = (0.0, 0.0) if k == 0 else _tilt(det, ref_det)
                tilts.append((tilt, axis))
                cov = _coverage(centres, res.scan.white.shape)
                tilted = [(a, b) for a, b in tilts if np.isfinite(a) and a >= 3.0]
                dirs = len({int(b // 45) for _a, b in tilted})
                info(f"  grid found: {det.n_found}/{target.rows * target.cols} markers; "
                     f"tilt from the reference {tilt:.1f} deg (axis {axis:.0f} deg); field "
                     f"covered "
                     f"{100 * cov:.0f} %; tilted poses {len(tilted)}, tilt axes in {dirs}/4 "
                     f"directions")
                k += 1
            man = CalibrationSetManifest(target=target,
                                         camera_pixel_size=sizes.get("camera"),
                                         projector_pixel_size=sizes.get("projector"),
                                         poses=tuple(names), reference_pose=names[0],
                                         models=models, pixel_sizes=sizes,
                                         projector_side=side)
            write_calibration_manifest(tmp, man)
    if len([t for t in tilts if t[0] >= 3.0]) < 2:
        err_console.print("[yellow]warning:[/yellow] fewer than 2 poses tilted by 3 deg or "
                          "more: the calibration may not separate the devices' parameters")
    info(f"wrote {out}: {len(names)} poses and calibration.json")


# --------------------------------------------------------------------------- latency
def latency_cmd(
    camera: str = typer.Option(..., "--camera", help=_CAMERA_HELP),
    projector: str = typer.Option(..., "--projector", help=_PROJECTOR_HELP),
    exposure: float = typer.Option(None, "--exposure", help="Short exposure, seconds "
                                   "(default: a quarter of a refresh period)."),
    max_delay: float = typer.Option(0.2, "--max-delay", help="Longest delay tried, seconds."),
    latency_file: Path = typer.Option(None, "--latency-file", envvar="TELEFRINGE_LATENCY_FILE",
                                      help="Where to keep it (default: the user config dir)."),
    save: bool = typer.Option(True, "--save/--no-save", help="Keep the result for captures."),
):
    """Measure the display-to-camera latency (black/white steps, the camera triggered at
    increasing delays after the flip) and keep it for later captures of this pair.

    Example: telefringe capture latency --camera sim --projector sim:preset=fast
    --latency-file lat.json
    """
    from telefringe.acquisition.base import Trigger
    from telefringe.acquisition.latency import (
        latency_file as default_file,
    )
    from telefringe.acquisition.latency import (
        measure_latency,
        pair_key,
        save_latency,
    )
    from telefringe.acquisition.sequence import wait_periods
    from telefringe.io.errors import InputError

    if not (math.isfinite(max_delay) and 0.001 <= max_delay <= 5):
        raise InputError(f"--max-delay must be 0.001..5 s, got {max_delay}")
    with _errors(), contextlib.ExitStack() as stack:
        cam, proj = _open_pair(camera, projector, stack)
        period = proj.info.period_s
        e = exposure if exposure is not None else (period / 4 if period > 0 else 0.002)
        if not (math.isfinite(e) and 1e-6 <= e <= 1):
            raise InputError(f"--exposure must be 1e-6..1 s, got {e}")
        settings = cam.configure(exposure_s=e, trigger=Trigger.SOFTWARE)
        cam.start()
        n = int(max_delay / (settings.exposure_s / 2)) + 1
        with progress_bar("black/white steps", n) as advance:
            m = measure_latency(cam, proj, exposure_s=settings.exposure_s,
                                max_delay_s=max_delay, progress=advance)
        cam.stop()
        k = wait_periods(m.latency_s, period)
        info(f"latency {m.latency_s * 1e3:.2f} ms (50 % point {m.half_s * 1e3:.2f} ms, "
             f"exposure {m.exposure_s * 1e3:.3f} ms, {len(m.delays_s)} delays); captures will "
             f"wait {k} refresh period(s) = {k * period * 1e3:.1f} ms after each flip")
        if save:
            path = save_latency(pair_key(cam.info, proj.info), {
                "latency_s": m.latency_s, "half_s": m.half_s, "exposure_s": m.exposure_s,
                "refresh_hz": proj.info.refresh_hz, "wait_periods": k,
                "camera": f"{cam.info.driver}:{cam.info.address}",
                "projector": f"{proj.info.driver}:{proj.info.address}"},
                latency_file or default_file())
            info(f"kept in {path}")


# --------------------------------------------------------------------------- devices
def devices_cmd(
    kind: str = typer.Option("all", "--kind", help="camera, projector or all."),
):
    """List what each camera and projector driver finds (and what a missing driver needs).

    Example: telefringe capture devices --kind camera
    """
    from telefringe.acquisition.base import list_devices
    from telefringe.io.errors import InputError

    if kind not in ("camera", "projector", "all"):
        raise InputError(f"--kind must be camera, projector or all, got {kind!r}")
    for k in (("camera", "projector") if kind == "all" else (kind,)):
        info(f"[bold]{k}s[/bold]")
        for driver, found in list_devices(k).items():
            if isinstance(found, str):
                info(f"  {driver}: {found}")
            elif not found:
                info(f"  {driver}: nothing found")
            else:
                for d in found:
                    info(f"  {driver}:{d.address}  {d.model} {d.serial}  {d.detail}".rstrip())


def register(app: typer.Typer) -> None:
    """Add ``telefringe capture scan|calibration|latency|devices``."""
    cap = typer.Typer(name="capture", no_args_is_help=True,
                      help="Capture scans and calibration sets from a camera and a "
                           "projector, every frame verified.")
    cap.command("scan")(scan_cmd)
    cap.command("calibration")(calibration_cmd)
    cap.command("latency")(latency_cmd)
    cap.command("devices")(devices_cmd)
    app.add_typer(cap, name="capture")
