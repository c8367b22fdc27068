"""Compiled inner loops of the virtual rig (numba, no fastmath: plain IEEE arithmetic)."""

from __future__ import annotations

import math

import numba
import numpy as np

from telefringe.devices import _telecentric_kernels as _tk

__all__ = ["heightfield_eval", "heightfield_intersect", "camera_rays",
           "shade", "interp_samples", "plate_intersect", "boxes_intersect",
           "sphere_intersect", "bga_intersect", "plane_intersect", "hit_points",
           "accumulate_many", "sensor_counts", "shadow_origins"]


@numba.njit(cache=True, nogil=True)
def _hf_at(z, px, x0, y0, x, y):
    """Bilinear height and gradient at (x, y); nan outside the grid."""
    rows, cols = z.shape
    fx = (x - x0) / px
    fy = (y - y0) / px
    if not (fx >= 0.0 and fy >= 0.0 and fx <= cols - 1 and fy <= rows - 1):
        return np.nan, 0.0, 0.0
    j = min(int(fx), cols - 2)
    i = min(int(fy), rows - 2)
    a = fx - j
    b = fy - i
    z00 = z[i, j]
    z01 = z[i, j + 1]
    z10 = z[i + 1, j]
    z11 = z[i + 1, j + 1]
    h = (z00 * (1 - a) * (1 - b) + z01 * a * (1 - b) + z10 * (1 - a) * b + z11 * a * b)
    dhdx = ((z01 - z00) * (1 - b) + (z11 - z10) * b) / px
    dhdy = ((z10 - z00) * (1 - a) + (z11 - z01) * a) / px
    return h, dhdx, dhdy


@numba.njit(cache=True, nogil=True)
def heightfield_eval(z, px, x0, y0, xs, ys):
    """Bilinear height (nan outside) and gradient at points (xs, ys) (N,)."""
    n = xs.shape[0]
    h = np.empty(n)
    gx = np.empty(n)
    gy = np.empty(n)
    for k in range(n):
        h[k], gx[k], gy[k] = _hf_at(z, px, x0, y0, xs[k], ys[k])
    return h, gx, gy


@numba.njit(cache=True, nogil=True)
def heightfield_intersect(z, px, x0, y0, o, d):
    """First crossing from above of rays ``o + t d`` with a bilinear height field.

    ``o`` (N, 3) origins, ``d`` (N, 3) unit directions (one per ray). Marches in steps
    of px/4 in x-y (at most 1/8 of the height range in z), then bisects the first sign
    change of ``z_ray - h`` to 1e-9 mm. Returns t (N,) (inf: no hit) and the upward unit
    normal (N, 3).
    """
    n = o.shape[0]
    t_out = np.full(n, np.inf)
    nrm = np.zeros((n, 3))
    zmin = z.min()
    zmax = z.max()
    span = max(zmax - zmin, 1e-9)
    for k in range(n):
        if not (o[k, 0] == o[k, 0] and o[k, 1] == o[k, 1] and o[k, 2] == o[k, 2]):
            continue
        d0 = d[k, 0]
        d1 = d[k, 1]
        d2 = d[k, 2]
        dxy = np.sqrt(d0 * d0 + d1 * d1)
        step = np.inf
        if dxy > 0:
            step = 0.25 * px / dxy
        if abs(d2) > 0:
            step = min(step, 0.125 * span / abs(d2))
            step = max(step, 1e-9)
        if not np.isfinite(step):
            continue
        # parameter range where the ray is within [zmin, zmax]
        if d2 != 0.0:
            ta = (zmax - o[k, 2]) / d2
            tb = (zmin - o[k, 2]) / d2
            if ta > tb:
                ta, tb = tb, ta
        else:
            if o[k, 2] < zmin or o[k, 2] > zmax:
                continue
            ta = 0.0
            tb = 1e6
        ta = max(ta, 0.0) - step
        tb = tb + step
        if tb <= 0:
            continue
        prev_f = np.nan
        prev_t = ta
        t = ta
        found = False
        while t <= tb + step:
            x = o[k, 0] + t * d0
            y = o[k, 1] + t * d1
            h, _, _ = _hf_at(z, px, x0, y0, x, y)
            f = o[k, 2] + t * d2 - h
            if prev_f > 0.0 and f <= 0.0:
                lo = prev_t
                hi = t
                for _ in range(200):
                    if hi - lo <= 1e-9:
                        break
                    mid = 0.5 * (lo + hi)
                    hm, _, _ = _hf_at(z, px, x0, y0, o[k, 0] + mid * d0, o[k, 1] + mid * d1)
                    fm = o[k, 2] + mid * d2 - hm
                    if fm > 0.0:
                        lo = mid
                    elif fm <= 0.0:
                        hi = mid
                    else:  # left the grid in between: keep the inside end
                        lo = mid
                th = 0.5 * (lo + hi)
                h, gx, gy = _hf_at(z, px, x0, y0, o[k, 0] + th * d0, o[k, 1] + th * d1)
                if h == h:
                    t_out[k] = th
                    s = np.sqrt(gx * gx + gy * gy + 1.0)
                    nrm[k, 0] = -gx / s
                    nrm[k, 1] = -gy / s
                    nrm[k, 2] = 1.0 / s
                    found = True
            if found:
                break
            prev_f = f  # nan outside the grid: no crossing from outside
            prev_t = t
            t += step
    return t_out, nrm


