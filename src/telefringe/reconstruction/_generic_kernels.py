"""Compiled solvers of :mod:`telefringe.reconstruction.generic` for one projector model
each, chosen by the projector's ``model`` (:func:`solver_for`); the NumPy path in
``generic`` is the reference they are tested against (same equations, same tolerance,
same flags).

Pinhole projector: the camera line ``X(s) = o + s d`` in the projector's frame is ``Y(s) =
Y0 + s Yd``; its normalised image ``(Y0 + s Yd)_{x,y} / (Y0 + s Yd)_z`` is distorted with
OpenCV's model. Start: the root without distortion (the line meets the plane of the
projector column ``(u_P - cx) / fx``: exact for an undistorted projector); then Newton on
s (Gauss-Newton with both axes, as the reference), halving steps that go behind the
projector, to ``|step| <= 1e-12 (1 + |s|)`` mm within 50 steps. The fold check is the
sign test of the distortion's Jacobian at the solution (where the reference's round trip
through the projector's back-projection fails).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from telefringe import _recycle
from telefringe.devices import _pinhole_kernels as _pk
from telefringe.devices import _telecentric_kernels as _tk
from telefringe.reconstruction.cloud import (
    FLAG_INCONSISTENT,
    FLAG_NO_PHASE,
    FLAG_NOT_CONVERGED,
    FLAG_OUTSIDE,
    FLAG_UNCERTAIN,
)

__all__ = ["solver_for", "camera_lines"]

_TOL_S = 1e-12
_MAX_ITER = 50


def solver_for(projector):
    """The compiled solve for this projector's model, or None (then the NumPy path)."""
    if getattr(projector, "model", None) in _ARGS and hasattr(projector, "intrinsics"):
        return _run
    return None


def camera_lines(camera, u, v):
    """The camera's lines through pixels u, v (n,) by its compiled model, as
    ``safe_backproject`` gives them (origin, direction: (3,) or (n, 3); bad (n,)), or
    None where the model has no compiled back-projection (then use the protocol)."""
    if getattr(camera, "model", None) == "pinhole" and hasattr(camera, "intrinsics"):
        intr, R, t = _pk.kernel_args(camera)
        D = np.empty((3, u.size))
        _pk.backproject_many(u, v, intr, R, D)
        bad = ~np.isfinite(D[0]) & np.isfinite(u) & np.isfinite(v)
        return -R.T @ t, D.T, bad
    if getattr(camera, "model", None) == "telecentric" and hasattr(camera, "intrinsics"):
        intr, R, t = _tk.kernel_args(camera)
        a = np.empty(u.size)
        b = np.empty(u.size)
        if _tk.backproject_lines(u, v, intr, t, a, b):
            return None  # pixels beyond the fold: the protocol's path finds them
        return (a[:, None] * R[0] + b[:, None] * R[1], R[2].copy(),
                np.zeros(u.size, dtype=bool))
    return None


def _pinhole_args(proj):
    (fx, fy, cx, cy, k1, k2, p1, p2, k3), R, t = _pk.kernel_args(proj)
    return (fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0), R, t


def _telecentric_args(proj):
    # a telecentric projector in the same form: its undistorted sensor mm are the "frame"
    # coordinates (m R[0:2] X + m t, with a constant third coordinate 1), its pixel pitch
    # the inverse focal length, its distortion the radial k1 and the thin prism s1, s2
    (m, du, dv, u0, v0, k1, s1, s2), R, t = _tk.kernel_args(proj)
    Rp = np.zeros((3, 3))
    Rp[:2] = m * R[:2]
    tp = np.array([m * t[0], m * t[1], 1.0])
    return (1.0 / du, 1.0 / dv, u0, v0, k1, 0.0, 0.0, 0.0, 0.0, s1, s2), Rp, tp


_ARGS = {"pinhole": _pinhole_args, "telecentric": _telecentric_args}


