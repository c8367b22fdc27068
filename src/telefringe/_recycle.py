"""Recycled memory for the large per-scan output arrays (private).

Decoding and triangulating a 1.3 Mpx scan return about 110 MB of fresh arrays. Fresh
memory costs more than the arithmetic that fills it: the kernel maps and zeroes every
page on first touch (measured on the 2-core machine: about 0.2 ms per MB with 2 MB
pages, 0.6 ms per MB with 4 kB pages; some 20 ms of CPU per scan, as much as the
decoding itself), and the C allocator gives those pages back to the system as soon as
the arrays are freed, so a loop over scans pays it again for every scan.

:func:`empty` hands out arrays whose memory comes back here, instead of to the system,
when the last array (or view) using it is gone; the next array of the same size reuses
it, pages already mapped. The arrays are ordinary NumPy arrays (uninitialised, like
``numpy.empty``; their ``base`` is a small owner object). The pool is bounded
(:data:`MAX_BYTES`, least recently returned dropped first) and thread-safe; only arrays
of at least :data:`MIN_BYTES` take part.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np

__all__ = ["empty", "clear", "pooled_bytes", "MAX_BYTES", "MIN_BYTES"]

#: bytes of returned memory the pool keeps at most (about two 1.3 Mpx scans' outputs)
MAX_BYTES = 256 * 2 ** 20
#: smaller arrays are plain ``numpy.empty`` (the C allocator reuses small blocks itself)
MIN_BYTES = 256 * 2 ** 10

# re-entrant: an owner may be finalised (and give its memory back) by a garbage
# collection that runs while this thread holds the lock
_LOCK = threading.RLock()
_FREE: OrderedDict[int, list] = OrderedDict()  # nbytes -> raw uint8 buffers
_STATE = {"bytes": 0}


class _Owner:
    """Owns one raw buffer for the arrays made from it; gives it back when collected."""

    __slots__ = ("_buf", "__array_interface__")

    def __init__(self, buf: np.ndarray, shape: tuple, dtype: np.dtype):
        self._buf = buf
        self.__array_interface__ = {"shape": shape, "typestr": dtype.str,
                                    "descr": dtype.descr, "data": (buf.ctypes.data, False),
                                    "strides": None, "version": 3}

    def __del__(self):
        try:
            _give_back(self._buf)
        except Exception:  # noqa: BLE001 - interpreter shutdown: nothing to give back to
            pass


def _give_back(buf: np.ndarray) -> None:
    n = buf.nbytes
    with _LOCK:
        if n > MAX_BYTES:
            return
        _FREE.setdefault(n, []).append(buf)
        _FREE.move_to_end(n)
        _STATE["bytes"] += n
        while _STATE["bytes"] > MAX_BYTES:
            size, bufs = next(iter(_FREE.items()))
            bufs.pop(0)
            _STATE["bytes"] -= size
            if not bufs:
                del _FREE[size]


def _take(n: int) -> np.ndarray | None:
    with _LOCK:
        bufs = _FREE.get(n)
        if not bufs:
            return None
        buf = bufs.pop()
        _STATE["bytes"] -= n
        if not bufs:
            del _FREE[n]
        return buf


def empty(shape, dtype=np.float64) -> np.ndarray:
    """An uninitialised C-contiguous array like ``numpy.empty(shape, dtype)``, its memory
    recycled (see the module's notes).

    Parameters
    ----------
    shape : int or tuple of int
    dtype : data type (fixed size, no objects)

    Returns
    -------
    ndarray
        Writeable, aligned, C-contiguous; every element must be written before it is read.
    """
    dtype = np.dtype(dtype)
    shape = (int(shape),) if np.ndim(shape) == 0 else tuple(int(s) for s in shape)
    n = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if n < MIN_BYTES or n > MAX_BYTES or dtype.hasobject:
        return np.empty(shape, dtype=dtype)
    buf = _take(n)
    if buf is None:
        buf = np.empty(n, dtype=np.uint8)
    return np.asarray(_Owner(buf, shape, dtype))


def pooled_bytes() -> int:
    """Bytes of memory waiting in the pool for reuse."""
    with _LOCK:
        return _STATE["bytes"]


def clear() -> None:
    """Give the pooled memory back to the system."""
    with _LOCK:
        _FREE.clear()
        _STATE["bytes"] = 0
