"""Fringe and Gray-code pattern images for a projector of W x H pixels.

Convention (DESIGN.md): image k of a phase group shows
``0.5 + 0.5 cos(2 pi periods x / L + offset + 2 pi k / steps)`` with x the projector
column (axis "u", L = W) or row (axis "v", L = H), evaluated at pixel centres.
"""

from __future__ import annotations

import numpy as np

from .scan import GrayGroup, PhaseGroup

__all__ = ["fringe_intensity", "gray_code_bits", "pattern_stack", "quantize"]


def fringe_intensity(x, *, periods: int, steps: int, k: int, length: int,
                     offset: float = 0.0) -> np.ndarray:
    """Relative intensity in [0, 1] of fringe image ``k`` at projector coordinate ``x``.

    Parameters
    ----------
    x : ndarray of float, any shape, projector pixels along the fringe axis.
    periods, steps, k : int.  length : int, W or H in pixels.  offset : float, rad.
    """
    x = np.asarray(x, dtype=float)
    return 0.5 + 0.5 * np.cos(2.0 * np.pi * periods * x / length + offset
                              + 2.0 * np.pi * k / steps)


def gray_code_bits(x, *, bits: int, length: int, complementary: bool) -> np.ndarray:
    """Bit images (0/1) of the Gray code at integer projector coordinate ``x``.

    Returns an array of shape (bits [+1], *x.shape): bit j < bits is bit j (most
    significant first) of the Gray code of block ``floor(x 2^bits / L)``; with
    ``complementary`` one more row holds the least significant bit of the Gray code of
    the half-blocks ``floor(x 2^(bits+1) / L)``.
    """
    x = np.asarray(x)
    block = np.floor(x * (2 ** bits) / length).astype(np.int64)
    gray = block ^ (block >> 1)
    out = [((gray >> (bits - 1 - j)) & 1) for j in range(bits)]
    if complementary:
        half = np.floor(x * (2 ** (bits + 1)) / length).astype(np.int64)
        out.append((half ^ (half >> 1)) & 1)
    return np.stack(out).astype(np.uint8)


def quantize(values, *, bit_depth: int = 8) -> np.ndarray:
    """Relative intensities in [0, 1] -> integer pattern levels (uint8 or uint16)."""
    top = 2 ** bit_depth - 1
    q = np.clip(np.round(np.asarray(values, dtype=float) * top), 0, top)
    return q.astype(np.uint8 if bit_depth <= 8 else np.uint16)


def pattern_stack(group: PhaseGroup | GrayGroup, *, width: int, height: int,
                  bit_depth: int = 8) -> np.ndarray:
    """The projector images of one group, (count, height, width) uint8 (or uint16).

    Phase images are quantised to ``bit_depth`` bits; Gray-code images are 0 or full.
    """
    length = width if group.axis == "u" else height
    coord = np.arange(length, dtype=float)
    if isinstance(group, PhaseGroup):
        rows = np.stack([quantize(fringe_intensity(coord, periods=group.periods,
                                                   steps=group.steps, k=k, length=length,
                                                   offset=group.offset), bit_depth=bit_depth)
                         for k in range(group.steps)])
    else:
        top = 2 ** bit_depth - 1
        rows = gray_code_bits(coord, bits=group.bits, length=length,
                              complementary=group.complementary).astype(np.uint32) * top
        rows = rows.astype(np.uint8 if bit_depth <= 8 else np.uint16)
    if group.axis == "u":
        return np.ascontiguousarray(np.broadcast_to(rows[:, None, :],
                                                    (rows.shape[0], height, width)))
    return np.ascontiguousarray(np.broadcast_to(rows[:, :, None], (rows.shape[0], height, width)))
