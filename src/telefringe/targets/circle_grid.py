"""Circle-grid calibration targets: sub-pixel marker detection and grid ordering (the
ellipse fits are in :mod:`telefringe.targets.ellipse`, the projector's view of each circle
centre in :mod:`telefringe.targets.observations`).

Under telecentric projection a circle images as an ellipse whose centre is the image of
the circle's centre (affine maps keep centres), so each marker's centre is the centre of
an ellipse fitted to sub-pixel points of its edge. Lens distortion bends the ellipse by
a few thousandths of a pixel over a marker; the fit ignores that.

Labelling (DESIGN.md): circle (row, col) sits at ``(col * pitch, row * pitch, 0)`` in
the target frame, x along the grid's ``cols`` direction, y along ``rows``, z = x cross
y toward the camera. A target that faces the camera therefore images with a negative
determinant of ``[d(u, v)/d col, d(u, v)/d row]`` (the camera's v axis points down the
image). Of the labellings with that handedness (two, 180 degrees apart, for a
rectangular grid), the one whose circle (0, 0) is nearer the bottom-left corner of the
image is taken. The same rule applied to every pose gives the same labelling as long as
the plate is not turned in its plane by more than about 45-90 degrees between poses (a
symmetric grid cannot tell more).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from telefringe.targets.ellipse import _ellipse_quadratic, _fit_blurred_ellipse, fit_ellipse

__all__ = [
    "GridDetection",
    "detect_circle_grid",
]


# --------------------------------------------------------------------------- results
@dataclass(frozen=True, eq=False)
class GridDetection:
    """The markers of a circle grid found in one image.

    Attributes
    ----------
    rows, cols : int, the grid's shape.
    centers : (rows * cols, 2) ndarray of float, px (u, v), row-major (row, col) target
        order; NaN where a marker was not found.
    found : (rows * cols,) ndarray of bool.
    ellipses : (rows * cols, 5) ndarray of float, (u_c, v_c, a, b, theta): centre px,
        semi-axes px (a >= b) and the angle of the major axis from +u (rad); NaN where
        not found.
    fit_rms : (rows * cols,) ndarray of float, quality of each marker's fit: RMS
        residual relative to the background level ("model"), or RMS distance of the
        edge points from the ellipse in px ("edge"); NaN where not found.
    lattice : (2, 2) ndarray, px, image of one pitch along +col (first column) and +row
        (second column).
    reason : str, why the grid was not found or ordered ("" on success). A failed
        detection is falsy.
    center_covariance : (rows * cols, 2, 2) ndarray of float, px^2, or None: the
        standard covariance of each centre from its fit (the residuals' variance times
        the inverse normal matrix: image noise and the part of the image the fit's model
        misses, as independent per pixel or edge point); NaN where not found. A detected
        centre is a measurement: its error reaches every quantity read at it (a plate's
        marker spacing, :func:`telefringe.metrology.measure_plate`). For "model" it
        predicts the centres' error (tests/test_spacing_centre_sigma.py); for "edge" it
        bounds the noise's part but falls short of the edge interpolation's error of
        about 0.01 px (normalised RMS error 1.2-1.5).
    """

    rows: int
    cols: int
    centers: np.ndarray
    found: np.ndarray
    ellipses: np.ndarray
    fit_rms: np.ndarray
    lattice: np.ndarray
    reason: str = ""
    center_covariance: np.ndarray | None = None

    def __bool__(self) -> bool:
        return not self.reason

    @property
    def n_found(self) -> int:
        return int(np.count_nonzero(self.found))

    @property
    def center_sigma(self) -> np.ndarray | None:
        """(rows * cols, 2) px, standard uncertainties of the centres (u, v), from
        ``center_covariance`` (None without it)."""
        if self.center_covariance is None:
            return None
        return np.sqrt(np.diagonal(self.center_covariance, axis1=1, axis2=2))


def _failure(rows, cols, reason) -> GridDetection:
    n = rows * cols
    return GridDetection(rows, cols, np.full((n, 2), np.nan), np.zeros(n, dtype=bool),
                         np.full((n, 5), np.nan), np.full(n, np.nan),
                         np.full((2, 2), np.nan), reason, np.full((n, 2, 2), np.nan))


# --------------------------------------------------------------------------- blobs
def _otsu(values: np.ndarray) -> float:
    """Otsu's threshold of a 1-D sample (256 bins over its range)."""
    lo, hi = float(values.min()), float(values.max())
    if hi <= lo:
        return lo
    hist, edges = np.histogram(values, bins=256, range=(lo, hi))
    centres = 0.5 * (edges[1:] + edges[:-1])
    w0 = np.cumsum(hist)
    w1 = w0[-1] - w0
    s0 = np.cumsum(hist * centres)
    m0 = s0 / np.maximum(w0, 1)
    m1 = (s0[-1] - s0) / np.maximum(w1, 1)
    between = w0 * w1 * (m0 - m1) ** 2
    return float(centres[int(np.argmax(between))])