# --------------------------------------------------------------------------- devices
@numba.njit(cache=True, nogil=True)
def camera_rays(u, v, intr, R, t, start):
    """Orthographic camera rays through pixels (u, v) (N,) (the telecentric device model's
    back-projection, :mod:`telefringe.devices._telecentric_kernels`).

    ``intr``, ``R``, ``t`` as :func:`~telefringe.devices._telecentric_kernels.kernel_args`.
    Returns origins (N, 3) placed ``start`` mm behind the zero-depth plane along the
    viewing direction ``R[2]``, and ok (N,) bool (undistortion converged).
    """
    n = u.shape[0]
    o = np.empty((n, 3))
    ok = np.empty(n, dtype=np.bool_)
    m, du, dv, u0, v0, k1, s1, s2 = intr
    R9 = _tk.flat_rotation(R)
    for i in range(n):
        a, b, ok[i] = _tk.backproject_point(u[i], v[i], m, u0, v0, du, dv, k1, s1, s2, t[0],
                                            t[1])
        o[i, 0], o[i, 1], o[i, 2] = _tk.line_point(a, b, -start, R9)
    return o, ok


@numba.njit(cache=True, nogil=True)
def _phi(x):
    """Standard normal CDF (exactly 0 or 1 in double precision beyond |x| = 9)."""
    if x > 9.0:
        return 1.0
    if x < -9.0:
        return 0.0
    return 0.5 * math.erfc(-x * 0.7071067811865476)


@numba.njit(cache=True, nogil=True)
def shade(t, nrm, alb, spec, unshadowed, up, vp, to_proj, h_vec, spec_sigma, dn, ambient,
          W, H, sigma_p):
    """Per-sample weights of the pattern (see render._trace). Returns wu, wv, amb, lit.

    ``to_proj`` (N, 3) unit vectors toward the projector, ``h_vec`` (N, 3) unit half
    vectors (toward the projector + toward the camera), per sample."""
    n = t.shape[0]
    wu = np.zeros(n)
    wv = np.zeros(n)
    amb = np.zeros(n)
    lit = np.zeros(n, dtype=np.bool_)
    for i in numba.prange(n):
        if not np.isfinite(t[i]):
            continue
        amb[i] = dn * ambient * alb[i]
        cos_i = (nrm[i, 0] * to_proj[i, 0] + nrm[i, 1] * to_proj[i, 1]
                 + nrm[i, 2] * to_proj[i, 2])
        if cos_i <= 0.0 or not unshadowed[i]:
            continue
        w = dn * alb[i] * cos_i
        if spec[i] != 0.0:
            ch = nrm[i, 0] * h_vec[i, 0] + nrm[i, 1] * h_vec[i, 1] + nrm[i, 2] * h_vec[i, 2]
            ang = math.acos(min(1.0, max(-1.0, ch)))
            w += dn * spec[i] * math.exp(-0.5 * (ang / spec_sigma) ** 2)
        if sigma_p > 0.0:
            eu = _phi((up[i] + 0.5) / sigma_p) - _phi((up[i] - W + 0.5) / sigma_p)
            ev = _phi((vp[i] + 0.5) / sigma_p) - _phi((vp[i] - H + 0.5) / sigma_p)
        else:
            eu = 1.0 if (up[i] >= -0.5 and up[i] <= W - 0.5) else 0.0
            ev = 1.0 if (vp[i] >= -0.5 and vp[i] <= H - 0.5) else 0.0
        wu[i] = w * ev
        wv[i] = w * eu
        lit[i] = up[i] >= -0.5 and up[i] <= W - 0.5 and vp[i] >= -0.5 and vp[i] <= H - 0.5
    return wu, wv, amb, lit


