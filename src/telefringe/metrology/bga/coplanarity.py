"""Seating plane and coplanarity of ball apexes (JEDEC)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from telefringe.metrology._common import MetrologyError, _freeze, _tangent_basis
from telefringe.metrology.planes import Plane


@dataclass(frozen=True, eq=False)
class Coplanarity:
    """Coplanarity of the ball apexes against the seating plane (JEDEC).

    Attributes
    ----------
    value : float, mm, the largest distance of an apex from the seating plane: of the
        seating planes the package may rest on (``alternatives``), the largest.
    distances : (n,) mm, each ball's apex distance from that seating plane (>= 0).
    contacts : (k,) int, indices of the balls it rests on there (k >= 3, usually 3).
    normal : (3,) world unit normal of that seating plane (toward the camera).
    offset : float, mm, ``normal . x = offset`` on it.
    alternatives : (m,) mm, the coplanarity on each seating plane the package may rest
        on, largest first (``alternatives[0] == value``). m > 1 when the centre of
        gravity lies within ``cog_tolerance`` of an edge (or a ball) shared by seating
        triangles: the package rocks there, and the data cannot tell on which plane it
        rests. (On a point-symmetric grid this is common: every pair of balls placed
        symmetrically about the centre has its midpoint on the centre.)
    cog_tolerance : float, mm, the distance from the centre of gravity within which a
        seating triangle counts as one the package may rest on.
    sigma : float, mm, standard uncertainty of ``value`` propagated from the apexes'
        height uncertainties (to first order, the plane held on its contacts); NaN when
        none were given.
    """

    value: float
    distances: np.ndarray
    contacts: np.ndarray
    normal: np.ndarray
    offset: float
    alternatives: np.ndarray = None
    cog_tolerance: float = 0.0
    sigma: float = np.nan

    def __post_init__(self):
        if self.alternatives is None:
            object.__setattr__(self, "alternatives", np.array([self.value]))
        _freeze(self, "distances", "contacts", "normal", "alternatives")

    @property
    def rocks(self) -> bool:
        """The package may rest on more than one seating plane (see ``alternatives``)."""
        return int(self.alternatives.size) > 1


def _hull_2d(p: np.ndarray) -> np.ndarray:
    """Indices of the convex hull of points p (k, 2), counter-clockwise (monotone
    chain; collinear points dropped)."""
    order = np.lexsort((p[:, 1], p[:, 0]))

    def cross(o, a, b):
        return (p[a, 0] - p[o, 0]) * (p[b, 1] - p[o, 1]) - (p[a, 1] - p[o, 1]) * (
            p[b, 0] - p[o, 0])

    def chain(idx):
        out = []
        for k in idx:
            while len(out) >= 2 and cross(out[-2], out[-1], k) <= 0:
                out.pop()
            out.append(int(k))
        return out

    lower, upper = chain(order), chain(order[::-1])
    return np.array(lower[:-1] + upper[:-1], dtype=np.int64)


def _segment_distance(g, a, b) -> float:
    t = b - a
    s = float(np.clip((g - a) @ t / (t @ t), 0.0, 1.0))
    return float(np.hypot(*(g - a - s * t)))


def seating_plane_coplanarity(apexes, centre_of_gravity, *, reference: Plane,
                              cog_tolerance: float = 0.0,
                              sigma_heights=None) -> Coplanarity:
    """Seating plane and coplanarity of ball apexes (JEDEC definition).

    Turned balls-down onto a flat surface, a package rests on three balls: the plane
    through three apexes that has all other apexes on the package side and whose
    triangle contains the package's centre of gravity. Coplanarity is the largest
    distance of any apex from that seating plane (JEDEC JESD22-B108 / the "seating
    plane" coplanarity of package outline standards).

    Here the balls point toward the camera: in coordinates (x', y') on the ``reference``
    (substrate) plane and height h above it, the seating plane ``h = a x' + b y' + c`` is
    the lowest plane lying on or above every apex at the centre of gravity, i.e. the
    linear program ``min a x_g + b y_g + c  s.t.  a x'_i + b y'_i + c >= h_i``, whose
    solution is the facet of the apexes' upper convex hull above the centre of gravity.

    When the centre of gravity lies on an edge (or a vertex) of those facets, or within
    ``cog_tolerance`` of one, the package may rest on either side: every facet within
    ``cog_tolerance`` of it is a seating plane, and the largest of their coplanarities
    is reported (the worst case; all of them in ``alternatives``). Exact ties (a
    tolerance of 1e-9 of the footprint) are always resolved so, never by the solver's
    choice.

    Parameters
    ----------
    apexes : (n, 3) world mm, n >= 3.
    centre_of_gravity : (2,) or (3,) world mm; projected onto ``reference``.
    reference : Plane, the substrate plane.
    cog_tolerance : float, mm, >= 0: how far from the centre of gravity a seating
        triangle may lie (e.g. k sigma of the balls' in-plane positions).
    sigma_heights : (n,) mm, optional, standard uncertainty of each apex's height above
        ``reference``; gives ``Coplanarity.sigma``.
    """
    from scipy.optimize import linprog

    A = np.asarray(apexes, dtype=np.float64)
    if A.ndim != 2 or A.shape[1] != 3 or A.shape[0] < 3 or not np.all(np.isfinite(A)):
        raise MetrologyError("coplanarity needs at least 3 finite apexes (n, 3)")
    if not (np.isfinite(cog_tolerance) and cog_tolerance >= 0):
        raise MetrologyError(f"cog_tolerance must be >= 0, got {cog_tolerance!r}")
    sig = None
    if sigma_heights is not None:
        sig = np.asarray(sigma_heights, dtype=np.float64).reshape(-1)
        if sig.shape != (A.shape[0],):
            raise MetrologyError(f"sigma_heights must have shape ({A.shape[0]},), got "
                                 f"{np.shape(sigma_heights)}")
    T = _tangent_basis(reference.normal)
    q = A @ T.T  # (n, 2)
    h = A @ reference.normal - reference.offset
    g = np.asarray(centre_of_gravity, dtype=np.float64).reshape(-1)
    if g.size == 2:
        g = np.array([g[0], g[1], float(reference.z_at(g[0], g[1]))])
    qg = T @ g
    q0 = q.mean(axis=0)  # centred for conditioning
    qc = q - q0
    gc = qg - q0
    res = linprog(np.array([gc[0], gc[1], 1.0]),
                  A_ub=-np.column_stack([qc, np.ones(len(h))]), b_ub=-h,
                  bounds=[(None, None)] * 3, method="highs")
    if res.status != 0:
        raise MetrologyError(
            "no seating plane: the centre of gravity is outside the balls' footprint")
    scale = float(np.ptp(qc, axis=0).max())
    htol = 1e-9 + 1e-9 * np.max(np.abs(h))
    tol = float(cog_tolerance) + 1e-9 * scale

    def facet(abc):
        above = qc @ abc[:2] + abc[2] - h
        contacts = np.flatnonzero(above <= htol)
        return contacts, above

    # every facet of the upper hull within tol of the centre of gravity: walk across
    # the edges that pass within tol of it (the facets meeting a disc are connected by
    # the edges that cross it)
    start = np.asarray(res.x, dtype=np.float64)
    found = {}
    queue = [start]
    while queue:
        abc = queue.pop()
        contacts, above = facet(abc)
        key = frozenset(contacts.tolist())
        if key in found:
            continue
        found[key] = (abc, contacts, above)
        ring = contacts[_hull_2d(qc[contacts])]
        for p, r in zip(ring, np.roll(ring, -1), strict=True):
            if _segment_distance(gc, qc[p], qc[r]) > tol:
                continue
            # the neighbour across edge (p, r): the plane through the edge that leans
            # outward onto the apexes beyond it (largest slope they need)
            t = qc[r] - qc[p]
            L = float(np.hypot(*t))
            out = np.array([t[1], -t[0]]) / L  # outward: the ring is counter-clockwise
            d = (qc - qc[p]) @ out
            s = (qc - qc[p]) @ t / (L * L)
            line = h[p] + s * (h[r] - h[p])
            beyond = d > 1e-9 * scale
            if not np.any(beyond):
                continue  # the footprint's boundary: the package tips off it
            m = float(np.max((h[beyond] - line[beyond]) / d[beyond]))
            # h = line(x') + m * d(x'), as a x' + b y' + c in centred coordinates
            grad_s = t / (L * L)
            ab = (h[r] - h[p]) * grad_s + m * out
            c = h[p] - ab @ qc[p]
            queue.append(np.array([ab[0], ab[1], c]))
    planes = []
    for abc, contacts, above in found.values():
        if any(np.all(np.abs(abc - p[1]) <= htol + 1e-9 * np.abs(p[1])) for p in planes):
            continue  # one plane reached twice (contacts differing by rounding)
        norm = np.sqrt(1.0 + abc[0] ** 2 + abc[1] ** 2)
        dist = np.maximum(above, 0.0) / norm
        planes.append((float(dist.max()), abc, contacts, dist, norm))
    planes.sort(key=lambda x: -x[0])
    value, (a, b, c), contacts, dist, norm = planes[0]
    sigma = np.nan if sig is None else _sigma_value(qc, gc, contacts, dist, sig)
    # the plane in world coordinates: h - a x' - b y' = c  (x' measured from q0)
    nw = (reference.normal - a * T[0] - b * T[1]) / norm
    off = (c + reference.offset - a * q0[0] - b * q0[1]) / norm
    return Coplanarity(value, dist, contacts, nw, float(off),
                       alternatives=np.array([p[0] for p in planes]),
                       cog_tolerance=float(cog_tolerance), sigma=float(sigma))


def _sigma_value(qc, gc, contacts, dist, sig) -> float:
    """First-order sigma of the coplanarity: the farthest apex's height less the plane
    through three contacts (the triangle holding the centre of gravity, or nearest it)
    at its place: d value = d h_far - sum_i lambda_i d h_i (lambda: barycentric)."""
    far = int(np.argmax(dist))
    best = None
    for i in range(len(contacts)):
        for j in range(i + 1, len(contacts)):
            for k in range(j + 1, len(contacts)):
                tri = contacts[[i, j, k]]
                P = np.column_stack([qc[tri], np.ones(3)])
                if abs(np.linalg.det(P)) < 1e-12:
                    continue
                lam_g = np.linalg.solve(P.T, np.array([gc[0], gc[1], 1.0]))
                score = float(lam_g.min())
                if best is None or score > best[0]:
                    best = (score, tri, P)
    if best is None:
        return np.nan
    _, tri, P = best
    lam = np.linalg.solve(P.T, np.array([qc[far, 0], qc[far, 1], 1.0]))
    if far in tri:  # the farthest apex is a contact only when the value is 0
        return 0.0
    return float(np.sqrt(sig[far] ** 2 + np.sum((lam * sig[tri]) ** 2)))
