"""Exports of reconstructions and measurements (see docs/formats.md).

- ``points.npz``: the organised point cloud (:func:`write_points`, :func:`read_points`);
- ``cloud.ply``: binary little-endian PLY of the valid points (CloudCompare, MeshLab,
  Open3D read it);
- ``heightmap.tif``: 32-bit float height map (NaN = no data) with its pixel size in the
  TIFF resolution tags and, exactly, in the sidecar ``heightmap.json``;
- ``heightmap.png``: a preview with a colour bar;
- BGA: a CSV with one row per grid position and a PNG map coloured by apex height;
- any result dataclass as JSON (:func:`to_jsonable`).

Every writer writes atomically (temporary name, then rename) and refuses to replace an
existing file unless ``force``.
"""

from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path

import numpy as np

from telefringe.io.atomic import atomic_file, write_json_atomic
from telefringe.io.errors import InputError

__all__ = [
    "POINTS_FORMAT",
    "HEIGHTMAP_FORMAT",
    "write_points",
    "read_points",
    "load_points",
    "PointsFile",
    "write_ply",
    "write_height_tiff",
    "read_height_tiff",
    "write_height_png",
    "write_bga_csv",
    "write_bga_png",
    "write_reconstruction",
    "to_jsonable",
    "write_json",
    "plane_summary",
    "plate_summary",
    "sphere_summary",
    "bga_summary",
    "steps_summary",
    "cloud_summary",
]

POINTS_FORMAT = "telefringe-points"
HEIGHTMAP_FORMAT = "telefringe-heightmap"
_VERSION = 1


# --------------------------------------------------------------------------------------
# JSON
# --------------------------------------------------------------------------------------
def to_jsonable(obj):
    """Convert results (dataclasses, numpy arrays and scalars, tuples) to JSON values.

    NaN and infinities become ``null``; arrays become (nested) lists.
    """
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        if obj.dtype == bool:
            return obj.tolist()
        if obj.dtype.kind in "iu":
            return obj.tolist()
        a = np.asarray(obj, dtype=np.float64)
        return to_jsonable(a.tolist())
    if isinstance(obj, np.bool_ | bool):
        return bool(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, float | np.floating):
        f = float(obj)
        return f if np.isfinite(f) else None
    return obj


def write_json(path, obj, *, force: bool = True) -> Path:
    """Write ``to_jsonable(obj)`` as indented JSON, atomically."""
    write_json_atomic(path, to_jsonable(obj), force=force)
    return Path(path)


# --------------------------------------------------------------------------------------
# points.npz
# --------------------------------------------------------------------------------------
def write_points(path, cloud, *, texture=None, radiance=None, force: bool = False) -> Path:
    """Write an organised point cloud to ``path`` (uncompressed .npz).

    Arrays: ``xyz`` (rows, cols, 3) float64 mm, NaN where invalid; ``mask`` bool;
    ``sigma_z`` float64 mm; ``sigma_line`` float64 mm (along the camera line);
    ``direction`` (3,) the camera's viewing direction; ``flags`` uint8 (why a point is
    invalid, ``telefringe.reconstruction.cloud.FLAG_*``); ``residual`` float64 projector px (only
    with both fringe axes); ``texture`` float32 (rows, cols) fringe-free camera image
    (optional, for marker detection); ``radiance`` float32 (rows, cols) the decoder's
    background per unit exposure (optional, for BGA highlights); ``format`` and
    ``version``.
    """
    arrays = {
        "format": np.array(POINTS_FORMAT),
        "version": np.array(_VERSION),
        "xyz": np.ascontiguousarray(cloud.xyz, dtype=np.float64),
        "mask": np.asarray(cloud.mask, dtype=bool),
        "sigma_z": np.asarray(cloud.sigma_z, dtype=np.float64),
        "sigma_line": np.asarray(cloud.sigma_line, dtype=np.float64),
        "direction": np.asarray(cloud.direction, dtype=np.float64),
        "flags": np.asarray(cloud.flags, dtype=np.uint8),
    }
    if cloud.residual is not None:
        arrays["residual"] = np.asarray(cloud.residual, dtype=np.float64)
    for name, img in (("texture", texture), ("radiance", radiance)):
        if img is not None:
            t = np.asarray(img, dtype=np.float32)
            if t.shape != cloud.shape:
                raise ValueError(f"{name} has shape {t.shape}, the cloud {cloud.shape}")
            arrays[name] = t
    path = Path(path)
    with atomic_file(path, force=force) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)
    return path


