"""Circle-grid calibration targets: sub-pixel marker detection, grid ordering and the
projector's view of each circle centre.

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

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

__all__ = [
    "GridDetection",
    "ProjectorObservations",
    "detect_circle_grid",
    "fit_ellipse",
    "projector_observations",
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
    """

    rows: int
    cols: int
    centers: np.ndarray
    found: np.ndarray
    ellipses: np.ndarray
    fit_rms: np.ndarray
    lattice: np.ndarray
    reason: str = ""

    def __bool__(self) -> bool:
        return not self.reason

    @property
    def n_found(self) -> int:
        return int(np.count_nonzero(self.found))


def _failure(rows, cols, reason) -> GridDetection:
    n = rows * cols
    return GridDetection(rows, cols, np.full((n, 2), np.nan), np.zeros(n, dtype=bool),
                         np.full((n, 5), np.nan), np.full(n, np.nan),
                         np.full((2, 2), np.nan), reason)


# --------------------------------------------------------------------------- ellipse fit
def fit_ellipse(x, y):
    """Direct least-squares ellipse fit (Fitzgibbon, Pilu and Fisher; in the numerically
    stable form of Halir and Flusser) to points (x, y).

    Parameters
    ----------
    x, y : (n,) array_like of float, n >= 6.

    Returns
    -------
    params : (5,) ndarray, (x_c, y_c, a, b, theta), semi-axes a >= b, theta the angle
        of the major axis from +x (rad, in (-pi/2, pi/2]).
    rms : float, RMS of the (first-order) geometric distance of the points from it.

    Raises
    ------
    ValueError
        Fewer than 6 points, or no ellipse fits (collinear or degenerate points).
    """
    x = np.asarray(x, dtype=float).ravel()
    y = np.asarray(y, dtype=float).ravel()
    if x.size < 6 or x.size != y.size:
        raise ValueError("fit_ellipse needs at least 6 points (x and y of equal length)")
    mx, my = x.mean(), y.mean()
    s = max(np.sqrt(np.mean((x - mx) ** 2 + (y - my) ** 2)), 1e-12)
    xs, ys = (x - mx) / s, (y - my) / s
    D1 = np.column_stack([xs * xs, xs * ys, ys * ys])
    D2 = np.column_stack([xs, ys, np.ones_like(xs)])
    S1, S2, S3 = D1.T @ D1, D1.T @ D2, D2.T @ D2
    try:
        T = -np.linalg.solve(S3, S2.T)
    except np.linalg.LinAlgError:
        raise ValueError("fit_ellipse: degenerate points") from None
    M = S1 + S2 @ T
    M = np.array([M[2] / 2.0, -M[1], M[0] / 2.0])
    w, V = np.linalg.eig(M)
    V = np.real(V)
    cond = 4.0 * V[0] * V[2] - V[1] ** 2
    ok = np.flatnonzero(cond > 0)
    if ok.size == 0:
        raise ValueError("fit_ellipse: no ellipse fits these points")
    a1 = V[:, ok[np.argmin(np.abs(np.real(w[ok])))]]
    A, B, C = a1
    Dd, E, F = T @ a1
    # undo the normalisation: conic in original coordinates
    A0, B0, C0 = A / s**2, B / s**2, C / s**2
    D0 = Dd / s - 2 * A0 * mx - B0 * my
    E0 = E / s - 2 * C0 * my - B0 * mx
    F0 = F + A0 * mx**2 + B0 * mx * my + C0 * my**2 - Dd / s * mx - E / s * my
    det = 4 * A0 * C0 - B0**2
    if det <= 0:
        raise ValueError("fit_ellipse: no ellipse fits these points")
    xc = (B0 * E0 - 2 * C0 * D0) / det
    yc = (B0 * D0 - 2 * A0 * E0) / det
    Fc = A0 * xc**2 + B0 * xc * yc + C0 * yc**2 + D0 * xc + E0 * yc + F0
    Q = np.array([[A0, B0 / 2], [B0 / 2, C0]]) / (-Fc)
    ev, evec = np.linalg.eigh(Q)
    if np.any(ev <= 0):
        raise ValueError("fit_ellipse: no ellipse fits these points")
    # ev ascending: the smaller eigenvalue belongs to the major axis
    a_ax, b_ax = 1 / np.sqrt(ev[0]), 1 / np.sqrt(ev[1])
    d = evec[:, 0]
    theta = float(np.arctan2(d[1], d[0]))
    if theta > np.pi / 2:
        theta -= np.pi
    elif theta <= -np.pi / 2:
        theta += np.pi
    params = np.array([xc, yc, a_ax, b_ax, theta])
    # first-order geometric distance: (q - 1) / |grad q| with q = p^T Q p
    px, py = x - xc, y - yc
    q = Q[0, 0] * px**2 + 2 * Q[0, 1] * px * py + Q[1, 1] * py**2
    gx = 2 * (Q[0, 0] * px + Q[0, 1] * py)
    gy = 2 * (Q[0, 1] * px + Q[1, 1] * py)
    dist = (q - 1) / np.maximum(np.hypot(gx, gy), 1e-300)
    return params, float(np.sqrt(np.mean(dist**2)))


