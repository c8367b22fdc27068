"""The nominal ball grid of a BGA."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from telefringe.metrology._common import MetrologyError


@dataclass(frozen=True, eq=False)
class BGANominal:
    """The nominal ball grid.

    Attributes
    ----------
    rows, cols : int, or None: the grid spanned by the balls found (then a missing ball
        on the outer rows or columns cannot be told from a smaller grid).
    pitch_mm, ball_diameter_mm : float.
    present : (rows, cols) bool, optional: populated positions (default: all).
    centre_of_gravity : (2,) world (x, y) mm, optional: where the package's weight acts,
        for the seating plane (default: the centre of the ball grid).
    """

    rows: int | None
    cols: int | None
    pitch_mm: float
    ball_diameter_mm: float
    present: np.ndarray | None = None
    centre_of_gravity: tuple | None = None

    def __post_init__(self):
        if (self.rows is None) != (self.cols is None):
            raise MetrologyError("give both rows and cols, or neither")
        if self.rows is not None and (int(self.rows) < 1 or int(self.cols) < 1):
            raise MetrologyError("rows and cols must be >= 1")
        if self.rows is None and self.present is not None:
            raise MetrologyError("a populated map needs rows and cols")
        if not (np.isfinite(self.pitch_mm) and self.pitch_mm > 0):
            raise MetrologyError("pitch_mm must be > 0")
        if not (np.isfinite(self.ball_diameter_mm) and 0 < self.ball_diameter_mm):
            raise MetrologyError("ball_diameter_mm must be > 0")
        if self.present is not None:
            p = np.array(self.present, dtype=bool)
            if p.shape != (self.rows, self.cols):
                raise MetrologyError(f"present must have shape ({self.rows}, {self.cols})")
            p.setflags(write=False)
            object.__setattr__(self, "present", p)

    def populated(self) -> np.ndarray:
        return (np.ones((self.rows, self.cols), dtype=bool) if self.present is None
                else self.present)
