"""The fast path of the decoder: the fused compiled kernel (wrapped phase, HDR fusion,
hierarchical unwrapping and the nonlinearity correction in one pass, float32 where that
is exact or bounded by tests), its cached correction tables, and ``decode_axis_fast``.
:func:`telefringe.fringes.decode.decode` uses it for every stack it can fuse."""

from __future__ import annotations

import collections
import functools
import math
import threading
from dataclasses import dataclass

import numpy as np

from telefringe import _recycle
from telefringe.fringes.errors import DecodeError, LadderDecodeError
from telefringe.fringes.nonlinearity import PhaseErrorModel
from telefringe.fringes.phase import NoiseModel

__all__ = ["FastCoordinates", "decode_axis_fast"]

TWO_PI = 2.0 * np.pi


@dataclass(frozen=True)
class FastCoordinates:
    """Result of :func:`decode_axis_fast` (arrays (rows, cols)).

    Attributes
    ----------
    coordinate : float64 (or float32), projector pixels, NaN where invalid.
    mask : bool.
    modulation : float64, DN, of the finest group.
    """

    coordinate: np.ndarray
    mask: np.ndarray
    modulation: np.ndarray


#: the correction tables of recent models, least recently used first; bounded in entries
#: and in bytes (a table has up to 2^20 + 2 entries: 8 MB with its noise factors), guarded by
#: a lock (decode runs in threads, e.g. under a Dask threaded scheduler)
_TABLE_CACHE: collections.OrderedDict = collections.OrderedDict()
_TABLE_CACHE_LOCK = threading.Lock()
_TABLE_CACHE_MAX_ENTRIES = 64
_TABLE_CACHE_MAX_BYTES = 64 * 2 ** 20
#: the corrections' Fourier series (:func:`_model_series`), least recently used first
_SERIES_CACHE: collections.OrderedDict = collections.OrderedDict()


def _table_bytes(value) -> int:
    g, nf, series = value
    return g.nbytes + nf.nbytes + (0 if series is None else series[0].nbytes
                                   + series[1].nbytes)


def _model_key(model: PhaseErrorModel) -> tuple:
    return (model.periods, tuple(model.harmonics), np.asarray(model.cos_coef).tobytes(),
            np.asarray(model.sin_coef).tobytes())


def _cache_get(key):
    with _TABLE_CACHE_LOCK:
        hit = _TABLE_CACHE.get(key)
        if hit is not None:
            _TABLE_CACHE.move_to_end(key)
        return hit


def _cache_put(key, value) -> None:
    for arr in (value[0], value[1], *(() if value[2] is None else value[2][:2])):
        arr.flags.writeable = False
    with _TABLE_CACHE_LOCK:
        _TABLE_CACHE[key] = value
        _TABLE_CACHE.move_to_end(key)
        total = sum(_table_bytes(v) for v in _TABLE_CACHE.values())
        while len(_TABLE_CACHE) > 1 and (len(_TABLE_CACHE) > _TABLE_CACHE_MAX_ENTRIES
                                         or total > _TABLE_CACHE_MAX_BYTES):
            _, old = _TABLE_CACHE.popitem(last=False)
            total -= _table_bytes(old)


#: the fused kernel's correction tables: the bounds their size is chosen for (linear
#: interpolation, from the correction's derivatives, :func:`_table_size`): the correction
#: g within TABLE_TOL rad, the noise factor 1 - g' within TABLE_NF_TOL (relative)
TABLE_TOL = 1e-7
TABLE_NF_TOL = 5e-7
TABLE_MIN_SIZE = 4096
TABLE_MAX_SIZE = 2 ** 20
#: a level's correction comes from the tables when its series has more terms than this,
#: or has none, or (full decode) its noise factor is not exact. The series costs 4 float32
#: operations per term and pixel (8 with the noise factor; Clenshaw's recurrence,
#: vectorised, in registers); the tables two (four with the noise factor) scalar look-ups
#: per pixel (LLVM does not gather on this machine's CPU): measured no faster in the full
#: decode for the paper rig's learned models (27, 16 and 4 terms;
#: benchmarks/reconstruct.py) even with the series' earlier complex powers (~8 operations
#: per term), so the tables serve only where the series cannot (48 = SERIES_MAX_TERMS:
#: never by length)
TABLE_MIN_TERMS = 48