@numba.njit(cache=True, nogil=True)
def interp_samples(f, offsets, scale, out):
    """Quadratic interpolation of a per-pixel field at sub-pixel offsets.

    f (rows, cols); offsets (ns, 2) as (du, dv); out (rows * cols * ns,) pixel-major,
    written with ``scale * value``; border pixels get the centre value.
    """
    rows, cols = f.shape
    ns = offsets.shape[0]
    for r in numba.prange(rows):
        for c in range(cols):
            base = (r * cols + c) * ns
            f0 = f[r, c]
            if r == 0 or c == 0 or r == rows - 1 or c == cols - 1:
                for s in range(ns):
                    out[base + s] = scale * f0
                continue
            fx = 0.5 * (f[r, c + 1] - f[r, c - 1])
            fy = 0.5 * (f[r + 1, c] - f[r - 1, c])
            fxx = f[r, c + 1] - 2.0 * f0 + f[r, c - 1]
            fyy = f[r + 1, c] - 2.0 * f0 + f[r - 1, c]
            fxy = 0.25 * (f[r + 1, c + 1] - f[r + 1, c - 1] - f[r - 1, c + 1]
                          + f[r - 1, c - 1])
            for s in range(ns):
                a = offsets[s, 0]
                b = offsets[s, 1]
                out[base + s] = scale * (f0 + a * fx + b * fy + 0.5 * a * a * fxx
                                         + 0.5 * b * b * fyy + a * b * fxy)


# --------------------------------------------------------------------------- scenes
@numba.njit(cache=True, nogil=True)
def _new_hits(n):
    return (np.full(n, np.inf), np.zeros((n, 3)), np.zeros(n), np.zeros(n),
            np.full(n, -1, dtype=np.int32))


@numba.njit(cache=True, nogil=True)
def _set_normal(nrm, i, nx, ny, nz, d):
    """Store a unit normal facing the incoming ray."""
    if nx * d[0] + ny * d[1] + nz * d[2] > 0.0:
        nx, ny, nz = -nx, -ny, -nz
    nrm[i, 0] = nx
    nrm[i, 1] = ny
    nrm[i, 2] = nz


@numba.njit(cache=True, nogil=True)
def plate_intersect(o, d, R, tw, rows, cols, pitch, radius, margin, albedo, marker_albedo):
    """Circle plate: the plane Z = 0 of the target frame (R world<-target, origin tw)."""
    n = o.shape[0]
    t_out, nrm, alb, spec, part = _new_hits(n)
    x1 = (cols - 1) * pitch + margin
    y1 = (rows - 1) * pitch + margin
    r2max = radius * radius
    for i in numba.prange(n):
        if not (o[i, 0] == o[i, 0]):
            continue
        dlz = R[0, 2] * d[i, 0] + R[1, 2] * d[i, 1] + R[2, 2] * d[i, 2]
        if dlz == 0.0:
            continue
        dlx = R[0, 0] * d[i, 0] + R[1, 0] * d[i, 1] + R[2, 0] * d[i, 2]
        dly = R[0, 1] * d[i, 0] + R[1, 1] * d[i, 1] + R[2, 1] * d[i, 2]
        px = o[i, 0] - tw[0]
        py = o[i, 1] - tw[1]
        pz = o[i, 2] - tw[2]
        lx = R[0, 0] * px + R[1, 0] * py + R[2, 0] * pz
        ly = R[0, 1] * px + R[1, 1] * py + R[2, 1] * pz
        lz = R[0, 2] * px + R[1, 2] * py + R[2, 2] * pz
        t = -lz / dlz
        if not t > 0.0:
            continue
        x = lx + t * dlx
        y = ly + t * dly
        if x < -margin or x > x1 or y < -margin or y > y1:
            continue
        j = min(max(np.round(x / pitch), 0.0), cols - 1.0)
        k = min(max(np.round(y / pitch), 0.0), rows - 1.0)
        r2 = (x - j * pitch) ** 2 + (y - k * pitch) ** 2
        t_out[i] = t
        _set_normal(nrm, i, R[0, 2], R[1, 2], R[2, 2], d[i])
        if r2 <= r2max:
            alb[i] = marker_albedo
            part[i] = 1
        else:
            alb[i] = albedo
            part[i] = 0
    return t_out, nrm, alb, spec, part


