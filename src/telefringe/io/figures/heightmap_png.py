"""``heightmap.png``: a preview of a height map with a colour bar, drawn with Pillow (no
plotting library: fast to start), and the colour map it uses."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from telefringe.io.atomic import atomic_file

__all__ = ["write_height_png", "height_colours"]


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
