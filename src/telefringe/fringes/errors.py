"""The decoder's error types."""

from telefringe.fringes.unwrap import LadderError

__all__ = ["DecodeError", "LadderDecodeError"]


class DecodeError(ValueError):
    """The scan cannot be decoded as asked (message says why)."""


class LadderDecodeError(DecodeError, LadderError):
    """The fringe periods of an axis cannot give its absolute phase."""