@numba.njit(cache=True, nogil=True)
def boxes_intersect(o, d, R, tw, blocks, base, albedo, base_albedo):
    """Step gauge: base rectangle at Z = 0 plus axis-aligned blocks, in the scene frame."""
    n = o.shape[0]
    t_out, nrm, alb, spec, part = _new_hits(n)
    nb = blocks.shape[0]
    for i in numba.prange(n):
        if not (o[i, 0] == o[i, 0]):
            continue
        dl = np.empty(3)
        for k in range(3):
            dl[k] = R[0, k] * d[i, 0] + R[1, k] * d[i, 1] + R[2, k] * d[i, 2]
        ol = np.empty(3)
        for k in range(3):
            ol[k] = (R[0, k] * (o[i, 0] - tw[0]) + R[1, k] * (o[i, 1] - tw[1])
                     + R[2, k] * (o[i, 2] - tw[2]))
        best = np.inf
        bn = np.zeros(3)
        bp = -1
        if dl[2] != 0.0:
            t = -ol[2] / dl[2]
            x = ol[0] + t * dl[0]
            y = ol[1] + t * dl[1]
            if t > 0.0 and x >= base[0] and x <= base[1] and y >= base[2] and y <= base[3]:
                best = t
                bn[0] = 0.0
                bn[1] = 0.0
                bn[2] = 1.0
                bp = 0
        for b in range(nb):
            tnear = -np.inf
            tfar = np.inf
            axis = 0
            miss = False
            for k in range(3):
                lo = blocks[b, 2 * k]
                hi = blocks[b, 2 * k + 1]
                if dl[k] == 0.0:
                    if ol[k] < lo or ol[k] > hi:
                        miss = True
                    continue
                t1 = (lo - ol[k]) / dl[k]
                t2 = (hi - ol[k]) / dl[k]
                if t1 > t2:
                    t1, t2 = t2, t1
                if t1 > tnear:
                    tnear = t1
                    axis = k
                if t2 < tfar:
                    tfar = t2
            if miss or tnear > tfar or not tnear > 0.0 or tnear >= best:
                continue
            best = tnear
            bn[0] = 0.0
            bn[1] = 0.0
            bn[2] = 0.0
            bn[axis] = -1.0 if dl[axis] > 0 else 1.0
            bp = b + 1
        if bp >= 0:
            t_out[i] = best
            wx = R[0, 0] * bn[0] + R[0, 1] * bn[1] + R[0, 2] * bn[2]
            wy = R[1, 0] * bn[0] + R[1, 1] * bn[1] + R[1, 2] * bn[2]
            wz = R[2, 0] * bn[0] + R[2, 1] * bn[1] + R[2, 2] * bn[2]
            _set_normal(nrm, i, wx, wy, wz, d[i])
            alb[i] = base_albedo if bp == 0 else albedo
            part[i] = bp
    return t_out, nrm, alb, spec, part


@numba.njit(cache=True, nogil=True)
def _sphere_t(ox, oy, oz, d, cx, cy, cz, r):
    """Nearest intersection parameter with a sphere (closest-approach form); inf if none."""
    px = ox - cx
    py = oy - cy
    pz = oz - cz
    tc = -(px * d[0] + py * d[1] + pz * d[2])
    qx = px + tc * d[0]
    qy = py + tc * d[1]
    qz = pz + tc * d[2]
    disc = r * r - (qx * qx + qy * qy + qz * qz)
    if disc < 0.0:
        return np.inf
    return tc - math.sqrt(disc)