@dataclasses.dataclass(frozen=True, eq=False)
class PointsFile:
    """Content of ``points.npz``: the cloud and its optional images (float32 or None)."""

    cloud: object
    texture: np.ndarray | None
    radiance: np.ndarray | None


def read_points(path):
    """Read ``points.npz`` (or a folder holding it).

    Returns
    -------
    cloud : telefringe.reconstruction.cloud.PointCloud
    texture : (rows, cols) float32 ndarray or None

    Raises
    ------
    InputError
        Missing file, not a points file, inconsistent arrays.
    """
    pf = load_points(path)
    return pf.cloud, pf.texture


def load_points(path) -> PointsFile:
    """Like :func:`read_points`, with every optional array (:class:`PointsFile`)."""
    from telefringe.reconstruction.cloud import PointCloud

    path = Path(path)
    if path.is_dir():
        path = path / "points.npz"
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise InputError(f"{path}: not found (run 'telefringe reconstruct' first)") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not a points file ({exc})") from None
    if str(arrays.get("format", "")) != POINTS_FORMAT:
        raise InputError(f"{path}: not a telefringe points file (no format '{POINTS_FORMAT}')")
    if int(arrays.get("version", -1)) != _VERSION:
        raise InputError(f"{path}: points file version {arrays.get('version')} is not "
                         f"supported (this telefringe reads version {_VERSION})")
    for k in ("xyz", "mask", "sigma_line", "direction", "flags"):
        if k not in arrays:
            raise InputError(f"{path}: array '{k}' is missing")
    xyz = arrays["xyz"]
    if xyz.ndim != 3 or xyz.shape[2] != 3 or xyz.dtype.kind != "f":
        raise InputError(f"{path}: 'xyz' must be a float (rows, cols, 3) array")
    shape = xyz.shape[:2]
    for k in ("mask", "sigma_line", "flags", "residual", "texture", "radiance"):
        if k in arrays and arrays[k].shape != shape:
            raise InputError(f"{path}: '{k}' has shape {arrays[k].shape}, expected {shape}")
    d = np.asarray(arrays["direction"], dtype=np.float64)
    if d.shape != (3,) or not np.all(np.isfinite(d)) or abs(np.linalg.norm(d) - 1) > 1e-6:
        raise InputError(f"{path}: 'direction' must be a unit 3-vector")
    mask = arrays["mask"].astype(bool)
    if np.any(mask & ~np.all(np.isfinite(xyz), axis=2)):
        raise InputError(f"{path}: 'mask' marks points whose xyz is not finite")
    xyz = np.where(mask[..., None], xyz, np.nan).astype(np.float64)
    cloud = PointCloud(xyz, mask, np.where(mask, arrays["sigma_line"], np.nan),
                       arrays.get("residual"), arrays["flags"].astype(np.uint8), d)
    return PointsFile(cloud, arrays.get("texture"), arrays.get("radiance"))


