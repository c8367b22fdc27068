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
    value : float, mm, the largest distance of an apex from the seating plane.
    distances : (n,) mm, each ball's apex distance from the seating plane (>= 0).
    contacts : (k,) int, indices of the balls the package rests on (k >= 3, usually 3).
    normal : (3,) world unit normal of the seating plane (toward the camera).
    offset : float, mm, ``normal . x = offset`` on the seating plane.
    """

    value: float
    distances: np.ndarray
    contacts: np.ndarray
    normal: np.ndarray
    offset: float

    def __post_init__(self):
        _freeze(self, "distances", "contacts", "normal")


def seating_plane_coplanarity(apexes, centre_of_gravity, *, reference: Plane) -> Coplanarity:
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

    Parameters
    ----------
    apexes : (n, 3) world mm, n >= 3.
    centre_of_gravity : (2,) or (3,) world mm; projected onto ``reference``.
    reference : Plane, the substrate plane.
    """
    from scipy.optimize import linprog

    A = np.asarray(apexes, dtype=np.float64)
    if A.ndim != 2 or A.shape[1] != 3 or A.shape[0] < 3 or not np.all(np.isfinite(A)):
        raise MetrologyError("coplanarity needs at least 3 finite apexes (n, 3)")
    T = _tangent_basis(reference.normal)
    q = A @ T.T  # (n, 2)
    h = A @ reference.normal - reference.offset
    g = np.asarray(centre_of_gravity, dtype=np.float64).reshape(-1)
    if g.size == 2:
        g = np.array([g[0], g[1], float(reference.z_at(g[0], g[1]))])
    qg = T @ g
    q0 = q.mean(axis=0)  # centred for conditioning
    qc = q - q0
    res = linprog(np.array([qg[0] - q0[0], qg[1] - q0[1], 1.0]),
                  A_ub=-np.column_stack([qc, np.ones(len(h))]), b_ub=-h,
                  bounds=[(None, None)] * 3, method="highs")
    if res.status != 0:
        raise MetrologyError(
            "no seating plane: the centre of gravity is outside the balls' footprint")
    a, b, c = res.x
    above = a * qc[:, 0] + b * qc[:, 1] + c - h  # >= 0, vertical gap
    norm = np.sqrt(1.0 + a * a + b * b)
    dist = np.maximum(above, 0.0) / norm
    tol = 1e-9 + 1e-9 * np.max(np.abs(h))
    contacts = np.flatnonzero(above <= tol)
    # the plane in world coordinates: h - a x' - b y' = c  (x' measured from q0)
    nw = (reference.normal - a * T[0] - b * T[1]) / norm
    off = (c + reference.offset - a * q0[0] - b * q0[1]) / norm
    return Coplanarity(float(dist.max()), dist, contacts, nw, float(off))