@numba.njit(cache=True, nogil=True)
def sphere_intersect(o, d, c, r, plane_z, half, albedo, plane_albedo):
    """A sphere (hidden below Z = plane_z) on a square plane of half size ``half``."""
    n = o.shape[0]
    t_out, nrm, alb, spec, part = _new_hits(n)
    for i in numba.prange(n):
        if not (o[i, 0] == o[i, 0]):
            continue
        best = np.inf
        di = d[i]
        if di[2] != 0.0:
            t = (plane_z - o[i, 2]) / di[2]
            x = o[i, 0] + t * di[0]
            y = o[i, 1] + t * di[1]
            if t > 0.0 and abs(x - c[0]) <= half and abs(y - c[1]) <= half:
                best = t
                t_out[i] = t
                _set_normal(nrm, i, 0.0, 0.0, 1.0, di)
                alb[i] = plane_albedo
                part[i] = 0
        ts = _sphere_t(o[i, 0], o[i, 1], o[i, 2], di, c[0], c[1], c[2], r)
        if ts > 0.0 and ts < best:
            pz = o[i, 2] + ts * di[2]
            if pz >= plane_z:
                t_out[i] = ts
                _set_normal(nrm, i, (o[i, 0] + ts * di[0] - c[0]) / r,
                            (o[i, 1] + ts * di[1] - c[1]) / r, (pz - c[2]) / r, di)
                alb[i] = albedo
                part[i] = 1
    return t_out, nrm, alb, spec, part


@numba.njit(cache=True, nogil=True)
def bga_intersect(o, dirs, origin, pitch, centre_z, present, r, chip, reach, hmid,
                  substrate_albedo, board_albedo, ball_albedo, ball_specular):
    """BGA: substrate Z = 0 (chip rectangle ``chip`` = (x0, x1, y0, y1), board beyond)
    and spherical caps (centre heights ``centre_z`` (rows, cols), radius r, hidden
    below Z = 0) at ``origin + (j, i) * pitch`` where ``present``. A ray can only meet
    balls whose centre lies within ``reach`` mm (x-y) of its point at height ``hmid``."""
    n = o.shape[0]
    rows, cols = centre_z.shape
    t_out, nrm, alb, spec, part = _new_hits(n)
    for i in numba.prange(n):
        if not (o[i, 0] == o[i, 0] and o[i, 1] == o[i, 1] and o[i, 2] == o[i, 2]):
            continue
        best = np.inf
        d = dirs[i]
        if d[2] != 0.0:
            t = -o[i, 2] / d[2]
            if t > 0.0:
                x = o[i, 0] + t * d[0]
                y = o[i, 1] + t * d[1]
                best = t
                t_out[i] = t
                _set_normal(nrm, i, 0.0, 0.0, 1.0, d)
                if x >= chip[0] and x <= chip[1] and y >= chip[2] and y <= chip[3]:
                    alb[i] = substrate_albedo
                    part[i] = 0
                else:
                    alb[i] = board_albedo
                    part[i] = 1
            tm = (hmid - o[i, 2]) / d[2]
        else:
            tm = 0.0
        xm = o[i, 0] + tm * d[0]
        ym = o[i, 1] + tm * d[1]
        # only balls whose centre is within ``reach`` (mm) of the mid-height point
        j0 = max(0, int(math.ceil((xm - origin[0] - reach) / pitch)))
        j1 = min(cols - 1, int(math.floor((xm - origin[0] + reach) / pitch)))
        i0 = max(0, int(math.ceil((ym - origin[1] - reach) / pitch)))
        i1 = min(rows - 1, int(math.floor((ym - origin[1] + reach) / pitch)))
        for ii in range(i0, i1 + 1):
            for jj in range(j0, j1 + 1):
                if not present[ii, jj]:
                    continue
                cx = origin[0] + jj * pitch
                cy = origin[1] + ii * pitch
                cz = centre_z[ii, jj]
                ts = _sphere_t(o[i, 0], o[i, 1], o[i, 2], d, cx, cy, cz, r)
                if ts > 0.0 and ts < best:
                    pz = o[i, 2] + ts * d[2]
                    if pz >= 0.0:
                        best = ts
                        t_out[i] = ts
                        _set_normal(nrm, i, (o[i, 0] + ts * d[0] - cx) / r,
                                    (o[i, 1] + ts * d[1] - cy) / r, (pz - cz) / r, d)
                        alb[i] = ball_albedo
                        spec[i] = ball_specular
                        part[i] = 2
    return t_out, nrm, alb, spec, part


