"""Fringe and Gray-code pattern images for a projector of W x H pixels.

Convention (DESIGN.md): image k of a phase group shows
``0.5 + 0.5 cos(2 pi periods x / L + offset + 2 pi k / steps)`` with x the projector
column (axis "u", L = W) or row (axis "v", L = H), evaluated at pixel centres.
"""

from __future__ import annotations

import numpy as np

from telefringe.fringes.scan import GrayGroup, PhaseGroup

__all__ = ["fringe_intensity", "gray_code_bits", "pattern_stack", "quantize",
           "pattern_groups", "precompensate", "pattern_scan"]


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


# ------------------------------------------------------------------ pattern sets (decode)
def pattern_groups(*, steps: int, periods, axes=("u", "v"), gray_bits: int | None = None,
                   complementary: bool = True, offset: float = 0.0) -> tuple:
    """The groups of a pattern set: for each axis, one ``steps``-step phase group per
    period count (coarse to fine), then the Gray code (``gray_bits``) if asked.

    Returns
    -------
    tuple of PhaseGroup / GrayGroup (no image names).
    """
    groups = []
    for axis in axes:
        for p in sorted(int(q) for q in periods):
            groups.append(PhaseGroup(axis=axis, periods=p, steps=int(steps), offset=offset))
        if gray_bits:
            groups.append(GrayGroup(axis=axis, bits=int(gray_bits),
                                    complementary=bool(complementary)))
    return tuple(groups)


def precompensate(values, *, gamma: float | None = None, inverse_response=None) -> np.ndarray:
    """Pattern levels that make a nonlinear projector emit ``values`` (relative, 0..1).

    A projector emitting ``black + (1 - black) * p**gamma`` for level p emits an affine
    function of ``values`` when shown ``values**(1/gamma)``. For a measured response,
    pass ``inverse_response`` (a callable: wanted relative output -> level, e.g.
    :meth:`telefringe.gamma.ResponseCurve.inverse`).

    Parameters
    ----------
    values : array_like, relative intensities in [0, 1].
    gamma : float > 0 or None.  inverse_response : callable or None (exactly one of them).

    Returns
    -------
    ndarray of float, levels in [0, 1].
    """
    v = np.clip(np.asarray(values, dtype=float), 0.0, 1.0)
    if (gamma is None) == (inverse_response is None):
        raise ValueError("precompensate needs exactly one of gamma and inverse_response")
    if gamma is not None:
        if not (np.isfinite(gamma) and gamma > 0):
            raise ValueError(f"gamma must be finite and > 0, got {gamma!r}")
        return v ** (1.0 / float(gamma))
    return np.clip(np.asarray(inverse_response(v), dtype=float), 0.0, 1.0)


def pattern_scan(*, width: int, height: int, steps: int, periods, axes=("u", "v"),
                 gray_bits: int | None = None, complementary: bool = True,
                 white_black: bool = True, offset: float = 0.0, gamma: float | None = None,
                 inverse_response=None, bit_depth: int = 8):
    """The projector images of a whole pattern set as a :class:`~telefringe.scan.Scan`
    (stacks shaped (count, height, width); white/black frames when asked), ready for
    :func:`telefringe.io.scan_json.write_scan`. With ``gamma`` or ``inverse_response`` the
    fringes are pre-compensated (see :func:`precompensate`); Gray codes and white/black
    frames are binary and need none.
    """
    from telefringe.fringes.scan import Scan, ScanManifest

    groups = pattern_groups(steps=steps, periods=periods, axes=axes, gray_bits=gray_bits,
                            complementary=complementary, offset=offset)
    top = 2 ** bit_depth - 1
    dtype = np.uint8 if bit_depth <= 8 else np.uint16
    stacks = []
    for g in groups:
        if isinstance(g, PhaseGroup) and (gamma is not None or inverse_response is not None):
            length = width if g.axis == "u" else height
            coord = np.arange(length, dtype=float)
            rows = np.stack([quantize(precompensate(
                fringe_intensity(coord, periods=g.periods, steps=g.steps, k=k, length=length,
                                 offset=g.offset), gamma=gamma,
                inverse_response=inverse_response), bit_depth=bit_depth)
                for k in range(g.steps)])
            shape = (rows.shape[0], height, width)
            img = rows[:, None, :] if g.axis == "u" else rows[:, :, None]
            stacks.append(np.ascontiguousarray(np.broadcast_to(img, shape)))
        else:
            stacks.append(pattern_stack(g, width=width, height=height, bit_depth=bit_depth))
    white = np.full((height, width), top, dtype=dtype) if white_black else None
    black = np.zeros((height, width), dtype=dtype) if white_black else None
    man = ScanManifest(projector_width=int(width), projector_height=int(height),
                       groups=groups)
    return Scan(manifest=man, stacks=tuple(stacks), white=white, black=black,
                max_value=float(top), source="patterns")
