"""Per-pixel triangulation of a telecentric camera + projector rig (the paper's Eq. 8).

For a telecentric camera the world line seen by a camera pixel is fixed: undistort the
pixel once, and every point it can see is ``X(s) = o + s d`` with ``o`` on the plane of
zero depth and ``d`` the camera's viewing direction (unit, world frame). Eq. 8 of the
paper (the camera's two rows and the projector's first row: three linear equations in
X, Y, Z) is the same as intersecting that line with the projector's plane of constant
undistorted ``xu_P``. Along the line the projector's *undistorted* sensor coordinates are
affine in ``s``::

    xu_P(s) = A_u + B_u s,   yu_P(s) = A_v + B_v s

(``A`` per pixel, ``B`` constant per rig), so the projector's distortion is handled
exactly by solving, per pixel, the one-unknown problem

    u_P(s) = u_P observed                         (u fringes only: Newton root)
    min_s  (u_P(s) - u_P)^2 / sigma_u^2 + (v_P(s) - v_P)^2 / sigma_v^2   (both axes)

where ``u_P(s), v_P(s)`` are the projector's distorted pixels of ``X(s)``. With u fringes
only, the projector's second coordinate comes from the geometry itself (no need to
ignore it as the paper's Eq. 8 does). With both axes, this is the maximum-likelihood
solution of the four equations (camera rows exact: the camera pixel is known; the two
projector rows weighted by the decoder's uncertainties), and the distance between the
observed and predicted projector pixel is kept as a per-point consistency check
(``residual``, projector px): a wrong fringe order or a bad calibration shows up there.

Speed: everything that does not depend on the scan is computed once per rig and image
shape (:class:`Triangulator`, cached by :func:`triangulate`): each pixel's undistorted line
(``a``, ``b``) and the affine map to the projector's sensor. Per pixel, with u fringes
only, the cubic's coefficients come from ``a``, ``b`` in a few multiplications, then the
linear solution, two chord steps and one Newton step (two divisions), in a vectorised,
parallel compiled loop; the rare pixels whose error estimate is above the 1e-12 mm
tolerance, or which lie beyond the radius where the projector's distortion provably
cannot fold, are solved again by plain Newton iteration with the full checks. Tests hold
the fast path to the iterated solution within 1e-9 mm. The loop moves ~67 bytes per pixel
but is bound by its arithmetic (~110 floating-point operations in a chain of dependent
steps, four AVX2 vectors at a time): on one core the full frame costs the CPU time of the
same number of pixels solved from the core's cache (``benchmarks/triangulate_identity.py``
prints both).

Uncertainty: the only noisy input is the decoded projector coordinate. Its standard
uncertainty moves the point along the camera line only, by ``sigma_s = sigma_u / |du_P/ds|``
(or ``1 / sqrt((du_P/ds)^2 / sigma_u^2 + (dv_P/ds)^2 / sigma_v^2)`` with both axes), so
the covariance of a point is ``sigma_s^2 d d^T`` and ``sigma_xyz = |d| sigma_s``.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from telefringe import _recycle
from telefringe.devices import _telecentric_kernels as _tk
from telefringe.devices.rig import Rig
from telefringe.devices.telecentric import TelecentricDevice
from telefringe.geometry._distortion_kernels import (
    distortion_jacobian,
    is_unfolded,
    unfolded_radius2,
)
from telefringe.reconstruction._rig import as_rig as _as_rig
from telefringe.reconstruction.cloud import (
    FLAG_INCONSISTENT,
    FLAG_NO_PHASE,
    FLAG_NOT_CONVERGED,
    FLAG_OUTSIDE,
    FLAG_UNCERTAIN,
    PointCloud,
    TriangulationError,
    _readonly,
    pixel_rows,
    projector_axes,
)

__all__ = ["Triangulator", "triangulate", "triangulate_pixels", "TRIANGULATOR_CACHE_BYTES"]

_TOL_S = 1e-12  # mm, convergence of the line parameter
_MAX_ITER = 30


def _telecentric_rig(rig) -> Rig:
    """The Rig of ``rig`` (see :func:`~telefringe.reconstruction._rig.as_rig`), checked to
    be a telecentric camera and projector: the only model this fast path is for."""
    rig = _as_rig(rig)
    for role in ("camera", "projector"):
        dev = getattr(rig, role)
        if not isinstance(dev, TelecentricDevice) or dev.model != "telecentric":
            raise TriangulationError(
                f"the telecentric triangulator needs a telecentric {role}, the rig's is "
                f"{getattr(dev, 'model', type(dev).__name__)!r}")
    return rig


# --------------------------------------------------------------------------------------
# The per-rig precomputation
# --------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Triangulator:
    """Everything about the rig that does not depend on the scan, per camera pixel.

    Build it once per rig and image shape with :meth:`for_shape` (or for arbitrary
    camera pixel positions with :meth:`for_pixels`) and call :meth:`triangulate` for
    every scan.

    Attributes
    ----------
    rig : Rig
    shape : tuple of int
        Shape of the camera pixel array the triangulator was built for.
    a, b : ndarray of float64, shape ``shape``
        Each pixel's line ``X(s) = a R_c[0] + b R_c[1] + s d`` (mm) with ``R_c`` the
        camera's ``R_dev_world`` and ``d = R_c[2]``.
    coef : (2, 3) ndarray of float64
        Projector undistorted sensor mm along the line: ``[xu_P, yu_P] = coef @ [a, b, s]
        + m_P t_P``.
    """

    rig: Rig
    shape: tuple
    a: np.ndarray
    b: np.ndarray
    coef: np.ndarray

    @classmethod
    def for_shape(cls, rig: Rig, shape) -> Triangulator:
        """Triangulator for a full camera image of ``shape`` (rows, cols) pixels.

        Raises :class:`TriangulationError` when ``shape`` does not match the camera's
        declared image size (when it declares one).
        """
        rig = _telecentric_rig(rig)
        rows, cols = (int(n) for n in shape)
        if rows <= 0 or cols <= 0:
            raise TriangulationError(f"shape must be positive (rows, cols), got {shape}")
        k = rig.camera.intrinsics
        if k.width and k.height and (k.height, k.width) != (rows, cols):
            raise TriangulationError(
                f"the camera images are {rows} x {cols} (rows x cols) but the rig's camera "
                f"is {k.height} x {k.width}: the rig does not belong to this scan")
        intr, _, t_c = _tk.kernel_args(rig.camera)
        a = np.empty((rows, cols))
        b = np.empty((rows, cols))
        n_bad = _grid_lines_kernel(intr, t_c, a, b)
        if n_bad:
            # the model's own error message and checks
            v, u = np.mgrid[0:rows, 0:cols].astype(np.float64)
            return cls.for_pixels(rig, u, v)
        return cls(rig, (rows, cols), _readonly(a), _readonly(b),
                   _readonly(_projector_coef(rig)))

    @classmethod
    def for_pixels(cls, rig: Rig, u, v) -> Triangulator:
        """Triangulator for camera pixels at (u, v) (any shape, observed/distorted px)."""
        rig = _telecentric_rig(rig)
        u, v = np.broadcast_arrays(np.asarray(u, dtype=np.float64),
                                   np.asarray(v, dtype=np.float64))
        cam: TelecentricDevice = rig.camera
        intr, _, t_c = _tk.kernel_args(cam)
        a = np.empty(u.shape)
        b = np.empty(u.shape)
        n_bad = _tk.backproject_lines(np.ascontiguousarray(u).reshape(-1),
                                      np.ascontiguousarray(v).reshape(-1), intr, t_c,
                                      a.reshape(-1), b.reshape(-1))
        if n_bad:
            cam.backproject(u, v)  # raises the model's ConvergenceError, with its message
        return cls(rig, tuple(u.shape), _readonly(a), _readonly(b),
                   _readonly(_projector_coef(rig)))

    @property
    def direction(self) -> np.ndarray:
        """Camera viewing direction (3,), unit, world frame."""
        return self.rig.camera.R_dev_world[2].copy()

    def line_points(self, s) -> np.ndarray:
        """World points (..., 3) mm at line parameter ``s`` (broadcast with ``shape``)."""
        Rc = self.rig.camera.R_dev_world
        s = np.asarray(s, dtype=np.float64)
        return (self.a[..., None] * Rc[0] + self.b[..., None] * Rc[1]
                + s[..., None] * Rc[2])

    def triangulate(self, coords, *, max_residual: float | None = 1.0,
                    max_sigma_z: float | None = None, use_v_p: bool = True,
                    check_bounds: bool = True) -> PointCloud:
        """Triangulate decoded projector coordinates; see :func:`triangulate`."""
        # v fringes only: the same solve with the projector's axes swapped (the distortion
        # model is symmetric under x <-> y with s1 <-> s2)
        up, vp, su, sv, mask_in, swap = projector_axes(coords, self.shape)
        mask_in = (np.ones(self.shape, dtype=bool) if mask_in is None
                   else np.asarray(mask_in, dtype=bool))
        has_v = vp is not None
        combine = has_v and use_v_p
        coef = self.coef[::-1] if swap else self.coef
        Bu, Bv = float(coef[0, 2]), float(coef[1, 2])
        m_p = self.rig.projector.intrinsics.m
        # sensitivity of the projector's undistorted sensor coordinate to depth, relative
        # to a device looking straight along it (1): below 1 % there is no triangulation
        if combine:
            if np.hypot(Bu, Bv) < 1e-2 * m_p:
                raise TriangulationError(
                    "the projector's image does not move with depth along the camera's "
                    "lines (camera and projector axes are parallel): cannot triangulate")
        elif abs(Bu) < 1e-2 * m_p:
            a1, a2 = ("v", "u") if swap else ("u", "v")
            raise TriangulationError(
                f"{a1}_p barely changes with depth for this rig (the projector's {a1} axis "
                f"is nearly perpendicular to the camera's axis); capture {a2} fringes and "
                f"triangulate with {a2}_p")
        ki = self.rig.projector.intrinsics
        W = float(ki.width) if check_bounds and ki.width else np.inf
        H = float(ki.height) if check_bounds and ki.height else np.inf
        t_p = m_p * np.asarray(self.rig.projector.t_dev, dtype=np.float64)
        u0, v0, du, dv, s1, s2 = ki.u0, ki.v0, ki.du, ki.dv, ki.s1, ki.s2
        if swap:
            u0, v0, du, dv, s1, s2, W, H = v0, u0, dv, du, s2, s1, H, W
            t_p = t_p[::-1]
        n = int(np.prod(self.shape))

        def flat(x):
            if x is None:  # no uncertainty given: NaN (recycled memory, filled)
                nan = _recycle.empty(n)
                nan.fill(np.nan)
                return nan
            x = np.asarray(x)
            if x.dtype not in (np.float32, np.float64, np.bool_):
                x = x.astype(np.float64)
            return np.ascontiguousarray(x).reshape(n)

        up_f = flat(up)
        su_f = flat(su)
        mask_f = flat(mask_in.astype(bool, copy=False))
        # x, y, z planes: the kernels write contiguous planes, the cloud views them as
        # (rows, cols, 3)
        # (recycled memory: the kernels write every element)
        xyz_planar = _recycle.empty((3,) + self.shape)
        x, y, z = (xyz_planar[k].reshape(n) for k in range(3))
        sig = _recycle.empty(n)
        flags = _recycle.empty(n, dtype=np.uint8)
        ok = _recycle.empty(n, dtype=np.bool_)
        Rc = np.ascontiguousarray(self.rig.camera.R_dev_world)
        kp = np.array((u0, v0, du, dv, ki.k1, s1, s2, W, H, coef[0, 0], coef[0, 1], Bu,
                       coef[1, 0], coef[1, 1], Bv, t_p[0], t_p[1], 1.0 / du, 1.0 / dv,
                       unfolded_radius2(ki.k1, s1, s2)), dtype=np.float64)
        max_res = np.inf if max_residual is None else float(max_residual)
        max_sz = np.inf if max_sigma_z is None else float(max_sigma_z)
        a_f, b_f = self.a.reshape(n), self.b.reshape(n)
        if has_v:
            vp_f = flat(vp)
            sv_f = flat(sv)
            res = _recycle.empty(n)
            n_slow = _solve_fast(a_f, b_f, up_f, vp_f, su_f, sv_f, mask_f, True, combine, kp,
                                 Rc, max_res, max_sz, x, y, z, sig, res, flags, ok)
        else:
            # u_p alone (the usual scan): the lean kernel, no v_p, no residual
            vp_f, sv_f, res = up_f, su_f, None
            n_slow = _solve_u_fast(a_f, b_f, up_f, su_f, mask_f, kp, Rc, max_sz, x, y, z, sig,
                                   flags, ok)
        if n_slow:
            _solve_slow(a_f, b_f, up_f, vp_f, su_f, sv_f, mask_f, has_v, combine, kp, Rc,
                        max_res, max_sz, x, y, z, sig, np.empty(n) if res is None else res,
                        flags, ok)
        shape = self.shape
        xyz = np.moveaxis(xyz_planar, 0, -1)
        # the kernels' fresh arrays: the cloud adopts them without a copy
        return PointCloud._adopt(xyz, ok.reshape(shape), sig.reshape(shape),
                                 None if res is None else res.reshape(shape),
                                 flags.reshape(shape), self.direction)


# The per-pixel solve. Along a camera line the projector's undistorted sensor coordinates
# are affine in s, so its distorted ones are exact cubics, xd(s) = cu0 + cu1 s + cu2 s^2 +
# cu3 s^3 and yd(s) = cv0 + ... . With u fringes only, s is the root of xd(s) = xd_obs
# (Newton); with both axes, s minimises wu (xd - xd_obs)^2 + wv (yd - yd_obs)^2 (Newton on
# the derivative, exact second derivative). Both start from the linear solution (exact
# without distortion). The fast pass takes a fixed number of steps with no branches, so
# that the loop vectorises, and estimates the error left from Newton's quadratic
# convergence (next step ~ |F'' / (2 F')| ds^2 for the equation F = 0 being solved);
# pixels above the tolerance are solved again by the slow pass, which iterates.
_N_FAST = 2
_CHUNK = 16384


@njit(cache=True, inline="always", error_model="numpy")
def _axis_cubic(A, B, q0, q1, q2, k1, s):  # pragma: no cover - numba
    """Coefficients (c0, c1, c2, c3) in s of one distorted sensor coordinate along the
    line A + B s (the other coordinate's A', B' enter through q0 = A^2 + A'^2, q1 =
    2 (A B + A' B'), q2 = B^2 + B'^2); k1 radial, s the axis' thin-prism term."""
    return (A + (k1 * A + s) * q0, B + k1 * (A * q1 + B * q0) + s * q1,
            k1 * (A * q2 + B * q1) + s * q2, k1 * B * q2)


@njit(cache=True, inline="always", error_model="numpy")
def _line_cubics(ai, bi, kp):  # pragma: no cover - numba
    k1 = kp[4]
    s1 = kp[5]
    s2 = kp[6]
    Bu = kp[11]
    Bv = kp[14]
    Au = kp[9] * ai + kp[10] * bi + kp[15]
    Av = kp[12] * ai + kp[13] * bi + kp[16]
    q2 = Bu * Bu + Bv * Bv
    q0 = Au * Au + Av * Av
    q1 = 2.0 * (Au * Bu + Av * Bv)
    cu0, cu1, cu2, cu3 = _axis_cubic(Au, Bu, q0, q1, q2, k1, s1)
    cv0, cv1, cv2, cv3 = _axis_cubic(Av, Bv, q0, q1, q2, k1, s2)
    return cu0, cu1, cu2, cu3, cv0, cv1, cv2, cv3, Au, Av


@njit(cache=True, inline="always", error_model="numpy")
def _start(c, xd_obs, yd_obs, wu, wv, combine):  # pragma: no cover - numba
    cu0, cu1, cu2, cu3, cv0, cv1, cv2, cv3, Au, Av = c
    if combine:
        return (wu * cu1 * (xd_obs - cu0) + wv * cv1 * (yd_obs - cv0)) / (
            wu * cu1 * cu1 + wv * cv1 * cv1)
    return (xd_obs - cu0) / cu1


@njit(cache=True, inline="always", error_model="numpy")
def _newton_step(s, c, xd_obs, yd_obs, wu, wv, combine):  # pragma: no cover - numba
    # returns the new s and the estimated error left after the step
    cu0, cu1, cu2, cu3, cv0, cv1, cv2, cv3, Au, Av = c
    fu = ((cu3 * s + cu2) * s + cu1) * s + cu0 - xd_obs
    gu = (3.0 * cu3 * s + 2.0 * cu2) * s + cu1
    hu = 6.0 * cu3 * s + 2.0 * cu2
    if combine:
        fv = ((cv3 * s + cv2) * s + cv1) * s + cv0 - yd_obs
        gv = (3.0 * cv3 * s + 2.0 * cv2) * s + cv1
        hv = 6.0 * cv3 * s + 2.0 * cv2
        F1 = wu * gu * fu + wv * gv * fv  # half the objective's derivative
        F2 = wu * (gu * gu + fu * hu) + wv * (gv * gv + fv * hv)
        F3 = wu * (3.0 * gu * hu + fu * 6.0 * cu3) + wv * (3.0 * gv * hv + fv * 6.0 * cv3)
    else:
        F1 = fu
        F2 = gu
        F3 = hu
    r2 = 1.0 / F2
    ds = F1 * r2
    return s - ds, abs(0.5 * F3 * r2) * ds * ds


@njit(cache=True, inline="always", error_model="numpy")
def _observe(i, up, vp, su, sv, mask, combine, kp):  # pragma: no cover - numba
    u_obs = up[i]
    v_obs = vp[i]
    valid = mask[i] & (abs(u_obs) < np.inf)
    if combine:
        valid = valid & (abs(v_obs) < np.inf)
    s_u = su[i]
    s_v = sv[i]
    # weights of the sensor-mm residuals: 1 / sigma^2 in px (equal without sigmas)
    wu = 1.0
    wv = 1.0
    if combine:  # loop-invariant: the u-only loop skips these divisions
        wu = (1.0 / (s_u * s_u) if s_u > 0.0 else 1.0) * (kp[17] * kp[17])
        wv = (1.0 / (s_v * s_v) if s_v > 0.0 else 1.0) * (kp[18] * kp[18])
    return u_obs, v_obs, valid, (u_obs - kp[0]) * kp[2], (v_obs - kp[1]) * kp[3], s_u, s_v, wu, wv


@njit(cache=True, inline="always", error_model="numpy")
def _set_up(i, a, b, up, vp, su, sv, mask, combine, kp):  # pragma: no cover - numba
    # pixel i's observations, its line's cubics and the linear start (both passes)
    u_obs, v_obs, valid, xd_obs, yd_obs, s_u, s_v, wu, wv = _observe(
        i, up, vp, su, sv, mask, combine, kp)
    ai = a[i]
    bi = b[i]
    c = _line_cubics(ai, bi, kp)
    s = _start(c, xd_obs, yd_obs, wu, wv, combine)
    return u_obs, v_obs, valid, xd_obs, yd_obs, s_u, s_v, wu, wv, ai, bi, c, s


@njit(cache=True, inline="always", error_model="numpy")
def _finish(i, s, valid, converged, ai, bi, u_obs, v_obs, s_u, s_v, c, has_v, combine, kp,
            Rc, max_res, max_sz, x, y, z, sig, res, flags, ok):  # pragma: no cover - numba
    cu0, cu1, cu2, cu3, cv0, cv1, cv2, cv3, Au, Av = c
    idu = kp[17]  # 1 / du
    idv = kp[18]
    xd = ((cu3 * s + cu2) * s + cu1) * s + cu0
    yd = ((cv3 * s + cv2) * s + cv1) * s + cv0
    Ju = ((3.0 * cu3 * s + 2.0 * cu2) * s + cu1) * idu  # projector px per mm of line
    Jv = ((3.0 * cv3 * s + 2.0 * cv2) * s + cv1) * idv
    up_pred = kp[0] + xd * idu
    vp_pred = kp[1] + yd * idv
    # residual: NaN where v_p is NaN, which passes the check below. Stored whatever
    # has_v: a conditional store would stop the loop from vectorising
    ru = up_pred - u_obs
    rv = vp_pred - v_obs
    r = np.sqrt(ru * ru + rv * rv) if has_v else 0.0
    res[i] = r if (valid & has_v) else np.nan
    if combine:
        sg = 1.0 / np.sqrt(Ju * Ju / (s_u * s_u) + Jv * Jv / (s_v * s_v))
    else:
        sg = s_u / abs(Ju)
    inside = ((up_pred >= -0.5) & (up_pred <= kp[7] - 0.5) & (vp_pred >= -0.5)
              & (vp_pred <= kp[8] - 0.5))
    # a solution where the projector's distortion is folded is not the inverse (as in
    # telefringe.geometry.distortion.undistort_sensor): count it as not converged
    fa, fb, fc, fd = distortion_jacobian(Au + kp[11] * s, Av + kp[14] * s, kp[4], kp[5],
                                         kp[6])
    converged = converged & is_unfolded(fa, fb, fc, fd)
    f = (FLAG_INCONSISTENT * (r > max_res) + FLAG_OUTSIDE * (1 - inside)
         + FLAG_NOT_CONVERGED * (1 - converged) + FLAG_UNCERTAIN * (sg * abs(Rc[8]) > max_sz))
    f = f if valid else FLAG_NO_PHASE
    _store(i, f, sg, ai, bi, s, Rc, x, y, z, sig, flags, ok)
    return (f & FLAG_NOT_CONVERGED) != 0  # left to the slow pass


@njit(cache=True, inline="always")
def _store(i, f, sg, ai, bi, s, R9, x, y, z, sig, flags, ok):  # pragma: no cover - numba
    # one pixel's result: flags f, and where f == 0 its sigma and its point on the line
    flags[i] = f
    good = f == 0
    ok[i] = good
    sig[i] = sg if good else np.nan
    px, py, pz = _tk.line_point(ai, bi, s, R9)
    x[i] = px if good else np.nan
    y[i] = py if good else np.nan
    z[i] = pz if good else np.nan


@njit(cache=True, inline="always")
def _invariants(kp, Rc):  # pragma: no cover - numba
    # the rig's constants as tuples: loop invariants the compiler keeps in registers (read
    # from arrays, they would be reloaded every pixel: the stores could alias them)
    return ((kp[0], kp[1], kp[2], kp[3], kp[4], kp[5], kp[6], kp[7], kp[8], kp[9], kp[10],
             kp[11], kp[12], kp[13], kp[14], kp[15], kp[16], kp[17], kp[18]),
            _tk.flat_rotation(Rc))


@njit(cache=True, nogil=True, error_model="numpy")
def _solve_block(a, b, up, vp, su, sv, mask, has_v, combine, kp, Rc, max_res, max_sz,
                 x, y, z, sig, res, flags, ok):  # pragma: no cover - numba
    # fixed steps, no data-dependent branches: LLVM vectorises this loop
    # returns the number of pixels left to the slow pass
    kp, Rc = _invariants(kp, Rc)
    n_slow = 0
    for i in range(a.shape[0]):
        u_obs, v_obs, valid, xd_obs, yd_obs, s_u, s_v, wu, wv, ai, bi, c, s = _set_up(
            i, a, b, up, vp, su, sv, mask, combine, kp)
        est = 0.0
        for _ in range(_N_FAST):
            s, est = _newton_step(s, c, xd_obs, yd_obs, wu, wv, combine)
        converged = est <= _TOL_S * (1.0 + abs(s))
        n_slow += _finish(i, s, valid, converged, ai, bi, u_obs, v_obs, s_u, s_v, c, has_v,
                          combine, kp, Rc, max_res, max_sz, x, y, z, sig, res, flags, ok)
    return n_slow


@njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _solve_fast(a, b, up, vp, su, sv, mask, has_v, combine, kp, Rc, max_res, max_sz,
                x, y, z, sig, res, flags, ok):  # pragma: no cover - numba
    n = a.shape[0]
    n_slow = 0
    for k in prange((n + _CHUNK - 1) // _CHUNK):
        lo = k * _CHUNK
        hi = min(lo + _CHUNK, n)
        n_slow += _solve_block(a[lo:hi], b[lo:hi], up[lo:hi], vp[lo:hi], su[lo:hi],
                               sv[lo:hi], mask[lo:hi], has_v, combine, kp, Rc, max_res,
                               max_sz, x[lo:hi], y[lo:hi], z[lo:hi], sig[lo:hi], res[lo:hi],
                               flags[lo:hi], ok[lo:hi])
    return n_slow


# u fringes only (the usual scan): s is the root of xd(s) = xd_obs. From the linear
# solution, _N_CHORD chord steps with the slope cu1 (one reciprocal serves them all; each
# multiplies the error by |xd'(s) / cu1 - 1|, the distortion's small share of the slope:
# ~1e-4 for the paper's projector), then one Newton step, whose reciprocal slope also
# gives sigma. The error left after the Newton step is estimated from its quadratic
# convergence as in _newton_step; pixels above the tolerance go to the slow pass. Two
# divisions per pixel, no v_p, no residual. The loop is bound by its arithmetic, not by
# its memory traffic (see the module's notes). FMA contraction (fastmath "contract", no
# other flag): one rounding instead of two in the polynomial and chord arithmetic, ~10 %
# less CPU for the loop; the points move by at most 2e-14 mm against the uncontracted
# loop on the paper rig, and tests/test_triangulate_generic.py holds the fast path to the
# generic solve within 1e-9 mm.
_N_CHORD = 2


@njit(cache=True, nogil=True, error_model="numpy", fastmath={"contract"})
def _solve_u_block(a, b, up, su, mask, kp, Rc, max_sz, x, y, z, sig, flags,
                   ok):  # pragma: no cover - numba
    # returns the number of pixels left to the slow pass
    u0 = kp[0]
    v0 = kp[1]
    du = kp[2]
    k1 = kp[4]
    s1 = kp[5]
    s2 = kp[6]
    W = kp[7]
    H = kp[8]
    Bu = kp[11]
    Bv = kp[14]
    idu = kp[17]
    idv = kp[18]
    r2_unfolded = kp[19]
    pu_a = kp[9]
    pu_b = kp[10]
    pv_a = kp[12]
    pv_b = kp[13]
    tu = kp[15]
    tv = kp[16]
    q2 = Bu * Bu + Bv * Bv
    # loop invariants in locals: the stores below could alias kp and Rc for all the
    # compiler knows, which would reload them every pixel
    R9 = _tk.flat_rotation(Rc)
    d22 = abs(R9[8])
    n_slow = 0
    for i in range(a.shape[0]):
        ai = a[i]
        bi = b[i]
        u_obs = up[i]
        valid = mask[i] & (abs(u_obs) < np.inf)
        Au = pu_a * ai + pu_b * bi + tu
        Av = pv_a * ai + pv_b * bi + tv
        q0 = Au * Au + Av * Av
        q1 = 2.0 * (Au * Bu + Av * Bv)
        cu0, cu1, cu2, cu3 = _axis_cubic(Au, Bu, q0, q1, q2, k1, s1)
        t = (u_obs - u0) * du - cu0
        r1 = 1.0 / cu1
        s = t * r1
        for _ in range(_N_CHORD):
            s = (t - s * s * (cu2 + cu3 * s)) * r1
        f = s * (cu1 + s * (cu2 + cu3 * s)) - t
        g = cu1 + s * (2.0 * cu2 + 3.0 * cu3 * s)
        h = 2.0 * cu2 + 6.0 * cu3 * s
        rg = 1.0 / g
        ds = f * rg
        s = s - ds
        converged = abs(0.5 * h * rg) * ds * ds <= _TOL_S * (1.0 + abs(s))
        # 1 / xd'(s) at the new s, to first order in ds (relative error ~ (h ds / g)^2)
        rg = rg * (1.0 + h * ds * rg)
        sg = su[i] * du * abs(rg)  # sigma_u / |du_P/ds|
        # the predicted projector pixel (for the bounds) and the fold check, from the
        # undistorted projector coordinates at s
        xu = Au + Bu * s
        yu = Av + Bv * s
        q = xu * xu + yu * yu
        up_pred, vp_pred = _tk.pixel_of_sensor(xu, yu, u0, v0, idu, idv, k1, s1, s2)
        inside = ((up_pred >= -0.5) & (up_pred <= W - 0.5) & (vp_pred >= -0.5)
                  & (vp_pred <= H - 0.5))
        # the fold check: true within the radius of unfolded_radius2; beyond it (never,
        # for a real projector) the slow pass solves the pixel again with the full check
        converged = converged & (q <= r2_unfolded)
        fl = (FLAG_OUTSIDE * (1 - inside) + FLAG_NOT_CONVERGED * (1 - converged)
              + FLAG_UNCERTAIN * (sg * d22 > max_sz))
        fl = fl if valid else FLAG_NO_PHASE
        n_slow += (fl & FLAG_NOT_CONVERGED) != 0
        _store(i, fl, sg, ai, bi, s, R9, x, y, z, sig, flags, ok)
    return n_slow


@njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _solve_u_fast(a, b, up, su, mask, kp, Rc, max_sz, x, y, z, sig, flags,
                  ok):  # pragma: no cover - numba
    n = a.shape[0]
    n_slow = 0
    for k in prange((n + _CHUNK - 1) // _CHUNK):
        lo = k * _CHUNK
        hi = min(lo + _CHUNK, n)
        n_slow += _solve_u_block(a[lo:hi], b[lo:hi], up[lo:hi], su[lo:hi], mask[lo:hi], kp, Rc,
                                 max_sz, x[lo:hi], y[lo:hi], z[lo:hi], sig[lo:hi],
                                 flags[lo:hi], ok[lo:hi])
    return n_slow


@njit(cache=True, nogil=True, error_model="numpy")
def _solve_slow(a, b, up, vp, su, sv, mask, has_v, combine, kp, Rc, max_res, max_sz,
                x, y, z, sig, res, flags, ok):  # pragma: no cover - numba
    # the pixels the fast pass left unconverged: iterate
    kp, Rc = _invariants(kp, Rc)
    for i in range(a.shape[0]):
        if not (flags[i] & FLAG_NOT_CONVERGED):
            continue
        u_obs, v_obs, valid, xd_obs, yd_obs, s_u, s_v, wu, wv, ai, bi, c, s = _set_up(
            i, a, b, up, vp, su, sv, mask, combine, kp)
        converged = False
        for _ in range(_MAX_ITER):
            s, est = _newton_step(s, c, xd_obs, yd_obs, wu, wv, combine)
            if not np.isfinite(s):
                break
            if est <= _TOL_S * (1.0 + abs(s)):
                converged = True
                break
        _finish(i, s, valid, converged, ai, bi, u_obs, v_obs, s_u, s_v, c, has_v, combine, kp,
                Rc, max_res, max_sz, x, y, z, sig, res, flags, ok)


def _projector_coef(rig: Rig) -> np.ndarray:
    """(2, 3): the projector's undistorted sensor mm along a camera line, ``[xu_P, yu_P]
    = coef @ [a, b, s] + m_P t_P``."""
    Rc = rig.camera.R_dev_world
    basis = np.stack([Rc[0], Rc[1], Rc[2]], axis=1)  # (3, 3): columns = Rc0, Rc1, d
    return rig.projector.intrinsics.m * (rig.projector.R_dev_world[:2] @ basis)


_N_UNDISTORT = 3


@njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _grid_lines_kernel(intr, t, a, b):  # pragma: no cover - numba
    # Triangulator.for_pixels on the full pixel grid, the device model's back-projection
    # fused per row: _N_UNDISTORT fixed Newton steps with no data-dependent branch (the row
    # vectorises), then the pixels that fail its acceptance test are redone with the
    # iterating inversion. Returns the number of pixels where that fails too.
    m, du, dv, u0, v0, k1, s1, s2 = intr
    t0 = t[0]
    t1 = t[1]
    rows, cols = a.shape
    n_bad = 0
    for r in prange(rows):
        redo = 0
        for c in range(cols):
            ai, bi, good = _tk.backproject_point_fixed(float(c), float(r), m, u0, v0, du, dv,
                                                       k1, s1, s2, t0, t1, _N_UNDISTORT)
            redo += not good
            a[r, c] = ai if good else np.nan
            b[r, c] = bi
        if redo:
            for c in range(cols):
                if np.isnan(a[r, c]):
                    ai, bi, ok = _tk.backproject_point(float(c), float(r), m, u0, v0, du, dv,
                                                       k1, s1, s2, t0, t1)
                    if not ok:
                        n_bad += 1
                    a[r, c] = ai
                    b[r, c] = bi
    return n_bad


#: Bytes the per-process cache of :class:`Triangulator` may hold (its a, b planes: 21 MB
#: for a 1280 x 1024 camera). A triangulator larger than this is built and not kept.
TRIANGULATOR_CACHE_BYTES = 64 * 2**20


class _TriangulatorCache:
    """(rig, shape) -> Triangulator, the least recently used dropped first, holding at most
    ``max_bytes``; safe to share between threads.

    Keyed by the rig's identity (a Rig is immutable); the entry holds its rig, so the id
    of a cached rig cannot be reused. A miss builds outside the lock (the compiled set-up
    releases the GIL), so two threads may build the same entry once each: one is kept.
    """

    def __init__(self, max_bytes: int):
        self.max_bytes = int(max_bytes)
        self._lock = threading.Lock()
        self._items: OrderedDict[tuple, Triangulator] = OrderedDict()
        self._bytes = 0

    @staticmethod
    def _size(tri: Triangulator) -> int:
        return int(tri.a.nbytes + tri.b.nbytes + tri.coef.nbytes)

    @property
    def nbytes(self) -> int:
        """Bytes held now."""
        with self._lock:
            return self._bytes

    def __len__(self) -> int:
        with self._lock:
            return len(self._items)

    def get(self, rig: Rig, shape: tuple) -> Triangulator:
        key = (id(rig), tuple(shape))
        with self._lock:
            tri = self._items.get(key)
            if tri is not None and tri.rig is rig:
                self._items.move_to_end(key)
                return tri
        tri = Triangulator.for_shape(rig, shape)
        size = self._size(tri)
        if size > self.max_bytes:
            return tri
        with self._lock:
            old = self._items.pop(key, None)
            if old is not None:
                self._bytes -= self._size(old)
            self._items[key] = tri
            self._bytes += size
            while self._bytes > self.max_bytes:
                _, dropped = self._items.popitem(last=False)
                self._bytes -= self._size(dropped)
        return tri

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self._bytes = 0


_TRIANGULATORS = _TriangulatorCache(TRIANGULATOR_CACHE_BYTES)


def triangulate(rig: Rig, coords, *, max_residual: float | None = 1.0,
                max_sigma_z: float | None = None, use_v_p: bool = True,
                check_bounds: bool = True) -> PointCloud:
    """Triangulate decoded projector coordinates into an organised point cloud.

    Parameters
    ----------
    rig : Rig (or an object holding one as ``.rig``, like ``load_rig``'s result)
        The calibrated rig (world frame: the calibration target's reference pose).
    coords : object with attributes ``u_p``, ``v_p``, ``mask``, ``sigma_u_p``, ``sigma_v_p``
        E.g. :class:`telefringe.decode.ProjectorCoordinates`. ``u_p`` (rows, cols)
        projector columns (px) per camera pixel, NaN where invalid; ``v_p`` projector
        rows (px) or None without horizontal fringes (with v fringes only, ``u_p`` may be
        None: ``v_p`` then plays its part); ``mask`` (rows, cols) bool or None;
        ``sigma_u_p`` / ``sigma_v_p`` standard uncertainties (projector px) or None
        (then the uncertainties of the result are NaN and both axes weigh the same).
    max_residual : float or None, keyword-only
        With ``v_p``: points whose observed projector pixel is farther than this (projector
        px) from the one predicted by the solution are invalid (``FLAG_INCONSISTENT``).
        The default 1 px lets decoding noise and calibration error through and stops
        fringe-order errors (one period is many projector pixels) across the epipolar
        line, i.e. on the axis that carries little depth (usually v). An error along the
        epipolar line only moves the point in depth and cannot be seen here. None: no
        check.
    max_sigma_z : float or None, keyword-only
        Points with a larger standard uncertainty of Z (mm) are invalid.
    use_v_p : bool, keyword-only
        Combine ``v_p`` with ``u_p`` in the solution (default). When false, ``v_p`` is
        used for the consistency check only.
    check_bounds : bool, keyword-only
        Flag solutions outside the projector's image (when the rig declares its size).

    Returns
    -------
    PointCloud
        ``xyz`` (rows, cols, 3) mm in the rig's world frame, NaN where invalid.

    Notes
    -----
    The rig's per-pixel precomputation (:class:`Triangulator`) is cached per process for
    the most recently used (rig, shape) pairs, within ``TRIANGULATOR_CACHE_BYTES``
    (thread-safe), so repeated calls with the same rig are fast.
    """
    up = getattr(coords, "u_p", None)
    if up is None:
        up = getattr(coords, "v_p", None)
        if up is None:
            raise TriangulationError("coords has neither u_p nor v_p")
    shape = tuple(int(n) for n in np.shape(up))
    if len(shape) != 2:
        raise TriangulationError(f"u_p must be a (rows, cols) array, got shape {shape}")
    tri = _TRIANGULATORS.get(_as_rig(rig), shape)
    return tri.triangulate(coords, max_residual=max_residual, max_sigma_z=max_sigma_z,
                           use_v_p=use_v_p, check_bounds=check_bounds)


def triangulate_pixels(rig: Rig, u_c, v_c, u_p, v_p=None, *, sigma_u_p=None, sigma_v_p=None,
                       max_residual: float | None = None) -> PointCloud:
    """Triangulate arbitrary (sub-pixel) camera pixels, e.g. marker centres.

    Parameters
    ----------
    rig : Rig
    u_c, v_c : (n,) array_like of float
        Camera pixels (observed, distorted).
    u_p, v_p : (n,) array_like of float
        Projector pixels seen there (``v_p`` may be None).
    sigma_u_p, sigma_v_p : (n,) array_like of float or None
        Standard uncertainties of ``u_p`` / ``v_p`` (projector px).
    max_residual : float or None
        As in :func:`triangulate` (default: no check).

    Returns
    -------
    PointCloud
        With ``shape == (1, n)``; ``cloud.xyz[0]`` is the (n, 3) array of points.
    """
    u_c, v_c, c = pixel_rows(u_c, v_c, u_p, v_p, sigma_u_p, sigma_v_p)
    tri = Triangulator.for_pixels(rig, u_c, v_c)
    return tri.triangulate(c, max_residual=max_residual, check_bounds=False)
