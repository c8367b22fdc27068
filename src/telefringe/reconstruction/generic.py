"""Camera + projector triangulation for any pair of devices (the reference path).

Written against the :class:`~telefringe.devices.base.Device` protocol only: each camera
pixel's world line comes from ``camera.backproject`` (``X(s) = o + s d``, ``d`` unit,
``s`` in mm), and the projector is asked only for its projection and its Jacobian. Per
pixel, the line meets the projector's surface of constant ``u_P`` (a plane for a pinhole
projector without distortion, a curved surface with it), solved exactly with the
projector's distortion:

    u_P(X(s)) = u_P observed                         (u fringes only: Newton on s)
    min_s (u_P(s) - u_P)^2 / sigma_u^2 + (v_P(s) - v_P)^2 / sigma_v^2   (both axes)

The second is the maximum-likelihood solution of the four equations (the camera pixel is
known; the two projector coordinates weighted by the decoder's uncertainties), solved by
Gauss-Newton (its linear rate is the residual times the curvature over the squared slope:
far below 1e-3 for a consistent pixel), and the distance between the observed and the
predicted projector pixel is kept as a consistency check (``residual``, projector px). With
v fringes only, ``v_P`` plays the part of ``u_P``.

Start: without distortion a projector's pixel along a line is a Moebius function of the
line parameter, ``u(s) = (A + B s) / (1 + C s)`` (affine for a telecentric projector), so
three samples of the projection around the rig's working point give the exact solution
of an undistorted projector and a start within the distortion's share for a real one.
Newton then iterates to 1e-12 mm (relative to 1 + |s|), halving steps that leave the
projector's domain (e.g. behind a pinhole projector); a pixel that does not converge in 50
steps is flagged ``FLAG_NOT_CONVERGED``. A solution beyond the fold of the projector's
distortion (where its projection is not invertible) is found by a round trip: the
projector's back-projection of the predicted pixel must pass through the point (to 1e-6
mm); where it does not, or cannot be computed, the point is flagged not converged.

Uncertainty: the decoded projector coordinate is the only noisy input; it moves the point
along its camera line by ``sigma_s = sigma_u / |du_P/ds|`` (or ``1 / sqrt((du_P/ds)^2 /
sigma_u^2 + (dv_P/ds)^2 / sigma_v^2)`` with both axes), the covariance is ``sigma_s^2 d
d^T`` and ``PointCloud.sigma_line = sigma_s`` (``d`` is unit).

The cloud's ``directions`` are the camera's: (3,) for a telecentric camera, one per
pixel (rows, cols, 3) for a pinhole one. A compiled solver for pinhole and telecentric
projectors (:mod:`telefringe.reconstruction._generic_kernels`, chosen by the projector's
``model``; ``compiled=False`` bypasses it) reproduces this path fast: this module is the
reference it is tested against (same flags, points within 1e-9 mm). Building a
triangulator (the camera's lines, once per rig and image size, cached) likewise uses the
camera model's compiled back-projection where there is one, tested against the protocol's.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from telefringe import _recycle
from telefringe.devices.rig import Rig
from telefringe.geometry.distortion import ConvergenceError
from telefringe.reconstruction import _generic_kernels as _gk
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

__all__ = ["GenericTriangulator", "triangulate", "triangulate_pixels", "safe_backproject",
           "device_centre_pixel", "working_point"]

_TOL_S = 1e-12  # mm, relative to 1 + |s|
_MAX_ITER = 50
_CHUNK = 1 << 16
_ROUND_TRIP_TOL = 1e-6  # mm


# --------------------------------------------------------------------------------------
# Rays of a device, robust to pixels its distortion cannot invert
# --------------------------------------------------------------------------------------
def safe_backproject(device, u, v):
    """``device.backproject(u, v)`` as arrays, NaN where the device cannot invert its
    distortion (instead of raising for the whole array).

    Parameters
    ----------
    device : Device
    u, v : (n,) ndarray of float, observed px.

    Returns
    -------
    origin, direction : (n, 3) ndarray of float (mm; unit), or (3,) when shared by every
        pixel (a pinhole device's centre, a telecentric device's axis).
    bad : (n,) ndarray of bool, the finite pixels whose back-projection failed.
    """
    u = np.asarray(u, dtype=np.float64).reshape(-1)
    v = np.asarray(v, dtype=np.float64).reshape(-1)
    try:
        o, d = device.backproject(u, v)
        return np.asarray(o), np.asarray(d), np.zeros(u.shape, dtype=bool)
    except ConvergenceError:
        pass
    # bisect to the pixels that fail (rare: only beyond the fold of the distortion)
    n = u.size
    o_full = np.full((n, 3), np.nan)
    d_full = np.full((n, 3), np.nan)
    bad = np.zeros(n, dtype=bool)
    stack = [(0, n)]
    while stack:
        lo, hi = stack.pop()
        try:
            o, d = device.backproject(u[lo:hi], v[lo:hi])
            o_full[lo:hi] = o
            d_full[lo:hi] = d
        except ConvergenceError:
            if hi - lo == 1:
                bad[lo] = True
            else:
                mid = (lo + hi) // 2
                stack += [(lo, mid), (mid, hi)]
    return o_full, d_full, bad


def device_centre_pixel(device) -> tuple[float, float]:
    """The centre of a device's image (px): of its declared size, else its principal
    point (from the protocol's ``principal_point_names``)."""
    size = device.image_size
    if size is not None:
        return (size[0] - 1) / 2.0, (size[1] - 1) / 2.0
    p = device.to_params()
    names = device.param_names
    cx, cy = device.principal_point_names
    return float(p[names.index(cx)]), float(p[names.index(cy)])


def _central_ray(device):
    uc, vc = device_centre_pixel(device)
    o, d, bad = safe_backproject(device, np.array([uc]), np.array([vc]))
    if bad[0]:
        raise TriangulationError(f"the {device.model} device cannot back-project its own "
                                 "image centre: check its distortion")
    return (np.broadcast_to(o, (1, 3))[0].astype(float),
            np.broadcast_to(d, (1, 3))[0].astype(float))


def _is_central(device) -> bool:
    """Whether all the device's rays pass through one point (a pinhole device)."""
    uc, vc = device_centre_pixel(device)
    o, _, bad = safe_backproject(device, np.array([uc, uc + 50.0]), np.array([vc, vc + 50.0]))
    if bad.any():
        return False
    o = np.broadcast_to(o, (2, 3))
    return bool(np.linalg.norm(o[0] - o[1]) <= 1e-9 * (1.0 + np.linalg.norm(o[0])))


def working_point(dev_a, dev_b) -> tuple[np.ndarray, float]:
    """Where two devices look together: the midpoint of the closest approach of their
    central rays (world mm), and a length scale of the rig (mm): the larger distance from
    a pinhole device's centre to that point (at least 1 mm).

    Where the central rays are (nearly) parallel, the point of ``dev_a``'s central ray
    nearest the world origin stands in for it.
    """
    oa, da = _central_ray(dev_a)
    ob, db = _central_ray(dev_b)
    w = oa - ob
    b = float(da @ db)
    den = 1.0 - b * b
    if den > 1e-8:
        sa = (b * (db @ w) - (da @ w)) / den
        sb = ((db @ w) - b * (da @ w)) / den
        P0 = 0.5 * ((oa + sa * da) + (ob + sb * db))
    else:
        P0 = oa - (oa @ da) * da
    scale = 1.0
    for dev, o in ((dev_a, oa), (dev_b, ob)):
        if _is_central(dev):
            scale = max(scale, float(np.linalg.norm(P0 - o)))
    return P0, scale


# --------------------------------------------------------------------------------------
# The per-rig precomputation
# --------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class GenericTriangulator:
    """The camera's lines for a grid of pixels, and the rig's working point.

    Build it once per rig and image shape with :meth:`for_shape` (or for arbitrary
    camera pixels with :meth:`for_pixels`) and call :meth:`triangulate` per scan.

    Attributes
    ----------
    rig : Rig
    shape : tuple of int, shape of the camera pixel array.
    origin : (n, 3) or (3,) ndarray, mm, a point of each pixel's line (n = prod(shape)).
    direction : (n, 3) or (3,) ndarray, unit, each line's direction into the scene.
    bad : (n,) ndarray of bool, pixels the camera cannot back-project (beyond the fold of
        its distortion): their lines are NaN and their points flagged not converged.
    s_ref : (n,) ndarray, mm, the line parameter nearest the rig's working point.
    step : float, mm, the spacing of the three samples of the start.
    """

    rig: Rig
    shape: tuple
    origin: np.ndarray
    direction: np.ndarray
    bad: np.ndarray
    s_ref: np.ndarray
    step: float
    planes: tuple | None = None  #: the lines as (3, n) planes for a compiled solver

    @classmethod
    def for_shape(cls, rig, shape) -> GenericTriangulator:
        """For a full camera image of ``shape`` (rows, cols) px. Raises
        :class:`TriangulationError` when the camera declares another image size."""
        rig = _as_rig(rig)
        rows, cols = (int(n) for n in shape)
        if rows <= 0 or cols <= 0:
            raise TriangulationError(f"shape must be positive (rows, cols), got {shape}")
        size = rig.camera.image_size
        if size is not None and (size[1], size[0]) != (rows, cols):
            raise TriangulationError(
                f"the camera images are {rows} x {cols} (rows x cols) but the rig's camera "
                f"is {size[1]} x {size[0]}: the rig does not belong to this scan")
        v, u = np.mgrid[0:rows, 0:cols].astype(np.float64)
        return cls._build(rig, (rows, cols), u, v)

    @classmethod
    def for_pixels(cls, rig, u, v) -> GenericTriangulator:
        """For camera pixels at (u, v) (any shape, observed px)."""
        rig = _as_rig(rig)
        u, v = np.broadcast_arrays(np.asarray(u, dtype=np.float64),
                                   np.asarray(v, dtype=np.float64))
        return cls._build(rig, tuple(u.shape), u, v)

    @classmethod
    def _build(cls, rig: Rig, shape, u, v) -> GenericTriangulator:
        if rig.projector is None:
            raise TriangulationError("the rig has no projector: a camera + projector "
                                     "triangulation needs a calibrated projector")
        uf = np.ascontiguousarray(u, dtype=np.float64).reshape(-1)
        vf = np.ascontiguousarray(v, dtype=np.float64).reshape(-1)
        # the camera model's compiled back-projection where it has one (tested equal to
        # the protocol's), else the protocol
        lines = _gk.camera_lines(rig.camera, uf, vf)
        o, d, bad = lines if lines is not None else safe_backproject(rig.camera, uf, vf)
        P0, scale = working_point(rig.camera, rig.projector)
        s_ref = np.sum((P0 - o) * d, axis=-1)
        n = int(np.prod(shape))
        s_ref = np.broadcast_to(s_ref, (n,)).copy()
        planes = None
        if _gk.solver_for(rig.projector) is not None:
            # contiguous planes for the compiled solver (a shared point or direction is
            # repeated: the loop then reads every pixel's alike, and vectorises); the
            # per-pixel arrays become views of them
            O = np.ascontiguousarray(np.broadcast_to(o, (n, 3)).T)
            D = np.ascontiguousarray(np.broadcast_to(d, (n, 3)).T)
            o = o if o.ndim == 1 else O.T
            d = d if d.ndim == 1 else D.T
            planes = (_readonly(O), _readonly(D))
        for a in (o, d, bad, s_ref):
            _readonly(a)
        return cls(rig, tuple(shape), o, d, bad, s_ref, 0.05 * scale, planes)

    @property
    def directions(self) -> np.ndarray:
        """The cloud's directions: (3,) shared, or shape + (3,)."""
        d = self.direction
        return d if d.ndim == 1 else _readonly(d.reshape(self.shape + (3,)))

    def line_points(self, s) -> np.ndarray:
        """World points (..., 3) mm at line parameter ``s`` (shape ``shape``)."""
        s = np.asarray(s, dtype=np.float64).reshape(-1)
        X = self.origin + s[:, None] * self.direction
        return X.reshape(self.shape + (3,))

    def triangulate(self, coords, *, max_residual: float | None = 1.0,
                    max_sigma_z: float | None = None, use_v_p: bool = True,
                    check_bounds: bool = True, compiled: bool = True) -> PointCloud:
        """Triangulate decoded projector coordinates; see :func:`triangulate`."""
        obs = _observations(coords, self.shape)
        n = int(np.prod(self.shape))
        proj = self.rig.projector
        size = proj.image_size if check_bounds else None
        W, H = (float(size[0]), float(size[1])) if size is not None else (np.inf, np.inf)
        solver = _gk.solver_for(proj) if compiled and self.planes is not None else None
        out = _Out(n, empty=solver is not None)
        if solver is not None:
            self._check_sample(obs, use_v_p)
            # recycled memory: the compiled solvers write every element
            xyz = _recycle.empty((3, n))
            if obs.has_v:
                out.res = _recycle.empty(n)
            solver(proj, self.planes[0], self.planes[1], obs.a, obs.b, obs.sa, obs.sb,
                   obs.mask, obs.has_v and use_v_p, obs.swap, W, H,
                   np.inf if max_residual is None else max_residual,
                   np.inf if max_sigma_z is None else max_sigma_z, xyz, out.sig,
                   out.res, out.flags, out.ok)
            out.xyz = np.moveaxis(xyz.reshape((3,) + self.shape), 0, -1)
            return self._cloud(out)
        if obs.has_v:
            out.res = np.full(n, np.nan)
        o_full = np.broadcast_to(self.origin, (n, 3))
        d_full = np.broadcast_to(self.direction, (n, 3))
        for lo in range(0, n, _CHUNK):
            hi = min(lo + _CHUNK, n)
            sl = slice(lo, hi)
            _solve_chunk(proj, o_full[sl], d_full[sl], self.s_ref[sl], self.step,
                         self.bad[sl], obs, sl, use_v_p, max_residual, max_sigma_z, W, H, out)
        return self._cloud(out)

    def _check_sample(self, obs: _Obs, use_v_p: bool):
        """The sensitivity check of the reference path on up to 512 valid pixels, at the
        rig's working depth (the compiled solvers do not make it)."""
        n = int(np.prod(self.shape))
        idx = np.arange(0, n, max(1, n // 4096))
        idx = idx[obs.mask[idx] & np.isfinite(obs.a[idx]) & ~self.bad[idx]]
        if idx.size == 0:
            valid = obs.mask & np.isfinite(obs.a) & ~self.bad
            idx = np.flatnonzero(valid)
            if idx.size == 0:
                return
        idx = idx[np.linspace(0, idx.size - 1, min(idx.size, 512)).astype(np.intp)]
        o = np.broadcast_to(self.origin, (n, 3))[idx]
        d = np.broadcast_to(self.direction, (n, 3))[idx]
        X = o + self.s_ref[idx, None] * d
        with np.errstate(all="ignore"):
            _, _, ga, gb, na, nb = _project_slope(self.rig.projector, X, d, obs.swap)
            combine = obs.has_v and use_v_p
            ratio = np.hypot(ga, gb) / np.maximum(na, nb) if combine else np.abs(ga) / na
        _check_sensitivity(ratio[np.isfinite(ratio)], obs, use_v_p)

    def _cloud(self, out: _Out) -> PointCloud:
        xyz = out.xyz if out.xyz.ndim == 3 else out.xyz.reshape(self.shape + (3,))
        return PointCloud._adopt(xyz, out.ok.reshape(self.shape),
                                 out.sig.reshape(self.shape),
                                 None if out.res is None else out.res.reshape(self.shape),
                                 out.flags.reshape(self.shape),
                                 # the triangulator's read-only lines, shared by its clouds
                                 self.directions)


class _Out:
    """The flat outputs; ``empty``: the compiled solvers write every element."""

    def __init__(self, n, empty=False):
        if empty:  # recycled memory (telefringe._recycle)
            self.xyz = None
            self.sig = _recycle.empty(n)
            self.flags = _recycle.empty(n, dtype=np.uint8)
            self.ok = _recycle.empty(n, dtype=bool)
        else:
            self.xyz = np.full((n, 3), np.nan)
            self.sig = np.full(n, np.nan)
            self.flags = np.full(n, FLAG_NO_PHASE, dtype=np.uint8)
            self.ok = np.zeros(n, dtype=bool)
        self.res = None


@dataclass(frozen=True)
class _Obs:
    """Flat observations: ``a`` the primary axis (u, or v with v fringes only), ``b``
    the other one (None without); ``swap`` when the primary is v."""

    a: np.ndarray
    b: np.ndarray | None
    sa: np.ndarray
    sb: np.ndarray
    mask: np.ndarray
    swap: bool

    @property
    def has_v(self) -> bool:
        return self.b is not None


def _observations(coords, shape) -> _Obs:
    up, vp, su, sv, mask, swap = projector_axes(coords, shape)
    n = int(np.prod(shape))

    def flat(x):
        if x is None:  # no uncertainty given: NaN (recycled memory, filled)
            nan = _recycle.empty(n)
            nan.fill(np.nan)
            return nan
        return np.asarray(x, np.float64).reshape(n)

    m = np.ones(n, dtype=bool) if mask is None else np.asarray(mask, dtype=bool).reshape(n)
    sa = flat(su)
    # without a second axis its uncertainty is never used: no plane of NaN for it
    sb = sa if vp is None and sv is None else flat(sv)
    return _Obs(flat(up), None if vp is None else flat(vp), sa, sb, m, swap)


def _check_sensitivity(ratio, obs: _Obs, use_v_p: bool):
    """Raise where the projector coordinate barely changes along the camera lines: the
    relative slope (1 for a line along the projector's steepest direction) below 1 %."""
    if ratio.size == 0:
        return
    if float(np.median(ratio)) >= 1e-2:
        return
    if obs.has_v and use_v_p:
        raise TriangulationError(
            "the projector's image does not move with depth along the camera's lines "
            "(camera and projector axes are parallel): cannot triangulate")
    a1, a2 = ("v", "u") if obs.swap else ("u", "v")
    raise TriangulationError(
        f"{a1}_p barely changes with depth for this rig (the projector's {a1} axis is "
        f"nearly perpendicular to the camera's axis); capture {a2} fringes and "
        f"triangulate with {a2}_p")


def _project(proj, X, swap):
    """The projector's (primary, other) pixels of X (m, 3) mm (the slopes too:
    :func:`_project_slope`)."""
    u, v = proj.project(X)
    return (v, u) if swap else (u, v)


def _project_slope(proj, X, d, swap):
    """Projector pixels (primary, other) of X (m, 3) mm, their derivatives along the
    directions d (m, 3) (px / mm), and the gradients' norms (px / mm)."""
    uv, _, J = proj.project_jacobian(X)
    g = np.einsum("mij,mj->mi", J, d)
    gn = np.linalg.norm(J, axis=2)
    if swap:
        return uv[:, 1], uv[:, 0], g[:, 1], g[:, 0], gn[:, 1], gn[:, 0]
    return uv[:, 0], uv[:, 1], g[:, 0], g[:, 1], gn[:, 0], gn[:, 1]


def _moebius_start(f_m, f_0, f_p, L, target):
    """The root t of (A + B t) / (1 + C t) = target through (-L, f_m), (0, f_0), (L, f_p);
    the linear (secant) root where that fails. All arrays (m,)."""
    with np.errstate(all="ignore"):
        lin = (target - f_0) * (2.0 * L) / (f_p - f_m)
        C = (2.0 * f_0 - f_p - f_m) / (L * (f_p - f_m))
        B = (f_p * (1.0 + C * L) - f_0) / L
        t = (target - f_0) / (B - C * target)
        good = np.isfinite(t) & (1.0 + C * t > 0.0)
    return np.where(good, t, lin)


def _solve_chunk(proj, o, d, s_ref, L, bad, obs: _Obs, sl, use_v_p, max_residual,
                 max_sigma_z, W, H, out: _Out):
    """Solve the pixels of slice ``sl`` into ``out``; raises where the projector
    coordinate does not change along the lines (:func:`_check_sensitivity`)."""
    a_obs = obs.a[sl]
    b_obs = None if obs.b is None else obs.b[sl]
    combine = obs.has_v and use_v_p
    valid = obs.mask[sl] & np.isfinite(a_obs)
    if combine:
        valid &= np.isfinite(b_obs)
    out.flags[np.arange(sl.start, sl.stop)[valid & bad]] = FLAG_NOT_CONVERGED
    valid &= ~bad
    idx = np.flatnonzero(valid)
    if idx.size == 0:
        return
    o = o[idx]
    d = d[idx]
    s0 = s_ref[idx]
    ao = a_obs[idx]
    bo = None if b_obs is None else b_obs[idx]
    sa = obs.sa[sl][idx]
    sb = obs.sb[sl][idx]
    with np.errstate(divide="ignore", invalid="ignore"):
        wa = np.where(sa > 0, 1.0 / (sa * sa), 1.0)
        wb = np.where(sb > 0, 1.0 / (sb * sb), 1.0)
    # the start: three samples around the working point, a Moebius fit per axis
    fa, fb = [], []
    for k in (-1.0, 0.0, 1.0):
        pa, pb = _project(proj, o + (s0 + k * L)[:, None] * d, obs.swap)
        fa.append(pa)
        fb.append(pb)
    t = _moebius_start(fa[0], fa[1], fa[2], L, ao)
    if combine:
        tb = _moebius_start(fb[0], fb[1], fb[2], L, bo)
        use_b = np.sqrt(wb) * np.abs(fb[2] - fb[0]) > np.sqrt(wa) * np.abs(fa[2] - fa[0])
        t = np.where(use_b & np.isfinite(tb), tb, t)
    s = s0 + np.where(np.isfinite(t), t, 0.0)
    # Newton (u only) / Gauss-Newton (both axes), with step halving out of the domain
    converged = np.zeros(idx.size, dtype=bool)
    alive = np.ones(idx.size, dtype=bool)
    with np.errstate(all="ignore"):
        for it in range(_MAX_ITER):
            act = np.flatnonzero(alive & ~converged)
            if act.size == 0:
                break
            X = o[act] + s[act, None] * d[act]
            pa, pb, ga, gb, na, nb = _project_slope(proj, X, d[act], obs.swap)
            if it == 0:
                ratio = (np.hypot(ga, gb) / np.maximum(na, nb) if combine
                         else np.abs(ga) / na)
                _check_sensitivity(ratio[np.isfinite(ratio)], obs, use_v_p)
            if combine:
                ra = pa - ao[act]
                rb = pb - bo[act]
                step = ((wa[act] * ga * ra + wb[act] * gb * rb)
                        / (wa[act] * ga * ga + wb[act] * gb * gb))
            else:
                step = (pa - ao[act]) / ga
            lost = ~np.isfinite(step)
            alive[act[lost]] = False
            step = np.where(lost, 0.0, step)
            s_new = s[act] - step
            # halve steps whose point leaves the projector's domain
            for _ in range(30):
                pa_n, _ = _project(proj, o[act] + s_new[:, None] * d[act], obs.swap)
                out_of = ~np.isfinite(pa_n) & ~lost
                if not out_of.any():
                    break
                step = np.where(out_of, 0.5 * step, step)
                s_new = s[act] - step
            s[act] = s_new
            converged[act] = (np.abs(step) <= _TOL_S * (1.0 + np.abs(s_new))) & ~lost
    # the final projection, slopes, residual and sigma
    X = o + s[:, None] * d
    pa, pb, ga, gb, _, _ = _project_slope(proj, X, d, obs.swap)
    with np.errstate(all="ignore"):
        if combine:
            sg = 1.0 / np.sqrt(ga * ga / (sa * sa) + gb * gb / (sb * sb))
        else:
            sg = sa / np.abs(ga)
        res = np.hypot(pa - ao, pb - bo) if obs.has_v else None
    up, vp = (pb, pa) if obs.swap else (pa, pb)
    inside = (up >= -0.5) & (up <= W - 0.5) & (vp >= -0.5) & (vp <= H - 0.5)
    converged &= alive & np.isfinite(s) & _round_trip(proj, X, up, vp)
    dz = np.abs(d[:, 2])
    f = np.zeros(idx.size, dtype=np.uint8)
    with np.errstate(invalid="ignore"):
        if res is not None and max_residual is not None:
            f |= np.where(res > max_residual, FLAG_INCONSISTENT, 0).astype(np.uint8)
        f |= np.where(inside, 0, FLAG_OUTSIDE).astype(np.uint8)
        f |= np.where(converged, 0, FLAG_NOT_CONVERGED).astype(np.uint8)
        if max_sigma_z is not None:
            f |= np.where(sg * dz > max_sigma_z, FLAG_UNCERTAIN, 0).astype(np.uint8)
    gi = np.arange(sl.start, sl.stop)[idx]
    out.flags[gi] = f
    good = f == 0
    out.ok[gi] = good
    out.sig[gi] = np.where(good, sg, np.nan)
    out.xyz[gi] = np.where(good[:, None], X, np.nan)
    if res is not None:
        out.res[gi] = res


def _round_trip(proj, X, u, v):
    """(m,) bool: the projector's line through its pixel (u, v) passes through X (to
    1e-6 mm): false beyond the fold of its distortion, where the projection is not
    invertible, or where it cannot back-project."""
    ok = np.isfinite(u) & np.isfinite(v)
    if not ok.any():
        return ok
    i = np.flatnonzero(ok)
    o, d, bad = safe_backproject(proj, u[i], v[i])
    o = np.broadcast_to(o, (i.size, 3))
    d = np.broadcast_to(d, (i.size, 3))
    with np.errstate(all="ignore"):
        w = X[i] - o
        along = np.einsum("ij,ij->i", w, d)
        dist = np.linalg.norm(w - along[:, None] * d, axis=1)
        good = ~bad & (dist <= _ROUND_TRIP_TOL * (1.0 + np.abs(along)))
    ok[i] = good
    return ok


# --------------------------------------------------------------------------------------
# Cache and public functions
# --------------------------------------------------------------------------------------
#: Bytes the per-process cache of :class:`GenericTriangulator` may hold (per-pixel lines of
#: a camera with a pinhole projector: 74 MB for 1280 x 1024).
GENERIC_CACHE_BYTES = 160 * 2**20


class _Cache:
    """(rig, shape) -> GenericTriangulator, least recently used dropped first."""

    def __init__(self, max_bytes):
        self.max_bytes = int(max_bytes)
        self._lock = threading.Lock()
        self._items: OrderedDict[tuple, GenericTriangulator] = OrderedDict()

    @staticmethod
    def _size(t):
        planes = 0 if t.planes is None else sum(p.nbytes for p in t.planes)
        own = sum(a.nbytes for a in (t.origin, t.direction) if a.base is None)
        return int(own + planes + t.s_ref.nbytes + t.bad.nbytes)

    def get(self, rig, shape, build):
        key = (id(rig), tuple(shape))
        with self._lock:
            t = self._items.get(key)
            if t is not None and t.rig is rig:
                self._items.move_to_end(key)
                return t
        t = build(rig, shape)
        if self._size(t) > self.max_bytes:
            return t
        with self._lock:
            self._items[key] = t
            while sum(self._size(x) for x in self._items.values()) > self.max_bytes:
                self._items.popitem(last=False)
        return t

    def clear(self):
        with self._lock:
            self._items.clear()


_CACHE = _Cache(GENERIC_CACHE_BYTES)


def triangulate(rig, coords, *, max_residual: float | None = 1.0,
                max_sigma_z: float | None = None, use_v_p: bool = True,
                check_bounds: bool = True, compiled: bool = True) -> PointCloud:
    """Triangulate decoded projector coordinates with any camera and projector.

    Parameters
    ----------
    rig : Rig (or an object holding one as ``.rig``, like ``load_rig``'s result)
        A calibrated camera and projector, any models (world frame in mm).
    coords : object with attributes ``u_p``, ``v_p``, ``mask``, ``sigma_u_p``, ``sigma_v_p``
        ``u_p`` (rows, cols) projector columns (px) per camera pixel, NaN where invalid;
        ``v_p`` projector rows (px) or None (with v fringes only, ``u_p`` may be None);
        ``mask`` (rows, cols) bool or None; ``sigma_u_p`` / ``sigma_v_p`` standard
        uncertainties (projector px) or None (then the result's uncertainties are NaN
        and both axes weigh the same).
    max_residual : float or None, keyword-only
        With ``v_p``: points whose observed projector pixel is farther than this
        (projector px) from the predicted one are invalid (``FLAG_INCONSISTENT``). None:
        no check.
    max_sigma_z : float or None, keyword-only
        Points with a larger standard uncertainty of Z (mm) are invalid (``FLAG_UNCERTAIN``).
    use_v_p : bool, keyword-only
        Combine ``v_p`` with ``u_p`` (default); when false, ``v_p`` only checks.
    check_bounds : bool, keyword-only
        Flag solutions outside the projector's image (when it declares its size).
    compiled : bool, keyword-only
        Use the projector model's compiled solver where there is one (a pinhole
        projector; the same equations, tolerance and flags, tested against this path);
        False: the NumPy reference.

    Returns
    -------
    PointCloud
        ``xyz`` (rows, cols, 3) mm, NaN where invalid; ``directions`` (3,) for a
        telecentric camera, (rows, cols, 3) for a pinhole one; ``sigma_line`` (mm along
        each line); ``residual`` (projector px) with ``v_p``; ``flags``.

    Raises
    ------
    TriangulationError
        For shapes that do not fit, a camera of another image size, a rig without a
        projector, or a projector coordinate that does not change with depth.

    Notes
    -----
    The per-rig lines are cached per process (see ``GENERIC_CACHE_BYTES``).
    """
    up = getattr(coords, "u_p", None)
    if up is None:
        up = getattr(coords, "v_p", None)
        if up is None:
            raise TriangulationError("coords has neither u_p nor v_p")
    shape = tuple(int(n) for n in np.shape(up))
    if len(shape) != 2:
        raise TriangulationError(f"u_p must be a (rows, cols) array, got shape {shape}")
    tri = _CACHE.get(_as_rig(rig), shape, GenericTriangulator.for_shape)
    return tri.triangulate(coords, max_residual=max_residual, max_sigma_z=max_sigma_z,
                           use_v_p=use_v_p, check_bounds=check_bounds, compiled=compiled)


def triangulate_pixels(rig, u_c, v_c, u_p, v_p=None, *, sigma_u_p=None, sigma_v_p=None,
                       max_residual: float | None = None, compiled: bool = True) -> PointCloud:
    """Triangulate arbitrary (sub-pixel) camera pixels, e.g. marker centres.

    Parameters
    ----------
    rig : Rig, any camera and projector models.
    u_c, v_c : (n,) array_like of float, camera pixels (observed px).
    u_p, v_p : (n,) array_like of float, the projector pixels seen there (``v_p`` may be
        None; ``u_p`` may be None when ``v_p`` is given).
    sigma_u_p, sigma_v_p : (n,) array_like or None, their standard uncertainties (px).
    max_residual : float or None, as in :func:`triangulate` (default: no check).
    compiled : bool, as in :func:`triangulate`.

    Returns
    -------
    PointCloud
        With ``shape == (1, n)``; ``cloud.xyz[0]`` is the (n, 3) array of points (mm).
        No projector bounds are checked.
    """
    u_c, v_c, c = pixel_rows(u_c, v_c, u_p, v_p, sigma_u_p, sigma_v_p)
    tri = GenericTriangulator.for_pixels(rig, u_c, v_c)
    return tri.triangulate(c, max_residual=max_residual, check_bounds=False,
                           compiled=compiled)
