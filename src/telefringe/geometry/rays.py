"""Rays: lines in the world, one per pixel, as a device sees them.

A ray is a point ``origin`` (mm) and a unit ``direction`` (from the device into the
scene). Arrays broadcast over leading axes: a telecentric device gives one direction
(3,) for every pixel, a pinhole device one origin (its centre, (3,)) for every pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Rays"]


def _frozen_copy(a, name: str) -> np.ndarray:
    arr = np.array(a, dtype=float)  # a copy: the caller's array is never changed
    if arr.ndim < 1 or arr.shape[-1] != 3:
        raise ValueError(f"Rays.{name} must have shape (..., 3), got {arr.shape}")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class Rays:
    """Lines ``origin + s * direction`` (s in mm along the direction).

    Attributes
    ----------
    origin : (..., 3) ndarray of float, mm, a point of each line (world frame).
    direction : (..., 3) ndarray of float, unit vectors, broadcastable with ``origin``.

    Unpacks as ``origin, direction = rays``. Both arrays are read-only copies of what
    was given. Raises ``ValueError`` if the shapes do not broadcast or a finite
    direction is not of unit length (to 1e-9).
    """

    origin: np.ndarray
    direction: np.ndarray

    def __post_init__(self):
        o = _frozen_copy(self.origin, "origin")
        d = _frozen_copy(self.direction, "direction")
        try:
            np.broadcast_shapes(o.shape, d.shape)
        except ValueError:
            raise ValueError(f"Rays: origin {o.shape} and direction {d.shape} do not "
                             "broadcast") from None
        n = np.linalg.norm(d, axis=-1)
        bad = np.isfinite(n) & (np.abs(n - 1.0) > 1e-9)
        if np.any(bad):
            raise ValueError("Rays.direction must hold unit vectors")
        object.__setattr__(self, "origin", o)
        object.__setattr__(self, "direction", d)

    def __iter__(self):
        yield self.origin
        yield self.direction

    @property
    def shape(self) -> tuple[int, ...]:
        """The broadcast shape of the rays (without the trailing 3)."""
        return np.broadcast_shapes(self.origin.shape, self.direction.shape)[:-1]

    def point_at(self, s) -> np.ndarray:
        """Points ``origin + s * direction`` (..., 3) mm for distances ``s`` (...,) mm."""
        s = np.asarray(s, dtype=float)
        return self.origin + s[..., None] * self.direction

    def directions(self) -> np.ndarray:
        """The direction of every ray, broadcast to (..., 3) (a read-only view)."""
        return np.broadcast_to(self.direction, self.shape + (3,))