def _smallest_size(n_min: int) -> int:
    """The smallest table size considered: a power of two >= max(n_min, TABLE_MIN_SIZE)."""
    return max(TABLE_MIN_SIZE, 1 << max(int(n_min) - 1, 0).bit_length())


def _derivative_bounds(model: PhaseErrorModel) -> tuple[float, float, float]:
    """Upper bounds (G1, G2, G3) of the first three derivatives' magnitudes (rad per
    rad^k) of the correction g of ``model`` (the measured phase minus the true one,
    against the measured phase): ``G_m = sum_k k^m |c_k|`` over the amplitudes |c_k| of
    g's Fourier series, from the FFT of g solved exactly at ``_SERIES_GRID`` points. The
    FFT's coefficients are g's own within the aliasing of the orders above
    _SERIES_GRID / 2, checked negligible: the amplitudes above order _SERIES_GRID / 4 sum
    to < 1e-13 rad (else ValueError)."""
    n = _SERIES_GRID
    grid = -np.pi + TWO_PI * np.arange(n) / n
    g = grid - model._invert(grid)
    amp = 2.0 * np.abs(np.fft.rfft(g)) / n
    amp[0] = 0.0
    if amp[n // 4:].sum() >= 1e-13:
        raise ValueError("the correction's Fourier series does not converge within "
                         f"{n // 4} orders: no table bound")
    k = np.arange(amp.size, dtype=np.float64)
    return tuple(float(np.sum(k ** m * amp)) for m in (1, 2, 3))


def _table_size(bounds, n_min: int = 1) -> int:
    """The smallest power of two M >= max(n_min, TABLE_MIN_SIZE) (at most TABLE_MAX_SIZE)
    whose linear interpolation, spacing h = 2 pi / M, keeps the correction within
    TABLE_TOL and the noise factor within TABLE_NF_TOL (relative): the error of linear
    interpolation of f on a cell of width h is at most h^2 / 8 max |f''|, i.e. h^2 / 8 G2
    for g and h^2 / 8 G3 for 1 - g' (which is at least 1 - G1 > 0)."""
    g1, g2, g3 = bounds
    m = _smallest_size(n_min)
    while m < TABLE_MAX_SIZE:
        c = (TWO_PI / m) ** 2 / 8.0
        if c * g2 <= TABLE_TOL and (g1 < 1.0 and c * g3 <= TABLE_NF_TOL * (1.0 - g1)):
            break
        m *= 2
    return m


def _checked_table_size(model: PhaseErrorModel, n_min: int = 1) -> int:
    """The table size where :func:`_derivative_bounds` has no bound (a correction whose
    Fourier series does not converge, e.g. a model learned from few pixels close to
    non-invertible): the smallest power of two M >= max(n_min, TABLE_MIN_SIZE) whose
    linear interpolation of the correction, checked against the exact inverse at every
    cell's mid-point (``PhaseErrorModel.correction_table``), is within TABLE_TOL rad;
    TABLE_MAX_SIZE at most."""
    m = _smallest_size(n_min)
    while m < TABLE_MAX_SIZE and model.correction_table(m)[1] > TABLE_TOL:
        m *= 2
    return m


def _model_tables(model: PhaseErrorModel, n_min: int) -> tuple[np.ndarray, np.ndarray, tuple]:
    """The fused kernel's tables of ``model``: the correction g (the measured phase minus
    the true one, by Newton's exact inverse) and the noise factor ``1 / (1 + e'(true
    phase)) = 1 - g'`` at the measured phases ``-pi + 2 pi j / M``, j = 0..M + 1 (the last
    two repeat the first two: no wrap in the look-up), float32 (M + 2,), M from
    :func:`_table_size` (>= n_min); and g as a Fourier series (:func:`_model_series`).
    Cached (thread-safe, at most ``_TABLE_CACHE_MAX_ENTRIES`` models and
    ``_TABLE_CACHE_MAX_BYTES``, least recently used evicted first); the arrays are
    read-only."""
    key = _model_key(model) + (int(n_min),)
    hit = _cache_get(key)
    if hit is not None:
        return hit
    # (computed outside the lock: two threads may build the same tables, equal ones)
    try:
        n = _table_size(_derivative_bounds(model), n_min)
    except ValueError:
        n = _checked_table_size(model, n_min)
    grid = -np.pi + TWO_PI * np.arange(n) / n
    phi = model._invert(grid)
    g = grid - phi
    nf = 1.0 / (1.0 + model.slope(phi))
    value = (np.append(g, g[:2]).astype(np.float32), np.append(nf, nf[:2]).astype(np.float32),
             _model_series(model))
    _cache_put(key, value)
    return value


#: the samples of the exact correction its Fourier series is computed from and checked on
#: (the series' highest harmonic is below SERIES_MAX_TERMS * d < 1024: the FFT of 4096
#: exact samples gives its coefficients to rounding, aliasing ~ the harmonics >= 3000)
_SERIES_GRID = 4096


def _model_series(model: PhaseErrorModel):
    """The correction g of ``model`` as a Fourier series (:func:`_series`, from g at
    ``_SERIES_GRID`` points solved exactly by Newton's method) with a fifth element:
    whether 1 - g' from it is the exact noise factor ``1 / (1 + e'(true phase))`` within
    NF_SERIES_TOL at those points (:func:`_series_noise_ok`); None when the series needs
    more than SERIES_MAX_TERMS terms. Cached (at most ``_TABLE_CACHE_MAX_ENTRIES`` models,
    a few kB each, under the tables' lock; its arrays read-only)."""
    key = _model_key(model)
    with _TABLE_CACHE_LOCK:
        if key in _SERIES_CACHE:
            _SERIES_CACHE.move_to_end(key)
            return _SERIES_CACHE[key]
    n = _SERIES_GRID
    grid = -np.pi + TWO_PI * np.arange(n) / n
    phi = model._invert(grid)  # the true phases
    series = _series(grid - phi)
    if series is not None:
        nf = 1.0 / (1.0 + model.slope(phi))
        series = (*series, _series_noise_ok(series, nf))
        for arr in series[:2]:
            arr.flags.writeable = False
    with _TABLE_CACHE_LOCK:
        _SERIES_CACHE[key] = series
        _SERIES_CACHE.move_to_end(key)
        while len(_SERIES_CACHE) > _TABLE_CACHE_MAX_ENTRIES:
            _SERIES_CACHE.popitem(last=False)
    return series


#: the Fourier series of a correction may drop terms summing to at most this (rad)
SERIES_TAIL = 1e-7
#: ... and terms whose derivatives sum to at most this (rad/rad): the noise factor 1 - g'
SERIES_DERIV_TAIL = 2e-7
SERIES_MAX_TERMS = 48


def _series(g: np.ndarray):
    """The correction table ``g`` (samples at ``-pi + 2 pi j / M``) as a Fourier series in
    harmonics of one order step d: ``g(phi) = c0 + sum_t a[t-1] cos(t d phi) + b[t-1]
    sin(t d phi)``, its dropped terms summing to <= SERIES_TAIL rad (and their
    derivatives to <= SERIES_DERIV_TAIL, for the noise factor); None when that needs
    more than SERIES_MAX_TERMS terms (the kernel then interpolates the table).

    Returns (a, b, c0, d) or None.
    """
    m = g.size
    k = np.arange(m // 2 + 1)
    coef = np.fft.rfft(g) / m * np.where(k % 2 == 0, 1.0, -1.0)  # grid starts at -pi
    a, b = 2.0 * coef.real, -2.0 * coef.imag
    c0 = coef[0].real
    mag = np.abs(a) + np.abs(b)
    mag[0] = 0.0
    order = np.argsort(mag)
    tail = np.cumsum(mag[order])
    kept = mag > 0
    kept[order[tail <= SERIES_TAIL]] = False  # the smallest terms, their sum within the bound
    dmag = k * mag  # (the derivative's terms)
    order = np.argsort(dmag)
    kept[order[np.cumsum(dmag[order]) > SERIES_DERIV_TAIL]] = True
    kept[0] = False
    kept &= mag > 0
    keep = np.nonzero(kept)[0]
    if keep.size == 0:
        return np.zeros(1), np.zeros(1), c0, 1
    d = int(np.gcd.reduce(keep))
    n = int(keep.max()) // d
    if n > SERIES_MAX_TERMS or keep.max() >= m // 4:
        return None
    idx = d * np.arange(1, n + 1)
    return a[idx], b[idx], c0, d


#: largest relative error of the noise factor 1 - g' from the series (float64, against the
#: exact factor at every table point) for the fused kernel to use it; the float32
#: evaluation adds ~1e-7 (tests/test_decode_fast.py bounds the total by 1e-6). The factor
#: scales sigma, an uncertainty: 1e-6 relative is far below anything it is quoted to.
NF_SERIES_TOL = 5e-7


def _series_derivative(series):
    """Coefficients (da, db) of g' = sum_t da[t-1] cos(t d phi) + db[t-1] sin(t d phi)
    of the series (a, b, c0, d, ...) of :func:`_series`."""
    a, b, _, d = series[:4]
    k = d * np.arange(1, len(a) + 1)
    return k * np.asarray(b), -k * np.asarray(a)


def _series_noise_ok(series, nf: np.ndarray) -> bool:
    """Whether 1 - g' from ``series`` (float64) is within NF_SERIES_TOL (relative) of the
    exact noise factors ``nf`` at the table's points ``-pi + 2 pi j / M``."""
    da, db = _series_derivative(series)
    d = series[3]
    m = nf.size
    grid = -np.pi + TWO_PI * np.arange(m) / m
    z = np.exp(1j * d * grid)
    w = np.ones(m, dtype=complex)
    deriv = np.zeros(m)
    for t in range(len(da)):
        w *= z
        deriv += da[t] * w.real + db[t] * w.imag
    return bool(np.max(np.abs((1.0 - deriv) / nf - 1.0)) <= NF_SERIES_TOL)


#: the fused kernel cuts a coarse level's series where the dropped terms move the next
#: level's order prediction (its phase times the period ratio) by at most this (rad): the
#: residual check's outcome then differs from the exact path's only for residuals within
#: this of its threshold (pi / 2)
ORDER_TOL = 1e-5
#: whether the fused kernel cuts the series per tile (False: every term, everywhere; for
#: tests and benchmarks)
SERIES_CUT = True


def _series_tails(series, n_pad: int):
    """Bounds of what the series (a, b, c0, d, ...) of :func:`_series` drops when cut after
    its first n terms, n = 0..n_pad: of the correction g (rad: the amplitudes |a_t| +
    |b_t| of the terms after n, plus SERIES_TAIL, what :func:`_series` dropped) and of the
    noise factor 1 - g' (relative: the derivative's amplitudes t d (|a_t| + |b_t|), plus
    SERIES_DERIV_TAIL, over the factor's least value); and the range [lo, hi] of the
    weight's factor 1 / nf^2, from |g'| <= G1 = the derivative's amplitudes' sum (hi huge
    where G1 >= 1). Returns (tg (n_pad + 1,), tn (n_pad + 1,), (hi, lo)) float64."""
    a, b, _, d = series[:4]
    mag = np.abs(np.asarray(a, dtype=np.float64)) + np.abs(np.asarray(b, dtype=np.float64))
    dmag = d * np.arange(1, mag.size + 1) * mag
    tg = np.full(n_pad + 1, SERIES_TAIL)
    tn = np.full(n_pad + 1, SERIES_DERIV_TAIL)
    # tail[n] = sum of the terms n + 1.. (the reversed cumulative sum)
    tg[:mag.size] += np.cumsum(mag[::-1])[::-1]
    tn[:mag.size] += np.cumsum(dmag[::-1])[::-1]
    g1 = tn[0]
    if g1 >= 1.0:
        return tg, np.full(n_pad + 1, np.inf), (1e30, 1.0 / (1.0 + g1) ** 2)
    return tg, tn / (1.0 - g1), (1.0 / (1.0 - g1) ** 2, 1.0 / (1.0 + g1) ** 2)


_EXACT_WEIGHTS = (0.0, 0.5, -0.5, 1.0, -1.0)
_MAX_MEMBERS = 16  # phase groups (exposures included) per axis in the fused kernel


@functools.lru_cache(maxsize=64)
def _weights(steps: int, offset: float):
    """N-step weights (cos, sin, second-harmonic cos, sin; read-only) and whether they are
    all 0, +-1/2 or +-1."""
    from telefringe.fringes.phase import phase_shift_coefficients

    c, s = phase_shift_coefficients(steps, offset)
    c2, s2 = phase_shift_coefficients(steps, 2.0 * offset, harmonic=2)
    for arr in (c, s, c2, s2):
        arr.flags.writeable = False
    exact = bool(np.all(np.isin(c, _EXACT_WEIGHTS)) and np.all(np.isin(s, _EXACT_WEIGHTS)))
    return c, s, c2, s2, exact


def _top_limit(max_value: float, dtype) -> tuple[np.ndarray, bool]:
    """The fused kernel's saturation test in the samples' own type: (lim, all) with, for
    every value v of ``dtype``, ``v < max_value`` (exactly, as real numbers) if and only if
    ``v < lim[0] or all``. lim : (1,) array of ``dtype``."""
    dt = np.dtype(dtype)
    mv = float(max_value)
    if dt.kind in "ui":
        info = np.iinfo(dt)
        if np.isnan(mv):  # nothing is below NaN
            return np.array([info.min], dtype=dt), False
        if mv > info.max:  # every value, info.max included
            return np.array([info.max], dtype=dt), True
        # integers: v < mv exactly when v < ceil(mv); below info.min: none is
        return np.array([max(math.ceil(mv), info.min) if np.isfinite(mv) else info.min],
                        dtype=dt), False
    # floats: v < mv exactly when v < the smallest value of the type >= mv (none lies
    # between mv and it); NaN stays NaN (nothing is below it)
    with np.errstate(over="ignore"):  # (above the type's range: inf)
        lim = dt.type(mv)
        if float(lim) < mv:
            lim = np.nextafter(lim, dt.type(np.inf))
    return np.array([lim], dtype=dt), False


def _tile_width(cols: int, tile: int) -> int:
    """The kernel's tile width: ``cols`` split into the fewest equal tiles of at most
    ``tile`` pixels."""
    cols = max(int(cols), 1)
    n = -(-cols // max(int(tile), 1))
    return -(-cols // n)


def _fused(levels, periods, steps, offsets, *, length: int, max_value: float, min_mod: float,
           max_residual: float, models=None, full: bool, noise: NoiseModel | None = None,
           dtype=np.float64, block_rows: int = 4, tile: int = 2048) -> dict:
    """Run the fused kernel (telefringe._kernels.fused_ladder) over a hierarchical ladder.

    levels : list (sorted by periods, first one period) of lists of (stack, exposure), the
    group's exposures (any order). periods, steps, offsets : per level. models : per level
    PhaseErrorModel or None. Returns the output arrays by name.
    """
    from telefringe.fringes import _kernels as _k

    n_lev = len(levels)
    members = []
    lev_first = [0]
    for lv in levels:
        members.extend(sorted(lv, key=lambda se: -se[1]))  # longest exposure first
        lev_first.append(len(members))
    n_mem = len(members)
    mem_steps = [steps[i] for i in range(n_lev) for _ in levels[i]]
    mem_off = [offsets[i] for i in range(n_lev) for _ in levels[i]]
    k4 = 4 * ((max(steps) + 3) // 4)  # the kernel sums steps four at a time
    sw, cw = np.zeros((n_mem, k4)), np.zeros((n_mem, k4))
    s2w, c2w = np.zeros((n_mem, k4)), np.zeros((n_mem, k4))
    ew = np.zeros((n_mem, k4), dtype=np.float32)  # 1 for the steps, 0 for the padding
    stacks = []
    dt = members[0][0].dtype
    integer = dt.kind in "ui" and dt.itemsize <= 2
    exact32 = np.zeros(n_mem, dtype=np.bool_)
    for i, ((st, _), k, off) in enumerate(zip(members, mem_steps, mem_off, strict=True)):
        c, s, c2, s2, exact = _weights(k, off)
        cw[i, :k], sw[i, :k] = c, s
        c2w[i, :k], s2w[i, :k] = c2, s2
        ew[i, :k] = 1.0
        # integer samples below 2^16, weights 0, +-1/2, +-1 and N <= 128: every partial
        # sum is a multiple of 1/2 below 2^23, so the float32 sums are exact
        exact32[i] = integer and k <= 128 and exact
        stacks.append(np.ascontiguousarray(st))
    use = [m is not None and bool(m.harmonics) for m in (models or [None] * n_lev)]
    series = [_model_series(m) if u else None for m, u in zip(models or [None] * n_lev, use,
                                                                strict=True)]
    # tables where the series is long (TABLE_MIN_TERMS), missing, or (full decode) its
    # noise factor is not within NF_SERIES_TOL; the series elsewhere
    table = [u and (s is None or len(s[0]) > TABLE_MIN_TERMS or (full and not s[4]))
             for u, s in zip(use, series, strict=True)]
    m_tab = 1
    if any(table):
        m_tab = max(_model_tables(m, 1)[0].size - 2
                    for m, t in zip(models, table, strict=True) if t)
    tables = np.zeros((n_lev, m_tab + 2), dtype=np.float32)
    nf_tables = np.ones((n_lev, m_tab + 2), dtype=np.float32)
    for i, t in enumerate(table):
        if t:
            tables[i], nf_tables[i] = _model_tables(models[i], m_tab)[:2]
    n_ser = max([len(s[0]) for s in series if s is not None] + [1])
    n_ser = -(-n_ser // _k.SERIES_BLOCK) * _k.SERIES_BLOCK  # zero-padded (see the kernel)
    ser_a = np.zeros((n_lev, n_ser), dtype=np.float32)
    ser_b = np.zeros((n_lev, n_ser), dtype=np.float32)
    ser_c0 = np.zeros(n_lev, dtype=np.float32)
    ser_d = np.ones(n_lev, dtype=np.int64)
    ser_n = np.ones(n_lev, dtype=np.int64)
    has_series = np.zeros(n_lev, dtype=np.bool_)
    ser_da = np.zeros((n_lev, n_ser), dtype=np.float32)
    ser_db = np.zeros((n_lev, n_ser), dtype=np.float32)
    # what the terms after the first n drop (n = 0..n_ser), and the range of the weight's
    # factor 1 / nf^2 (see the kernel: it cuts the series per tile with these)
    ser_tg = np.zeros((n_lev, n_ser + 1))
    ser_tn = np.zeros((n_lev, n_ser + 1))
    wbound = np.ones((n_lev, 2), dtype=np.float32)
    for i, (s, t) in enumerate(zip(series, table, strict=True)):
        if s is not None and not t:
            a, b, c0, d, _ = s
            ser_a[i, :a.size], ser_b[i, :b.size] = a, b
            ser_c0[i], ser_d[i], ser_n[i], has_series[i] = c0, d, a.size, True
            ser_da[i, :a.size], ser_db[i, :b.size] = _series_derivative(s)
            ser_tg[i], ser_tn[i], wbound[i] = _series_tails(s, n_ser)
        elif t:
            nft = nf_tables[i].astype(np.float64)
            wbound[i] = 1.0 / nft.min() ** 2, 1.0 / nft.max() ** 2
    nst = np.asarray(steps, dtype=np.int64)
    # thresholds on S^2 + C^2 (float32 in the kernel): the smallest float32 >= the exact
    # value, so that m2 >= thr32 exactly when m2 >= thr
    thr = (nst * float(min_mod) / 2.0) ** 2
    min_mod2 = thr.astype(np.float32)
    low = min_mod2.astype(np.float64) < thr
    min_mod2[low] = np.nextafter(min_mod2[low], np.float32(np.inf))
    shape = stacks[0].shape[1:]
    one = (1, 1)
    # (recycled memory: every element is written by the kernel)
    out = {"coordinate": _recycle.empty(shape), "valid": _recycle.empty(shape, dtype=bool),
           "modulation": _recycle.empty(shape)}
    names = (("sigma", np.float64), ("background", np.float64), ("exposure", np.float64),
             ("saturated", bool), ("low_modulation", bool), ("shadow", bool),
             ("order_reliable", bool))
    # one exposure on the finest level: the exposure map is that constant, a read-only
    # view (no plane of 8 bytes per pixel to write)
    one_exposure = len(levels[-1]) == 1
    for name, t in names:
        small = not full or (name == "exposure" and one_exposure)
        out[name] = _recycle.empty(one if small else shape, dtype=t)
    noise = noise if noise is not None else NoiseModel()
    if n_mem > _MAX_MEMBERS:
        raise DecodeError(f"the fused kernel takes at most {_MAX_MEMBERS} phase groups per "
                          f"axis, got {n_mem}")
    # pad the tuple to a fixed length: one compiled signature per dtype
    pad = np.zeros((1, 1, 1), dtype=dt)
    stacks += [pad] * (_MAX_MEMBERS - n_mem)
    _k.fused_ladder(
        tuple(stacks), np.asarray(lev_first, dtype=np.int64),
        np.asarray([e for _, e in members], dtype=np.float64), exact32, nst,
        sw.astype(np.float32), cw.astype(np.float32), sw, cw, s2w.astype(np.float32),
        c2w.astype(np.float32), ew,
        np.asarray(periods, dtype=np.float64), float(length), tables, nf_tables,
        np.asarray(table, dtype=np.bool_), ser_a, ser_b, ser_c0, ser_d, ser_n, has_series,
        ser_da, ser_db, ser_tg, ser_tn, wbound,
        *((SERIES_TAIL * float(length) / (TWO_PI * float(periods[-1])), ORDER_TOL,
           NF_SERIES_TOL) if SERIES_CUT else (0.0, 0.0, 0.0)),
        *_top_limit(max_value, dt), min_mod2,
        float(max_residual), bool(full), float(noise.read_noise ** 2 + noise.quantization ** 2),
        float(noise.gain), bool(integer and max(steps) <= 256), int(block_rows),
        _tile_width(shape[1], tile),
        out["coordinate"], out["valid"], out["modulation"],
        *(out[name] for name, _ in names))
    if full and one_exposure:
        out["exposure"] = np.broadcast_to(np.float64(levels[-1][0][1]), shape)
    if dtype != np.float64:
        out["coordinate"] = out["coordinate"].astype(dtype)
    return out


def decode_axis_fast(stacks, periods, steps, *, length: int, offsets=0.0,
                     max_value: float = 255.0, min_modulation: float | None = None,
                     max_residual: float = np.pi / 2, phase_errors=None,
                     dtype=np.float64, block_rows: int = 4) -> FastCoordinates:
    """One fused pass (numba, parallel, vectorised) from the images of a hierarchical
    ladder to the projector coordinate, its mask and the modulation.

    The same decoding as :func:`decode_axis` with the hierarchical method, single
    exposure, except: the arctangent is a float32 polynomial (error <= 1e-6 rad, tested),
    the groups are combined with weights ``(p B)^2`` (the same sigma_I for all groups of a
    pixel), and no uncertainty or diagnostics are returned (``decode`` gives them, through
    the same kernel). Memory: the outputs only.

    Parameters
    ----------
    stacks : sequence of (N_g, rows, cols) ndarray (uint8, uint16 or float), one per group.
    periods : sequence of int (one of them 1).  steps : int or sequence of int.
    length : int, projector pixels along the axis.  offsets : float or sequence, rad.
    max_value : float, saturation level (DN).  min_modulation : float, DN (default 2 % of
        ``max_value``).  max_residual : float, rad.
    phase_errors : PhaseErrorFit or sequence of PhaseErrorModel (one per group, input
        order) or None: the nonlinearity correction to apply (e.g. learned once with
        :func:`decode` or :func:`telefringe.gamma.fit_phase_errors` for a rig).
    dtype : float64 or float32, of ``coordinate``.
    block_rows : int, image rows per parallel task.

    Returns
    -------
    FastCoordinates
    """
    stacks = list(stacks)
    n = len(stacks)
    per = [int(p) for p in periods]
    if len(per) != n:
        raise DecodeError(f"{n} stacks but {len(per)} periods")
    st = [int(steps)] * n if np.ndim(steps) == 0 else [int(x) for x in steps]
    off = [float(offsets)] * n if np.ndim(offsets) == 0 else [float(x) for x in offsets]
    if len(st) != n or len(off) != n:
        raise DecodeError("steps and offsets need one value per stack")
    if len(set(per)) != n or min(per) != 1:
        raise LadderDecodeError(f"the fast path needs a hierarchical ladder with a one-period "
                                f"group and distinct periods, got {per}")
    shape = stacks[0].shape[1:]
    for s_, k in zip(stacks, st, strict=True):
        if s_.ndim != 3 or s_.shape[0] != k or s_.shape[1:] != shape:
            raise DecodeError(f"stack of shape {s_.shape} does not match steps {k} and image "
                              f"shape {shape}")
        if s_.dtype != stacks[0].dtype:
            raise DecodeError("stacks differ in dtype")
    if min(st) < 3:
        raise DecodeError(f"steps must be >= 3, got {st}")
    models = None
    if phase_errors is not None:
        models = list(getattr(phase_errors, "models", phase_errors))
        if len(models) != n:
            raise DecodeError("phase_errors needs one model per stack")
    order = list(np.argsort(per))
    min_mod = 0.02 * float(max_value) if min_modulation is None else float(min_modulation)
    out = _fused([[(stacks[g], 1.0)] for g in order], [per[g] for g in order],
                 [st[g] for g in order], [off[g] for g in order], length=length,
                 max_value=max_value, min_mod=min_mod, max_residual=max_residual,
                 models=None if models is None else [models[g] for g in order], full=False,
                 dtype=dtype, block_rows=block_rows)
    return FastCoordinates(coordinate=out["coordinate"], mask=out["valid"],
                           modulation=out["modulation"])