@numba.njit(cache=True, nogil=True)
def plane_intersect(o, d, normal, point, albedo):
    """An infinite plane through ``point`` with unit ``normal``."""
    n = o.shape[0]
    t_out, nrm, alb, spec, part = _new_hits(n)
    for i in numba.prange(n):
        if not (o[i, 0] == o[i, 0]):
            continue
        den = normal[0] * d[i, 0] + normal[1] * d[i, 1] + normal[2] * d[i, 2]
        if den == 0.0:
            continue
        t = ((point[0] - o[i, 0]) * normal[0] + (point[1] - o[i, 1]) * normal[1]
             + (point[2] - o[i, 2]) * normal[2]) / den
        if t > 0.0:
            t_out[i] = t
            _set_normal(nrm, i, normal[0], normal[1], normal[2], d[i])
            alb[i] = albedo
            part[i] = 0
    return t_out, nrm, alb, spec, part


@numba.njit(cache=True, nogil=True)
def sensor_counts(signal_e, normal, read_e, dn_per_e, full_scale, out):
    """Shot + read noise (Gaussian approximation), quantisation and saturation.

    signal_e (rows, cols) mean electrons; normal (rows, cols) standard normal deviates;
    out (rows, cols) integer counts in [0, full_scale] (written).
    """
    rows, cols = signal_e.shape
    r2 = read_e * read_e
    for r in numba.prange(rows):
        for c in range(cols):
            e = signal_e[r, c]
            sd = math.sqrt(max(e, 0.0) + r2)
            dn = np.round((e + sd * normal[r, c]) * dn_per_e)
            out[r, c] = min(max(dn, 0.0), full_scale)


@numba.njit(cache=True, parallel=True)
def accumulate_many(coord, weight, per_pixel, profiles, x_first, inv_step, out):
    """Sum the samples of each pixel for K profiles at once:
    ``out[k, p] = sum_s weight * profiles[k](coord)`` (each sample's table position is
    computed once).

    Parameters
    ----------
    coord : (P * n,) float64, projector coordinate of each sample (pixel-major).
    weight : (P * n,) float32 or float64, weight of each sample (includes 1/n).
    per_pixel : int, n, the number of samples of each pixel.
    profiles : (K, n_table) float64, the emitted intensities sampled at
        ``x_first + i / inv_step``; linear interpolation between samples, 0 beyond both
        ends.
    out : (K, P) float64, written.
    """
    npix = out.shape[1]
    nk = profiles.shape[0]
    last = profiles.shape[1] - 1
    for p in numba.prange(npix):
        acc = np.zeros(nk)
        base = p * per_pixel
        for s in range(per_pixel):
            w = weight[base + s]
            if w == 0.0:
                continue
            x = (coord[base + s] - x_first) * inv_step
            if x < 0.0 or x >= last:
                continue
            i = int(x)
            f = x - i
            wa = w * (1.0 - f)
            wb = w * f
            for k in range(nk):
                acc[k] += wa * profiles[k, i] + wb * profiles[k, i + 1]
        for k in range(nk):
            out[k, p] = acc[k]


@numba.njit(cache=True, nogil=True)
def hit_points(o, d, t):
    """Hit points P (N, 3) of rays ``o`` (N, 3) + t (N,) ``d`` (N, 3); NaN where no hit."""
    n = o.shape[0]
    P = np.full((n, 3), np.nan)
    for i in numba.prange(n):
        if not np.isfinite(t[i]):
            continue
        for k in range(3):
            P[i, k] = o[i, k] + t[i] * d[i, k]
    return P


@numba.njit(cache=True, nogil=True)
def shadow_origins(P, nrm, to_proj, start):
    """Origins of the shadow rays toward the projector, ``P + start * to_proj`` (N, 3)
    (``to_proj`` (N, 3) unit, ``start`` (N,) mm); NaN where no hit or facing away."""
    n = P.shape[0]
    so = np.full((n, 3), np.nan)
    for i in numba.prange(n):
        if not (P[i, 0] == P[i, 0]):
            continue
        if (nrm[i, 0] * to_proj[i, 0] + nrm[i, 1] * to_proj[i, 1]
                + nrm[i, 2] * to_proj[i, 2]) > 0.0:
            for k in range(3):
                so[i, k] = P[i, k] + start[i] * to_proj[i, k]
    return so
