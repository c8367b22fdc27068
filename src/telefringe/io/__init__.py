"""File formats and file access. The only package (with ``cli``) that touches files."""

from .errors import InputError

__all__ = ["InputError"]
