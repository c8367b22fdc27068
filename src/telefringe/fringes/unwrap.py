"""Temporal phase unwrapping: multi-frequency hierarchical, multi-wavelength heterodyne,
number-theoretic and Gray-code assisted.

All functions take wrapped phases in (-pi, pi] (rad) of fringe groups with ``periods``
periods across the projector axis of ``length`` pixels, and return the absolute phase of
every input group, ``Phi_j = 2 pi periods_j x / length`` (x the projector coordinate,
pixel centres at integers), together with a per-pixel ``reliable`` flag. A pixel whose
fringe order cannot be trusted (the consistency residual exceeds its tolerance) is
flagged, never silently guessed.

The absolute phase of a one-period pattern is taken in ``[-pi/L, 2 pi - pi/L)``, i.e. x in
``[-0.5, L - 0.5)``: the projector's own extent.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from telefringe.fringes.patterns import gray_code_bits

__all__ = [
    "LadderError",
    "Unwrapped",
    "GrayCode",
    "absolute_unit_phase",
    "unwrap_step",
    "unwrap_hierarchical",
    "heterodyne_plan",
    "unwrap_heterodyne",
    "number_theoretic_candidates",
    "unwrap_number_theoretic",
    "decode_gray",
    "unwrap_gray",
]

TWO_PI = 2.0 * np.pi


class LadderError(ValueError):
    """The set of fringe periods cannot determine the absolute phase (by this method)."""


@dataclass(frozen=True)
class Unwrapped:
    """Result of an unwrapping method.

    Attributes
    ----------
    phases : tuple of (rows, cols) ndarray of float64, the absolute phase (rad) of each
        input group, in input order.
    reliable : (rows, cols) ndarray of bool, False where the fringe order is not trusted.
    residual : (rows, cols) ndarray of float64, the worst consistency residual relative to
        its tolerance (reliable <=> residual <= 1); 0 for the Gray code when consistent.
    """

    phases: tuple[np.ndarray, ...]
    reliable: np.ndarray
    residual: np.ndarray


def _as_phases(phases, name="phases") -> list[np.ndarray]:
    out = [np.asarray(p, dtype=np.float64) for p in phases]
    if not out:
        raise LadderError(f"{name}: no phase given")
    shape = out[0].shape
    for p in out:
        if p.shape != shape:
            raise ValueError(f"{name}: shapes differ ({shape} vs {p.shape})")
    return out


def _check_periods(periods, n: int) -> list[int]:
    per = [int(p) for p in periods]
    if len(per) != n:
        raise ValueError(f"got {n} phases but {len(per)} periods")
    if any(p < 1 for p in per):
        raise LadderError(f"periods must be >= 1, got {per}")
    if len(set(per)) != len(per):
        raise LadderError(f"periods must differ, got {per}")
    return per


def _check_length(length) -> int:
    if isinstance(length, bool) or not isinstance(length, int | np.integer) or length < 1:
        raise ValueError(f"length must be a positive integer (projector pixels), got {length!r}")
    return int(length)


def absolute_unit_phase(phase, *, length: int) -> np.ndarray:
    """Absolute phase of a one-period group: the wrapped phase moved to
    ``[-pi/L, 2 pi - pi/L)`` (x in [-0.5, L - 0.5)).

    Parameters
    ----------
    phase : (...) array_like, rad, wrapped.  length : int, projector pixels L.
    """
    length = _check_length(length)
    cut = np.pi / length
    return np.mod(np.asarray(phase, dtype=np.float64) + cut, TWO_PI) - cut


def unwrap_step(phase, periods: float, reference, reference_periods: float):
    """Unwrap one wrapped phase with an absolute reference phase of fewer periods.

    Parameters
    ----------
    phase : (...) array_like, rad, wrapped phase of the group with ``periods``.
    reference : (...) array_like, rad, absolute phase of a group with ``reference_periods``.

    Returns
    -------
    absolute : ndarray, rad. ``phase + 2 pi k`` with k the nearest integer to
        ``(reference * periods / reference_periods - phase) / 2 pi``.
    residual : ndarray, rad, in [-pi, pi]: predicted minus chosen absolute phase. An
        order is safe while the error of the prediction stays below pi.
    """
    phase = np.asarray(phase, dtype=np.float64)
    pred = np.asarray(reference, dtype=np.float64) * (float(periods) / float(reference_periods))
    k = np.round((pred - phase) / TWO_PI)
    absolute = phase + TWO_PI * k
    return absolute, pred - absolute


def unwrap_hierarchical(phases: Sequence, periods: Sequence[int], *, length: int,
                        max_residual: float = np.pi / 2) -> Unwrapped:
    """Multi-frequency hierarchical unwrapping over a ladder such as 1, 8, 64.

    Each group (sorted by periods) is unwrapped with the absolute phase of the previous
    one; the coarsest must have one period. A pixel is unreliable when any step's
    residual exceeds ``max_residual`` (rad, default pi/2: half the distance to a wrong
    order).

    Parameters
    ----------
    phases : sequence of (rows, cols) array_like, rad, wrapped, one per group.
    periods : sequence of int, distinct, one of them 1.
    length : int, projector pixels along the axis.
    max_residual : float, rad, in (0, pi].

    Returns
    -------
    Unwrapped
    """
    ph = _as_phases(phases)
    per = _check_periods(periods, len(ph))
    length = _check_length(length)
    _check_tolerance(max_residual, np.pi, "max_residual")
    if min(per) != 1:
        raise LadderError(f"a hierarchical ladder needs a one-period group; periods are {per}")
    order = np.argsort(per)
    out: list[np.ndarray | None] = [None] * len(ph)
    ref = absolute_unit_phase(ph[order[0]], length=length)
    out[order[0]] = ref
    worst = np.zeros(ph[0].shape)
    for a, b in zip(order[:-1], order[1:], strict=True):
        ref, res = unwrap_step(ph[b], per[b], out[a], per[a])
        out[b] = ref
        np.maximum(worst, np.abs(res) / max_residual, out=worst)
    return Unwrapped(phases=tuple(out), reliable=worst <= 1.0, residual=worst)


def _check_tolerance(value, top, name):
    if not (np.isfinite(value) and 0 < value <= top):
        raise ValueError(f"{name} must be in (0, {top:g}], got {value!r}")


# ----------------------------------------------------------------------------- heterodyne
@dataclass(frozen=True)
class _Node:
    periods: int
    parents: tuple[int, int] | None  # indices into the node list (a - b) or None (real)
    noise: float  # noise of the phase relative to one real group's


def heterodyne_plan(periods: Sequence[int]):
    """Beat tree and unwrapping order of a multi-wavelength heterodyne set.

    Periods sorted in decreasing order are beaten pairwise (consecutive differences), and
    the beats again, until one element is left. A beat with one period gives the absolute
    phase; then every node (beats and real groups) is unwrapped in increasing order of
    periods, each from the already unwrapped node whose absolute phase is most precise
    (smallest noise / periods).

    Returns
    -------
    nodes : list of _Node (the first ``len(periods)`` are the real groups, input order).
    steps : list of (node, reference node) pairs, the first with reference None.

    Raises
    ------
    LadderError
        No beat has exactly one period (the set does not cover the projector uniquely).
    """
    per = _check_periods(periods, len(periods))
    if len(per) < 2:
        raise LadderError(f"heterodyne unwrapping needs >= 2 groups, got periods {per}")
    nodes = [_Node(p, None, 1.0) for p in per]
    level = sorted(range(len(per)), key=lambda i: -per[i])
    while len(level) > 1:
        nxt = []
        for a, b in zip(level[:-1], level[1:], strict=True):
            pa, pb = nodes[a].periods, nodes[b].periods
            if pa == pb:
                raise LadderError(f"heterodyne beat of equal periods in {per}")
            if pa < pb:
                a, b = b, a
            noise = float(np.hypot(nodes[a].noise, nodes[b].noise))
            nodes.append(_Node(abs(pa - pb), (a, b), noise))
            nxt.append(len(nodes) - 1)
        level = sorted(nxt, key=lambda i: -nodes[i].periods)
    ones = [i for i, n in enumerate(nodes) if n.periods == 1]
    if not ones:
        raise LadderError(f"periods {per}: no heterodyne beat has one period (beats: "
                          f"{sorted({n.periods for n in nodes[len(per):]})}); the set "
                          "cannot unwrap the projector's full width")
    start = min(ones, key=lambda i: nodes[i].noise)
    done = [start]
    steps: list[tuple[int, int | None]] = [(start, None)]
    todo = sorted((i for i in range(len(nodes)) if i != start and nodes[i].periods > 1),
                  key=lambda i: (nodes[i].periods, nodes[i].noise))
    for i in todo:
        cands = [j for j in done if nodes[j].periods < nodes[i].periods]
        ref = min(cands, key=lambda j: nodes[j].noise / nodes[j].periods)
        steps.append((i, ref))
        done.append(i)
    # real groups with one period that were not the start: unwrap from the start
    for i in range(len(per)):
        if i not in done:
            steps.append((i, start))
            done.append(i)
    return nodes, steps


def unwrap_heterodyne(phases: Sequence, periods: Sequence[int], *, length: int,
                      max_residual: float = np.pi / 2) -> Unwrapped:
    """Multi-wavelength heterodyne unwrapping (e.g. periods 70, 64, 59: beats 6 and 5,
    and their beat 1).

    The synthetic (beat) phase of groups a and b is ``wrap(phi_a - phi_b)`` with
    ``periods_a - periods_b`` periods. See :func:`heterodyne_plan` for the order. A pixel
    is unreliable when any step's residual exceeds ``max_residual`` (rad).

    Parameters
    ----------
    phases : sequence of (rows, cols) array_like, rad, wrapped.
    periods : sequence of int, distinct.  length : int, projector pixels.

    Returns
    -------
    Unwrapped (absolute phases of the real groups, input order)
    """
    ph = _as_phases(phases)
    length = _check_length(length)
    _check_tolerance(max_residual, np.pi, "max_residual")
    nodes, steps = heterodyne_plan(periods)
    wrapped: dict[int, np.ndarray] = {}

    def get_wrapped(i):
        if i not in wrapped:
            n = nodes[i]
            if n.parents is None:
                wrapped[i] = ph[i]
            else:
                d = get_wrapped(n.parents[0]) - get_wrapped(n.parents[1])
                wrapped[i] = np.mod(d + np.pi, TWO_PI) - np.pi
        return wrapped[i]

    absolute: dict[int, np.ndarray] = {}
    worst = np.zeros(ph[0].shape)
    for i, ref in steps:
        if ref is None:
            absolute[i] = absolute_unit_phase(get_wrapped(i), length=length)
            continue
        absolute[i], res = unwrap_step(get_wrapped(i), nodes[i].periods, absolute[ref],
                                       nodes[ref].periods)
        np.maximum(worst, np.abs(res) / max_residual, out=worst)
    return Unwrapped(phases=tuple(absolute[i] for i in range(len(ph))), reliable=worst <= 1.0,
                     residual=worst)


# ----------------------------------------------------------------------- number-theoretic
def number_theoretic_candidates(periods: Sequence[int], *, length: int) -> np.ndarray:
    """All fringe-order vectors ``k_j = round(periods_j x / L)`` met for x in
    [-0.5, L - 0.5), as an (n_candidates, n_groups) int array (in increasing x).

    The vector equal to ``periods`` (met near x = L - 0.5) is left out: it gives the same
    wrapped phases as k = 0 at x - L; :func:`unwrap_number_theoretic` moves estimates
    below x = -0.5 up by L."""
    per = _check_periods(periods, len(periods))
    length = _check_length(length)
    brk = [-0.5, length - 0.5]
    for p in per:
        m = np.arange(0, p + 1)
        x = (m - 0.5) * length / p
        brk.extend(x[(x > -0.5) & (x < length - 0.5)].tolist())
    brk = np.unique(np.asarray(brk))
    mids = 0.5 * (brk[:-1] + brk[1:])
    k = np.floor(np.asarray(per)[None, :] * mids[:, None] / length + 0.5).astype(np.int64)
    keep = np.ones(len(k), dtype=bool)
    keep[1:] = np.any(k[1:] != k[:-1], axis=1)
    # k = periods (near x = L - 0.5) is k = 0 one projector width later: the same phases
    keep &= ~np.all(k == np.asarray(per)[None, :], axis=1)
    return k[keep]


def _projected_separation(cands: np.ndarray, per: np.ndarray) -> float:
    """Smallest distance between candidates' order vectors (times 2 pi) once the
    direction of ``periods`` is projected out."""
    u = per / np.linalg.norm(per)
    pts = TWO_PI * cands.astype(float)
    pts = pts - np.outer(pts @ u, u)
    d = np.sqrt(((pts[:, None, :] - pts[None, :, :]) ** 2).sum(-1))
    d[np.diag_indices_from(d)] = np.inf
    return float(d.min())


def unwrap_number_theoretic(phases: Sequence, periods: Sequence[int], *, length: int,
                            max_fraction: float = 0.5, chunk: int = 4096) -> Unwrapped:
    """Number-theoretic (maximum-likelihood lattice) unwrapping of coprime period sets.

    For wrapped phases phi_j of groups with periods p_j, the orders k are those of the
    candidate (see :func:`number_theoretic_candidates`) minimising the residual of the
    least-squares fit ``phi_j + 2 pi k_j = p_j t``, i.e. the distance of ``phi + 2 pi k``
    to the line along p. Unambiguous over the whole projector when the candidates stay
    apart once that line is projected out (periods coprime, e.g. 7 and 8 or 11, 13, 16).

    A pixel is unreliable when its distance exceeds ``max_fraction`` times half the
    smallest separation between candidates (the decision radius).

    Parameters
    ----------
    phases : sequence of (rows, cols) array_like, rad, wrapped.
    periods : sequence of int, distinct.  length : int, projector pixels.
    max_fraction : float in (0, 1].

    Returns
    -------
    Unwrapped
    """
    ph = _as_phases(phases)
    per = _check_periods(periods, len(ph))
    length = _check_length(length)
    _check_tolerance(max_fraction, 1.0, "max_fraction")
    if len(per) < 2:
        raise LadderError(f"number-theoretic unwrapping needs >= 2 groups, got {per}")
    cands = number_theoretic_candidates(per, length=length)
    p = np.asarray(per, dtype=float)
    sep = _projected_separation(cands, p)
    if sep < 1e-9:
        raise LadderError(f"periods {per} are not coprime enough: two fringe orders give "
                          "the same phases, the projector width is not covered uniquely")
    tol = max_fraction * sep / 2.0
    # where two groups' orders change within the noise of each other, the measured
    # phases may show a combination that no exact x gives: add, for neighbouring
    # candidates (one or two apart), every mixture of their components
    extra = [cands]
    for gap in (1, 2):
        a, b = cands[:-gap], cands[gap:]
        for mask in range(1, 2 ** len(per) - 1):
            pick = np.array([(mask >> i) & 1 for i in range(len(per))], dtype=bool)
            extra.append(np.where(pick[None, :], b, a))
    cands = np.unique(np.concatenate(extra), axis=0)
    shape = ph[0].shape
    flat = np.stack([q.ravel() for q in ph], axis=1)
    n = flat.shape[0]
    best_k = np.zeros((n, len(per)), dtype=np.int64)
    best_d = np.zeros(n)
    u = p / np.linalg.norm(p)
    # projection of (phi + 2 pi k) on the complement of u: P phi + 2 pi P k
    pk = TWO_PI * cands.astype(float)
    pk = pk - np.outer(pk @ u, u)
    for s in range(0, n, chunk):
        f = flat[s:s + chunk]
        pf = f - np.outer(sum(f[:, i] * u[i] for i in range(len(per))), u)
        d2 = ((pf[:, None, :] + pk[None, :, :]) ** 2).sum(-1)
        j = np.argmin(d2, axis=1)
        best_k[s:s + chunk] = cands[j]
        best_d[s:s + chunk] = np.sqrt(d2[np.arange(len(j)), j])
    # refine each order against the fitted line: near places where two groups' orders
    # change within the noise of each other the right combination is not among the
    # candidates (it occurs for no exact x), but its neighbour is
    t = sum(p[i] * (flat[:, i] + TWO_PI * best_k[:, i]) for i in range(len(per))) / (p @ p)
    for i in range(len(per)):
        best_k[:, i] = np.round((p[i] * t - flat[:, i]) / TWO_PI).astype(np.int64)
    t = sum(p[i] * (flat[:, i] + TWO_PI * best_k[:, i]) for i in range(len(per))) / (p @ p)
    resid = flat + TWO_PI * best_k - np.outer(t, p)
    best_d = np.sqrt(np.sum(resid ** 2, axis=1))
    # estimates left of the projector (x < -0.5) are the wrap-around of its right edge
    best_k += (t * length / TWO_PI < -0.5)[:, None].astype(np.int64) * np.asarray(per)[None, :]
    absolute = tuple((flat[:, i] + TWO_PI * best_k[:, i]).reshape(shape)
                     for i in range(len(per)))
    worst = (best_d / tol).reshape(shape)
    return Unwrapped(phases=absolute, reliable=worst <= 1.0, residual=worst)


# ------------------------------------------------------------------------------ Gray code
@dataclass(frozen=True)
class GrayCode:
    """Decoded Gray-code images.

    Attributes
    ----------
    index : (rows, cols) int64, the decoded binary index (block, or half-block with the
        complementary bit).
    bits : (n, rows, cols) bool, the bits as read.
    contrast : (n, rows, cols) float64, |I - threshold| (DN) of each bit image.
    """

    index: np.ndarray
    bits: np.ndarray
    contrast: np.ndarray


def decode_gray(images, threshold) -> GrayCode:
    """Read Gray-code bit images (most significant first) against a threshold image.

    Parameters
    ----------
    images : (n, rows, cols) array_like, DN; bright = 1 (any trailing shape).
    threshold : (rows, cols) array_like, DN (e.g. the mean of the phase images).

    Returns
    -------
    GrayCode, ``index`` the binary value of the n-bit Gray code.
    """
    imgs = np.asarray(images)
    thr = np.asarray(threshold, dtype=np.float64)
    if imgs.ndim < 2 or imgs.shape[1:] != thr.shape:
        raise ValueError(f"Gray images {imgs.shape} and threshold {thr.shape} do not match")
    n = imgs.shape[0]
    bits = np.empty(imgs.shape, dtype=bool)
    contrast = np.empty(imgs.shape, dtype=np.float64)
    index = np.zeros(thr.shape, dtype=np.int64)
    prev = np.zeros(thr.shape, dtype=bool)
    for j in range(n):
        d = imgs[j].astype(np.float64) - thr
        bits[j] = d > 0
        contrast[j] = np.abs(d)
        prev = prev ^ bits[j]  # binary bit j = XOR of Gray bits 0..j
        index |= prev.astype(np.int64) << (n - 1 - j)
    return GrayCode(index=index, bits=bits, contrast=contrast)


def _block_edges(block, periods, length):
    """Phases of the left and right edges of block(s) b: block b covers the projector
    pixels with ``floor(x periods / L) = b``, i.e. x from ``ceil(b L / p) - 0.5``."""
    b = np.clip(block, 0, periods - 1)
    start = -((-b * length) // periods)  # ceil(b L / p), exact integers
    end = -((-(b + 1) * length) // periods)
    return (TWO_PI * periods * (start - 0.5) / length,
            TWO_PI * periods * (end - 0.5) / length)


def _order_in_block(phase, block, periods, length):
    """Fringe order putting ``phase + 2 pi m`` nearest the middle of block b."""
    s_b, e_b = _block_edges(block, periods, length)
    return np.round((0.5 * (s_b + e_b) - phase) / TWO_PI).astype(np.int64)


def _edge_bit_contrast(block, neighbour, code: GrayCode, bits: int):
    """Contrast (DN) of the bit that changes between Gray(block) and Gray(neighbour);
    +inf where the neighbour is outside 0 .. 2**bits - 1 (no edge there)."""
    inside = (neighbour >= 0) & (neighbour < 2 ** bits)
    nb_ = np.clip(neighbour, 0, 2 ** bits - 1)
    diff = (block ^ (block >> 1)) ^ (nb_ ^ (nb_ >> 1))
    diff = np.where(inside & (diff > 0), diff, 1)
    j = bits - 1 - np.floor(np.log2(diff)).astype(np.int64)
    c = np.take_along_axis(code.contrast[:bits], j[None], axis=0)[0]
    return np.where(inside, c, np.inf)


def unwrap_gray(phase, images, threshold, *, bits: int, complementary: bool, length: int,
                min_contrast: float) -> Unwrapped:
    """Gray-code assisted unwrapping of the phase group with ``2**bits`` periods.

    Block b = floor(x 2^bits / L) (x integer projector pixels) is the Gray-coded index;
    the wrapped phase is about 0 at block edges (exactly ``-pi p / L`` when L / p is an
    integer: the edge lies between pixel centres) and +-pi at block middles. Plain code:
    the order that puts the phase inside block b (``ceil((s_b - phi) / 2 pi)``, s_b the
    phase of the block's left edge), which fails where the bit that changes at a block
    edge is misread. Complementary code (one more bit: half-blocks h): near block edges
    (|phi| <= pi/2) the order is ``floor((h + 1) / 2)``, the same on both sides of the edge
    whichever way its bit is read; near block middles (|phi| > pi/2) it is the in-block
    order of block ``floor(h / 2)``, where none of the n block bits changes.

    With the plain code a pixel whose phase puts it within a quarter period of a block
    edge takes, of the block's two ends, the one whose edge bit reads with less contrast
    (its contrast below half the pixel's typical bit contrast and below the other's; the
    phase and the code may disagree by a fraction of a pixel at an edge).

    Reliability: a pixel is unreliable when a clear bit (contrast >= ``min_contrast`` and
    >= a quarter of the median contrast of the pixel's bits) disagrees with the bit
    expected within 2 projector pixels of the decoded coordinate, and, for the plain code,
    near a block edge where both edge bits are unclear and alike.

    The complementary code on a (rows, cols) grid with finite inputs runs as one parallel
    numba pass (:mod:`telefringe.fringes._gray_kernels`, the same float64 operations:
    bit-identical to the NumPy path, tests/test_gray_kernels.py); the plain code and other
    inputs take the NumPy path.

    Parameters
    ----------
    phase : (rows, cols) array_like, rad, wrapped phase of the group with 2**bits periods.
    images : (bits [+1], rows, cols) array_like, DN, Gray-code images.
    threshold : (rows, cols) array_like, DN.
    bits : int.  complementary : bool.  length : int, projector pixels.
    min_contrast : float, DN (e.g. 3 sigma_I).

    Returns
    -------
    Unwrapped with one phase.
    """
    phase = np.asarray(phase, dtype=np.float64)
    length = _check_length(length)
    need = bits + (1 if complementary else 0)
    imgs = np.asarray(images)
    if imgs.ndim < 2 or imgs.shape[0] != need:
        raise ValueError(f"Gray code with {bits} bits{' + complementary' if complementary else ''}"
                         f" needs {need} images, got stack of shape {imgs.shape}")
    if complementary and _compiled_ok(phase, imgs, threshold, min_contrast, need):
        return _unwrap_gray_compiled(phase, imgs, threshold, bits=bits, length=length,
                                     min_contrast=min_contrast)
    return _unwrap_gray_numpy(phase, imgs, threshold, bits=bits, complementary=complementary,
                              length=length, min_contrast=min_contrast)


def _compiled_ok(phase, imgs, threshold, min_contrast, need) -> bool:
    """The compiled complementary kernel applies: a 2-D image grid, integer or float
    images, finite phase, threshold and min_contrast broadcastable to the image (where
    any of them is NaN or infinite, the NumPy path keeps its own behaviour)."""
    thr = np.asarray(threshold)
    mc = np.asarray(min_contrast)
    return (phase.ndim == 2 and imgs.ndim == 3 and imgs.shape[1:] == phase.shape
            and thr.shape == phase.shape and imgs.dtype.kind in "uif" and need <= 62
            and mc.ndim <= 2 and np.broadcast_shapes(mc.shape, phase.shape) == phase.shape
            and bool(np.isfinite(phase).all()) and bool(np.isfinite(thr).all())
            and bool(np.isfinite(mc).all())
            and (imgs.dtype.kind != "f" or bool(np.isfinite(imgs).all())))


def _unwrap_gray_compiled(phase, imgs, threshold, *, bits, length, min_contrast) -> Unwrapped:
    """:func:`unwrap_gray` with the complementary code in one parallel numba pass
    (:mod:`telefringe.fringes._gray_kernels`); bit-identical to :func:`_unwrap_gray_numpy`."""
    from telefringe.fringes._gray_kernels import unwrap_gray_complementary

    thr = np.ascontiguousarray(threshold, dtype=np.float64)
    mc = np.ascontiguousarray(np.broadcast_to(np.asarray(min_contrast, dtype=np.float64),
                                              phase.shape))
    absolute = np.empty(phase.shape, dtype=np.float64)
    bad = np.empty(phase.shape, dtype=bool)
    unwrap_gray_complementary(np.ascontiguousarray(phase), np.ascontiguousarray(imgs), thr, mc,
                              int(bits), int(length), absolute, bad)
    return Unwrapped(phases=(absolute,), reliable=~bad, residual=bad.astype(np.float64))


def _unwrap_gray_numpy(phase, imgs, threshold, *, bits, complementary, length,
                       min_contrast) -> Unwrapped:
    """:func:`unwrap_gray` in float64 NumPy (the reference of the compiled path, and the
    plain code's implementation)."""
    code = decode_gray(imgs, threshold)
    periods = 2 ** bits
    # a bit is clear when its contrast beats the noise and a quarter of the pixel's typical
    # bit contrast (a bit inside a blurred edge is neither)
    typical = np.median(code.contrast, axis=0)
    clear = code.contrast >= np.maximum(min_contrast, 0.25 * typical)
    ambiguous = np.zeros(phase.shape, dtype=bool)
    if complementary:
        h = code.index
        near_edge = np.abs(phase) <= np.pi / 2
        order = np.where(near_edge, (h + 1) // 2, _order_in_block(phase, h // 2, periods, length))
    else:
        b = code.index
        order = _order_in_block(phase, b, periods, length)
        s_b, e_b = _block_edges(b, periods, length)
        full = phase + TWO_PI * order
        near_start = full - s_b < np.pi / 2
        near_end = e_b - full < np.pi / 2
        c_start = _edge_bit_contrast(b, b - 1, code, bits)
        c_end = _edge_bit_contrast(b, b + 1, code, bits)
        # near a block edge the phase alone cannot tell the block's two ends apart when the
        # code and phase disagree by a hair: the end whose edge bit is less clear wins
        # (its contrast below half the pixel's typical bit contrast: the other end's bit,
        # 3/4 of a period away, reads at full contrast; no edge beyond the projector)
        half = 0.5 * typical
        order = (order + (near_start & (c_end < half) & (c_end < c_start))
                 - (near_end & (c_start < half) & (c_start < c_end)))
        lo, hi = np.minimum(c_start, c_end), np.maximum(c_start, c_end)
        ambiguous = (near_start | near_end) & (lo < min_contrast) & (hi < 2.0 * lo)
    absolute = phase + TWO_PI * order
    x = absolute * length / (TWO_PI * periods)
    # a clear bit must match the code at the decoded coordinate, give or take a couple of
    # pixels (an order error moves x by a whole period, L / 2**bits pixels)
    tol = min(2.0, length / periods / 4.0)
    mismatch = clear.copy()
    for dx in (-tol, -0.5 * tol, 0.0, 0.5 * tol, tol):
        xr = np.clip(np.round(x + dx), 0, length - 1)  # the nearest projector pixel
        expect = gray_code_bits(xr, bits=bits, length=length,
                                complementary=complementary).astype(bool)
        mismatch &= expect != code.bits
    bad = np.any(mismatch, axis=0) | ambiguous
    bad |= (x < -0.5) | (x >= length - 0.5)
    return Unwrapped(phases=(absolute,), reliable=~bad, residual=bad.astype(np.float64))