@njit(inline="always")
def _distort(x, y, k1, k2, p1, p2, k3, s1, s2):  # pragma: no cover - numba
    # OpenCV's model plus the thin prism (s1, s2 r^2): the pinhole model with s = 0, the
    # telecentric sensor model with k2 = p = k3 = 0 (adding zeros changes no bit)
    xd, yd = _pk.distort_point(x, y, k1, k2, p1, p2, k3)
    r2 = x * x + y * y
    return xd + s1 * r2, yd + s2 * r2


@njit(inline="always")
def _distortion_jacobian(x, y, k1, k2, p1, p2, k3, s1, s2):  # pragma: no cover - numba
    a, b, c, d = _pk.distortion_jacobian(x, y, k1, k2, p1, p2, k3)
    return a + 2.0 * s1 * x, b + 2.0 * s1 * y, c + 2.0 * s2 * x, d + 2.0 * s2 * y


def _run(proj, O, D, a_obs, b_obs, sa, sb, mask, combine, swap, W, H, max_res,
         max_sz, xyz, sig, res, flags, ok):
    """Solve every pixel: the lines' points and directions as planes O, D (3, n), the
    observations (n,), into xyz (3, n) and the flat outputs."""
    intr, R, t = _ARGS[proj.model](proj)
    has_b = b_obs is not None
    n = a_obs.shape[0]
    if b_obs is None:
        b_obs = a_obs
        sb = sa
    if res is None:  # scratch: the solver writes a residual for every pixel
        res = _recycle.empty(n)
    _solve_pinhole(O, D, a_obs, b_obs, sa, sb, mask, has_b, combine, swap, intr, R, t,
                   float(W), float(H), float(max_res), float(max_sz), xyz, sig, res, flags, ok)


@njit(inline="always")
def _eval(s, Y00, Y01, Y02, Yd0, Yd1, Yd2, intr):  # pragma: no cover - numba
    """Projector pixel (u, v), its derivatives along the line (du/ds, dv/ds), the
    distortion's Jacobian and the depth in the projector at line parameter s."""
    fx, fy, cx, cy, k1, k2, p1, p2, k3, s1, s2 = intr
    Y0 = Y00 + s * Yd0
    Y1 = Y01 + s * Yd1
    Y2 = Y02 + s * Yd2
    iz = 1.0 / Y2
    x = Y0 * iz
    y = Y1 * iz
    xd, yd = _distort(x, y, k1, k2, p1, p2, k3, s1, s2)
    a, b, c, d = _distortion_jacobian(x, y, k1, k2, p1, p2, k3, s1, s2)
    dx = (Yd0 - x * Yd2) * iz
    dy = (Yd1 - y * Yd2) * iz
    gu = fx * (a * dx + b * dy)
    gv = fy * (c * dx + d * dy)
    # for the error estimate of the fast pass, |u''| / |u'| along the line is bounded by
    # the perspective's |2 Yd_z / Y_z| plus the distortion's |dX^T Hess dX| / |slope|:
    # kdd bounds the numerator (twice the bound of the second derivatives for |x|, |y|
    # <= r, times (|dx| + |dy|)^2), divided by the slope in _step
    r = np.sqrt(x * x + y * y)
    kd = 2.0 * (6.0 * abs(k1) * r + 20.0 * abs(k2) * r * r * r + 42.0 * abs(k3) * r ** 5
                + 6.0 * (abs(p1) + abs(p2)) + 2.0 * (abs(s1) + abs(s2)))
    dd = abs(dx) + abs(dy)
    persp = abs(2.0 * Yd2 * iz)
    return fx * xd + cx, fy * yd + cy, gu, gv, a, b, c, d, Y2, persp, kd * dd * dd


# The fast pass: from the undistorted start, _N_FAST Newton (Gauss-Newton) steps with no
# data-dependent branch, then the error left is estimated from the quadratic convergence:
# next step ~ |u''/(2 u')| step^2, with u''/u' ~ -2 Yd_z / Y_z the line's perspective
# (taken twice for the distortion's share, which is smaller by the field angle times the
# distortion). Pixels above the tolerance, behind the projector or with a non-finite step
# are solved again by the slow pass, which iterates as the NumPy reference does.
_N_FAST = 2
_CHUNK = 4096


