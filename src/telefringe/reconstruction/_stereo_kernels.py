"""Compiled matcher of :mod:`telefringe.reconstruction.stereo`, parallel over the first
camera's rows; the NumPy path in ``stereo`` is the reference it is tested against (same
samples, brackets, edge bisection, Illinois iteration, Gauss-Newton with both axes,
uncertainty and flags; the least-squares intersection with the second camera's ray and
its gap check stay in ``stereo``, on the matched pixels only).

The second camera (pinhole or telecentric) is projected in the form of
:mod:`telefringe.reconstruction._generic_kernels`: frame coordinates ``Y = R X + t``,
normalised ``(Y_x / Y_z, Y_y / Y_z)`` (``Y_z = 1`` for a telecentric device), OpenCV's
distortion plus the thin prism, then ``f x + c``; a pinhole device gives NaN at or behind
its centre, as its ``project`` does.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from telefringe.reconstruction._generic_kernels import _ARGS, _distort, _distortion_jacobian
from telefringe.reconstruction.cloud import (
    FLAG_INCONSISTENT,
    FLAG_NO_PHASE,
    FLAG_NOT_CONVERGED,
    FLAG_OUTSIDE,
    FLAG_UNCERTAIN,
)

__all__ = ["has_kernel", "match_all"]

#: ``matched`` value of a pixel solved to a single root (its xyz still to be intersected)
MATCHED = 1


def has_kernel(camera) -> bool:
    """Whether the second camera's model has a compiled projection."""
    return getattr(camera, "model", None) in _ARGS and hasattr(camera, "intrinsics")


@njit(inline="always")
def _project(s, Y, intr):  # pragma: no cover - numba
    """Pixel (u, v) of the line point at s; NaN at or behind a pinhole camera."""
    Y00, Y01, Y02, Yd0, Yd1, Yd2 = Y
    fx, fy, cx, cy, k1, k2, p1, p2, k3, s1, s2 = intr
    z = Y02 + s * Yd2
    if not z > 0.0:
        return np.nan, np.nan
    iz = 1.0 / z
    xd, yd = _distort((Y00 + s * Yd0) * iz, (Y01 + s * Yd1) * iz, k1, k2, p1, p2, k3, s1, s2)
    return fx * xd + cx, fy * yd + cy


@njit(inline="always")
def _along(s, Y, intr):  # pragma: no cover - numba
    """d(u, v)/ds of the projection of the line at s (the projection's Jacobian times the
    line's direction)."""
    Y00, Y01, Y02, Yd0, Yd1, Yd2 = Y
    fx, fy, cx, cy, k1, k2, p1, p2, k3, s1, s2 = intr
    iz = 1.0 / (Y02 + s * Yd2)
    x = (Y00 + s * Yd0) * iz
    y = (Y01 + s * Yd1) * iz
    a, b, c, d = _distortion_jacobian(x, y, k1, k2, p1, p2, k3, s1, s2)
    dx = (Yd0 - x * Yd2) * iz
    dy = (Yd1 - y * Yd2) * iz
    return fx * (a * dx + b * dy), fy * (c * dx + d * dy)


@njit(inline="always")
def _cell(u, v, rows, cols):  # pragma: no cover - numba
    """The reference's bilinear cell: inside, corner indices (clamped as it does) and
    fractions."""
    inside = (u >= 0.0) & (u <= cols - 1.0) & (v >= 0.0) & (v <= rows - 1.0)
    uu = u if inside else 0.0
    vv = v if inside else 0.0
    j = min(int(np.floor(uu)), cols - 2)
    i = min(int(np.floor(vv)), rows - 2)
    return inside, i, j, uu - j, vv - i


@njit(inline="always")
def _value(M, u, v):  # pragma: no cover - numba
    """Bilinear value of M at (u, v); NaN outside or where a corner is NaN."""
    rows, cols = M.shape
    inside, i, j, fx, fy = _cell(u, v, rows, cols)
    if not inside:
        return np.nan
    return ((1.0 - fy) * ((1.0 - fx) * M[i, j] + fx * M[i, j + 1])
            + fy * ((1.0 - fx) * M[i + 1, j] + fx * M[i + 1, j + 1]))


@njit(inline="always")
def _value_grad(M, i, j, fx, fy):  # pragma: no cover - numba
    m00 = M[i, j]
    m01 = M[i, j + 1]
    m10 = M[i + 1, j]
    m11 = M[i + 1, j + 1]
    val = (1.0 - fy) * ((1.0 - fx) * m00 + fx * m01) + fy * ((1.0 - fx) * m10 + fx * m11)
    gu = (1.0 - fy) * (m01 - m00) + fy * (m11 - m10)
    gv = (1.0 - fx) * (m10 - m00) + fx * (m11 - m01)
    return val, gu, gv