def _blobs(dark: np.ndarray, threshold: float, min_area: int):
    """Connected dark components: (label image, stats table (n, 9): area, mean u, mean
    v, var u, var v, cov uv, bbox (u0, v0, u1, v1) packed) for plausible blobs."""
    import cv2

    mask = (dark > threshold).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if n <= 1:
        return labels, np.zeros((0,), dtype=int), None
    H, W = mask.shape
    rows_i, cols_i = np.nonzero(labels)
    lab = labels[rows_i, cols_i]
    area = np.bincount(lab, minlength=n).astype(float)
    su = np.bincount(lab, cols_i, minlength=n)
    sv = np.bincount(lab, rows_i, minlength=n)
    suu = np.bincount(lab, cols_i.astype(float) ** 2, minlength=n)
    svv = np.bincount(lab, rows_i.astype(float) ** 2, minlength=n)
    suv = np.bincount(lab, cols_i.astype(float) * rows_i, minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        mu, mv = su / area, sv / area
        cuu = suu / area - mu**2 + 1 / 12
        cvv = svv / area - mv**2 + 1 / 12
        cuv = suv / area - mu * mv
        det = cuu * cvv - cuv**2
        # an ellipse of area A has 4 pi sqrt(det) = A
        fill = area / (4 * np.pi * np.sqrt(np.maximum(det, 1e-12)))
    x0, y0 = stats[:, 0], stats[:, 1]
    x1, y1 = x0 + stats[:, 2] - 1, y0 + stats[:, 3] - 1
    ok = (np.arange(n) > 0) & (area >= min_area) & (x0 > 0) & (y0 > 0) & (x1 < W - 1) \
        & (y1 < H - 1) & (fill > 0.85) & (fill < 1.15)
    idx = np.flatnonzero(ok)
    table = np.column_stack([area, mu, mv, cuu, cvv, cuv, x0, y0, x1, y1])[idx]
    return labels, idx, table


# --------------------------------------------------------------------------- ordering
def _lattice_coords(pts: np.ndarray):
    """Integer lattice coordinates of points on an (affinely distorted) regular grid.

    Returns (ij (n, 2) int with -9999 for points not on the lattice, basis (2, 2)
    columns a, b) or raises ValueError with a reason.
    """
    from scipy.spatial import cKDTree

    n = pts.shape[0]
    k = min(9, n)
    tree = cKDTree(pts)
    dist, nbr = tree.query(pts, k=k)
    vec = pts[nbr[:, 1:]] - pts[:, None, :]  # (n, k-1, 2)
    flat = vec.reshape(-1, 2)
    flat = np.where((flat[:, :1] < 0) | ((flat[:, :1] == 0) & (flat[:, 1:] < 0)), -flat, flat)
    lengths = np.hypot(flat[:, 0], flat[:, 1])
    # a: the nearest-neighbour displacement most points agree on
    nn = vec[:, 0, :]
    nn = np.where((nn[:, :1] < 0) | ((nn[:, :1] == 0) & (nn[:, 1:] < 0)), -nn, nn)

    def cluster(cands, among):
        best, best_n = None, -1
        for c in cands:
            close = np.hypot(*(among - c).T) < 0.2 * np.hypot(*c)
            if close.sum() > best_n:
                best, best_n = np.median(among[close], axis=0), int(close.sum())
        return best

    a = cluster(nn[:: max(1, n // 60)], nn)
    la = np.hypot(*a)
    sin = np.abs(a[0] * flat[:, 1] - a[1] * flat[:, 0]) / (la * np.maximum(lengths, 1e-12))
    other = flat[(sin > np.sin(np.radians(25))) & (lengths < 3.5 * la)]
    if other.shape[0] < 2:
        raise ValueError("the markers do not form a 2-D grid")
    shortest = other[np.hypot(*other.T) < 1.25 * np.hypot(*other.T).min()]
    b = cluster(shortest, other)
    basis = np.column_stack([a, b])
    if abs(np.linalg.det(basis)) < 1e-6 * la * la:
        raise ValueError("the markers do not form a 2-D grid")
    inv = np.linalg.inv(basis)
    ij = np.full((n, 2), -9999, dtype=int)
    start = int(np.argmin(np.hypot(*(pts - np.median(pts, axis=0)).T)))
    ij[start] = (0, 0)
    queue = deque([start])
    while queue:
        p = queue.popleft()
        for q in nbr[p, 1:]:
            if ij[q, 0] != -9999:
                continue
            ab = inv @ (pts[q] - pts[p])
            r = np.round(ab)
            if np.all(np.abs(ab - r) < 0.25) and np.abs(r).sum() == 1:
                ij[q] = ij[p] + r.astype(int)
                queue.append(q)
    return ij, basis


def _order(pts: np.ndarray, rows: int, cols: int, image_shape):
    """Assign (row, col) labels; returns (index (rows*cols,) into pts or -1, lattice
    (2, 2) px per pitch along +col and +row) or raises ValueError(reason)."""
    ij, _ = _lattice_coords(pts)
    on = np.flatnonzero(ij[:, 0] != -9999)
    if on.size < 4:
        raise ValueError("fewer than 4 markers form a grid")
    # affine (i, j) -> (u, v) and rejection of stray points
    for _ in range(2):
        M = np.column_stack([ij[on], np.ones(on.size)])
        coef, *_ = np.linalg.lstsq(M, pts[on], rcond=None)
        res = np.hypot(*(M @ coef - pts[on]).T)
        step = min(np.hypot(*coef[0]), np.hypot(*coef[1]))
        keep = res < 0.2 * step
        on = on[keep]
    M = np.column_stack([ij[on], np.ones(on.size)])
    coef, *_ = np.linalg.lstsq(M, pts[on], rcond=None)
    lo = ij[on].min(axis=0)
    ext = ij[on].max(axis=0) - lo + 1
    cells = {}
    for p in on:
        key = tuple(ij[p] - lo)
        if key in cells:
            raise ValueError("two markers claim the same grid position")
        cells[key] = p
    H = image_shape[0]
    options = []
    for i_is_col in (True, False):
        n_i, n_j = (cols, rows) if i_is_col else (rows, cols)
        if (ext[0], ext[1]) != (n_i, n_j):
            continue
        for si in (1, -1):
            for sj in (1, -1):
                # direction in the image of +col and +row
                d_i, d_j = si * coef[0], sj * coef[1]
                e_col, e_row = (d_i, d_j) if i_is_col else (d_j, d_i)
                if e_col[0] * e_row[1] - e_col[1] * e_row[0] >= 0:
                    continue  # wrong handedness: z would point away from the camera
                i0 = lo[0] if si == 1 else lo[0] + ext[0] - 1
                j0 = lo[1] if sj == 1 else lo[1] + ext[1] - 1
                origin = coef[2] + i0 * coef[0] + j0 * coef[1]
                dist = float(np.hypot(origin[0] - 0.0, origin[1] - (H - 1)))
                options.append((dist, i_is_col, si, sj, e_col, e_row))
    if not options:
        if ext[0] * ext[1] > rows * cols or max(ext) > max(rows, cols):
            raise ValueError(f"found a {ext[0]} x {ext[1]} lattice of markers, larger than "
                             f"the {rows} x {cols} grid")
        raise ValueError(f"found a {ext[0]} x {ext[1]} lattice of markers, expected "
                         f"{rows} x {cols}: part of the grid is hidden or outside the image, "
                         "so its markers cannot be labelled")
    options.sort(key=lambda o: o[0])
    _, i_is_col, si, sj, e_col, e_row = options[0]
    index = np.full(rows * cols, -1)
    for (a, b), p in cells.items():
        ia = a if si == 1 else ext[0] - 1 - a
        jb = b if sj == 1 else ext[1] - 1 - b
        col, row = (ia, jb) if i_is_col else (jb, ia)
        index[row * cols + col] = p
    return index, np.column_stack([e_col, e_row])


# --------------------------------------------------------------------------- sub-pixel
def _edge_points(win: np.ndarray, level: float, band: np.ndarray):
    """Sub-pixel crossings of ``level`` between 4-neighbours inside ``band``.

    Row pairs are used where the local gradient is mostly along u, column pairs where it
    is mostly along v; the crossing is found on the cubic through four samples along
    the line (exact for a cubic profile), falling back to linear interpolation.
    Returns (x, y) window coordinates.
    """
    f = win - level
    gy, gx = np.gradient(win)
    xs, ys = [], []
    for axis in (1, 0):
        g_along = gx if axis == 1 else gy
        g_across = gy if axis == 1 else gx
        a = f[:, :-1] if axis == 1 else f[:-1, :]
        b = f[:, 1:] if axis == 1 else f[1:, :]
        sel = (np.sign(a) != np.sign(b)) & (a != b)
        ga = g_along[:, :-1] if axis == 1 else g_along[:-1, :]
        gc = g_across[:, :-1] if axis == 1 else g_across[:-1, :]
        bd = band[:, :-1] & band[:, 1:] if axis == 1 else band[:-1, :] & band[1:, :]
        sel &= bd & (np.abs(ga) >= np.abs(gc))
        r, c = np.nonzero(sel)
        fa, fb = a[r, c], b[r, c]
        t = fa / (fa - fb)  # linear
        # cubic refinement with samples at -1, 0, 1, 2 along the axis
        if axis == 1:
            ok = (c >= 1) & (c + 2 < f.shape[1])
            fm = np.where(ok, f[r, np.clip(c - 1, 0, None)], 0.0)
            fp = np.where(ok, f[r, np.clip(c + 2, None, f.shape[1] - 1)], 0.0)
        else:
            ok = (r >= 1) & (r + 2 < f.shape[0])
            fm = np.where(ok, f[np.clip(r - 1, 0, None), c], 0.0)
            fp = np.where(ok, f[np.clip(r + 2, None, f.shape[0] - 1), c], 0.0)
        t = np.where(ok, _cubic_root(fm, fa, fb, fp, t), t)
        if axis == 1:
            xs.append(c + t)
            ys.append(r.astype(float))
        else:
            xs.append(c.astype(float))
            ys.append(r + t)
    return np.concatenate(xs), np.concatenate(ys)


def _cubic_root(fm, f0, f1, f2, t0):
    """Root in [0, 1] of the cubic through (-1, fm), (0, f0), (1, f1), (2, f2), by
    Newton's method from ``t0`` (kept where Newton leaves [0, 1])."""
    c0 = f0
    c1 = -fm / 3 - f0 / 2 + f1 - f2 / 6
    c2 = fm / 2 - f0 + f1 / 2
    c3 = -fm / 6 + f0 / 2 - f1 / 2 + f2 / 6
    t = t0.copy()
    for _ in range(6):
        val = c0 + t * (c1 + t * (c2 + t * c3))
        der = c1 + t * (2 * c2 + 3 * t * c3)
        t = t - val / np.where(np.abs(der) > 1e-12, der, np.inf)
    bad = ~np.isfinite(t) | (t < 0) | (t > 1)
    return np.where(bad, t0, t)


def _refine(img: np.ndarray, blob, labels, label, *, margin: float, method: str = "model"):
    """Sub-pixel ellipse of one dark blob. ``blob`` is its stats row. Returns (params in
    image px, rms, centre covariance (2, 2) px^2) or None."""
    H, W = img.shape
    area, mu, mv, cuu, cvv, cuv = blob[:6]
    C = np.array([[cuu, cuv], [cuv, cvv]])
    r_max = 2.0 * np.sqrt(np.linalg.eigvalsh(C)[-1])  # semi-major axis of the blob
    half = int(np.ceil(r_max + margin + 3))
    u0, v0 = max(int(round(mu)) - half, 0), max(int(round(mv)) - half, 0)
    u1, v1 = min(int(round(mu)) + half + 1, W), min(int(round(mv)) + half + 1, H)
    reach = r_max + 2.0
    if mu - reach < 1 or mv - reach < 1 or mu + reach > W - 2 or mv + reach > H - 2:
        return None  # the marker's edge leaves the image
    win = img[v0:v1, u0:u1].astype(float)
    lab = labels[v0:v1, u0:u1]
    yy, xx = np.mgrid[v0:v1, u0:u1]
    px, py = xx - mu, yy - mv
    Ci = np.linalg.inv(4.0 * C)  # the blob's ellipse (uniform: C = diag(a^2, b^2) / 4)
    q = np.sqrt(np.maximum(Ci[0, 0] * px**2 + 2 * Ci[0, 1] * px * py + Ci[1, 1] * py**2, 0))
    r_min = 2.0 * np.sqrt(np.linalg.eigvalsh(C)[0])
    rel = (margin + 1.0) / r_min
    outside = (q > 1 + rel) & (lab == 0)
    inside = q < max(1 - rel, 0.3)
    if outside.sum() < 20 or inside.sum() < 5:
        return None
    # bright background: a plane fitted to the surround; dark level: median inside
    A = np.column_stack([np.ones(outside.sum()), px[outside], py[outside]])
    bg, *_ = np.linalg.lstsq(A, win[outside], rcond=None)
    back = bg[0] + bg[1] * px + bg[2] * py
    if np.any(back <= 0):
        return None
    norm = win / back
    dark = float(np.median(norm[inside]))
    if not dark < 0.8:
        return None
    level = 0.5 * (1.0 + dark)
    if method == "model":
        th = 0.5 * np.arctan2(2 * cuv, cuu - cvv)
        ev = np.linalg.eigvalsh(C)
        start = np.array([mu, mv, 2 * np.sqrt(ev[1]), 2 * np.sqrt(ev[0]), th])
        return _fit_blurred_ellipse(win, xx, yy, start, bg, (mu, mv), 1.0 - dark)
    band = np.abs(q - 1) < rel
    x, y = _edge_points(norm, level, band)
    if x.size < 12:
        return None
    try:
        params, rms = fit_ellipse(x + u0, y + v0)
    except ValueError:
        return None
    # the centre moves each point's distance from the ellipse by minus its unit normal:
    # covariance rms^2 (N^T N)^-1 over the n - 5 degrees of freedom (the normals of
    # points around the ellipse are orthogonal to the shape's derivatives to first order)
    Q = _ellipse_quadratic(params)
    nrm = np.stack([x + u0 - params[0], y + v0 - params[1]], axis=1) @ Q
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
    try:
        cov = rms**2 * x.size / (x.size - 5) * np.linalg.inv(nrm.T @ nrm)
    except np.linalg.LinAlgError:
        return None
    return params, rms, cov


def _near_hole(holes: np.ndarray, params: np.ndarray, margin: float) -> bool:
    """Whether a non-finite pixel lies within the fit window of the ellipse ``params``
    (x_c, y_c, a, b, theta): its major semi-axis plus the margin and 4 px of edge."""
    xc, yc, a = params[:3]
    r = a + margin + 4.0
    x0, x1 = max(int(np.floor(xc - r)), 0), min(int(np.ceil(xc + r)) + 1, holes.shape[1])
    y0, y1 = max(int(np.floor(yc - r)), 0), min(int(np.ceil(yc + r)) + 1, holes.shape[0])
    return bool(holes[y0:y1, x0:x1].any())


def detect_circle_grid(image, *, rows: int, cols: int, dark: bool = True,
                       method: str = "model", min_area: int = 12,
                       edge_margin_px: float = 2.0) -> GridDetection:
    """Find, order and locate to sub-pixel precision the markers of a circle grid.

    Parameters
    ----------
    image : (H, W) array_like, a fringe-free image of the target (the white frame or the
        background of a phase group), any numeric dtype. Non-finite pixels (NaN, inf)
        are allowed: a marker whose fit window holds one is not found (its centre would
        be biased), the others are unaffected.
    rows, cols : int, the grid's shape (rows along target y, cols along x).
    dark : bool, markers darker than the plate (dark-on-light); False for light-on-dark.
    method : {"model", "edge"}
        "model" (default): the centre of a blurred-ellipse image model fitted to the
        pixels near each marker's edge. "edge": the centre of an ellipse fitted to
        sub-pixel edge points (about twice the bias, see Notes).
    min_area : int, px, smallest marker considered.
    edge_margin_px : float, px, half-width of the band around each coarse marker edge
        searched for sub-pixel edge points (covers the blur).

    Returns
    -------
    GridDetection
        Falsy, with ``reason``, when the grid cannot be found or ordered (too few
        markers, part of the grid hidden or outside the image, stray blobs on the grid).
        Interior markers that are missing (occluded, unreadable) are ``found == False``.

    Notes
    -----
    Coarse: Otsu threshold, connected components, a size and shape filter (all markers
    of a telecentric view have the same size), integer lattice coordinates by breadth-
    first search over neighbours with the two dominant neighbour vectors. Fine, per
    marker: the bright surround is fitted with a plane; then either ("model") a dark
    ellipse on that plane with a Gaussian edge (centre, shape, edge width, depth,
    background: 10 parameters) is fitted by Levenberg-Marquardt to the pixels within
    4 px of the edge, or ("edge") the image is divided by the plane, the half-way level
    between the marker's interior and 1 traced to sub-pixel edge points (cubic
    interpolation along rows or columns, whichever crosses the edge more squarely) and
    a direct ellipse fit gives the centre. Edge-point interpolation errs by an amount
    that depends on where the edge falls within a pixel, which leaves about 0.01 px on
    20-40 px markers; the model is evaluated at the pixel centres and has no such error.
    Either way the marker is taken as an ellipse: lens distortion bends it, which moves
    the fitted centre by (1/2) d2(distortion) <x^2>, about 0.001-0.003 px at the
    corners of the preset rigs (``tests/test_targets.py`` bounds the total).
    """
    rows, cols = int(rows), int(cols)
    if rows < 2 or cols < 2:
        raise ValueError(f"rows and cols must be >= 2, got {rows} x {cols}")
    if method not in ("model", "edge"):
        raise ValueError(f"method must be 'model' or 'edge', got {method!r}")
    img = np.asarray(image)
    if img.ndim != 2 or min(img.shape) < 8:
        raise ValueError(f"image must be a 2-D array, got shape {img.shape}")
    img = img.astype(np.float64)
    holes = ~np.isfinite(img)
    if holes.all():
        return _failure(rows, cols, "the image has no finite pixel")
    if holes.any():  # filled for the blob search only; markers near a hole are dropped
        img = np.where(holes, np.nanmedian(img), img)
    work = img if dark else (img.max() - img)
    inv = work.max() - work  # markers bright in ``inv``
    if np.ptp(work) <= 0:
        return _failure(rows, cols, "the image is uniform (no markers)")
    thr = _otsu(inv.ravel())
    labels, idx, table = _blobs(inv, thr, min_area)
    need = rows * cols
    if table is None or table.shape[0] < 4:
        return _failure(rows, cols, f"found {0 if table is None else table.shape[0]} "
                                    f"marker-like blobs, the grid has {need}")
    area = table[:, 0]
    med = np.median(np.sort(area)[-min(need, area.size):])
    good = (area > 0.5 * med) & (area < 1.8 * med)
    table, idx = table[good], idx[good]
    if table.shape[0] < 4:
        return _failure(rows, cols, "too few markers of a consistent size")
    try:
        index, lattice = _order(table[:, 1:3], rows, cols, img.shape)
    except ValueError as exc:
        return _failure(rows, cols, str(exc))
    centers = np.full((need, 2), np.nan)
    ellipses = np.full((need, 5), np.nan)
    rms = np.full(need, np.nan)
    cov = np.full((need, 2, 2), np.nan)
    for k in np.flatnonzero(index >= 0):
        j = index[k]
        out = _refine(work, table[j], labels, idx[j], margin=edge_margin_px, method=method)
        if out is None:
            continue
        params, e, c = out
        if holes.any() and _near_hole(holes, params, edge_margin_px):
            continue  # a filled pixel would bias the centre: the marker is not found
        ellipses[k] = params
        centers[k] = params[:2]
        rms[k] = e
        cov[k] = c
    found = np.all(np.isfinite(centers), axis=1)
    if found.sum() < 4:
        return _failure(rows, cols, "fewer than 4 markers could be located")
    return GridDetection(rows, cols, centers, found, ellipses, rms, lattice, "", cov)
