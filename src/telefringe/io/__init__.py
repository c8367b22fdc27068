"""File formats and file access. The only package (with ``cli``) that touches files."""

from telefringe.io.errors import InputError

__all__ = ["InputError"]
