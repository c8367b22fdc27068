"""The calibration's error type."""

__all__ = ["CalibrationError"]


class CalibrationError(ValueError):
    """Calibration cannot proceed: too few poses, degenerate views, no convergence."""
