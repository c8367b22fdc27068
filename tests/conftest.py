"""Shared test helpers."""

import fcntl
import hashlib
import os
import shutil
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


def _built_once(tmp_path_factory, name: str, build) -> Path:
    """The folder ``name`` that ``build(folder)`` fills, built once per test run and shared
    by every test module (and every pytest-xdist worker) that asks for it: treat it as
    read-only (copy what a test writes into).

    It sits beside the workers' own temporary folders (in the run's base folder, which
    xdist's workers share), behind an exclusive file lock: the first asker builds it into
    a ``.part`` folder renamed when complete, the others wait and then find it. A build
    that raises leaves nothing, and the next asker builds it again."""
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent
    folder = root / f"shared-{name}"
    with open(root / f"shared-{name}.lock", "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            if not folder.exists():
                part = root / f"shared-{name}.part"
                shutil.rmtree(part, ignore_errors=True)
                part.mkdir()
                build(part)
                part.rename(folder)
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)
    return folder


def _paper_bga_window():
    """The paper rig read out in the 160 x 160 px window of its BGA view (about 6 x 6 balls
    at full resolution), a VirtualRig."""
    from telefringe.simulate.experiments import bga_window
    from telefringe.simulate.presets import crop_camera, get_preset

    paper = get_preset("paper")
    col0, row0 = bga_window(paper, size=160)
    return crop_camera(paper, col0=col0, row0=row0, width=160, height=160)


@pytest.fixture(scope="session")
def bga_window_reconstruction(tmp_path_factory):
    """``(vrig, folder)``: the paper rig read out in the 160 x 160 px window of its BGA
    view (about 6 x 6 balls at full resolution, a VirtualRig), and the reconstruction
    folder (``reconstruct_to_folder``'s output; read-only: copy it before a command
    writes into it) of its HDR scan of the virtual BGA (``make_scene("bga", seed=4)``,
    ``HDR_EXPOSURES``, seed 4), made once per test run for every module that measures
    it."""
    def build(folder):
        import telefringe.simulate.render as sim
        from telefringe.cli.reconstruct import reconstruct_to_folder
        from telefringe.io.scan_json import write_scan
        from telefringe.simulate import scenes
        from telefringe.simulate.presets import HDR_EXPOSURES

        vr = _paper_bga_window()
        scan, _ = sim.render_scan(vr, scenes.make_scene("bga", seed=4),
                                  sim.default_groups(vr), exposures=HDR_EXPOSURES, seed=4)
        write_scan(folder / "scan", scan)
        reconstruct_to_folder(folder / "scan", vr.rig, folder / "out")

    return _paper_bga_window(), _built_once(tmp_path_factory, "bga-window", build) / "out"


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