@njit(inline="always")
def _interp_var(S, i, j, fx, fy):  # pragma: no cover - numba
    w0 = (1.0 - fx) * (1.0 - fy)
    w1 = fx * (1.0 - fy)
    w2 = (1.0 - fx) * fy
    w3 = fx * fy
    return ((w0 * S[i, j]) ** 2 + (w1 * S[i, j + 1]) ** 2 + (w2 * S[i + 1, j]) ** 2
            + (w3 * S[i + 1, j + 1]) ** 2)


@njit(inline="always")
def _f(s, Y, intr, A2, target):  # pragma: no cover - numba
    u, v = _project(s, Y, intr)
    return _value(A2, u, v) - target


@njit(inline="always")
def _border_root(lo, hi, Y, intr, coord, bound, g_hi):  # pragma: no cover - numba
    """The line parameter, inside the image and within 1e-10 px of the border, where
    the line crosses the image border ``coord`` (0: u, 1: v) = ``bound`` between lo
    (inside) and hi (g_hi: its signed distance, outside); Illinois on the projection."""
    a, b = lo, hi
    u, v = _project(a, Y, intr)
    ga = (u if coord == 0 else v) - bound
    gb = g_hi
    pos_in = ga > 0.0  # the inside's sign of the distance
    inside = a
    g_in = ga
    for _ in range(80):
        c = (a * gb - b * ga) / (gb - ga)
        if not (min(a, b) < c < max(a, b)):
            c = 0.5 * (a + b)
        u, v = _project(c, Y, intr)
        gc = (u if coord == 0 else v) - bound
        if not np.isfinite(gc):
            return np.nan
        if (gc > 0.0) == pos_in or gc == 0.0:
            inside = c
            g_in = gc
        if abs(g_in) <= 1e-10 or abs(b - a) <= 1e-15 * (1.0 + abs(c)):
            return inside
        if gc * gb > 0.0:
            ga = 0.5 * ga
        else:
            a = b
            ga = gb
        b = c
        gb = gc
    return np.nan


@njit(inline="always")
def _border(lo, hi, Y, intr, rows, cols):  # pragma: no cover - numba
    """Where the line, inside the image at lo, leaves it before hi (projected outside,
    in front of the camera): the first crossing of a border, its inside end (line
    parameter); NaN where hi is not outside the image in front of the camera."""
    u, v = _project(hi, Y, intr)
    if not (np.isfinite(u) and np.isfinite(v)):
        return np.nan
    best = np.nan
    for coord in range(2):
        x = u if coord == 0 else v
        top = (cols if coord == 0 else rows) - 1.0
        bound = np.nan
        if x < 0.0:
            bound = 0.0
        elif x > top:
            bound = top
        if np.isfinite(bound):
            e = _border_root(lo, hi, Y, intr, coord, bound, x - bound)
            if not np.isfinite(e):
                return np.nan
            if not np.isfinite(best) or abs(e - lo) < abs(best - lo):
                best = e
    return best


@njit(inline="always")
def _neg(f):  # pragma: no cover - numba
    return f <= 0.0


@njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def match_all(rows, cols, O, D, bad, P0, offsets, A1, S1, B1, T1, A2, S2, B2, T2,
              has_s1, has_s2, has_t1, has_t2, has_b, combine, intr, R, t, jump, max_res,
              max_sz, tol_f, max_iter, s_out, u2_out, v2_out, sig_out, res_out, flags_out,
              matched):  # pragma: no cover - numba
    """Match every pixel of the first camera (``rows * cols``, row-major), parallel over
    rows (see :func:`_match_rows` for the arguments). The row is passed as int64: the
    parallel loop's own index is unsigned, and ``_match_rows`` would be compiled a
    second time for it (about 15 s of CPU)."""
    for r in prange(rows):
        r0 = np.int64(r)
        _match_rows(r0, r0 + 1, cols, O, D, bad, P0, offsets, A1, S1, B1, T1, A2, S2, B2, T2,
                    has_s1, has_s2, has_t1, has_t2, has_b, combine, intr, R, t, jump,
                    max_res, max_sz, tol_f, max_iter, s_out, u2_out, v2_out, sig_out,
                    res_out, flags_out, matched)