def _ellipse_quadratic(params):
    """(2, 2) matrix Q with p^T Q p = 1 on the ellipse (p relative to the centre)."""
    _, _, a, b, th = params
    c, s = np.cos(th), np.sin(th)
    Rm = np.array([[c, -s], [s, c]])
    return Rm @ np.diag([1 / a**2, 1 / b**2]) @ Rm.T


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
    image px, rms) or None."""
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
    return params, rms


def _blurred_ellipse(theta, x, y, *, jacobian: bool = False):
    """Image model of a dark ellipse on a planar background, blurred (Gaussian edge).

    ``theta`` (10,): (x_c, y_c, q11, q12, q22, sigma, depth, b0, b1, b2); ``x``, ``y``
    (n,) pixel coordinates relative to a fixed origin. Returns the model (n,) and, with
    ``jacobian``, its derivatives (n, 10). The edge distance is the first-order distance
    ``F / |grad F|`` of ``F = p^T Q p - 1``; its error grows with the distance from the
    edge but is the same at opposite points of the ellipse, so it changes the fitted
    size, not the centre.
    """
    from scipy.special import ndtr

    xc, yc, q11, q12, q22, sig, depth, b0, b1, b2 = theta
    px = x - xc
    py = y - yc
    qx = q11 * px + q12 * py
    qy = q12 * px + q22 * py
    F = px * qx + py * qy - 1.0
    G = np.sqrt(qx * qx + qy * qy) + 1e-300
    d = F / (2.0 * G)
    z = d / sig
    shade = ndtr(-z)  # 1 inside, 0 outside
    back = b0 + b1 * x + b2 * y
    one = 1.0 - depth * shade
    model = back * one
    if not jacobian:
        return model
    dM_dd = back * depth * np.exp(-0.5 * z * z) / (np.sqrt(2.0 * np.pi) * sig)
    # d = F / (2 G): dd = dF / (2 G) - F dG / (2 G^2), dG = (qx dqx + qy dqy) / G
    a1 = dM_dd / (2.0 * G)
    a2 = dM_dd * F / (2.0 * G * G * G)  # times (qx dqx + qy dqy)
    J = np.empty((x.size, 10))
    J[:, 0] = a1 * (-2 * qx) - a2 * (qx * -q11 + qy * -q12)
    J[:, 1] = a1 * (-2 * qy) - a2 * (qx * -q12 + qy * -q22)
    J[:, 2] = a1 * (px * px) - a2 * (qx * px)
    J[:, 3] = a1 * (2 * px * py) - a2 * (qx * py + qy * px)
    J[:, 4] = a1 * (py * py) - a2 * (qy * py)
    J[:, 5] = -dM_dd * z  # d shade / d sig = phi z / sig
    J[:, 6] = -back * shade
    J[:, 7] = one
    J[:, 8] = x * one
    J[:, 9] = y * one
    return model, J


def _normal_equations_py(theta, x, y, z):
    """(J^T J, J^T r, r^T r) of :func:`_blurred_ellipse` at ``theta`` (reference code
    for the compiled kernel)."""
    model, J = _blurred_ellipse(theta, x, y, jacobian=True)
    r = z - model
    return J.T @ J, J.T @ r, float(r @ r)


def _make_kernel():
    try:
        import numba
    except ImportError:  # pragma: no cover - numba is a dependency
        return _normal_equations_py

    @numba.njit(cache=True, fastmath=False)
    def kernel(theta, x, y, z):
        xc, yc, q11, q12, q22, sig, depth, b0, b1, b2 = theta
        A = np.zeros((10, 10))
        g = np.zeros(10)
        cost = 0.0
        j = np.empty(10)
        k = 1.0 / np.sqrt(2.0 * np.pi)
        for i in range(x.size):
            px = x[i] - xc
            py = y[i] - yc
            qx = q11 * px + q12 * py
            qy = q12 * px + q22 * py
            F = px * qx + py * qy - 1.0
            G = np.sqrt(qx * qx + qy * qy) + 1e-300
            d = F / (2.0 * G)
            zz = d / sig
            shade = 0.5 * math.erfc(zz / np.sqrt(2.0))
            back = b0 + b1 * x[i] + b2 * y[i]
            one = 1.0 - depth * shade
            r = z[i] - back * one
            dmd = back * depth * np.exp(-0.5 * zz * zz) * k / sig
            a1 = dmd / (2.0 * G)
            a2 = dmd * F / (2.0 * G * G * G)
            j[0] = a1 * (-2.0 * qx) - a2 * (qx * -q11 + qy * -q12)
            j[1] = a1 * (-2.0 * qy) - a2 * (qx * -q12 + qy * -q22)
            j[2] = a1 * (px * px) - a2 * (qx * px)
            j[3] = a1 * (2.0 * px * py) - a2 * (qx * py + qy * px)
            j[4] = a1 * (py * py) - a2 * (qy * py)
            j[5] = -dmd * zz
            j[6] = -back * shade
            j[7] = one
            j[8] = x[i] * one
            j[9] = y[i] * one
            for p in range(10):
                g[p] += j[p] * r
                for q in range(p, 10):
                    A[p, q] += j[p] * j[q]
            cost += r * r
        for p in range(10):
            for q in range(p):
                A[p, q] = A[q, p]
        return A, g, cost

    return kernel


_KERNEL = None


def _normal_equations(theta, x, y, z):
    global _KERNEL
    if _KERNEL is None:
        _KERNEL = _make_kernel()
    return _KERNEL(np.ascontiguousarray(theta, dtype=np.float64), x, y, z)


def _fit_blurred_ellipse(win, xx, yy, params, bg, origin, depth, *, max_iter=15):
    """Gauss-Newton fit of :func:`_blurred_ellipse` to the pixels near a marker's edge.

    The model is evaluated at the pixel centres, so its error does not depend on where
    the edge falls within a pixel (the interpolation of edge crossings does, and leaves a
    bias of about 0.01 px on 20-40 px markers). ``params`` (x_c, y_c, a, b, theta) is the
    start. Returns (params (5,), residual rms relative to the background) or None.
    """
    xc, yc, a, b, th = params
    c, s_ = np.cos(th), np.sin(th)
    Rm = np.array([[c, -s_], [s_, c]])
    Q = Rm @ np.diag([1 / a**2, 1 / b**2]) @ Rm.T
    ox, oy = origin
    # pixels within ~4 px of the edge
    px, py = xx - xc, yy - yc
    Fq = Q[0, 0] * px**2 + 2 * Q[0, 1] * px * py + Q[1, 1] * py**2 - 1
    g = 2 * np.hypot(Q[0, 0] * px + Q[0, 1] * py, Q[0, 1] * px + Q[1, 1] * py)
    sel = np.abs(Fq / np.maximum(g, 1e-12)) < 4.0
    x, y, z = (xx - ox)[sel].astype(float), (yy - oy)[sel].astype(float), win[sel]
    if z.size < 30:
        return None
    theta = np.array([xc - ox, yc - oy, Q[0, 0], Q[0, 1], Q[1, 1], 0.8, depth,
                      bg[0], bg[1], bg[2]], dtype=float)
    x = np.ascontiguousarray(x, dtype=np.float64)
    y = np.ascontiguousarray(y, dtype=np.float64)
    z = np.ascontiguousarray(z, dtype=np.float64)
    A, g_, cost = _normal_equations(theta, x, y, z)
    lam = 1e-6  # the start (blob moments) is close: begin near Gauss-Newton
    for _ in range(max_iter):
        dA = np.maximum(np.diag(A), 1e-300)
        try:
            delta = np.linalg.solve(A + lam * np.diag(dA), g_)
        except np.linalg.LinAlgError:
            return None
        trial = theta + delta
        A2, g2, c2 = _normal_equations(trial, x, y, z)
        if np.isfinite(c2) and c2 <= cost:
            theta, A, g_, cost = trial, A2, g2, c2
            lam = max(lam / 10, 1e-9)
            if np.max(np.abs(delta[:2])) < 1e-4:  # px; the noise is ~50x larger
                break
        else:
            lam *= 10
            if lam > 1e6:
                break
    q11, q12, q22 = theta[2:5]
    ev, evec = np.linalg.eigh(np.array([[q11, q12], [q12, q22]]))
    if not np.all(np.isfinite(theta)) or np.any(ev <= 0) or not 0.05 < abs(theta[5]) < 10:
        return None
    if np.hypot(theta[0] + ox - xc, theta[1] + oy - yc) > 2.0:
        return None
    d = evec[:, 0]
    ang = float(np.arctan2(d[1], d[0]))
    if ang > np.pi / 2:
        ang -= np.pi
    elif ang <= -np.pi / 2:
        ang += np.pi
    out = np.array([theta[0] + ox, theta[1] + oy, 1 / np.sqrt(ev[0]), 1 / np.sqrt(ev[1]), ang])
    rms = float(np.sqrt(cost / z.size)) / max(abs(theta[7]), 1e-12)
    return out, rms


def detect_circle_grid(image, *, rows: int, cols: int, dark: bool = True,
                       method: str = "model", min_area: int = 12,
                       edge_margin_px: float = 2.0) -> GridDetection:
    """Find, order and locate to sub-pixel precision the markers of a circle grid.

    Parameters
    ----------
    image : (H, W) array_like, a fringe-free image of the target (the white frame or the
        background of a phase group), any numeric dtype.
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
    if not np.all(np.isfinite(img)):
        img = np.where(np.isfinite(img), img, np.nanmedian(img))
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
    for k in np.flatnonzero(index >= 0):
        j = index[k]
        out = _refine(work, table[j], labels, idx[j], margin=edge_margin_px, method=method)
        if out is None:
            continue
        params, e = out
        ellipses[k] = params
        centers[k] = params[:2]
        rms[k] = e
    found = np.all(np.isfinite(centers), axis=1)
    if found.sum() < 4:
        return _failure(rows, cols, "fewer than 4 markers could be located")
    return GridDetection(rows, cols, centers, found, ellipses, rms, lattice, "")


