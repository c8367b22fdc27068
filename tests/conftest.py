"""Shared test helpers."""

import fcntl
import hashlib
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from telefringe.fringes.phase import NoiseModel


def _rig_noise(vrig) -> NoiseModel:
    """The virtual rig's camera noise in DN (8 bit): shot noise of ``full_well_e`` electrons
    at 255 DN and read noise (quantisation is added by the decoder's noise model)."""
    ph = vrig.photometry
    return NoiseModel(read_noise=ph.read_noise_e * 255 / ph.full_well_e,
                      gain=255 / ph.full_well_e)


@pytest.fixture(scope="session")
def rig_noise():
    """``rig_noise(vrig) -> NoiseModel``: the camera noise of a virtual rig, in DN."""
    return _rig_noise


def _jacobian_error(problem, x, rel_step: float = 1e-6) -> float:
    """Largest error of ``problem.jacobian(x)`` against central differences of
    ``problem.residuals`` (step ``rel_step`` of each parameter, at least of 1e-3), relative
    to each column's largest entry."""
    J = problem.jacobian(x).toarray()
    num = np.empty_like(J)
    for j in range(x.size):
        h = rel_step * max(abs(x[j]), 1e-3)
        xp, xm = x.copy(), x.copy()
        xp[j] += h
        xm[j] -= h
        num[:, j] = (problem.residuals(xp) - problem.residuals(xm)) / (2 * h)
    scale = np.maximum(np.abs(num).max(axis=0), 1e-12)
    return float(np.max(np.abs(J - num) / scale))


@pytest.fixture(scope="session")
def jacobian_error():
    """``jacobian_error(problem, x, rel_step=1e-6) -> float``: a bundle problem's analytic
    Jacobian against finite differences (relative to each column's scale)."""
    return _jacobian_error


def _share_numba_compilations_between_workers() -> None:
    """Under pytest-xdist, one worker compiles each cached (``cache=True``) numba kernel
    and the others load it from numba's disk cache.

    On a fresh clone numba's cache is empty, and both workers reach the common kernels
    (rendering, decoding, triangulation) at about the same time: each would compile them
    (several CPU minutes in all). Here a worker about to compile a cached kernel first
    takes an exclusive file lock named after the kernel's cache files; a worker asking for
    it meanwhile waits, then finds it in the cache (``Dispatcher.compile`` looks there
    first). The machine code run is the same either way: numba's cache holds what the
    other worker compiled from the same source file (its stamp is checked on loading).
    Locks are taken inside the process's own compiler lock, so threads never hold them in
    two orders; kernels calling each other form no cycle, so workers cannot deadlock.
    After 15 minutes' wait a worker compiles anyway."""
    from numba.core.caching import NullCache
    from numba.core.compiler_lock import global_compiler_lock
    from numba.core.dispatcher import Dispatcher

    lock_dir = Path(tempfile.gettempdir()) / f"telefringe-numba-locks-{os.getuid()}"
    lock_dir.mkdir(exist_ok=True)
    held: set[str] = set()
    compile_ = Dispatcher.compile

    def compile_once(self, sig):
        cache = getattr(self, "_cache", None)
        name = None
        if cache is not None and not isinstance(cache, NullCache):
            try:  # numba's private cache layout: a numba without it compiles as always
                name = os.path.join(cache._cache_path, cache._impl.filename_base)
            except AttributeError:
                name = None
        if name is None:
            return compile_(self, sig)
        key = hashlib.sha256(name.encode()).hexdigest()[:24]
        with global_compiler_lock:
            if key in held:  # a nested compilation of the same kernel in this process
                return compile_(self, sig)
            with open(lock_dir / key, "a") as f:
                deadline = time.monotonic() + 900.0
                while True:
                    try:
                        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
                        locked = True
                        break
                    except BlockingIOError:
                        if time.monotonic() > deadline:
                            locked = False
                            break
                        time.sleep(0.05)
                held.add(key)
                try:
                    return compile_(self, sig)
                finally:
                    held.discard(key)
                    if locked:
                        fcntl.flock(f, fcntl.LOCK_UN)

    Dispatcher.compile = compile_once


if os.environ.get("PYTEST_XDIST_WORKER"):
    _share_numba_compilations_between_workers()
