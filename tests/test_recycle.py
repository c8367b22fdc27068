"""The recycled output memory (telefringe._recycle): reused only once no array uses it,
bounded, thread-safe, and decode / triangulate give the same results with it as without."""

import gc
import sys
import threading

import numpy as np
import pytest

from telefringe import _recycle
from telefringe.fringes.decode import decode
from telefringe.fringes.scan import PhaseGroup, Scan, ScanManifest

MB = 2 ** 20


@pytest.fixture
def pool(monkeypatch):
    monkeypatch.setattr(_recycle, "MAX_BYTES", 8 * MB)
    monkeypatch.setattr(_recycle, "MIN_BYTES", 1024)
    _recycle.clear()
    yield _recycle
    _recycle.clear()


def test_memory_is_reused_only_when_no_array_uses_it(pool):
    a = pool.empty((256, 512))
    assert a.dtype == np.float64 and a.shape == (256, 512) and a.flags.c_contiguous
    assert a.flags.writeable and a.flags.aligned
    addr = a.ctypes.data
    view = a[3:7, ::2]
    del a
    gc.collect()
    b = pool.empty((256, 512))  # the view keeps the first block alive
    assert b.ctypes.data != addr and not np.shares_memory(b, view)
    del view
    assert pool.pooled_bytes() == 256 * 512 * 8
    c = pool.empty((512, 256))  # same size: the block comes back
    assert c.ctypes.data == addr and pool.pooled_bytes() == 0
    # another dtype over the same bytes
    del c
    d = pool.empty((256, 512, 8), dtype=np.uint8)
    assert d.ctypes.data == addr and d.dtype == np.uint8
    del b, d


def test_small_and_object_arrays_are_plain(pool):
    a = pool.empty(10, dtype=np.int32)
    assert a.base is None and a.shape == (10,)
    o = pool.empty((200, 200), dtype=object)
    assert o.base is None


def test_pool_is_bounded(pool):
    arrays = [pool.empty(MB // 8) for _ in range(12)]  # 12 MB handed out
    assert pool.pooled_bytes() == 0
    del arrays
    assert pool.pooled_bytes() == 8 * MB  # the other 4 MB went back to the system
    big = pool.empty(16 * MB // 8)  # larger than the bound: never pooled
    assert big.base is None
    pool.clear()
    assert pool.pooled_bytes() == 0


def test_pool_is_thread_safe(pool):
    errors = []
    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)

    def work(seed):
        rng = np.random.default_rng(seed)
        try:
            for _ in range(300):
                n = int(rng.choice([1024, 2048, 4096]))
                a = pool.empty(n)
                a[:] = seed
                b = pool.empty(n)
                b[:] = -seed
                if not (np.all(a == seed) and np.all(b == -seed)):
                    errors.append("two live arrays share memory")
                assert pool.pooled_bytes() <= pool.MAX_BYTES
        except Exception as exc:  # noqa: BLE001
            errors.append(repr(exc))

    try:
        threads = [threading.Thread(target=work, args=(s,)) for s in range(1, 5)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        sys.setswitchinterval(old)
    assert not errors, errors[:3]
    assert pool.pooled_bytes() <= pool.MAX_BYTES


def _scan():
    rng = np.random.default_rng(2)
    rows, cols = 40, 96
    yy, xx = np.mgrid[0:rows, 0:cols].astype(float)
    x = 20 + xx * 7.9 + 0.3 * yy
    stacks = []
    for p in (1, 8, 64):
        k = np.arange(4)[:, None, None]
        pat = 0.5 + 0.5 * np.cos(2 * np.pi * p * x / 800 + 2 * np.pi * k / 4)
        img = 40 + 160 * pat ** 2.2 + rng.normal(0, 1.2, (4, rows, cols))
        stacks.append(np.clip(np.round(img), 0, 255).astype(np.uint8))
    man = ScanManifest(800, 600, tuple(PhaseGroup("u", p, 4) for p in (1, 8, 64)))
    return Scan(man, tuple(stacks))


def test_decode_results_equal_and_independent_with_recycled_memory(pool):
    scan = _scan()
    pool.MAX_BYTES = 0  # plain numpy.empty: the reference
    ref = decode(scan)
    pool.MAX_BYTES = 8 * MB
    first = decode(scan)
    snapshot = {k: np.copy(v) for k, v in vars(first).items() if isinstance(v, np.ndarray)}
    del first
    gc.collect()
    assert pool.pooled_bytes() > 0  # the first result's memory came back
    again = decode(scan)  # ... and is reused
    live = decode(scan)  # while `again` lives, a new result has its own memory
    for name, arr in snapshot.items():
        for res in (again, live):
            np.testing.assert_array_equal(getattr(res, name), arr, err_msg=name)
            np.testing.assert_array_equal(getattr(ref, name), arr, err_msg=name)
        assert not np.shares_memory(getattr(again, name), getattr(live, name))
    for name in ("coordinate", "sigma", "valid", "modulation", "background", "saturated",
                 "low_modulation", "shadow", "order_reliable", "exposure"):
        a, b = getattr(again.axes["u"], name), getattr(live.axes["u"], name)
        np.testing.assert_array_equal(a, getattr(ref.axes["u"], name), err_msg=name)
        assert not np.shares_memory(a, b), name


@pytest.mark.parametrize("use_v", [False, True])
def test_triangulate_equal_and_independent_with_recycled_memory(pool, use_v):
    sys.path.insert(0, str(__import__("pathlib").Path(__file__).parent))
    from test_reconstruct import SHAPE, Coords, make_rig, surface_points

    from telefringe.reconstruction.telecentric import triangulate

    rig = make_rig()
    _, up, vp = surface_points(rig)
    sig = np.full(SHAPE, 0.02)
    c = Coords(up, vp if use_v else None, None, sig, sig if use_v else None)
    pool.MAX_BYTES = 0
    ref = triangulate(rig, c)
    pool.MAX_BYTES = 8 * MB
    pool.MIN_BYTES = 256
    first = triangulate(rig, c)
    del first
    gc.collect()
    assert pool.pooled_bytes() > 0
    a, b = triangulate(rig, c), triangulate(rig, c)
    for name in ("xyz", "mask", "sigma_line", "flags") + (("residual",) if use_v else ()):
        np.testing.assert_array_equal(getattr(a, name), getattr(ref, name), err_msg=name)
        np.testing.assert_array_equal(getattr(b, name), getattr(ref, name), err_msg=name)
        assert not np.shares_memory(getattr(a, name), getattr(b, name)), name
