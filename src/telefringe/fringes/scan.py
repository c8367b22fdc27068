"""In-memory scan description and content (no file access here; see ``telefringe.io``).

A scan is a set of pattern groups captured by the camera:

- :class:`PhaseGroup`: ``steps`` images of sinusoidal fringes with ``periods`` periods
  across the projector ``axis`` (``"u"``: vertical fringes, phase along columns and
  normalised by the projector width; ``"v"``: along rows, by the height). Image k shows
  ``0.5 + 0.5 cos(2 pi periods x / L + offset + 2 pi k / steps)``.
- :class:`GrayGroup`: ``bits`` Gray-code images (most significant first), plus one
  complementary image when ``complementary`` is true (see DESIGN.md).

Groups that differ only in ``exposure`` form one HDR set.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["PhaseGroup", "GrayGroup", "ScanManifest", "Scan", "AXES"]

AXES = ("u", "v")


@dataclass(frozen=True)
class PhaseGroup:
    """One phase-shifted fringe group (see module docstring). ``images`` are file names."""

    axis: str
    periods: int
    steps: int
    exposure: float = 1.0
    offset: float = 0.0
    images: tuple[str, ...] = ()

    def __post_init__(self):
        if self.axis not in AXES:
            raise ValueError(f"axis must be 'u' or 'v', got {self.axis!r}")
        if int(self.steps) < 3:
            raise ValueError(f"steps must be >= 3, got {self.steps!r}")
        if int(self.periods) < 1:
            raise ValueError(f"periods must be >= 1, got {self.periods!r}")
        if not (np.isfinite(self.exposure) and self.exposure > 0):
            raise ValueError(f"exposure must be finite and > 0, got {self.exposure!r}")
        if not np.isfinite(self.offset):
            raise ValueError(f"offset must be finite, got {self.offset!r}")

    @property
    def count(self) -> int:
        """Number of images the group holds."""
        return int(self.steps)

    @property
    def key(self) -> tuple:
        """Identity of the group apart from exposure (HDR sets share it)."""
        return ("phase", self.axis, int(self.periods), int(self.steps), float(self.offset))


@dataclass(frozen=True)
class GrayGroup:
    """A Gray-code group fixing the fringe order of the phase group with periods 2**bits."""

    axis: str
    bits: int
    complementary: bool = False
    exposure: float = 1.0
    images: tuple[str, ...] = ()

    def __post_init__(self):
        if self.axis not in AXES:
            raise ValueError(f"axis must be 'u' or 'v', got {self.axis!r}")
        if not 1 <= int(self.bits) <= 16:
            raise ValueError(f"bits must be in 1..16, got {self.bits!r}")
        if not (np.isfinite(self.exposure) and self.exposure > 0):
            raise ValueError(f"exposure must be finite and > 0, got {self.exposure!r}")

    @property
    def count(self) -> int:
        return int(self.bits) + (1 if self.complementary else 0)

    @property
    def key(self) -> tuple:
        return ("gray", self.axis, int(self.bits), bool(self.complementary))


@dataclass(frozen=True)
class ScanManifest:
    """What a scan holds (the content of ``scan.json``, validated)."""

    projector_width: int
    projector_height: int
    groups: tuple[PhaseGroup | GrayGroup, ...]
    white: str | None = None
    black: str | None = None

    @property
    def phase_groups(self) -> tuple[PhaseGroup, ...]:
        return tuple(g for g in self.groups if isinstance(g, PhaseGroup))

    @property
    def gray_groups(self) -> tuple[GrayGroup, ...]:
        return tuple(g for g in self.groups if isinstance(g, GrayGroup))

    def axis_length(self, axis: str) -> int:
        """Projector pixels across the given axis (width for 'u', height for 'v')."""
        return int(self.projector_width if axis == "u" else self.projector_height)


@dataclass(frozen=True, eq=False)
class Scan:
    """A scan's manifest with its images loaded.

    Attributes
    ----------
    manifest : ScanManifest
    stacks : tuple of (n_g, rows, cols) ndarray, one per ``manifest.groups`` entry, in the
        same order; dtype uint8 or uint16 (or float in [0, max_value] for synthetic data).
    white, black : (rows, cols) ndarray or None.
    max_value : float, the sensor's saturation value (255 for 8 bit, 65535 for 16 bit,
        4095 for 12-bit data stored in 16 bit when the manifest says so).
    source : str, where it came from (a folder name), for messages.
    """

    manifest: ScanManifest
    stacks: tuple[np.ndarray, ...]
    white: np.ndarray | None = None
    black: np.ndarray | None = None
    max_value: float = 255.0
    source: str = "<memory>"
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        if len(self.stacks) != len(self.manifest.groups):
            raise ValueError(
                f"{self.source}: {len(self.stacks)} image stacks for "
                f"{len(self.manifest.groups)} pattern groups"
            )
        shape = None
        for g, s in zip(self.manifest.groups, self.stacks, strict=True):
            if s.ndim != 3 or s.shape[0] != g.count:
                raise ValueError(
                    f"{self.source}: group {g.key} needs {g.count} images, stack has shape "
                    f"{s.shape}"
                )
            if shape is None:
                shape = s.shape[1:]
            elif s.shape[1:] != shape:
                raise ValueError(f"{self.source}: image sizes differ: {shape} vs {s.shape[1:]}")
        for name in ("white", "black"):
            im = getattr(self, name)
            if im is not None and shape is not None and im.shape != shape:
                raise ValueError(f"{self.source}: {name} image size {im.shape} != {shape}")

    @property
    def shape(self) -> tuple[int, int]:
        """Camera image shape (rows, cols)."""
        if self.stacks:
            return tuple(self.stacks[0].shape[1:])
        if self.white is not None:
            return tuple(self.white.shape)
        raise ValueError(f"{self.source}: scan has no images")