@njit(inline="always")
def _line_in_projector(o0, o1, o2, d0, d1, d2, R9, t0, t1, t2):  # pragma: no cover - numba
    return (R9[0] * o0 + R9[1] * o1 + R9[2] * o2 + t0, R9[3] * o0 + R9[4] * o1 + R9[5] * o2 + t1,
            R9[6] * o0 + R9[7] * o1 + R9[8] * o2 + t2, R9[0] * d0 + R9[1] * d1 + R9[2] * d2,
            R9[3] * d0 + R9[4] * d1 + R9[5] * d2, R9[6] * d0 + R9[7] * d1 + R9[8] * d2)


@njit(inline="always")
def _step(s, ua, ub, wa, wb, Y, intr, combine, swap):  # pragma: no cover - numba
    Y00, Y01, Y02, Yd0, Yd1, Yd2 = Y
    u, v, gu, gv, a, b, c, d, z, persp, kdd = _eval(s, Y00, Y01, Y02, Yd0, Yd1, Yd2, intr)
    pa = v if swap else u
    pb = u if swap else v
    ga = gv if swap else gu
    gb = gu if swap else gv
    if combine:
        step = (wa * ga * (pa - ua) + wb * gb * (pb - ub)) / (wa * ga * ga + wb * gb * gb)
    else:
        step = (pa - ua) / ga
    fa = intr[1] if swap else intr[0]
    curv = persp + kdd * fa / abs(ga)
    return step, u, v, pa, pb, ga, gb, a, b, c, d, z, curv


@njit(inline="always")
def _gu_of(ga, gb, swap):  # pragma: no cover - numba
    return gb if swap else ga


@njit(inline="always")
def _gv_of(ga, gb, swap):  # pragma: no cover - numba
    return ga if swap else gb


@njit(inline="always")
def _plane_root(xt, Y, swap):  # pragma: no cover - numba
    # where the line meets the plane of undistorted normalised projector coordinate xt
    Y00, Y01, Y02, Yd0, Yd1, Yd2 = Y
    if swap:
        return (Y01 - xt * Y02) / (xt * Yd2 - Yd1)
    return (Y00 - xt * Y02) / (xt * Yd2 - Yd0)


@njit(inline="always")
def _start(ua, Y, intr, fa, ca, swap):  # pragma: no cover - numba
    # the root without distortion, then once more with the distortion's offset there
    # taken off the target (a fixed-point step: its error shrinks by the distortion's
    # gradient, ~1e-2)
    xt = (ua - ca) / fa
    s0 = _plane_root(xt, Y, swap)
    Y00, Y01, Y02, Yd0, Yd1, Yd2 = Y
    iz = 1.0 / (Y02 + s0 * Yd2)
    x = (Y00 + s0 * Yd0) * iz
    y = (Y01 + s0 * Yd1) * iz
    xd, yd = _distort(x, y, intr[4], intr[5], intr[6], intr[7], intr[8], intr[9], intr[10])
    off = yd - y if swap else xd - x
    s1 = _plane_root(xt - off, Y, swap)
    return s1 if abs(s1) < np.inf else s0


@njit(error_model="numpy")
def _finish(i, s, conv, o0, o1, o2, d0, d1, d2, ua, ub, s_a, s_b, u, v, pa, pb, ga, gb, a, b,
            c, d, z, has_b, combine, W, H, max_res, max_sz, xyz, sig, res, flags,
            ok):  # pragma: no cover - numba
    if combine:
        sg = 1.0 / np.sqrt(ga * ga / (s_a * s_a) + gb * gb / (s_b * s_b))
    else:
        sg = s_a / abs(ga)
    r = np.sqrt((pa - ua) ** 2 + (pb - ub) ** 2) if has_b else np.nan
    res[i] = r
    inside = (u >= -0.5) & (u <= W - 0.5) & (v >= -0.5) & (v <= H - 0.5)
    conv = conv & (z > 0.0) & _pk.is_unfolded(a, b, c, d)
    f = (FLAG_INCONSISTENT * (r > max_res) + FLAG_OUTSIDE * (1 - inside)
         + FLAG_NOT_CONVERGED * (1 - conv) + FLAG_UNCERTAIN * (sg * abs(d2) > max_sz))
    flags[i] = f
    good = f == 0
    ok[i] = good
    sig[i] = sg if good else np.nan
    xyz[0][i] = o0 + s * d0 if good else np.nan
    xyz[1][i] = o1 + s * d1 if good else np.nan
    xyz[2][i] = o2 + s * d2 if good else np.nan


