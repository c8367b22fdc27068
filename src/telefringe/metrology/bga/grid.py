"""Registration of the balls found on the nominal grid (rotation, offset, indices)."""

from __future__ import annotations

import numpy as np

from telefringe.metrology._common import MetrologyError


def _register_grid(pos: np.ndarray, pitch: float, rows: int, cols: int,
                   populated: np.ndarray):
    """Integer grid indices of ball positions pos (n, 2) on the substrate plane."""
    n = pos.shape[0]
    # orientation: nearest-neighbour directions modulo 90 deg
    if n >= 2:
        d = pos[:, None, :] - pos[None, :, :]
        dist = np.hypot(d[..., 0], d[..., 1])
        np.fill_diagonal(dist, np.inf)
        nn = np.argmin(dist, axis=1)
        ok = np.abs(dist[np.arange(n), nn] - pitch) < 0.25 * pitch
        vec = d[nn, np.arange(n)][ok]
    else:
        vec = np.zeros((0, 2))
    if vec.shape[0] == 0:
        theta = 0.0
    else:
        ang = np.arctan2(vec[:, 1], vec[:, 0])
        z = np.mean(np.exp(4j * ang))
        theta = float(np.angle(z) / 4.0)  # in (-45, 45] deg
    c, s = np.cos(theta), np.sin(theta)
    local = pos @ np.array([[c, -s], [s, c]])  # rotate by -theta
    f = local / pitch
    # lattice offset: circular mean of the fractional parts
    off = np.angle(np.mean(np.exp(2j * np.pi * f), axis=0)) / (2 * np.pi)
    k = np.round(f - off).astype(np.int64)
    frac = f - off - k
    on_grid = np.all(np.abs(frac) < 0.3, axis=1)
    if not np.any(on_grid):
        raise MetrologyError("no ball lies on a lattice of the nominal pitch")
    kmin = k[on_grid].min(axis=0)
    span = k[on_grid].max(axis=0) - kmin + 1  # (cols, rows)
    if rows is None:
        return None, theta, None, span
    if span[0] > cols or span[1] > rows:
        raise MetrologyError(
            f"the balls found span {span[1]} x {span[0]} positions, more than the nominal "
            f"{rows} x {cols} grid (wrong pitch or grid size?)")
    # place the found block inside the nominal grid: the shift that best matches the
    # populated positions (unique when the found balls span the whole grid)
    best = None
    for si in range(rows - span[1] + 1):
        for sj in range(cols - span[0] + 1):
            jj = k[on_grid, 0] - kmin[0] + sj
            ii = k[on_grid, 1] - kmin[1] + si
            score = int(np.count_nonzero(populated[ii, jj]))
            cand = (score, -(si + sj), si, sj)
            if best is None or cand > best[0]:
                best = (cand, [(si, sj)])
            elif cand[0] == best[0][0]:
                best[1].append((si, sj))
    if len(best[1]) > 1:
        raise MetrologyError(
            "cannot place the balls found on the nominal grid: a whole edge row or column "
            "is missing and the populated map does not decide; give BGANominal.present")
    si, sj = best[1][0]
    idx = np.full((n, 2), -1, dtype=np.int64)
    idx[on_grid, 0] = k[on_grid, 1] - kmin[1] + si
    idx[on_grid, 1] = k[on_grid, 0] - kmin[0] + sj
    origin_local = (np.array([kmin[0] - sj, kmin[1] - si]) + off) * pitch
    return idx, theta, origin_local, span


def _grid_local(pos: np.ndarray, theta: float, origin_local: np.ndarray) -> np.ndarray:
    """Positions (n, 2) on the substrate plane in the grid's frame (mm): x' along the
    columns, y' along the rows, (0, 0) at grid position (0, 0)."""
    c, s = np.cos(theta), np.sin(theta)
    return pos @ np.array([[c, -s], [s, c]]) - origin_local


def _claim_positions(pos: np.ndarray, pitch: float, theta: float, origin_local: np.ndarray,
                     rows: int, cols: int, *, min_share: float = 0.25) -> list:
    """Grid positions (i, j) covered by a region whose points lie at ``pos`` (m, 2) on the
    substrate plane: a position is covered when it holds at least ``min_share`` of the
    points and their mean lies within 0.3 pitch of the position (so a region between two
    positions claims neither, and one spanning two balls claims both)."""
    if pos.shape[0] == 0:
        return []
    f = _grid_local(pos, theta, origin_local) / pitch
    k = np.round(f).astype(np.int64)  # (j, i)
    out = []
    cells, inverse, counts = np.unique(k, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    for c, (j, i) in enumerate(cells):
        if counts[c] < min_share * pos.shape[0] or not (0 <= i < rows and 0 <= j < cols):
            continue
        if np.all(np.abs(f[inverse == c].mean(axis=0) - (j, i)) < 0.3):
            out.append((int(i), int(j)))
    return out