# --------------------------------------------------------------------------- projector
@dataclass(frozen=True, eq=False)
class ProjectorObservations:
    """The projector's coordinates of each circle centre.

    Attributes
    ----------
    uv : (n, 2) ndarray, projector px (u_p, v_p) at each centre; NaN where the light
        surround had too few valid pixels or the centre itself was NaN.
    sigma : (n, 2) ndarray, projector px, standard deviation of each value from the
        fit's residuals.
    n_pixels : (n,) ndarray of int, surround pixels used.
    """

    uv: np.ndarray
    sigma: np.ndarray
    n_pixels: np.ndarray


def _surround_fit_py(u_p, v_p, valid, cu, cv, R, exps, reject, min_pixels):
    """Robust polynomial fit of u_p, v_p over the valid pixels of a disc of radius ``R``
    around (cu, cv); returns (u, v, sigma_u, sigma_v, n_used) with n_used = 0 on failure.
    Plain code, compiled by numba when available (:func:`_surround_kernel`)."""
    H, W = u_p.shape
    ri = int(np.ceil(R)) + 1
    ic, jc = int(np.floor(cv + 0.5)), int(np.floor(cu + 0.5))
    nmax = (2 * ri + 1) * (2 * ri + 1)
    t = exps.shape[0]
    A = np.empty((nmax, t))
    Y = np.empty((nmax, 2))
    m = 0
    quads = np.zeros(4)
    xp = np.ones(4)
    yp = np.ones(4)
    for i in range(max(ic - ri, 0), min(ic + ri + 1, H)):
        dy = (i - cv) / R
        for j in range(max(jc - ri, 0), min(jc + ri + 1, W)):
            if not valid[i, j]:
                continue
            dx = (j - cu) / R
            if dx * dx + dy * dy > 1.0:
                continue
            for q in range(1, 4):
                xp[q] = xp[q - 1] * dx
                yp[q] = yp[q - 1] * dy
            for q in range(t):
                A[m, q] = xp[exps[q, 0]] * yp[exps[q, 1]]
            Y[m, 0] = u_p[i, j]
            Y[m, 1] = v_p[i, j]
            quads[(1 if dx >= 0 else 0) * 2 + (1 if dy >= 0 else 0)] += 1
            m += 1
    out = np.zeros(5)
    if m < min_pixels or quads.min() < 0.05 * m:
        return out
    keep = np.ones(m, dtype=np.bool_)
    coef = np.zeros((t, 2))
    Ninv = np.zeros((t, t))
    res = np.zeros((m, 2))
    for _ in range(5):
        N = np.zeros((t, t))
        b = np.zeros((t, 2))
        for r in range(m):
            if keep[r]:
                for p in range(t):
                    b[p, 0] += A[r, p] * Y[r, 0]
                    b[p, 1] += A[r, p] * Y[r, 1]
                    for q in range(p, t):
                        N[p, q] += A[r, p] * A[r, q]
        for p in range(t):
            for q in range(p):
                N[p, q] = N[q, p]
        if np.linalg.matrix_rank(N) < t:
            return out
        Ninv = np.linalg.inv(N)
        coef = Ninv @ b
        nk = 0
        for r in range(m):
            for a in range(2):
                acc = Y[r, a]
                for p in range(t):
                    acc -= A[r, p] * coef[p, a]
                res[r, a] = acc
        # robust scale: median absolute residual of (a regular subsample of) the kept
        # pixels; 2000 values give it to about 3 %, plenty for a 5-sigma cut
        stride = max(1, m // 2000)
        absu = np.empty(m // stride + 1)
        absv = np.empty(m // stride + 1)
        for r in range(0, m, stride):
            if keep[r]:
                absu[nk] = abs(res[r, 0])
                absv[nk] = abs(res[r, 1])
                nk += 1
        if nk < 10:
            return out
        su = max(1.4826 * np.median(absu[:nk]), 1e-9)
        sv = max(1.4826 * np.median(absv[:nk]), 1e-9)
        changed = False
        for r in range(m):
            new = abs(res[r, 0]) <= reject * su and abs(res[r, 1]) <= reject * sv
            if new != keep[r]:
                changed = True
            keep[r] = new
        if not changed:
            break
    nk = 0
    ssu = 0.0
    ssv = 0.0
    for r in range(m):
        if keep[r]:
            nk += 1
            ssu += res[r, 0] ** 2
            ssv += res[r, 1] ** 2
    if nk < min_pixels:
        return out
    dof = max(nk - t, 1)
    out[0] = coef[0, 0]
    out[1] = coef[0, 1]
    out[2] = np.sqrt(ssu / dof * Ninv[0, 0])
    out[3] = np.sqrt(ssv / dof * Ninv[0, 0])
    out[4] = nk
    return out


_SURROUND = None


def _surround_kernel():
    global _SURROUND
    if _SURROUND is None:
        try:
            import numba

            _SURROUND = numba.njit(cache=True, fastmath=False)(_surround_fit_py)
        except ImportError:  # pragma: no cover - numba is a dependency
            _SURROUND = _surround_fit_py
    return _SURROUND


def projector_observations(u_p, v_p, mask, centers, *, ellipses=None,
                           marker_radius_px: float | None = None, window_px=None,
                           exclude_scale: float = 1.3, exclude_margin_px: float = 3.0,
                           degree: int = 2, min_pixels: int = 50,
                           reject_sigmas: float = 5.0) -> ProjectorObservations:
    """Projector coordinates (u_p, v_p) at each circle centre, read from the light
    surround of the marker.

    The dark marker has little modulation, and camera blur mixes its edge into the
    phase, so the phase is not read there: a polynomial of ``degree`` in (u, v) is fitted
    to u_p and to v_p over the valid pixels of a disc around the centre, minus every
    marker scaled by ``exclude_scale`` and grown by ``exclude_margin_px``, and evaluated at
    the centre. Pixels off the fit by more than ``reject_sigmas`` robust standard
    deviations (a wrong fringe order, a speck) are dropped and the fit repeated.

    Parameters
    ----------
    u_p, v_p : (H, W) array_like of float, projector px per camera pixel (NaN invalid).
    mask : (H, W) array_like of bool, valid pixels.
    centers : GridDetection or (n, 2) array_like, camera px (NaN = skip).
    ellipses : (n, 5) array_like, (u_c, v_c, a, b, theta) of each marker; taken from a
        GridDetection; else circles of ``marker_radius_px``.
    window_px : float, px, radius of the disc; default 0.9 of the shorter grid step
        (from a GridDetection) or 3.5 marker radii.
    degree : int, 1..3.
    min_pixels : int, fewest surround pixels for a value.

    Returns
    -------
    ProjectorObservations

    Raises
    ------
    ValueError
        Inconsistent shapes, or no way to know the marker size.
    """
    import cv2

    u_p = np.asarray(u_p, dtype=float)
    v_p = np.asarray(v_p, dtype=float)
    mask = np.asarray(mask, dtype=bool)
    if u_p.shape != v_p.shape or u_p.shape != mask.shape or u_p.ndim != 2:
        raise ValueError("u_p, v_p and mask must be 2-D arrays of the same shape")
    if not 1 <= int(degree) <= 3:
        raise ValueError(f"degree must be 1, 2 or 3, got {degree!r}")
    lattice = None
    if isinstance(centers, GridDetection):
        det = centers
        pts = np.where(det.found[:, None], det.centers, np.nan)
        if ellipses is None:
            ellipses = det.ellipses
        lattice = det.lattice
    else:
        pts = np.asarray(centers, dtype=float).reshape(-1, 2)
    n = pts.shape[0]
    if ellipses is None:
        if marker_radius_px is None or not marker_radius_px > 0:
            raise ValueError("give ellipses, a GridDetection or marker_radius_px")
        r = float(marker_radius_px)
        ellipses = np.column_stack([pts, np.full(n, r), np.full(n, r), np.zeros(n)])
    ellipses = np.asarray(ellipses, dtype=float).reshape(n, 5)
    if window_px is None:
        if lattice is not None and np.all(np.isfinite(lattice)):
            window_px = 0.9 * float(min(np.hypot(*lattice[:, 0]), np.hypot(*lattice[:, 1])))
        else:
            window_px = 3.5 * float(np.nanmedian(ellipses[:, 2]))
    R = float(window_px)
    H, W = u_p.shape
    # exclusion mask: every known marker, scaled and grown
    excl = np.zeros((H, W), dtype=np.uint8)
    shift = 4
    for e in ellipses:
        if not np.all(np.isfinite(e)):
            continue
        ax = (int(round((e[2] * exclude_scale + exclude_margin_px) * 2**shift)),
              int(round((e[3] * exclude_scale + exclude_margin_px) * 2**shift)))
        cv2.ellipse(excl, (int(round(e[0] * 2**shift)), int(round(e[1] * 2**shift))), ax,
                    float(np.degrees(e[4])), 0.0, 360.0, 1, thickness=-1, lineType=cv2.LINE_8,
                    shift=shift)
    valid = mask & (excl == 0) & np.isfinite(u_p) & np.isfinite(v_p)
    out = np.full((n, 2), np.nan)
    sig = np.full((n, 2), np.nan)
    npx = np.zeros(n, dtype=int)
    exps = np.array([(i, j) for i in range(degree + 1) for j in range(degree + 1 - i)],
                    dtype=np.int64)
    fit = _surround_kernel()
    up = np.ascontiguousarray(u_p, dtype=np.float64)
    vp = np.ascontiguousarray(v_p, dtype=np.float64)
    va = np.ascontiguousarray(valid)
    for k in range(n):
        c = pts[k]
        if not np.all(np.isfinite(c)):
            continue
        res = fit(up, vp, va, float(c[0]), float(c[1]), R, exps, float(reject_sigmas),
                  int(min_pixels))
        if res[4] <= 0:
            continue
        out[k] = res[0], res[1]
        sig[k] = res[2], res[3]
        npx[k] = int(res[4])
    return ProjectorObservations(out, sig, npx)