@njit(inline="always")
def _pixel(i, O, D, a_obs, b_obs, sa, sb, mask, combine):  # pragma: no cover - numba
    # O, D: the planes as tuples of three 1-D arrays
    o0, o1, o2 = O[0][i], O[1][i], O[2][i]
    d0, d1, d2 = D[0][i], D[1][i], D[2][i]
    ua = a_obs[i]
    ub = b_obs[i]
    phase = mask[i] & (abs(ua) < np.inf)
    if combine:
        phase = phase & (abs(ub) < np.inf)
    line = (abs(o0) < np.inf) & (abs(d0) < np.inf)
    s_a = sa[i]
    s_b = sb[i]
    wa = 1.0 / (s_a * s_a) if s_a > 0.0 else 1.0
    wb = 1.0 / (s_b * s_b) if s_b > 0.0 else 1.0
    return o0, o1, o2, d0, d1, d2, ua, ub, phase, line, s_a, s_b, wa, wb


@njit(cache=True, nogil=True, error_model="numpy")
def _fast_block(O, D, a_obs, b_obs, sa, sb, mask, has_b, combine,
                swap, intr, R, t, W, H, max_res, max_sz, xyz, sig, res, flags,
                ok):  # pragma: no cover - numba
    # no data-dependent branch: invalid pixels are computed too (NaN) and masked by the
    # flags, so that the loop can vectorise
    fa, ca = (intr[1], intr[3]) if swap else (intr[0], intr[2])
    R9 = (R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1], R[2, 2])
    t0, t1, t2 = t[0], t[1], t[2]
    n_slow = 0
    for i in range(a_obs.shape[0]):
        o0, o1, o2, d0, d1, d2, ua, ub, phase, line, s_a, s_b, wa, wb = _pixel(
            i, O, D, a_obs, b_obs, sa, sb, mask, combine)
        Y = _line_in_projector(o0, o1, o2, d0, d1, d2, R9, t0, t1, t2)
        s = _start(ua, Y, intr, fa, ca, swap)
        step = 0.0
        u = v = pa = pb = ga = gb = a = b = c = d = z = curv = 0.0
        for _ in range(_N_FAST):
            step, u, v, pa, pb, ga, gb, a, b, c, d, z, curv = _step(s, ua, ub, wa, wb, Y,
                                                                     intr, combine, swap)
            s = s - step
        # the last evaluation was at s + step: its pixel moved to s to first order, its
        # slopes are those of the solution to a relative 1e-12 once converged
        u = u - step * _gu_of(ga, gb, swap)
        v = v - step * _gv_of(ga, gb, swap)
        pa = pa - step * ga
        pb = pb - step * gb
        est = curv * step * step  # twice |u'' / (2 u')| step^2
        conv = (est <= _TOL_S * (1.0 + abs(s))) & (Y[2] + s * Y[5] > 0.0)
        conv = conv & _pk.is_unfolded(a, b, c, d)
        if combine:
            sg = 1.0 / np.sqrt(ga * ga / (s_a * s_a) + gb * gb / (s_b * s_b))
        else:
            sg = s_a / abs(ga)
        r = np.sqrt((pa - ua) ** 2 + (pb - ub) ** 2) if has_b else np.nan
        inside = (u >= -0.5) & (u <= W - 0.5) & (v >= -0.5) & (v <= H - 0.5)
        f = (FLAG_INCONSISTENT * (r > max_res) + FLAG_OUTSIDE * (1 - inside)
             + FLAG_UNCERTAIN * (sg * abs(d2) > max_sz))
        solved = phase & line
        # not converged here (or beyond the fold): the slow pass decides
        slow = solved & (1 - conv)
        n_slow += slow
        f = FLAG_NOT_CONVERGED if slow else f
        f = f if solved else (FLAG_NO_PHASE if not phase else FLAG_NOT_CONVERGED)
        flags[i] = f
        good = f == 0
        ok[i] = good
        res[i] = r if solved else np.nan
        sig[i] = sg if good else np.nan
        xyz[0][i] = o0 + s * d0 if good else np.nan
        xyz[1][i] = o1 + s * d1 if good else np.nan
        xyz[2][i] = o2 + s * d2 if good else np.nan
    return n_slow


