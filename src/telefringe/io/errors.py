"""Errors a user can fix (bad files, manifests, options)."""

from __future__ import annotations

__all__ = ["InputError"]


class InputError(ValueError):
    """A user input problem: the message names the file and what is wrong.

    The command line prints it as one line and exits with status 2.
    """
