"""Fringe-free images of a scan: where markers and radiance are read."""

from __future__ import annotations

import numpy as np

__all__ = ["fringe_free_image"]


def fringe_free_image(scan) -> np.ndarray:
    """The image of a scan in which to look for the target's markers (float64).

    The ``white`` frame when the scan has one, else the mean of the phase group with the
    most steps (ties: the finest), whose sum over a full set of equal shifts cancels the
    fringes.
    """
    if scan.white is not None:
        return np.asarray(scan.white, dtype=np.float64)
    groups = list(zip(scan.manifest.groups, scan.stacks, strict=True))
    phase = [(g, s) for g, s in groups if hasattr(g, "periods")]
    if not phase:
        raise ValueError(f"{scan.source}: no white frame and no phase group to average")
    g, s = max(phase, key=lambda gs: (gs[0].steps, gs[0].periods, gs[0].exposure <= 1.0))
    return np.asarray(s, dtype=np.float64).mean(axis=0)