# --------------------------------------------------------------------------------------
# PLY
# --------------------------------------------------------------------------------------
def write_ply(path, cloud, *, texture=None, force: bool = False) -> Path:
    """Binary little-endian PLY of the valid points (row-major pixel order).

    Vertex properties: ``x, y, z`` (float32, mm); ``red, green, blue`` (uint8, the
    texture's gray level scaled to its 0.5 / 99.5 percentiles) when ``texture`` is given;
    ``sigma_z`` (float32, mm) when the cloud has uncertainties (CloudCompare shows it as
    a scalar field; other readers skip it).
    """
    from plyfile import PlyData, PlyElement

    m = np.asarray(cloud.mask)
    pts = np.asarray(cloud.xyz)[m]
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    gray = None
    if texture is not None:
        t = np.asarray(texture, dtype=np.float64)
        vals = t[m]
        if vals.size:
            lo, hi = np.percentile(vals, [0.5, 99.5])
            gray = np.clip((vals - lo) / max(hi - lo, 1e-12) * 255.0, 0, 255).astype(np.uint8)
        else:
            gray = np.zeros(0, np.uint8)
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    sz = np.asarray(cloud.sigma_z)[m]
    has_sigma = bool(sz.size) and bool(np.all(np.isfinite(sz)))
    if has_sigma:
        fields.append(("sigma_z", "<f4"))
    v = np.empty(pts.shape[0], dtype=fields)
    v["x"], v["y"], v["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if gray is not None:
        v["red"] = v["green"] = v["blue"] = gray
    if has_sigma:
        v["sigma_z"] = sz
    el = PlyElement.describe(v, "vertex")
    ply = PlyData([el], text=False, byte_order="<",
                  comments=["telefringe point cloud, world frame, mm"])
    path = Path(path)
    with atomic_file(path, force=force) as tmp:
        ply.write(str(tmp))
    return path


# --------------------------------------------------------------------------------------
# Height maps
# --------------------------------------------------------------------------------------
def _heightmap_meta(hm) -> dict:
    h, w = hm.z.shape
    return {
        "format": HEIGHTMAP_FORMAT, "version": _VERSION, "units": "mm",
        "width": int(w), "height": int(h),
        "pixel_mm": float(hm.pixel_mm), "x0_mm": float(hm.x0), "y0_mm": float(hm.y0),
        "orientation": "z[row, col] is at x = x0_mm + col * pixel_mm, "
                       "y = y0_mm - row * pixel_mm (row 0 at the largest y, like the "
                       "camera image); world frame of the rig, z toward the camera",
        "nodata": "NaN",
    }


def write_height_tiff(path, hm, *, force: bool = False) -> tuple[Path, Path]:
    """Write a height map as a 32-bit float TIFF plus a sidecar JSON.

    The TIFF holds ``hm.z`` (mm, NaN where no data); its X/YResolution tags give the
    pixel size (pixels per centimetre, unit CENTIMETER) and its ImageDescription the
    metadata JSON; the sidecar ``<name>.json`` holds the same metadata exactly
    (``pixel_mm``, ``x0_mm``, ``y0_mm``, orientation). When ``hm.sigma_z`` is present it is
    written as a second TIFF ``<name>_sigma.tif``.

    Returns the paths of the TIFF and of the sidecar.
    """
    import tifffile

    path = Path(path)
    side = path.with_suffix(".json")
    meta = _heightmap_meta(hm)
    res = 10.0 / float(hm.pixel_mm)  # pixels per cm
    targets = [(path, hm.z)]
    if hm.sigma_z is not None:
        meta["sigma_file"] = path.with_name(path.stem + "_sigma.tif").name
        targets.append((path.with_name(path.stem + "_sigma.tif"), hm.sigma_z))
    for p, arr in targets:
        with atomic_file(p, force=force) as tmp:
            tifffile.imwrite(tmp, np.asarray(arr, dtype=np.float32),
                             resolution=(res, res), resolutionunit="CENTIMETER",
                             description=json.dumps(meta), metadata=None)
    write_json_atomic(side, meta, force=force)
    return path, side


def read_height_tiff(path):
    """Read a height map written by :func:`write_height_tiff` (HeightMap)."""
    import tifffile

    from telefringe.reconstruction.heightmap import HeightMap

    path = Path(path)
    side = path.with_suffix(".json")
    try:
        z = tifffile.imread(path)
        meta = json.loads(side.read_text())
    except FileNotFoundError as exc:
        raise InputError(f"{exc.filename}: not found") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not a height map ({exc})") from None
    if meta.get("format") != HEIGHTMAP_FORMAT or meta.get("version") != _VERSION:
        raise InputError(f"{side}: not a telefringe height map sidecar (version {_VERSION})")
    return HeightMap(np.asarray(z, dtype=np.float32), float(meta["x0_mm"]),
                     float(meta["y0_mm"]), float(meta["pixel_mm"]))


def _figure(figsize):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=100)
    FigureCanvasAgg(fig)
    return fig


