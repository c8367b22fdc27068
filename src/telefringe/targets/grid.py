"""The calibration target: a planar grid of circles."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["CIRCLE_STYLES", "CircleGridTarget"]

#: How the circles differ from the plate.
CIRCLE_STYLES = ("dark-on-light", "light-on-dark")


@dataclass(frozen=True)
class CircleGridTarget:
    """A planar grid of circles: ``rows`` x ``cols`` at ``pitch_mm``; dark on light."""

    rows: int
    cols: int
    pitch_mm: float
    diameter_mm: float
    circles: str = "dark-on-light"

    def __post_init__(self):
        for nm in ("rows", "cols"):
            v = getattr(self, nm)
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 2:
                raise ValueError(f"CircleGridTarget.{nm} must be an integer >= 2, got {v!r}")
        for nm in ("pitch_mm", "diameter_mm"):
            v = getattr(self, nm)
            if (isinstance(v, bool) or not isinstance(v, int | float | np.integer | np.floating)
                    or not np.isfinite(v) or v <= 0):
                raise ValueError(f"CircleGridTarget.{nm} must be a positive number, got {v!r}")
        if self.diameter_mm >= self.pitch_mm:
            raise ValueError("CircleGridTarget.diameter_mm must be smaller than pitch_mm")
        if self.circles not in CIRCLE_STYLES:
            raise ValueError(f"CircleGridTarget.circles must be one of {CIRCLE_STYLES}, got "
                             f"{self.circles!r}")

    def points_target(self) -> np.ndarray:
        """Circle centres in the target frame, (rows * cols, 3) mm, row-major (row, col):
        x = col * pitch, y = row * pitch, z = 0."""
        r, c = np.mgrid[0:self.rows, 0:self.cols]
        return np.stack([c.ravel() * self.pitch_mm, r.ravel() * self.pitch_mm,
                         np.zeros(r.size)], axis=1)

