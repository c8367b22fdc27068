"""Two cameras, the projector giving the phase only: match equal absolute phase along
epipolar lines, triangulate the two rays.

Written against the :class:`~telefringe.devices.base.Device` protocol only, for any two
cameras (telecentric or pinhole); the projector need not be calibrated, its decoded
coordinates (``u_P``, and ``v_P`` when present) only label the surface points.

Per pixel of the first camera, its line ``X(s) = o + s d`` (``d`` unit, ``s`` mm) is
projected into the second camera: the image of that line is the epipolar line (a
straight line for undistorted cameras, pinhole or telecentric; curved by distortion, which
projecting the 3D line handles exactly). Along it the second camera's projector coordinate
``u_P2(s)`` (bilinear interpolation of its decoded map, valid only where the four
neighbours are) is sampled over the search range, the bracket where it crosses the first
camera's ``u_P1`` is found, and the crossing is refined to 1e-9 projector px by the
Illinois variant of false position. With both fringe axes the point is then moved to the
maximum-likelihood solution of the two equations along the line (Gauss-Newton), each axis
weighted by ``1 / (sigma_1^2 + sigma_2^2)``.

The matched point of the second camera lies on the epipolar line, so the two rays meet:
the point is the least-squares (midpoint) intersection of the first camera's ray and the
second camera's ray through the matched sub-pixel, which is ``X(s)``; their distance is
kept as a check of the second camera's back-projection (above 1e-6 mm: flagged not
converged).

Flags (``PointCloud.flags``): ``FLAG_NO_PHASE`` no valid phase in the first camera or no
valid neighbourhood in the second at the match; ``FLAG_OUTSIDE`` no crossing within the
search range inside the second camera's image (occluded or out of its view);
``FLAG_INCONSISTENT`` more than one crossing (the data cannot decide), a match in a cell
of the second camera across a jump of its phase (an occlusion edge: more than 5 times the
map's median cell range) or, with both axes, a mismatch of the projector pixel above
``max_residual``; ``FLAG_NOT_CONVERGED``;
``FLAG_UNCERTAIN`` sigma_z above ``max_sigma_z``.

Uncertainty: the match solves ``u_P2(s) = u_P1``; both decoded values are noisy, so
``sigma_s = sqrt(sigma_1^2 + sigma_2^2) / |du_P2/ds|`` with ``du_P2/ds`` the phase
gradient along the epipolar line (px of projector per mm of line) and ``sigma_2^2`` the
interpolated variance ``sum w_i^2 sigma_i^2`` of the four neighbours' (bilinear weights
w_i); with both axes ``sigma_s^{-2} = sum_axes (du_P2/ds)^2 / (sigma_1^2 + sigma_2^2)``.
The point moves along the first camera's line: ``sigma_line = sigma_s``.

Neighbouring points' errors are correlated: the matches of neighbouring pixels of the
first camera interpolate the same pixels of the second (:func:`match_noise` gives each
point's error as its own part plus weighted shares of the second camera's pixels'
independent noise, from which a fit builds the exact covariance of its points;
:func:`match_noise_maps` its compact form, which ``telefringe reconstruct --second`` keeps
in points.npz for ``measure_sphere(..., noise=)`` and ``fit_plane(..., noise=)``).

Engines: the compiled matcher (:mod:`telefringe.reconstruction._stereo_kernels`, numba,
parallel over the first camera's rows) runs the same samples, brackets and iterations per
pixel for a pinhole or telecentric second camera; where a line leaves the second camera's
image it solves the projection for the border (to 1e-10 px) instead of bisecting. The
NumPy path below is the reference it is tested against (same flags, points within 1e-9
mm: tests/test_stereo_kernels.py) and serves any other Device. Speed:
``benchmarks/stereo.py``.

Accuracy (issue 11, ``stereo`` preset binned 4, held-out plate): with the true rig the
match is unbiased (-0.025 um on the plate from rendered, decoded scans; -0.008 um from the
true phase maps), so the plate offset of a calibrated rig is the calibration's: +0.27 um
(z 1.8, 0.08 of the per-pixel sigma_z) with 12 poses (``benchmarks/anyrig.py --rig stereo
--bin 4 --poses 12 --mc 6``), all of it from the detected camera centres (the true
centres give -0.008 um: ``benchmarks/detector_bias.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from telefringe.devices.rig import Rig
from telefringe.geometry.interpolation import bilinear
from telefringe.reconstruction import _generic_kernels as _gk
from telefringe.reconstruction import _stereo_kernels as _sk
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
)
from telefringe.reconstruction.generic import safe_backproject, working_point

__all__ = ["StereoMatch", "StereoNoise", "StereoNoiseMaps", "match_stereo", "match_noise",
           "match_noise_maps", "triangulate_stereo", "search_range", "stereo_rig"]

_CHUNK = 4096
_TOL_F = 1e-9  # projector px
_MAX_ITER = 60
_GAP_TOL = 1e-6  # mm, the two rays' distance at the match
_SAMPLE_PX = 16.0  # spacing of the bracketing samples in the second camera, px


@dataclass(frozen=True, eq=False)
class StereoMatch:
    """What :func:`match_stereo` finds.

    Attributes
    ----------
    cloud : PointCloud
        On the first camera's pixel grid (rows, cols), mm; directions the first camera's.
    u2, v2 : (rows, cols) ndarray of float
        The matched sub-pixel of the second camera (px), NaN where there is no match.
    """

    cloud: PointCloud
    u2: np.ndarray
    v2: np.ndarray


@dataclass(frozen=True, eq=False)
class StereoNoise:
    """The matched points' errors along the first camera's lines, as independent parts
    (:func:`match_noise`): the error of the point at a pixel is

        delta_s = e + sum_q weights[..., q] z[sources[..., q]]

    with ``e`` the first camera's own part (independent per point, variance ``var_own``)
    and ``z`` independent unit-variance sources, one per pixel and axis of the second
    camera, shared by every match whose bilinear cell reads that pixel. The covariance of
    two points is ``delta_kl var_own_k + sum over their common sources of the weights'
    products``; ``var_own + sum_q weights^2`` is the cloud's ``sigma^2``.

    Attributes
    ----------
    var_own : (rows, cols) mm^2, NaN where the cloud has no point.
    weights : (rows, cols, K) mm per unit source (K = 4 per axis matched), 0 where none.
    sources : (rows, cols, K) int64, ``axis * pixels_2 + row_2 * cols_2 + col_2`` (axis 0
        the primary, 1 the other), -1 where none.
    """

    var_own: np.ndarray
    weights: np.ndarray
    sources: np.ndarray


def _two_cameras(rig) -> tuple:
    rig = _as_rig(rig)
    if len(rig.cameras) < 2:
        raise TriangulationError(
            f"stereo needs a rig with two cameras, this one has {len(rig.cameras)} "
            f"({', '.join(rig.camera_names)})")
    names = rig.camera_names
    return rig, rig.cameras[names[0]], rig.cameras[names[1]]


def search_range(cam1, cam2) -> tuple[np.ndarray, float]:
    """The default search: the rig's working point (where the two cameras' central rays
    come closest, world mm) and the half-length (mm) searched along each line around it:
    the diagonal of the first camera's field there (depths within one field diagonal of
    the working point are found)."""
    P0, _ = working_point(cam1, cam2)
    size = cam1.image_size
    if size is None:
        raise TriangulationError("the first camera declares no image size: give search_mm")
    w, h = size
    cu = np.array([0.0, w - 1.0, 0.0, w - 1.0])
    cv = np.array([0.0, 0.0, h - 1.0, h - 1.0])
    o, d, bad = safe_backproject(cam1, cu, cv)
    o = np.broadcast_to(o, (4, 3))
    d = np.broadcast_to(d, (4, 3))
    s = np.sum((P0 - o) * d, axis=1)
    pts = o + s[:, None] * d
    half = float(np.nanmax(np.linalg.norm(pts[:, None] - pts[None], axis=2)))
    if not np.isfinite(half) or half <= 0:
        raise TriangulationError("cannot size the stereo search from the first camera's "
                                 "corners: give search_mm")
    return P0, half


def _axes(coords_1, coords_2, use_v_p):
    """Primary axis name and whether the other combines."""
    has = {ax: getattr(coords_1, f"{ax}_p", None) is not None
           and getattr(coords_2, f"{ax}_p", None) is not None for ax in ("u", "v")}
    if not (has["u"] or has["v"]):
        raise TriangulationError("the two cameras' coordinates share no projector axis "
                                 "(u_p or v_p in both)")
    primary = "u" if has["u"] else "v"
    other = "v" if primary == "u" else "u"
    return primary, (other if has[other] else None), has[other] and use_v_p


def _maps(coords, shape, label):
    up = getattr(coords, "u_p", None)
    ref = up if up is not None else getattr(coords, "v_p", None)
    sh = np.shape(ref)
    if shape is not None and sh != tuple(shape):
        raise TriangulationError(f"{label}: the coordinates have shape {sh}, expected "
                                 f"{tuple(shape)}")
    mask = getattr(coords, "mask", None)
    m = np.ones(sh, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    if m.shape != sh:
        raise TriangulationError(f"{label}: mask has shape {m.shape}, expected {sh}")
    out = {}
    for ax in ("u", "v"):
        a = getattr(coords, f"{ax}_p", None)
        s = getattr(coords, f"sigma_{ax}_p", None)
        if a is not None:
            a = np.asarray(a, dtype=np.float64)
            if a.shape != sh:
                raise TriangulationError(f"{label}: {ax}_p has shape {a.shape}, expected {sh}")
            a = np.where(m, a, np.nan)
        if s is not None:
            s = np.asarray(s, dtype=np.float64)
            if s.shape != sh:
                raise TriangulationError(f"{label}: sigma_{ax}_p has shape {s.shape}, "
                                         f"expected {sh}")
        out[ax] = (a, s)
    return sh, out


def _interp_var(S, corners):
    """Variance of a bilinear interpolation of independent values of std S."""
    i, j, fx, fy = corners
    w = ((1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy)
    s = (S[i, j], S[i, j + 1], S[i + 1, j], S[i + 1, j + 1])
    return sum(wk * wk * sk * sk for wk, sk in zip(w, s, strict=True))


def match_stereo(rig, coords_1, coords_2, *, max_residual: float | None = 1.0,
                 max_sigma_z: float | None = None, use_v_p: bool = True,
                 search_mm: float | None = None, engine: str = "auto") -> StereoMatch:
    """Match equal absolute projector phase along epipolar lines and triangulate.

    Parameters
    ----------
    rig : Rig with two cameras (the first is the reference: the cloud is on its grid); a
        projector is not needed.
    coords_1, coords_2 : decoded coordinates of each camera (attributes ``u_p``, ``v_p``,
        ``mask``, ``sigma_u_p``, ``sigma_v_p`` as for
        :func:`telefringe.reconstruction.generic.triangulate`), (rows, cols) of each
        camera's images, projector px.
    max_residual : float or None
        With both axes in both cameras: points whose two projector coordinates disagree
        between the cameras by more than this (projector px, after the match) are invalid.
    max_sigma_z : float or None
        Points with a larger standard uncertainty of Z (mm) are invalid.
    use_v_p : bool
        Combine the second axis into the match (default); when false it only checks.
    search_mm : float or None
        Half-length (mm) of each line searched around the rig's working point (default:
        the diagonal of the first camera's field there; see :func:`search_range`).
    engine : "auto" | "compiled" | "numpy"
        The compiled matcher (parallel over rows; "auto" takes it where the second
        camera's model has one: pinhole and telecentric) or the NumPy reference (any
        Device); both give the same points, to the iterations' tolerance.

    Returns
    -------
    StereoMatch
    """
    if engine not in ("auto", "compiled", "numpy"):
        raise TriangulationError(f"engine must be 'auto', 'compiled' or 'numpy', got "
                                 f"{engine!r}")
    rig, cam1, cam2 = _two_cameras(rig)
    if engine == "compiled" and not _sk.has_kernel(cam2):
        raise TriangulationError(f"no compiled matcher for a second camera of model "
                                 f"{getattr(cam2, 'model', None)!r}: use engine='numpy'")
    size1 = cam1.image_size
    shape1 = None if size1 is None else (size1[1], size1[0])
    shape1, m1 = _maps(coords_1, shape1, "first camera")
    size2 = cam2.image_size
    shape2, m2 = _maps(coords_2, None if size2 is None else (size2[1], size2[0]),
                       "second camera")
    primary, other, combine = _axes(coords_1, coords_2, use_v_p)
    P0, half = search_range(cam1, cam2) if search_mm is None else (
        working_point(cam1, cam2)[0], float(search_mm))
    if not (half > 0):
        raise TriangulationError(f"search_mm must be > 0, got {search_mm}")
    rows, cols = shape1
    n = rows * cols
    # samples: about one per _SAMPLE_PX px of the epipolar line in the second camera
    # (measured on the line of the central pixel)
    k_c = n // 2 + cols // 2
    o_c, d_c, _ = safe_backproject(cam1, np.array([float(k_c % cols)]),
                                   np.array([float(k_c // cols)]))
    o_c, d_c = np.reshape(o_c, (-1, 3))[0], np.reshape(d_c, (-1, 3))[0]
    s_c = float(np.sum((P0 - o_c) * d_c))
    ends = o_c + np.array([s_c - half, s_c + half])[:, None] * d_c
    eu, ev = cam2.project(ends)
    length = float(np.hypot(eu[1] - eu[0], ev[1] - ev[0]))
    if not np.isfinite(length):
        length = float(max(shape2))
    n_samples = int(np.clip(np.ceil(length / _SAMPLE_PX) + 1, 16, 2048))
    offsets = np.linspace(-half, half, n_samples)
    if engine != "numpy" and _sk.has_kernel(cam2):
        return _match_compiled(cam1, cam2, shape1, m1, m2, primary, other, combine, P0,
                               offsets, max_residual, max_sigma_z)

    v, u = np.mgrid[0:rows, 0:cols].astype(np.float64)
    o, d, bad = safe_backproject(cam1, u.reshape(-1), v.reshape(-1))
    o_f = np.broadcast_to(o, (n, 3))
    d_f = np.broadcast_to(d, (n, 3))
    s_ref = np.sum((P0 - o_f) * d_f, axis=1)
    out_xyz = np.full((n, 3), np.nan)
    out_sig = np.full(n, np.nan)
    out_res = np.full(n, np.nan) if other is not None else None
    out_flags = np.full(n, FLAG_NO_PHASE, dtype=np.uint8)
    out_u2 = np.full(n, np.nan)
    out_v2 = np.full(n, np.nan)
    A1, S1 = (x.reshape(-1) if x is not None else None for x in m1[primary])
    A2, S2 = m2[primary]
    jump = _jump_threshold(A2)
    if other is not None:
        B1, T1 = (x.reshape(-1) if x is not None else None for x in m1[other])
        B2, T2 = m2[other]
    for lo in range(0, n, _CHUNK):
        hi = min(lo + _CHUNK, n)
        idx = np.arange(lo, hi)
        valid = np.isfinite(A1[idx]) & ~bad[idx]
        if combine:
            valid &= np.isfinite(B1[idx])
        out_flags[idx[bad[idx] & np.isfinite(A1[idx])]] = FLAG_NOT_CONVERGED
        idx = idx[valid]
        if idx.size == 0:
            continue
        oo, dd, sr = o_f[idx], d_f[idx], s_ref[idx]
        target = A1[idx]

        def f_at(s, oo=oo, dd=dd, target=target, sel=None):
            if sel is not None:
                oo, dd, target = oo[sel], dd[sel], target[sel]
            X = oo + s[..., None] * dd
            u2, v2 = cam2.project(X)
            val = bilinear(A2, u2, v2)[0]
            return val - target

        with np.errstate(all="ignore"):
            S = sr[:, None] + offsets[None, :]
            X = oo[:, None, :] + S[..., None] * dd[:, None, :]
            u2, v2 = cam2.project(X)
            F = bilinear(A2, u2, v2)[0] - target[:, None]
            crossing = (np.isfinite(F[:, :-1]) & np.isfinite(F[:, 1:])
                        & ((F[:, :-1] <= 0) != (F[:, 1:] <= 0)))
        n_cross = crossing.sum(axis=1)
        k = np.argmax(crossing, axis=1)
        rows_ = np.arange(idx.size)
        a = S[rows_, k]
        b = S[rows_, k + 1]
        fa = F[rows_, k]
        fb = F[rows_, k + 1]
        # a crossing between the last valid sample and the edge of the valid phase (of
        # the image, or of a hole): find that edge by bisection and test it too
        fin = np.isfinite(F)
        pi, pk = np.nonzero(fin[:, :-1] != fin[:, 1:])
        if pi.size:
            good_k = np.where(fin[pi, pk], pk, pk + 1)  # the finite sample
            lo_s = S[pi, good_k]
            hi_s = S[pi, np.where(fin[pi, pk], pk + 1, pk)]
            f_lo = F[pi, good_k]
            for _ in range(40):
                mid_s = 0.5 * (lo_s + hi_s)
                f_mid = f_at(mid_s, sel=pi)
                ok_mid = np.isfinite(f_mid)
                lo_s = np.where(ok_mid, mid_s, lo_s)
                hi_s = np.where(ok_mid, hi_s, mid_s)
            f_edge = f_at(lo_s, sel=pi)
            edge = np.isfinite(f_edge) & ((f_edge <= 0) != (f_lo <= 0))
            pi, ea, eb = pi[edge], S[pi[edge], good_k[edge]], lo_s[edge]
            fea, feb = f_lo[edge], f_edge[edge]
            np.add.at(n_cross, pi, 1)
            # the pixels whose only crossing is at an edge take that bracket
            a[pi], b[pi], fa[pi], fb[pi] = ea, eb, fea, feb
        flags = np.zeros(idx.size, dtype=np.uint8)
        flags[n_cross == 0] = FLAG_OUTSIDE
        flags[n_cross > 1] = FLAG_INCONSISTENT
        one = np.flatnonzero(n_cross == 1)
        a, b, fa, fb = a[one], b[one], fa[one], fb[one]
        s = b.copy()
        done = np.zeros(one.size, dtype=bool)
        failed = np.zeros(one.size, dtype=bool)
        with np.errstate(all="ignore"):
            for _ in range(_MAX_ITER):
                act = np.flatnonzero(~done & ~failed)
                if act.size == 0:
                    break
                c = (a[act] * fb[act] - b[act] * fa[act]) / (fb[act] - fa[act])
                fc = f_at(c, sel=one[act])
                nan = ~np.isfinite(fc)
                failed[act[nan]] = True
                same = (fc * fb[act]) > 0  # c on b's side: the retained end a is halved
                # Illinois: keep the end of the other sign; halve it when kept twice
                a_new = np.where(same, a[act], b[act])
                fa_new = np.where(same, 0.5 * fa[act], fb[act])
                a[act] = a_new
                fa[act] = fa_new
                b[act] = c
                fb[act] = fc
                s[act] = c
                width = np.abs(b[act] - a[act])
                done[act] = (np.abs(fc) <= _TOL_F) | (width <= 1e-13 * (1.0 + np.abs(c)))
        sol = one[done & ~failed]
        flags[one[failed]] = FLAG_NO_PHASE
        flags[one[~done & ~failed]] = FLAG_NOT_CONVERGED
        s_sol = s[done & ~failed]
        gi = idx[sol]
        oo_s, dd_s = oo[sol], dd[sol]
        if combine and sol.size:
            # ML along the line with both axes: Gauss-Newton from the primary root, each
            # axis weighted by 1 / (sigma_1^2 + sigma_2^2) (equal weights without sigmas)
            with np.errstate(all="ignore"):
                X0 = oo_s + s_sol[:, None] * dd_s
                corners = bilinear(A2, *cam2.project(X0))[3]
                wa = 1.0 / _pair_var(S1, S2, gi, corners)
                wb = 1.0 / _pair_var(T1, T2, gi, corners)
                for _ in range(10):
                    ga, gb, fa_, fb_ = _slopes(cam2, A2, B2, oo_s, dd_s, s_sol, A1[gi], B1[gi])
                    wa_ = np.where(np.isfinite(wa), wa, 1.0)
                    wb_ = np.where(np.isfinite(wb), wb, 1.0)
                    step = ((wa_ * ga * fa_ + wb_ * gb * fb_) / (wa_ * ga * ga + wb_ * gb * gb))
                    step = np.where(np.isfinite(step), step, 0.0)
                    s_sol = s_sol - step
                    if np.all(np.abs(step) <= 1e-12 * (1.0 + np.abs(s_sol))):
                        break
        X = oo_s + s_sol[:, None] * dd_s
        with np.errstate(all="ignore"):
            u2s, v2s = cam2.project(X)
            va, ga_u, ga_v, corners = bilinear(A2, u2s, v2s)
            # along-line slope of the second camera's phase: gradient . dp2/ds
            _, _, J = cam2.project_jacobian(X)
            dp = np.einsum("mij,mj->mi", J, dd_s)
            ga = ga_u * dp[:, 0] + ga_v * dp[:, 1]
            var_a = _pair_var(S1, S2, gi, corners)
            if combine:
                vb, gb_u, gb_v, _ = bilinear(B2, u2s, v2s)
                gb = gb_u * dp[:, 0] + gb_v * dp[:, 1]
                var_b = _pair_var(T1, T2, gi, corners)
                sg = 1.0 / np.sqrt(ga * ga / var_a + gb * gb / var_b)
            else:
                sg = np.sqrt(var_a) / np.abs(ga)
            f = np.zeros(sol.size, dtype=np.uint8)
            if other is not None:
                vb = bilinear(B2, u2s, v2s)[0]
                pa = va - A1[gi]
                pb = vb - B1[gi]
                res = np.hypot(pa, pb)
                if max_residual is not None:
                    f |= np.where(res > max_residual, FLAG_INCONSISTENT, 0).astype(np.uint8)
                out_res[gi] = res
            # the second camera's ray through the match: the midpoint of the two rays and
            # their distance (zero on the epipolar line, up to the back-projection)
            o2, d2, bad2 = safe_backproject(cam2, u2s, v2s)
            mid, gap = _midpoint(oo_s, dd_s, np.broadcast_to(o2, X.shape),
                                 np.broadcast_to(d2, X.shape))
            ok_gap = ~bad2 & (gap <= _GAP_TOL)
            f |= np.where(ok_gap, 0, FLAG_NOT_CONVERGED).astype(np.uint8)
            f |= np.where(np.isfinite(va), 0, FLAG_NO_PHASE).astype(np.uint8)
            # a cell of the second camera across a jump of the phase (an occlusion edge:
            # two surfaces in one cell) interpolates a phase no surface has
            f |= np.where(_cell_range(A2, corners) <= jump, 0, FLAG_INCONSISTENT).astype(
                np.uint8)
            if max_sigma_z is not None:
                f |= np.where(sg * np.abs(dd_s[:, 2]) > max_sigma_z, FLAG_UNCERTAIN,
                              0).astype(np.uint8)
        flags[sol] = f
        out_flags[idx] = flags
        good = f == 0
        out_xyz[gi[good]] = mid[good]
        out_sig[gi[good]] = sg[good]
        out_u2[gi] = u2s
        out_v2[gi] = v2s
    ok = out_flags == 0
    shp = (rows, cols)
    dirs = np.array(d) if np.ndim(d) == 1 else np.array(d).reshape(shp + (3,))
    cloud = PointCloud._adopt(out_xyz.reshape(shp + (3,)), ok.reshape(shp),
                              out_sig.reshape(shp),
                              None if out_res is None else out_res.reshape(shp),
                              out_flags.reshape(shp), _readonly(dirs))
    return StereoMatch(cloud, _readonly(out_u2.reshape(shp)), _readonly(out_v2.reshape(shp)))


def _match_compiled(cam1, cam2, shape1, m1, m2, primary, other, combine, P0, offsets,
                    max_residual, max_sigma_z) -> StereoMatch:
    """The compiled path of :func:`match_stereo` (same results as the NumPy path below it
    in that function, to the iterations' tolerance)."""
    rows, cols = shape1
    n = rows * cols
    vg, ug = np.mgrid[0:rows, 0:cols].astype(np.float64)
    uf, vf = ug.reshape(-1), vg.reshape(-1)
    lines = _gk.camera_lines(cam1, uf, vf)
    o, d, bad = lines if lines is not None else safe_backproject(cam1, uf, vf)
    # writeable C arrays throughout: numba compiles (and caches) one signature
    O = _c(np.reshape(o, (-1, 3)))
    D = _c(np.reshape(d, (-1, 3)))
    bad = np.require(bad, np.bool_, ["C", "W"])
    none1 = np.empty(1)
    none2 = np.empty((2, 2))

    def flat(x):
        return none1 if x is None else _c(x.reshape(-1))

    def full(x):
        return none2 if x is None else _c(x)

    A1, S1 = m1[primary]
    A2, S2 = m2[primary]
    B1, T1 = m1[other] if other is not None else (None, None)
    B2, T2 = m2[other] if other is not None else (None, None)
    intr, R, t = _gk._ARGS[cam2.model](cam2)
    s_out = np.full(n, np.nan)
    u2 = np.empty(n)
    v2 = np.empty(n)
    sig = np.empty(n)
    res = np.empty(n)
    flags = np.empty(n, dtype=np.uint8)
    matched = np.empty(n, dtype=np.uint8)
    _sk.match_all(rows, cols, O, D, bad, _c(P0), _c(offsets), flat(A1), flat(S1),
                  flat(B1), flat(T1), full(A2), full(S2), full(B2), full(T2), S1 is not None,
                  S2 is not None, T1 is not None, T2 is not None, other is not None,
                  bool(combine), tuple(float(x) for x in intr), _c(R), _c(t),
                  _jump_threshold(A2),
                  np.inf if max_residual is None else float(max_residual),
                  np.inf if max_sigma_z is None else float(max_sigma_z), _TOL_F, _MAX_ITER,
                  s_out, u2, v2, sig, res, flags, matched)
    # the second camera's ray through each match: the least-squares intersection and the
    # rays' distance (zero on the epipolar line, up to the back-projection)
    gi = np.flatnonzero(matched)
    oo = O[0] if O.shape[0] == 1 else O[gi]
    dd = D[0] if D.shape[0] == 1 else D[gi]
    X = oo + s_out[gi, None] * dd
    lines2 = _gk.camera_lines(cam2, u2[gi], v2[gi])
    o2, d2, bad2 = lines2 if lines2 is not None else safe_backproject(cam2, u2[gi], v2[gi])
    with np.errstate(all="ignore"):
        mid, gap = _midpoint(np.broadcast_to(oo, X.shape), np.broadcast_to(dd, X.shape),
                             np.broadcast_to(o2, X.shape), np.broadcast_to(d2, X.shape))
    flags[gi] |= np.where(~bad2 & (gap <= _GAP_TOL), 0, FLAG_NOT_CONVERGED).astype(np.uint8)
    ok = flags == 0
    xyz = np.full((n, 3), np.nan)
    xyz[gi[ok[gi]]] = mid[ok[gi]]
    sig[~ok] = np.nan
    shp = (rows, cols)
    dirs = D[0].copy() if D.shape[0] == 1 else D.reshape(shp + (3,))
    cloud = PointCloud._adopt(xyz.reshape(shp + (3,)), ok.reshape(shp), sig.reshape(shp),
                              None if other is None else res.reshape(shp),
                              flags.reshape(shp), _readonly(dirs))
    return StereoMatch(cloud, _readonly(u2.reshape(shp)), _readonly(v2.reshape(shp)))


@dataclass(frozen=True, eq=False)
class StereoNoiseMaps:
    """:class:`StereoNoise` in the compact form a file keeps (``points.npz``), from which
    :meth:`expand` rebuilds it exactly: per point of the first camera's grid the matched
    sub-pixel of the second camera and the coefficient of each axis, and the second
    camera's sigma maps.

    Attributes
    ----------
    u2, v2 : (rows, cols) px, the matched sub-pixel of the second camera, NaN where the
        cloud has no point.
    var_own : (rows, cols) mm^2, the first camera's own part (NaN where no point).
    coef : (rows, cols, A) mm per projector px, ``c_a`` of each axis matched (A = 1 or
        2; axis 0 the primary) (NaN where no point).
    sigma_2 : (A, rows_2, cols_2) projector px, the second camera's ``sigma_u_p`` /
        ``sigma_v_p`` of the same axes.

    The point at a pixel moves along the first camera's line by ``e - sum_a c_a sum_i w_i
    sigma_2[a, pixel_i] z_(a, pixel_i)`` (``w_i`` the bilinear weights of the cell at
    (u2, v2), as :func:`telefringe.geometry.interpolation.bilinear` takes it).
    """

    u2: np.ndarray
    v2: np.ndarray
    var_own: np.ndarray
    coef: np.ndarray
    sigma_2: np.ndarray

    def __post_init__(self):
        shp = np.shape(self.var_own)
        cf = np.shape(self.coef)
        s2 = np.shape(self.sigma_2)
        if (len(shp) != 2 or np.shape(self.u2) != shp or np.shape(self.v2) != shp
                or cf[:2] != shp or len(cf) != 3 or cf[2] not in (1, 2) or len(s2) != 3
                or s2[0] != cf[2] or s2[1] < 2 or s2[2] < 2):
            raise ValueError(f"stereo noise maps of inconsistent shapes: u2 "
                             f"{np.shape(self.u2)}, v2 {np.shape(self.v2)}, var_own {shp}, "
                             f"coef {cf}, sigma_2 {s2}")

    @property
    def shape(self) -> tuple:
        return tuple(np.shape(self.var_own))

    def expand(self) -> StereoNoise:
        """The :class:`StereoNoise` of these maps (the weights and sources per point)."""
        var_own = np.asarray(self.var_own, dtype=np.float64)
        shp = var_own.shape
        coef = np.asarray(self.coef, dtype=np.float64).reshape(-1, np.shape(self.coef)[2])
        sig2 = np.asarray(self.sigma_2, dtype=np.float64)
        n_ax, rows2, cols2 = sig2.shape
        gi = np.flatnonzero(np.isfinite(var_own.reshape(-1)))
        u2 = np.asarray(self.u2, dtype=np.float64).reshape(-1)[gi]
        v2 = np.asarray(self.v2, dtype=np.float64).reshape(-1)[gi]
        if not (np.all(np.isfinite(u2) & np.isfinite(v2)) and np.all(u2 >= 0)
                and np.all(u2 <= cols2 - 1) and np.all(v2 >= 0) and np.all(v2 <= rows2 - 1)):
            raise ValueError("stereo noise maps: a point's match (u2, v2) is not inside the "
                             "second camera's image")
        i, j, fx, fy = bilinear(sig2[0], u2, v2)[3]
        w = ((1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy)
        pix = (i * cols2 + j, i * cols2 + j + 1, (i + 1) * cols2 + j, (i + 1) * cols2 + j + 1)
        n2 = rows2 * cols2
        K = 4 * n_ax
        n = var_own.size
        weights = np.zeros((n, K))
        sources = np.full((n, K), -1, dtype=np.int64)
        for a in range(n_ax):
            S2 = sig2[a].reshape(-1)
            c = coef[gi, a]
            for q in range(4):
                weights[gi, 4 * a + q] = -c * w[q] * S2[pix[q]]
                sources[gi, 4 * a + q] = a * n2 + pix[q]
        return StereoNoise(_readonly(var_own.copy()), _readonly(weights.reshape(shp + (K,))),
                           _readonly(sources.reshape(shp + (K,))))


def match_noise_maps(rig, coords_1, coords_2, match: StereoMatch, *,
                     use_v_p: bool = True) -> StereoNoiseMaps:
    """:func:`match_noise` in its compact form (:class:`StereoNoiseMaps`, what
    ``telefringe reconstruct --second`` keeps in points.npz); the arguments as there."""
    rig, cam1, cam2 = _two_cameras(rig)
    cloud = match.cloud
    shape1, m1 = _maps(coords_1, cloud.shape, "first camera")
    shape2, m2 = _maps(coords_2, None, "second camera")
    primary, other, combine = _axes(coords_1, coords_2, use_v_p)
    axes = (primary, other) if combine else (primary,)
    for ax in axes:
        if m1[ax][1] is None or m2[ax][1] is None:
            raise TriangulationError(f"the noise of the match needs sigma_{ax}_p of both "
                                     "cameras")
    gi = np.flatnonzero(cloud.mask.reshape(-1))
    X = cloud.xyz.reshape(-1, 3)[gi]
    dirs = np.asarray(cloud.directions, dtype=np.float64)
    dd = np.broadcast_to(dirs, X.shape) if dirs.ndim == 1 else dirs.reshape(-1, 3)[gi]
    u2 = np.asarray(match.u2, dtype=np.float64).reshape(-1)[gi]
    v2 = np.asarray(match.v2, dtype=np.float64).reshape(-1)[gi]
    _, _, J = cam2.project_jacobian(X)
    dp = np.einsum("mij,mj->mi", np.asarray(J, dtype=np.float64), dd)
    slopes, pair, own = [], [], []
    for ax in axes:
        M2, S2 = m2[ax]
        _, gu, gv, corners = bilinear(M2, u2, v2)
        slopes.append(gu * dp[:, 0] + gv * dp[:, 1])
        pair.append(_pair_var(m1[ax][1], S2, gi, corners))
        own.append(_var_of(m1[ax][1], gi))
    if combine:
        info = sum(g * g / V for g, V in zip(slopes, pair, strict=True))
        coef = [g / V / info for g, V in zip(slopes, pair, strict=True)]
    else:
        coef = [1.0 / slopes[0]]
    n = cloud.mask.size
    shp = cloud.shape
    var_own = np.full(n, np.nan)
    var_own[gi] = sum(c * c * o for c, o in zip(coef, own, strict=True))
    C = np.full((n, len(axes)), np.nan)
    U2 = np.full(n, np.nan)
    V2 = np.full(n, np.nan)
    C[gi] = np.stack(coef, axis=1)
    U2[gi] = u2
    V2[gi] = v2
    sig2 = np.stack([np.asarray(m2[ax][1], dtype=np.float64) for ax in axes])
    return StereoNoiseMaps(_readonly(U2.reshape(shp)), _readonly(V2.reshape(shp)),
                           _readonly(var_own.reshape(shp)),
                           _readonly(C.reshape(shp + (len(axes),))), _readonly(sig2))


def match_noise(rig, coords_1, coords_2, match: StereoMatch, *,
                use_v_p: bool = True) -> StereoNoise:
    """The matched points' errors split into the first camera's own part and the shares
    of the second camera's pixels (:class:`StereoNoise`), for the covariance of
    neighbouring points.

    At each valid point of ``match`` (from :func:`match_stereo` with the same arguments):
    the point moves along the first camera's line by ``delta_s = sum_axes c_a (delta_1a -
    sum_i w_i delta_2a,i)``, ``w_i`` the bilinear weights of the second camera's cell at
    the matched sub-pixel, ``c_a = 1 / g_a`` with one axis and ``c_a = (g_a / V_a) /
    sum_b (g_b^2 / V_b)`` with both (``g`` the along-line slopes, ``V`` the pair
    variances, as the matcher weighs them), ``delta`` the decoded coordinates' errors of
    std ``sigma_u_p`` / ``sigma_v_p`` (independent per pixel and axis).

    Parameters
    ----------
    rig, coords_1, coords_2, use_v_p : as for :func:`match_stereo` (the coordinates need
        their sigmas).
    match : StereoMatch of these arguments.

    Returns
    -------
    StereoNoise on the first camera's grid (:func:`match_noise_maps` expanded).
    """
    return match_noise_maps(rig, coords_1, coords_2, match, use_v_p=use_v_p).expand()


def _c(x):
    return np.require(x, np.float64, ["C", "W"])


def _jump_threshold(M):
    """The largest phase range (projector px) a 2 x 2 cell of the map M may hold: 5 times
    the median of |horizontal| + |vertical| neighbour differences (a smooth surface's
    cells hold about that median; one across an occlusion edge holds the jump)."""
    gx = np.abs(np.diff(M, axis=1))[:-1]
    gy = np.abs(np.diff(M, axis=0))[:, :-1]
    g = (gx + gy)[np.isfinite(gx + gy)]
    return 5.0 * float(np.median(g)) if g.size else np.inf


def _cell_range(M, corners):
    i, j, _, _ = corners
    c = np.stack([M[i, j], M[i, j + 1], M[i + 1, j], M[i + 1, j + 1]])
    return c.max(axis=0) - c.min(axis=0)


def _var_of(S, gi):
    return np.full(gi.size, np.nan) if S is None else S.reshape(-1)[gi] ** 2


def _pair_var(S1, S2, gi, corners):
    """sigma_1^2 + the interpolated sigma_2^2 at the match (NaN without sigmas)."""
    return _var_of(S1, gi) + (np.nan if S2 is None else _interp_var(S2, corners))


def _slopes(cam2, A2, B2, oo, dd, s, a_obs, b_obs):
    """Along-line slopes and mismatches of both axes at s."""
    X = oo + s[:, None] * dd
    u2, v2 = cam2.project(X)
    va, gau, gav, _ = bilinear(A2, u2, v2)
    vb, gbu, gbv, _ = bilinear(B2, u2, v2)
    _, _, J = cam2.project_jacobian(X)
    dp = np.einsum("mij,mj->mi", J, dd)
    return (gau * dp[:, 0] + gav * dp[:, 1], gbu * dp[:, 0] + gbv * dp[:, 1],
            va - a_obs, vb - b_obs)


def _midpoint(o1, d1, o2, d2):
    """Least-squares intersection of two lines (m, 3): the midpoint of their closest
    approach, and their distance (mm)."""
    w = o1 - o2
    b = np.sum(d1 * d2, axis=1)
    dw1 = np.sum(d1 * w, axis=1)
    dw2 = np.sum(d2 * w, axis=1)
    den = 1.0 - b * b
    s1 = (b * dw2 - dw1) / den
    s2 = (dw2 - b * dw1) / den
    p1 = o1 + s1[:, None] * d1
    p2 = o2 + s2[:, None] * d2
    return 0.5 * (p1 + p2), np.linalg.norm(p1 - p2, axis=1)


def triangulate_stereo(rig, coords_1, coords_2, *, max_residual: float | None = 1.0,
                       max_sigma_z: float | None = None, use_v_p: bool = True,
                       search_mm: float | None = None, engine: str = "auto") -> PointCloud:
    """The cloud of :func:`match_stereo` (on the first camera's grid, mm)."""
    return match_stereo(rig, coords_1, coords_2, max_residual=max_residual,
                        max_sigma_z=max_sigma_z, use_v_p=use_v_p, search_mm=search_mm,
                        engine=engine).cloud


def stereo_rig(camera_1, camera_2, projector=None) -> Rig:
    """A two-camera Rig (names ``camera`` and ``camera_2``)."""
    return Rig(cameras={"camera": camera_1, "camera_2": camera_2}, projector=projector)