@njit(cache=True, nogil=True, error_model="numpy")
def _match_rows(r0, r1, cols, O, D, bad, P0, offsets, A1, S1, B1, T1, A2, S2, B2, T2,
                has_s1, has_s2, has_t1, has_t2, has_b, combine, intr, R, t, jump, max_res,
                max_sz, tol_f, max_iter, s_out, u2_out, v2_out, sig_out, res_out, flags_out,
                matched):  # pragma: no cover - numba
    """Match the pixels of rows r0 .. r1 - 1 of the first camera (``cols`` per row).

    O, D : (1 or n, 3) the first camera's lines (origin, unit direction), mm; bad (n,)
    where its back-projection failed. P0 (3,) the working point; offsets (K,) the samples
    along each line around the point nearest P0, mm. A1, B1 (n,) the first camera's
    primary and other projector coordinate, S1, T1 their std (n,); A2, B2 the second
    camera's maps (rows2, cols2), S2, T2 theirs. intr, R, t the second camera in the form
    of ``_generic_kernels._ARGS``. Outputs (n,): line parameter s, matched sub-pixel u2,
    v2 (NaN where the match did not reach the final stage), sigma along the line, the
    residual (projector px), flags and ``matched`` (1 where xyz is to be intersected).
    """
    R9 = (R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1], R[2, 2])
    t0, t1, t2 = t[0], t[1], t[2]
    one_o = O.shape[0] == 1
    one_d = D.shape[0] == 1
    K = offsets.shape[0]
    rows2, cols2 = A2.shape
    for r in range(r0, r1):
        for c in range(cols):
            k = r * cols + c
            ko = 0 if one_o else k
            kd = 0 if one_d else k
            matched[k] = 0
            u2_out[k] = np.nan
            v2_out[k] = np.nan
            sig_out[k] = np.nan
            res_out[k] = np.nan
            a_obs = A1[k]
            ok = np.isfinite(a_obs) and not bad[k]
            b_obs = B1[k] if has_b else np.nan
            if combine:
                ok = ok and np.isfinite(b_obs)
            if not ok:
                flags_out[k] = FLAG_NOT_CONVERGED if (bad[k] and np.isfinite(a_obs)) \
                    else FLAG_NO_PHASE
                continue
            o0, o1, o2 = O[ko, 0], O[ko, 1], O[ko, 2]
            d0, d1, d2 = D[kd, 0], D[kd, 1], D[kd, 2]
            Y = (R9[0] * o0 + R9[1] * o1 + R9[2] * o2 + t0,
                 R9[3] * o0 + R9[4] * o1 + R9[5] * o2 + t1,
                 R9[6] * o0 + R9[7] * o1 + R9[8] * o2 + t2,
                 R9[0] * d0 + R9[1] * d1 + R9[2] * d2,
                 R9[3] * d0 + R9[4] * d1 + R9[5] * d2,
                 R9[6] * d0 + R9[7] * d1 + R9[8] * d2)
            sr = (P0[0] - o0) * d0 + (P0[1] - o1) * d1 + (P0[2] - o2) * d2
            # the samples: count the crossings (both ends finite, signs differ) and the
            # crossings at an edge of the valid phase (found by bisection, as the
            # reference does); keep the first bracket (the only one that is used)
            n_cross = 0
            ba = 0.0
            bb = 0.0
            bfa = 0.0
            bfb = 0.0
            s_prev = sr + offsets[0]
            f_prev = _f(s_prev, Y, intr, A2, a_obs)
            for q in range(1, K):
                s_q = sr + offsets[q]
                f_q = _f(s_q, Y, intr, A2, a_obs)
                fin_p = np.isfinite(f_prev)
                fin_q = np.isfinite(f_q)
                if fin_p and fin_q:
                    if _neg(f_prev) != _neg(f_q):
                        if n_cross == 0:
                            ba, bb, bfa, bfb = s_prev, s_q, f_prev, f_q
                        n_cross += 1
                elif fin_p != fin_q:
                    lo_s = s_prev if fin_p else s_q
                    hi_s = s_q if fin_p else s_prev
                    f_lo = f_prev if fin_p else f_q
                    # where the line leaves the image, solve for the border (a few
                    # projections); else (a hole, behind the camera) bisect as the
                    # reference does
                    e_s = _border(lo_s, hi_s, Y, intr, rows2, cols2)
                    f_edge = np.nan
                    if np.isfinite(e_s):
                        f_edge = _f(e_s, Y, intr, A2, a_obs)
                    if np.isfinite(f_edge):
                        lo_s = e_s
                    else:
                        for _ in range(40):
                            mid = 0.5 * (lo_s + hi_s)
                            if np.isfinite(_f(mid, Y, intr, A2, a_obs)):
                                lo_s = mid
                            else:
                                hi_s = mid
                        f_edge = _f(lo_s, Y, intr, A2, a_obs)
                    if np.isfinite(f_edge) and _neg(f_edge) != _neg(f_lo):
                        if n_cross == 0:
                            ba = s_prev if fin_p else s_q
                            bb, bfa, bfb = lo_s, f_lo, f_edge
                        n_cross += 1
                s_prev = s_q
                f_prev = f_q
            if n_cross == 0:
                flags_out[k] = FLAG_OUTSIDE
                continue
            if n_cross > 1:
                flags_out[k] = FLAG_INCONSISTENT
                continue
            # Illinois false position on the bracket
            a, b, fa, fb = ba, bb, bfa, bfb
            s = b
            done = False
            failed = False
            for _ in range(max_iter):
                cc = (a * fb - b * fa) / (fb - fa)
                fc = _f(cc, Y, intr, A2, a_obs)
                if not np.isfinite(fc):
                    failed = True
                    break
                if fc * fb > 0.0:
                    fa = 0.5 * fa
                else:
                    a = b
                    fa = fb
                b = cc
                fb = fc
                s = cc
                if abs(fc) <= tol_f or abs(b - a) <= 1e-13 * (1.0 + abs(cc)):
                    done = True
                    break
            if failed:
                flags_out[k] = FLAG_NO_PHASE
                continue
            if not done:
                flags_out[k] = FLAG_NOT_CONVERGED
                continue
            if combine:
                # ML along the line with both axes (Gauss-Newton), weights from the
                # primary root's cell
                u, v = _project(s, Y, intr)
                _, i, j, fx, fy = _cell(u, v, rows2, cols2)
                va1 = S1[k] ** 2 if has_s1 else np.nan
                vb1 = T1[k] ** 2 if has_t1 else np.nan
                wa = 1.0 / (va1 + (_interp_var(S2, i, j, fx, fy) if has_s2 else np.nan))
                wb = 1.0 / (vb1 + (_interp_var(T2, i, j, fx, fy) if has_t2 else np.nan))
                if not np.isfinite(wa):
                    wa = 1.0
                if not np.isfinite(wb):
                    wb = 1.0
                for _ in range(10):
                    u, v = _project(s, Y, intr)
                    inside, i, j, fx, fy = _cell(u, v, rows2, cols2)
                    pu, pv = _along(s, Y, intr)
                    va, gau, gav = _value_grad(A2, i, j, fx, fy)
                    vb, gbu, gbv = _value_grad(B2, i, j, fx, fy)
                    ga = gau * pu + gav * pv
                    gb = gbu * pu + gbv * pv
                    step = ((wa * ga * (va - a_obs) + wb * gb * (vb - b_obs))
                            / (wa * ga * ga + wb * gb * gb))
                    if not (inside and np.isfinite(step)):
                        step = 0.0
                    s = s - step
                    if abs(step) <= 1e-12 * (1.0 + abs(s)):
                        break
            # the final point: uncertainty, residual, flags
            u, v = _project(s, Y, intr)
            inside, i, j, fx, fy = _cell(u, v, rows2, cols2)
            pu, pv = _along(s, Y, intr)
            va, gau, gav = _value_grad(A2, i, j, fx, fy)
            if not inside:
                va = np.nan
            ga = gau * pu + gav * pv
            var_a = ((S1[k] ** 2 if has_s1 else np.nan)
                     + (_interp_var(S2, i, j, fx, fy) if has_s2 else np.nan))
            if combine:
                vb, gbu, gbv = _value_grad(B2, i, j, fx, fy)
                gb = gbu * pu + gbv * pv
                var_b = ((T1[k] ** 2 if has_t1 else np.nan)
                         + (_interp_var(T2, i, j, fx, fy) if has_t2 else np.nan))
                sg = 1.0 / np.sqrt(ga * ga / var_a + gb * gb / var_b)
            else:
                sg = np.sqrt(var_a) / abs(ga)
            f = 0
            if has_b:
                vb = _value_grad(B2, i, j, fx, fy)[0] if inside else np.nan
                res = np.hypot(va - a_obs, vb - b_obs)
                if res > max_res:
                    f |= FLAG_INCONSISTENT
                res_out[k] = res
            if not np.isfinite(va):
                f |= FLAG_NO_PHASE
            # a cell across a jump of the phase (an occlusion edge) or with a NaN corner
            m00 = A2[i, j]
            m01 = A2[i, j + 1]
            m10 = A2[i + 1, j]
            m11 = A2[i + 1, j + 1]
            if (np.isfinite(m00) and np.isfinite(m01) and np.isfinite(m10)
                    and np.isfinite(m11)):
                cell_range = (max(max(m00, m01), max(m10, m11))
                              - min(min(m00, m01), min(m10, m11)))
                if not cell_range <= jump:
                    f |= FLAG_INCONSISTENT
            else:
                f |= FLAG_INCONSISTENT
            if sg * abs(d2) > max_sz:
                f |= FLAG_UNCERTAIN
            flags_out[k] = f
            s_out[k] = s
            u2_out[k] = u
            v2_out[k] = v
            sig_out[k] = sg
            matched[k] = MATCHED