#: the viridis colour map (CC0) at 17 evenly spaced levels, RGB 0..255; the preview
#: interpolates linearly between them (within 6/255 of the full map) and its colour bar
#: uses the same mapping
_VIRIDIS17 = np.array([
    [68, 1, 84], [72, 24, 106], [71, 45, 123], [66, 64, 134], [59, 82, 139], [51, 99, 141],
    [44, 114, 142], [38, 130, 142], [33, 145, 140], [31, 160, 136], [40, 174, 128],
    [63, 188, 115], [94, 201, 98], [132, 212, 75], [173, 220, 48], [216, 226, 25],
    [253, 231, 37]], dtype=np.float64)
_NO_DATA_RGB = (217, 217, 217)


def height_colours(z, lo: float, hi: float) -> np.ndarray:
    """(..., 3) uint8 RGB of heights ``z`` (any shape, mm) on the preview's colour map
    from ``lo`` to ``hi`` (clipped); NaN gives the no-data grey."""
    z = np.asarray(z, dtype=np.float64)
    t = np.clip((z - lo) / (hi - lo), 0.0, 1.0) * (len(_VIRIDIS17) - 1)
    t = np.where(np.isfinite(t), t, 0.0)
    i = np.minimum(t.astype(np.int64), len(_VIRIDIS17) - 2)
    f = (t - i)[..., None]
    rgb = _VIRIDIS17[i] * (1.0 - f) + _VIRIDIS17[i + 1] * f
    rgb = np.round(rgb).astype(np.uint8)
    rgb[~np.isfinite(z)] = _NO_DATA_RGB
    return rgb


def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: the fixed bitmap font
        return ImageFont.load_default()


def _ticks(lo: float, hi: float, n: int = 6) -> np.ndarray:
    """Round values within [lo, hi], a step of 1, 2, 2.5 or 5 x 10^k giving at most
    about ``n`` of them."""
    span = hi - lo
    if not span > 0:
        return np.array([lo])
    raw = span / n
    mag = 10.0 ** np.floor(np.log10(raw))
    step = min((m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw), default=10 * mag)
    first = np.ceil(lo / step) * step
    return np.arange(first, hi + step * 1e-9, step)


def _label(v: float, step: float) -> str:
    if abs(v) < 1e-9 * max(step, 1e-300):  # no "-0" for a tick at zero
        v = 0.0
    digits = max(0, int(-np.floor(np.log10(step))) + (1 if step / 10 ** np.floor(
        np.log10(step)) == 2.5 else 0)) if step > 0 else 3
    return f"{v:.{digits}f}"