@njit(cache=True, nogil=True, error_model="numpy")
def _slow_pixels(O, D, a_obs, b_obs, sa, sb, mask, has_b, combine, swap,
                 intr, R, t, W, H, max_res, max_sz, xyz, sig, res, flags,
                 ok):  # pragma: no cover - numba
    # the pixels the fast pass left: iterate as the reference does
    fa, ca = (intr[1], intr[3]) if swap else (intr[0], intr[2])
    R9 = (R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1], R[2, 2])
    t0, t1, t2 = t[0], t[1], t[2]
    for i in range(a_obs.shape[0]):
        if flags[i] != FLAG_NOT_CONVERGED:
            continue
        o0, o1, o2, d0, d1, d2, ua, ub, phase, line, s_a, s_b, wa, wb = _pixel(
            i, O, D, a_obs, b_obs, sa, sb, mask, combine)
        if not (phase & line):
            continue
        Y = _line_in_projector(o0, o1, o2, d0, d1, d2, R9, t0, t1, t2)
        s = _start(ua, Y, intr, fa, ca, swap)
        if not np.isfinite(s):
            s = 0.0
        conv = False
        for _ in range(_MAX_ITER):
            step = _step(s, ua, ub, wa, wb, Y, intr, combine, swap)[0]
            if not np.isfinite(step):
                break
            s_new = s - step
            for _h in range(30):  # behind the projector: halve the step
                if Y[2] + s_new * Y[5] > 0.0:
                    break
                step = 0.5 * step
                s_new = s - step
            s = s_new
            if abs(step) <= _TOL_S * (1.0 + abs(s)):
                conv = True
                break
        _, u, v, pa, pb, ga, gb, a, b, c, d, z, _ = _step(s, ua, ub, wa, wb, Y, intr,
                                                           combine, swap)
        _finish(i, s, conv & np.isfinite(s), o0, o1, o2, d0, d1, d2, ua, ub, s_a, s_b, u, v,
                pa, pb, ga, gb, a, b, c, d, z, has_b, combine, W, H, max_res, max_sz, xyz,
                sig, res, flags, ok)


@njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _solve_pinhole(O, D, a_obs, b_obs, sa, sb, mask, has_b, combine, swap, intr, R, t, W, H,
                   max_res, max_sz, xyz, sig, res, flags, ok):  # pragma: no cover - numba
    # chunks of contiguous slices, each looped from 0 (so that the compiler knows the
    # indices are not negative and vectorises the loads and stores)
    n = a_obs.shape[0]
    n_chunks = (n + _CHUNK - 1) // _CHUNK
    n_slow = 0
    for k in prange(n_chunks):
        lo = k * _CHUNK
        hi = min(lo + _CHUNK, n)
        n_slow += _fast_block((O[0][lo:hi], O[1][lo:hi], O[2][lo:hi]),
                              (D[0][lo:hi], D[1][lo:hi], D[2][lo:hi]), a_obs[lo:hi],
                              b_obs[lo:hi], sa[lo:hi], sb[lo:hi], mask[lo:hi], has_b, combine,
                              swap, intr, R, t, W, H, max_res, max_sz,
                              (xyz[0][lo:hi], xyz[1][lo:hi], xyz[2][lo:hi]), sig[lo:hi],
                              res[lo:hi], flags[lo:hi], ok[lo:hi])
    if n_slow:
        _slow_pixels((O[0], O[1], O[2]), (D[0], D[1], D[2]), a_obs, b_obs, sa, sb, mask,
                     has_b, combine, swap, intr, R, t, W, H, max_res, max_sz,
                     (xyz[0], xyz[1], xyz[2]), sig, res, flags, ok)