def write_height_png(path, hm, *, title: str | None = None, force: bool = False) -> Path:
    """A PNG preview of a height map: the map in colour (world x to the right, y up, as
    the map's grid), a colour bar in mm, tick labels in mm and the title. Drawn with
    Pillow (no plotting library: fast to start).

    The colour range spans the 0.5 / 99.5 percentiles of the heights (outliers do not
    wash the map out); pixels without a height are grey.
    """
    from PIL import Image, ImageDraw

    z = np.asarray(hm.z, dtype=np.float64)
    fin = z[np.isfinite(z)]
    if fin.size:
        lo, hi = (float(v) for v in np.percentile(fin, [0.5, 99.5]))
        if hi <= lo:
            lo, hi = lo - 1e-3, hi + 1e-3
    else:
        lo, hi = 0.0, 1.0
    h, w = z.shape
    scale = max(1, int(560 // max(h, w)))  # small maps drawn with square pixels enlarged
    mw, mh = w * scale, h * scale
    font, small = _font(15), _font(13)
    left, top, gap, bar_w = 80, 44 if title else 16, 24, 22
    bar_h = max(mh, 200)  # readable even beside a thin map
    width = left + mw + gap + bar_w + 90
    height = top + max(mh, bar_h) + 60
    img = Image.new("RGB", (width, height), "white")
    img.paste(Image.fromarray(height_colours(z, lo, hi)).resize((mw, mh), Image.NEAREST),
              (left, top))
    draw = ImageDraw.Draw(img)
    black = (0, 0, 0)
    draw.rectangle([left - 1, top - 1, left + mw, top + mh], outline=black)
    if title:
        draw.text((left + mw / 2, 10), title, fill=black, font=font, anchor="mt")
    # axes in mm: x of pixel edges left to right, y top (larger) to bottom
    x_l, x_r, y_b, y_t = hm.extent
    n_x, n_y = max(2, min(6, mw // 60)), max(2, min(6, mh // 40))
    for v in _ticks(x_l, x_r, n_x):
        px = left + (v - x_l) / (x_r - x_l) * mw
        draw.line([px, top + mh, px, top + mh + 5], fill=black)
        draw.text((px, top + mh + 7), _label(v, _step(x_l, x_r, n_x)), fill=black,
                  font=small, anchor="mt")
    for v in _ticks(y_b, y_t, n_y):
        py = top + (y_t - v) / (y_t - y_b) * mh
        draw.line([left - 6, py, left - 1, py], fill=black)
        draw.text((left - 8, py), _label(v, _step(y_b, y_t, n_y)), fill=black, font=small,
                  anchor="rm")
    draw.text((left + mw / 2, top + mh + 28), "x (mm)", fill=black, font=font, anchor="mt")
    label = Image.new("RGB", (80, 22), "white")
    ImageDraw.Draw(label).text((40, 11), "y (mm)", fill=black, font=font, anchor="mm")
    img.paste(label.rotate(90, expand=True), (4, top + mh // 2 - 40))
    # colour bar: the same mapping, top = hi
    bx = left + mw + gap
    ramp = np.linspace(hi, lo, bar_h)[:, None].repeat(bar_w, axis=1)
    img.paste(Image.fromarray(height_colours(ramp, lo, hi)), (bx, top))
    draw.rectangle([bx - 1, top - 1, bx + bar_w, top + bar_h], outline=black)
    n_z = max(2, min(6, bar_h // 40))
    for v in _ticks(lo, hi, n_z):
        py = top + (hi - v) / (hi - lo) * (bar_h - 1)
        draw.line([bx + bar_w, py, bx + bar_w + 5, py], fill=black)
        draw.text((bx + bar_w + 8, py), _label(v, _step(lo, hi, n_z)), fill=black,
                  font=small, anchor="lm")
    draw.text((bx + bar_w / 2, top + bar_h + 28), "z (mm)", fill=black, font=font,
              anchor="mt")
    path = Path(path)
    with atomic_file(path, force=force) as tmp:
        img.save(tmp, format="PNG")
    return path


def _step(lo: float, hi: float, n: int = 6) -> float:
    t = _ticks(lo, hi, n)
    return float(t[1] - t[0]) if t.size > 1 else max(abs(hi - lo), 1e-12)


# --------------------------------------------------------------------------------------
# BGA
# --------------------------------------------------------------------------------------
_BGA_COLUMNS = ("row", "col", "status", "x_mm", "y_mm", "z_mm", "apex_x_mm", "apex_y_mm",
                "apex_z_mm", "height_mm", "sigma_height_mm", "diameter_mm", "pos_x_mm",
                "pos_y_mm", "dx_mm", "dy_mm", "coplanarity_mm", "seating_contact", "fit_rms_mm",
                "n_points")


def write_bga_csv(path, m, *, force: bool = False) -> Path:
    """One row per grid position of a :class:`telefringe.metrology.BGAMeasurement`.

    ``status`` is ``ok``, ``missing`` (populated position with no ball) or ``unexpected``
    (a ball where the nominal grid has none); positions that are empty as they should be
    are left out. Columns: grid ``row``, ``col``; sphere centre ``x/y/z_mm`` and apex
    ``apex_*_mm`` (world); ``height_mm`` (apex above the substrate plane) and its
    ``sigma_height_mm``; ``diameter_mm``; ``pos_*_mm`` (centre in the grid frame) and
    ``dx/dy_mm`` (its offset from the nominal position); ``coplanarity_mm`` (distance of the
    apex from the JEDEC seating plane); ``seating_contact`` (1 for the balls the package
    rests on); ``fit_rms_mm``; ``n_points``.
    """
    pitch = m.nominal.pitch_mm
    contacts = set(int(k) for k in m.coplanarity.contacts)
    by_pos = {(int(i), int(j)): k for k, (i, j) in enumerate(m.index)}
    unexpected = set(m.unexpected)
    populated = m.nominal.populated()
    rows = []
    for i in range(m.nominal.rows):
        for j in range(m.nominal.cols):
            k = by_pos.get((i, j))
            if k is None:
                if populated[i, j]:
                    rows.append([i, j, "missing"] + [""] * (len(_BGA_COLUMNS) - 3))
                continue
            status = "unexpected" if (i, j) in unexpected else "ok"
            c, a = m.centre[k], m.apex[k]
            px, py = m.position[k]
            rows.append([i, j, status, *(f"{v:.6f}" for v in c), *(f"{v:.6f}" for v in a),
                         f"{m.height[k]:.6f}", f"{m.sigma_height[k]:.6f}",
                         f"{m.diameter[k]:.6f}", f"{px:.6f}", f"{py:.6f}",
                         f"{px - j * pitch:.6f}", f"{py - i * pitch:.6f}",
                         f"{m.coplanarity.distances[k]:.6f}", int(k in contacts),
                         f"{m.rms[k]:.6f}", int(m.n_points[k])])
    path = Path(path)
    with atomic_file(path, force=force) as tmp, open(tmp, "w", newline="") as f:
        wr = csv.writer(f)
        wr.writerow(_BGA_COLUMNS)
        wr.writerows(rows)
    return path


def write_bga_png(path, m, *, title: str | None = None, force: bool = False) -> Path:
    """A map of the balls on the grid, coloured by apex height (mm); missing balls are
    red crosses, the seating-plane contacts are circled."""
    rows, cols = m.nominal.rows, m.nominal.cols
    width_in = 7.5
    plot_in = 5.6  # about the axes' width
    fig = _figure((width_in, max(3.0, plot_in * (rows + 1) / (cols + 1)) + 1.6))
    ax = fig.add_subplot(1, 1, 1)
    pitch = m.nominal.pitch_mm
    x = m.index[:, 1] * pitch
    y = m.index[:, 0] * pitch
    # marker diameter: the nominal ball diameter at the plot's scale (points)
    pt_per_mm = plot_in * 72.0 / ((cols + 1) * pitch)
    size = (min(m.nominal.ball_diameter_mm, 0.9 * pitch) * pt_per_mm) ** 2
    sc = ax.scatter(x, y, c=m.height, cmap="viridis", s=size, marker="o", edgecolors="none")
    if len(m.coplanarity.contacts):
        k = m.coplanarity.contacts
        ax.scatter(x[k], y[k], s=size * 1.6, facecolors="none", edgecolors="k",
                   linewidths=1.2, label="seating-plane contacts")
    if m.missing:
        mi = np.array(m.missing)
        ax.scatter(mi[:, 1] * pitch, mi[:, 0] * pitch, marker="x", c="red", s=size * 0.6,
                   label=f"missing ({len(m.missing)})")
    ax.set_aspect("equal")
    ax.set_xlim(-pitch, cols * pitch)
    ax.set_ylim(-pitch, rows * pitch)
    ax.set_xlabel("column x' (mm)")
    ax.set_ylabel("row y' (mm)")
    ax.set_title(title or f"BGA: {m.n_balls} balls, coplanarity "
                 f"{m.coplanarity.value * 1000:.1f} um")
    cb = fig.colorbar(sc, ax=ax, shrink=0.9)
    cb.set_label("apex height above substrate (mm)")
    if len(m.coplanarity.contacts) or m.missing:
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=2,
                  fontsize="small", frameon=False, markerscale=0.5)
    fig.tight_layout()
    path = Path(path)
    with atomic_file(path, force=force) as tmp:
        fig.savefig(tmp, format="png")
    return path


# --------------------------------------------------------------------------------------
# Everything a reconstruction leaves
# --------------------------------------------------------------------------------------
def write_reconstruction(folder, cloud, hm=None, *, texture=None, radiance=None,
                         title: str | None = None, ply: bool = True,
                         force: bool = False) -> dict:
    """Write ``points.npz``, ``cloud.ply``, ``heightmap.tif`` (+ ``.json``, ``_sigma.tif``)
    and ``heightmap.png`` into an existing ``folder``.

    Returns a dict name -> Path of what was written.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder")
    out = {"points": write_points(folder / "points.npz", cloud, texture=texture,
                                  radiance=radiance, force=force)}
    if ply:
        out["ply"] = write_ply(folder / "cloud.ply", cloud, texture=texture, force=force)
    if hm is not None:
        out["heightmap"], out["heightmap_json"] = write_height_tiff(
            folder / "heightmap.tif", hm, force=force)
        out["heightmap_png"] = write_height_png(folder / "heightmap.png", hm, title=title,
                                                force=force)
    return out


# --------------------------------------------------------------------------------------
# Compact summaries (JSON-ready dicts; no per-point arrays)
# --------------------------------------------------------------------------------------
def _f(x):
    x = float(x)
    return x if np.isfinite(x) else None


def cloud_summary(cloud) -> dict:
    """Counts and uncertainty figures of a point cloud."""
    from telefringe.reconstruction.cloud import (
        FLAG_INCONSISTENT,
        FLAG_NO_PHASE,
        FLAG_NOT_CONVERGED,
        FLAG_OUTSIDE,
        FLAG_UNCERTAIN,
    )

    fl = np.asarray(cloud.flags)
    sz = np.asarray(cloud.sigma_z)[np.asarray(cloud.mask)]
    out = {
        "pixels": int(fl.size), "valid": int(cloud.count),
        "valid_fraction": _f(cloud.count / max(fl.size, 1)),
        "invalid": {name: int(np.count_nonzero(fl & bit)) for name, bit in (
            ("no_phase", FLAG_NO_PHASE), ("inconsistent", FLAG_INCONSISTENT),
            ("outside_projector", FLAG_OUTSIDE), ("not_converged", FLAG_NOT_CONVERGED),
            ("uncertain", FLAG_UNCERTAIN))},
        "sigma_z_median_mm": _f(np.median(sz)) if sz.size and np.isfinite(sz).all() else None,
        "sigma_z_p95_mm": (_f(np.percentile(sz, 95)) if sz.size and np.isfinite(sz).all()
                           else None),
    }
    if cloud.residual is not None:
        r = np.asarray(cloud.residual)[np.asarray(cloud.mask)]
        r = r[np.isfinite(r)]
        out["residual_median_px"] = _f(np.median(r)) if r.size else None
        out["residual_p99_px"] = _f(np.percentile(r, 99)) if r.size else None
    return out


def plane_summary(p) -> dict:
    """A :class:`telefringe.metrology.PlaneFit` without its per-point arrays."""
    return {"normal": to_jsonable(p.normal), "offset_mm": _f(p.offset),
            "centroid_mm": to_jsonable(p.centroid), "rms_mm": _f(p.rms),
            "flatness_mm": _f(p.flatness), "tilt_deg": _f(p.tilt_deg),
            "n_points": int(p.n_points), "n_inliers": int(p.n_inliers),
            "sigma_offset_mm": _f(p.sigma_offset)}


def plate_summary(m) -> dict:
    """A :class:`telefringe.metrology.PlateMeasurement` as in the paper's Table 3."""
    sp = m.spacing
    return {
        "z_mm": _f(m.z.distance), "sigma_z_mm": _f(m.z.sigma),
        "angle_to_reference_deg": _f(m.z.angle_deg),
        "plane": plane_summary(m.plane),
        "spacing": {
            "nominal_mm": _f(sp.nominal_mm),
            "mean_x_mm": _f(sp.mean_x), "mean_y_mm": _f(sp.mean_y),
            "abs_err_x_mm": _f(sp.abs_err_x), "abs_err_y_mm": _f(sp.abs_err_y),
            "std_x_mm": _f(sp.std_x), "std_y_mm": _f(sp.std_y),
            "rms_err_x_mm": _f(sp.rms_err_x), "rms_err_y_mm": _f(sp.rms_err_y),
            "n_x": int(sp.n_x), "n_y": int(sp.n_y),
            "dist_x_mm": to_jsonable(sp.dist_x), "dist_y_mm": to_jsonable(sp.dist_y),
        },
        "markers": {"measured": int(np.count_nonzero(m.centres.valid)),
                    "centres_mm": to_jsonable(m.centres.xyz),
                    "sigma_mm": to_jsonable(m.centres.sigma_xyz)},
    }


def sphere_summary(f, base=None) -> dict:
    """A :class:`telefringe.metrology.SphereFit` (and its base plane)."""
    out = {"centre_mm": to_jsonable(f.centre), "radius_mm": _f(f.radius),
           "diameter_mm": _f(f.diameter), "sigma_centre_mm": to_jsonable(f.sigma_centre),
           "sigma_radius_mm": _f(f.sigma_radius), "rms_mm": _f(f.rms),
           "form_error_mm": _f(f.form_error), "n_points": int(f.n_points),
           "n_inliers": int(f.n_inliers)}
    if base is not None:
        out["base_plane"] = plane_summary(base)
    return out


def bga_summary(m) -> dict:
    """A :class:`telefringe.metrology.BGAMeasurement` (per-ball arrays included)."""
    fin = np.concatenate([np.asarray(m.pitch_x)[np.isfinite(m.pitch_x)],
                          np.asarray(m.pitch_y)[np.isfinite(m.pitch_y)]])
    nom = m.nominal
    return {
        "nominal": {"rows": int(nom.rows), "cols": int(nom.cols), "pitch_mm": _f(nom.pitch_mm),
                    "ball_diameter_mm": _f(nom.ball_diameter_mm)},
        "balls_found": int(m.n_balls), "missing": [list(x) for x in m.missing],
        "unexpected": [list(x) for x in m.unexpected],
        "coplanarity_mm": _f(m.coplanarity.value),
        "seating_contacts": [list(map(int, m.index[k])) for k in m.coplanarity.contacts],
        "height_mean_mm": _f(np.mean(m.height)), "height_min_mm": _f(np.min(m.height)),
        "height_max_mm": _f(np.max(m.height)),
        "diameter_mean_mm": (_f(np.nanmean(m.diameter)) if np.any(np.isfinite(m.diameter))
                             else None),
        "diameters_measured": int(np.count_nonzero(np.isfinite(m.diameter))),
        "pitch_mean_mm": _f(np.mean(fin)) if fin.size else None,
        "pitch_std_mm": _f(np.std(fin, ddof=1)) if fin.size > 1 else None,
        "pitch_error_max_mm": _f(m.pitch_error_max),
        "grid_angle_deg": _f(m.grid_angle_deg),
        "substrate": plane_summary(m.substrate),
        "balls": {"index": to_jsonable(m.index), "height_mm": to_jsonable(m.height),
                  "sigma_height_mm": to_jsonable(m.sigma_height),
                  "diameter_mm": to_jsonable(m.diameter), "centre_mm": to_jsonable(m.centre),
                  "apex_mm": to_jsonable(m.apex)},
    }


def steps_summary(m) -> dict:
    """A :class:`telefringe.metrology.StepMeasurement` without the label image."""
    return {"levels": int(len(m.offsets)), "normal": to_jsonable(m.normal),
            "heights_mm": to_jsonable(m.heights),
            "sigma_heights_mm": to_jsonable(m.sigma_heights),
            "step_heights_mm": to_jsonable(m.step_heights),
            "sigma_steps_mm": to_jsonable(m.sigma_steps), "rms_mm": to_jsonable(m.rms),
            "n_points": to_jsonable(m.n_points)}
