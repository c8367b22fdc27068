"""The fused fast path: its polynomial arctangent and float32 table correction (error
bounds), agreement of decode_axis_fast and of decode() (fused kernel) with the exact
float64 decoder, and bad input."""

import numpy as np
import pytest

from telefringe.fringes import _kernels as _k
from telefringe.fringes.decode import decode
from telefringe.fringes.errors import DecodeError
from telefringe.fringes.fast import _top_limit, decode_axis_fast
from telefringe.fringes.nonlinearity import PhaseErrorModel
from telefringe.fringes.phase import NoiseModel
from telefringe.fringes.scan import PhaseGroup, Scan, ScanManifest


def _wrapped_diff(a, b):
    return np.abs(np.angle(np.exp(1j * (np.asarray(a, float) - np.asarray(b, float)))))


def test_polynomial_atan2_error_below_1e_6_rad_float32():
    # dense angles over the circle (spacing 3e-6 rad) at radii from 1e-3 to 1e6, rounded
    # to float32; the reference is the float64 atan2 of the same float32 inputs
    rng = np.random.default_rng(0)
    t = np.linspace(-np.pi, np.pi, 2_000_003)
    r = 10.0 ** rng.uniform(-3, 6, t.size)
    y = (r * np.sin(t)).astype(np.float32)
    x = (r * np.cos(t)).astype(np.float32)
    out = np.empty_like(y)
    _k.atan2_poly32_array(y, x, out)
    err = _wrapped_diff(out, np.arctan2(y.astype(float), x.astype(float)))
    # polynomial 3.7e-8 rad + float32 evaluation (FMA contracted) and output rounding
    # (half an ulp of pi is 1.2e-7): measured 3e-7; the bound asked for is 1e-6 rad
    assert err.max() <= 1e-6, err.max()
    assert np.all((out > -np.pi - 1e-6) & (out <= np.float32(np.pi)))
    sp_y = np.array([0.0, 0.0, -0.0, 1.0, -1.0, 0.0, 1.0, -1.0], dtype=np.float32)
    sp_x = np.array([1.0, -1.0, -1.0, 0.0, 0.0, 0.0, 1.0, -1.0], dtype=np.float32)
    o = np.empty(8, dtype=np.float32)
    _k.atan2_poly32_array(sp_y, sp_x, o)
    assert np.allclose(o, [0.0, np.pi, np.pi, np.pi / 2, -np.pi / 2, 0.0, np.pi / 4,
                           -3 * np.pi / 4], atol=1e-6)


def test_polynomial_atan2_error_below_1e_6_rad_float32_exact_inputs():
    # the kernel sees integer sums (4-step, 8- or 16-bit): all (S, C) with |S|, |C| <= 510
    # for 8 bit, plus a dense sample of the 16-bit range
    s, c = np.meshgrid(np.arange(-510, 511, dtype=np.float32),
                       np.arange(-510, 511, dtype=np.float32))
    rng = np.random.default_rng(1)
    s = np.concatenate([s.ravel(), rng.integers(-131070, 131071, 2_000_000).astype(
        np.float32)])
    c = np.concatenate([c.ravel(), rng.integers(-131070, 131071, 2_000_000).astype(
        np.float32)])
    out = np.empty_like(s)
    _k.atan2_poly32_array(-s, c, out)
    ref = np.arctan2(-s.astype(np.float64), c.astype(np.float64))
    assert _wrapped_diff(out, ref).max() <= 1e-6


_TABLE_MODELS = [
    PhaseErrorModel(64, (2, 3, 4), np.array([0.02, -0.004, 0.001]),
                    np.array([-0.03, 0.006, -0.002])),
    PhaseErrorModel(8, (3, 6, 9), np.array([0.05, -0.01, 0.003]),
                    np.array([-0.12, 0.02, -0.004])),
    PhaseErrorModel(1, (4, 8, 12, 16, 20, 24),
                    np.array([-2.6e-5, -3.0e-5, -8.0e-5, -4.9e-5, -3.4e-5, -5.1e-5]),
                    np.array([-0.0111, -0.00075, -0.00051, -0.00030, 0.00077, 0.00088]))]


@pytest.mark.parametrize("model", _TABLE_MODELS, ids=["2-3-4", "3-6-9 strong", "learned 1"])
def test_table_size_bounds_the_interpolation_error(model):
    """The tables' size M comes from h^2 / 8 max|f''| (f = g, and 1 - g' for the noise
    factor), max|g^(m)| bounded by the Fourier amplitudes: the bound holds (the float64
    interpolation of the table's exact values, checked at every cell's mid-point and
    quarter points against the exact inverse, is within TABLE_TOL and TABLE_NF_TOL), and M
    is the smallest power of two that the bound allows."""
    from telefringe.fringes import fast

    bounds = fast._derivative_bounds(model)
    n = fast._table_size(bounds)
    assert n == fast._table_size(bounds, n)  # (n_min at or below it changes nothing)
    c = lambda m: (2 * np.pi / m) ** 2 / 8  # noqa: E731
    g1, g2, g3 = bounds
    assert c(n) * g2 <= fast.TABLE_TOL and c(n) * g3 <= fast.TABLE_NF_TOL * (1 - g1)
    if n > fast.TABLE_MIN_SIZE:
        assert c(n // 2) * g2 > fast.TABLE_TOL or c(n // 2) * g3 > fast.TABLE_NF_TOL * (1 - g1)
    grid = -np.pi + 2 * np.pi * np.arange(n + 1) / n
    phi = model._invert(grid)
    g, nf = grid - phi, 1.0 / (1.0 + model.slope(phi))
    for frac in (0.25, 0.5, 0.75):
        x = grid[:-1] + frac * (2 * np.pi / n)
        phx = model._invert(x)
        gi = g[:-1] + frac * np.diff(g)
        ni = nf[:-1] + frac * np.diff(nf)
        assert np.abs(gi - (x - phx)).max() <= fast.TABLE_TOL
        exact_nf = 1.0 / (1.0 + model.slope(phx))
        assert np.abs(ni / exact_nf - 1).max() <= fast.TABLE_NF_TOL


def test_table_size_without_a_fourier_bound_is_checked_at_the_mid_points():
    """A correction whose Fourier series does not converge (a model close to
    non-invertible, slope 0.95, as learned from a few pixels) has no derivative bound: the
    tables are still built, at the smallest power of two whose interpolation error,
    checked at every mid-point against the exact inverse, is within TABLE_TOL."""
    from telefringe.fringes import fast

    model = PhaseErrorModel(1, (1,), np.array([0.95]), np.array([0.0]))
    with pytest.raises(ValueError, match="does not converge"):
        fast._derivative_bounds(model)
    g, nf, _ = fast._model_tables(model, 1)
    n = g.size - 2
    assert fast.TABLE_MIN_SIZE <= n < fast.TABLE_MAX_SIZE
    assert model.correction_table(n)[1] <= fast.TABLE_TOL
    assert model.correction_table(n // 2)[1] > fast.TABLE_TOL


@pytest.mark.parametrize("model", _TABLE_MODELS, ids=["2-3-4", "3-6-9 strong", "learned 1"])
def test_float32_table_correction_matches_the_exact_inverse(model):
    """The fused kernel's float32 table look-up (cell and fraction in float64, values and
    interpolation in float32) against the exact inverse (Newton, float64), over the whole
    circle and at its ends: the corrected phase within TABLE_TOL (interpolation) + half
    an ulp of pi in float32 (1.2e-7: the phase is float32) + |2 pi32 - 2 pi| = 1.75e-7
    (where the result wraps, by the float32 2 pi, as the series' does) + 4e-8 (the
    table's float32 values and arithmetic, |g| <= 0.13: a few ulp of 0.13);
    the noise factor within TABLE_NF_TOL + 2.5e-7 (float32 values and arithmetic: 4 ulp
    of 1 at most)."""
    from telefringe.fringes import fast

    g32, nf32, _ = fast._model_tables(model, 1)
    ph = np.linspace(-np.pi, np.pi, 1_000_001).astype(np.float32)
    ph = ph[(ph > -np.float32(np.pi))]  # (-pi32, pi32], as atan2_poly32 returns
    ph = np.concatenate([ph, np.float32([np.pi, np.nextafter(-np.float32(np.pi),
                                                             np.float32(0))])])
    out = np.empty_like(ph)
    fac = np.empty_like(ph)
    _k.table_correct32_array(ph, g32, nf32, out, fac)
    true = model._invert(ph.astype(float))
    tol_g = (fast.TABLE_TOL + 0.5 * np.spacing(np.float32(np.pi))
             + abs(2 * float(np.float32(np.pi)) - 2 * np.pi) + 4e-8)
    assert _wrapped_diff(out, true).max() <= tol_g
    assert np.all((out > -np.float32(np.pi)) & (out <= np.float32(np.pi)))
    exact = 1.0 / (1.0 + model.slope(true))
    assert np.abs(fac / exact - 1.0).max() <= fast.TABLE_NF_TOL + 2.5e-7
    assert np.abs(exact - 1.0).max() > 1e-3  # (not trivially 1)


def test_fused_decode_with_tables_matches_the_series(monkeypatch):
    """The fused decode with every level's correction from the tables against the
    default (series for these models): u_p within (1e-6 rad series + 2.4e-7 rad table,
    each level) * L / (2 pi p_fine) = 2.7e-6 px (L = 800, p = 64); sigma_u_p within
    1e-6 + 7.5e-7 relative (the two noise factors' bounds); masks equal."""
    from telefringe.fringes import fast

    x, stacks = _scan_stacks(gamma=2.2, rows=48, cols=160)
    fit = decode(_scan(stacks)).axes["u"].phase_errors
    assert all(m.harmonics for m in fit.models)
    rig = {("u", m.periods, 4): m for m in fit.models}
    ser = decode(_scan(stacks), phase_errors=rig)
    assert max(len(fast._model_series(m)[0]) for m in fit.models) > 4
    monkeypatch.setattr(fast, "TABLE_MIN_TERMS", 0)
    tab = decode(_scan(stacks), phase_errors=rig)
    assert np.array_equal(ser.mask, tab.mask) and ser.mask.mean() > 0.99
    m = ser.mask
    assert np.abs(ser.u_p - tab.u_p)[m].max() <= 1.24e-6 * 800 / (2 * np.pi * 64)
    assert np.abs(tab.sigma_u_p[m] / ser.sigma_u_p[m] - 1).max() <= 1.75e-6
    # the kernel's lean pass (u_p and mask only) likewise
    tab_fast = decode_axis_fast(stacks, (1, 8, 64), 4, length=800, phase_errors=fit)
    monkeypatch.setattr(fast, "TABLE_MIN_TERMS", 48)
    ser_fast = decode_axis_fast(stacks, (1, 8, 64), 4, length=800, phase_errors=fit)
    assert np.array_equal(ser_fast.mask, tab_fast.mask) and ser_fast.mask.mean() > 0.99
    m = ser_fast.mask
    assert (np.abs(ser_fast.coordinate - tab_fast.coordinate)[m].max()
            <= 1.24e-6 * 800 / (2 * np.pi * 64))


#: the one-period model learned for the paper rig (benchmarks/reconstruct.py, coefficients
#: to 3 digits): its correction's series has 27 terms, the longest the rig's scans need
_PAPER_RIG_MODEL = PhaseErrorModel(
    1, (4, 8, 12, 16, 20, 24),
    np.array([-2.57e-05, -3.04e-05, -7.98e-05, -4.85e-05, -3.42e-05, -5.06e-05]),
    np.array([-0.0111, -0.000749, -0.000512, -0.000304, 0.000768, 0.000883]))


@pytest.mark.parametrize("model", [
    PhaseErrorModel(64, (4, 8), np.array([0.0, 0.0]), np.array([-0.011, -0.001])),
    PhaseErrorModel(8, (3, 6, 9), np.array([0.05, -0.01, 0.003]),
                    np.array([-0.12, 0.02, -0.004])),
    _PAPER_RIG_MODEL])
def test_series_correction_matches_the_exact_inverse(model):
    from telefringe.fringes.fast import _model_tables

    a, b, c0, d = _model_tables(model, 1)[2][:4]
    # sums S, C of 8-bit 4-step data at every angle (radius 20 to 510 DN)
    rng = np.random.default_rng(4)
    t = np.linspace(-np.pi, np.pi, 1_000_001)
    r = rng.uniform(20, 510, t.size)
    s = np.round(-r * np.sin(t)).astype(np.float32)
    c = np.round(r * np.cos(t)).astype(np.float32)
    out = np.empty_like(s)
    _k.series_correct32_array(s, c, a.astype(np.float32), b.astype(np.float32),
                              np.float32(c0), d, a.size, out)
    ref = model.correct(np.arctan2(-s.astype(float), c.astype(float)))
    # dropped terms <= 1e-7 rad, float32 recurrence and atan2: measured < 5e-7 rad
    assert _wrapped_diff(out, ref).max() <= 1e-6


def _learned_models():
    """The gamma models decode learns from a 4-step 1/8/64 scan at gamma 2.2, a strong
    3-step one and the paper rig's one-period model."""
    x, stacks = _scan_stacks(gamma=2.2, rows=48, cols=160)
    fit = decode(_scan(stacks)).axes["u"].phase_errors
    return [m for m in fit.models if m.harmonics] + [
        PhaseErrorModel(8, (3, 6, 9), np.array([0.05, -0.01, 0.003]),
                        np.array([-0.12, 0.02, -0.004])), _PAPER_RIG_MODEL]


def test_series_noise_factor_matches_the_exact_one():
    """The fused kernel's noise factor 1 - g'(measured phase), from the correction's series
    in float32, against the exact 1 / (1 + e'(true phase)) over the phase circle. It scales
    sigma (an uncertainty): a relative error of 1e-6 is far below what sigma is quoted to;
    set-up check (float64) <= 5e-7; measured (Clenshaw's recurrence) 0.8e-7 to 1.0e-7 for
    the learned models, 3.5e-7 for the strong 3-step one (slope up to 0.43), 2.7e-7 for the
    paper rig's (27 terms, the derivative's coefficients up to 27 x 4 times the
    correction's; 5.3e-7 while exp(4 i phi) came through a square root): the bound is 2x
    the largest."""
    from telefringe.fringes.fast import _model_tables, _series_derivative

    models = _learned_models()
    assert len(models) >= 3
    rng = np.random.default_rng(5)
    t = np.linspace(-np.pi, np.pi, 200_001)
    r = rng.uniform(20, 510, t.size)
    s = np.round(-r * np.sin(t)).astype(np.float32)
    c = np.round(r * np.cos(t)).astype(np.float32)
    for model in models:
        ser = _model_tables(model, 1)[2]
        assert ser is not None and ser[4], model  # the kernel uses the series for these
        a, b, c0, d, _ = ser
        da, db = _series_derivative(ser)
        out = np.empty_like(s)
        fac = np.empty_like(s)
        _k.series_correct32_array(s, c, a.astype(np.float32), b.astype(np.float32),
                                  np.float32(c0), d, a.size, out, da.astype(np.float32),
                                  db.astype(np.float32), fac)
        measured = np.arctan2(-s.astype(float), c.astype(float))
        exact = 1.0 / (1.0 + model.slope(model._invert(measured)))
        assert np.abs(fac / exact - 1.0).max() <= 7e-7
        # ... and it is not trivially 1: the models have slopes of a few percent
        assert np.abs(exact - 1.0).max() > 1e-3


def test_series_noise_factor_falls_back_to_the_table_when_inexact(monkeypatch):
    from telefringe.fringes import fast

    model = PhaseErrorModel(8, (3, 6, 9), np.array([0.05, -0.01, 0.003]),
                            np.array([-0.12, 0.02, -0.004]))
    ser = fast._model_series(model)
    grid = -np.pi + 2 * np.pi * np.arange(4096) / 4096
    nf = 1.0 / (1.0 + model.slope(model._invert(grid)))
    assert fast._series_noise_ok(ser, nf)
    assert not fast._series_noise_ok(ser, nf * (1 + 2 * fast.NF_SERIES_TOL))


def _scan_stacks(seed=0, rows=96, cols=160, gamma=1.0, width=800, steps=4, dtype=np.uint8,
                 scale=1.0):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:rows, 0:cols].astype(float)
    x = 15 + xx * 4.7 + 0.2 * yy
    stacks = []
    for p in (1, 8, 64):
        k = np.arange(steps)[:, None, None]
        pat = 0.5 + 0.5 * np.cos(2 * np.pi * p * x / width + 2 * np.pi * k / steps)
        img = (40 + 160 * pat ** gamma + rng.normal(0, 1.2, (steps, rows, cols))) * scale
        stacks.append(np.clip(np.round(img), 0, 255 * scale).astype(dtype))
    return x, stacks


def _scan(stacks, steps=4, max_value=255.0):
    return Scan(ScanManifest(800, 600, tuple(PhaseGroup("u", p, steps) for p in (1, 8, 64))),
                tuple(stacks), max_value=max_value)


def test_fast_path_agrees_with_the_full_decoder():
    x, stacks = _scan_stacks()
    full = decode(_scan(stacks), gamma_correction=False, exact=True)
    fast = decode_axis_fast(stacks, (1, 8, 64), 4, length=800)
    assert np.array_equal(full.mask, fast.mask)
    # same orders; the combination weights differ slightly (fast: (p B)^2), a fraction of
    # the noise (sigma_u about 0.02 px)
    d = np.abs(full.u_p - fast.coordinate)[full.mask]
    assert d.max() < 0.002
    assert np.allclose(fast.modulation, full.modulation, rtol=1e-6)
    # input order does not matter, float32 output
    fast2 = decode_axis_fast(stacks[::-1], (64, 8, 1), 4, length=800, dtype=np.float32)
    assert fast2.coordinate.dtype == np.float32
    assert np.allclose(fast2.coordinate[fast.mask], fast.coordinate[fast.mask], atol=1e-4)


# fused decode() against the exact float64 path: masks and diagnostics equal; sigma_u_p
# and modulation to float32 precision; u_p moved by the float32 phase (polynomial atan2 and
# correction table, <= 1e-6 rad each, tested above), i.e. <= 2e-6 rad * L / (2 pi p_fine)
# = 4e-6 px here (L = 800, p = 64). Measured (every level's x_l and the combination in
# float64): <= 5.6e-7 px without a correction, 2.0e-6 px with the 3-step gamma-2.2 one;
# the bound is 2x that. (With the coarse levels' share in float32, before, it was 2e-5.)
_FUSED_BOUND_800 = 4e-6
@pytest.mark.parametrize("case", ["4-step", "3-step gamma", "16-bit", "hdr"])
def test_fused_decode_matches_the_exact_path(case):
    if case == "hdr":
        x, lo = _scan_stacks(seed=3, rows=48, cols=80)
        refl = np.linspace(0.5, 1.6, 80)[None, None, :]
        _, hi = _scan_stacks(seed=3, rows=48, cols=80)
        stacks, groups = [], []
        for p, a, b in zip((1, 8, 64), lo, hi, strict=True):
            for e, img in ((0.5, a), (1.0, b)):
                stacks.append(np.clip(np.round(img * refl * e * 1.3), 0, 255).astype(np.uint8))
                groups.append(PhaseGroup("u", p, 4, exposure=e))
        scan = Scan(ScanManifest(800, 600, tuple(groups)), tuple(stacks))
    elif case == "3-step gamma":
        x, stacks = _scan_stacks(gamma=2.2, steps=3, rows=64, cols=96)
        scan = _scan(stacks, steps=3)
    elif case == "16-bit":
        x, stacks = _scan_stacks(dtype=np.uint16, scale=257.0, rows=48, cols=80)
        scan = _scan(stacks, max_value=65535.0)
    else:
        x, stacks = _scan_stacks(rows=48, cols=80)
        scan = _scan(stacks)
    for gamma in (False, True):
        ex = decode(scan, gamma_correction=gamma, exact=True)
        fa = decode(scan, gamma_correction=gamma)
        assert np.array_equal(ex.mask, fa.mask)
        # (uncorrected 3-step fringes at gamma 2.2 lose most pixels to the residual check)
        low = case == "3-step gamma" and not gamma
        assert ex.mask.mean() > (0.5 if case == "hdr" else 0.2 if low else 0.99)
        m = ex.mask
        assert np.abs(ex.u_p - fa.u_p)[m].max() <= _FUSED_BOUND_800
        assert np.all(np.isnan(fa.u_p[~m]))
        assert np.allclose(fa.sigma_u_p[m], ex.sigma_u_p[m], rtol=1e-5)
        assert np.allclose(fa.modulation, ex.modulation, rtol=1e-6)
        assert np.allclose(fa.background, ex.background, rtol=1e-12, atol=1e-9)
        a, b = fa.axes["u"], ex.axes["u"]
        for name in ("saturated", "low_modulation", "shadow", "order_reliable", "exposure"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
        if case == "hdr":
            assert (a.exposure == 0.5).any() and (a.exposure == 1.0).any()


def _wide_scan(*, steps, gamma, dtype, seed=0, rows=40, cols=300):
    """L = 3840 px (the widest projector we support), 5 groups 1/4/16/64/256; the camera
    columns step 0.85 of a fine period, so the fine phase covers its whole circle."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:rows, 0:cols].astype(float)
    x = 10 + xx * (3800 / (cols - 1)) + 0.43 * yy
    ladder = (1, 4, 16, 64, 256)
    stacks = []
    for p in ladder:
        k = np.arange(steps)[:, None, None]
        pat = 0.5 + 0.5 * np.cos(2 * np.pi * p * x / 3840 + 2 * np.pi * k / steps)
        img = 40 + 160 * pat ** gamma + rng.normal(0, 1.2, (steps, rows, cols))
        img = np.clip(img, 0, 255)
        stacks.append(img.astype(np.float32) if dtype == np.float32
                      else np.round(img).astype(dtype))
    man = ScanManifest(3840, 2160, tuple(PhaseGroup("u", p, steps) for p in ladder))
    return Scan(man, tuple(stacks), max_value=255.0)


# At L = 3840 px with 5 groups the float32 terms that scale with L * periods are largest
# (ulp(x) = 2.4e-4 px). Measured max |u_p(fused) - u_p(exact)| over 3 seeds: <= 8e-7 px
# without a correction, 1.46e-6 px with the 3-step gamma-2.2 one (it was 1.3e-4 px, over
# the documented 1e-4, while the coarse levels' share of the combination was float32);
# bound 2x that.
@pytest.mark.parametrize("steps, gamma, dtype", [(4, 1.0, np.uint8), (3, 2.2, np.uint8),
                                                 (4, 2.2, np.float32)],
                         ids=["4-step", "3-step gamma", "float32 gamma"])
def test_fused_decode_matches_the_exact_path_at_3840_px_with_5_groups(steps, gamma, dtype):
    scan = _wide_scan(steps=steps, gamma=gamma, dtype=dtype)
    for correction in (False, True):
        ex = decode(scan, gamma_correction=correction, exact=True)
        fa = decode(scan, gamma_correction=correction)
        assert np.array_equal(ex.mask, fa.mask)
        assert ex.mask.mean() > 0.995
        m = ex.mask
        assert np.abs(ex.u_p - fa.u_p)[m].max() <= 3e-6
        assert np.allclose(fa.sigma_u_p[m], ex.sigma_u_p[m], rtol=1e-5)


def test_fast_path_float64_weights_for_three_steps():
    rng = np.random.default_rng(2)
    rows, cols = 32, 64
    x = np.linspace(10, 790, cols)[None, :].repeat(rows, 0)
    stacks = []
    for p in (1, 8, 64):
        k = np.arange(3)[:, None, None]
        img = 100 + 80 * np.cos(2 * np.pi * p * x / 800 + 2 * np.pi * k / 3)
        stacks.append(np.clip(np.round(img + rng.normal(0, 1, img.shape)), 0, 255)
                      .astype(np.uint8))
    r = decode_axis_fast(stacks, (1, 8, 64), 3, length=800)
    assert r.mask.all() and np.max(np.abs(r.coordinate - x)) < 0.1


def test_fast_path_applies_a_correction_table():
    x, stacks = _scan_stacks(gamma=2.2)
    full = decode(_scan(stacks), exact=True)
    fit = full.axes["u"].phase_errors
    assert any(m.harmonics for m in fit.models)
    fast = decode_axis_fast(stacks, (1, 8, 64), 4, length=800, phase_errors=fit)
    ok = full.mask & fast.mask
    assert ok.mean() > 0.99
    assert np.abs(full.u_p - fast.coordinate)[ok].max() < 0.002
    # the corrected fast path is at the noise floor: its error against sigma_u_p of the
    # exact decoder given the noise the stacks were made with (1.2 DN, quantised).
    # Measured e_fast / sigma = 1.0004, 1.0036, 1.0007 (seeds 0, 1, 2); n = 15360 pixels:
    # relative standard error 1 / sqrt(2 n) = 0.57 %, 5 of them. Uncorrected: 1.21.
    sig = decode(_scan(stacks), exact=True,
                 noise=NoiseModel(read_noise=1.2, gain=0.0)).sigma_u_p[ok]
    pred = np.sqrt(np.mean(sig ** 2))
    e_fast = np.sqrt(np.mean((fast.coordinate - x)[ok] ** 2))
    assert e_fast == pytest.approx(pred, rel=5 / np.sqrt(2 * ok.sum())), (e_fast, pred)
    raw = decode_axis_fast(stacks, (1, 8, 64), 4, length=800)
    e_raw = np.sqrt(np.nanmean((raw.coordinate - x)[ok] ** 2))
    assert e_raw > 1.1 * pred  # (the 4-step gamma-2.2 error the correction removes)


def test_saturation_limit_in_the_samples_type_is_exact():
    # the kernel tests v < max_value as v < lim or all, in the samples' dtype: the same
    # answer for every uint8 and uint16 value and for float32 values next to the limit
    mvs = [255.0, 254.5, 254.0, 1.0, 0.5, 0.0, -3.5, 256.0, 4095.0, 65535.0, 65535.5,
           1e30, np.inf, -np.inf, np.nan]
    for dt in (np.uint8, np.uint16, np.int16):
        info = np.iinfo(dt)
        v = np.arange(info.min, info.max + 1, dtype=np.int64).astype(dt)
        for mv in mvs:
            lim, every = _top_limit(mv, dt)
            assert lim.dtype == dt
            np.testing.assert_array_equal((v < lim[0]) | every, v.astype(float) < mv)
    f = np.float32
    for mv in [255.0, 254.5, 0.1, 1e-30, 3.4e38, 3.5e38, 1e300, -0.1, np.inf, np.nan]:
        lim, every = _top_limit(mv, f)
        c = f(mv) if abs(mv) < 3.4e38 or not np.isfinite(mv) else f(3.4028235e38)
        near = [c]
        with np.errstate(over="ignore"):
            for _ in range(3):
                near = [np.nextafter(near[0], f(-np.inf))] + near + [
                    np.nextafter(near[-1], f(np.inf))]
        v = np.array(near + [f(0.0), f(-1.0), f(np.inf), f(-np.inf), f(np.nan)], dtype=f)
        np.testing.assert_array_equal((v < lim[0]) | every, v.astype(float) < mv)
    v = np.array([254.99999999999997, 255.0, 255.00000000000003, np.nan], dtype=np.float64)
    lim, every = _top_limit(255.0, np.float64)
    np.testing.assert_array_equal((v < lim[0]) | every, v < 255.0)


def test_fast_path_bad_input():
    _, stacks = _scan_stacks(rows=8, cols=8)
    with pytest.raises(DecodeError, match="one-period"):
        decode_axis_fast(stacks[1:], (8, 64), 4, length=800)
    with pytest.raises(DecodeError):
        decode_axis_fast(stacks, (1, 8), 4, length=800)
    with pytest.raises(DecodeError, match="steps"):
        decode_axis_fast(stacks, (1, 8, 64), 3, length=800)
    with pytest.raises(DecodeError, match="one model per stack"):
        decode_axis_fast(stacks, (1, 8, 64), 4, length=800,
                         phase_errors=[PhaseErrorModel.zero(1)])


def test_table_cache_is_thread_safe_and_bounded(monkeypatch):
    """Many threads asking for more models than the cache holds: every answer is the
    tables of the model asked for (no KeyError when another thread evicts between the
    store and the return), and the cache stays within its entry and byte bounds."""
    import sys
    import threading

    from telefringe.fringes import fast as dec

    models = [PhaseErrorModel(8, (1, 2), np.array([0.01 * (i + 1), 0.0]),
                              np.array([0.0, 0.005])) for i in range(12)]
    monkeypatch.setattr(dec, "_TABLE_CACHE", type(dec._TABLE_CACHE)())
    # the answers one thread gets, one model at a time (copies)
    single = [dec._model_tables(m, 1) for m in models]
    expect = [v[0].copy() for v in single]
    one = max(dec._table_bytes(v) for v in single)
    monkeypatch.setattr(dec, "_TABLE_CACHE", type(dec._TABLE_CACHE)())
    monkeypatch.setattr(dec, "_TABLE_CACHE_MAX_ENTRIES", 5)
    monkeypatch.setattr(dec, "_TABLE_CACHE_MAX_BYTES", 4 * one)  # 4 of these at most
    errors, sizes = [], []

    def work(seed):
        rng = np.random.default_rng(seed)
        try:
            for i in rng.integers(0, len(models), 60):
                g, nf, _ = dec._model_tables(models[i], 1)
                if not np.array_equal(g, expect[i]):
                    errors.append(f"model {i}: wrong table")
                if g.flags.writeable or nf.flags.writeable:
                    errors.append("a cached table is writeable")
                sizes.append(len(dec._TABLE_CACHE))
        except Exception as exc:  # noqa: BLE001 - reported below
            errors.append(repr(exc))

    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # interleave the threads as much as possible
    try:
        threads = [threading.Thread(target=work, args=(s,)) for s in range(8)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        sys.setswitchinterval(old)
    assert not errors, errors[:5]
    assert max(sizes) <= 5
    with dec._TABLE_CACHE_LOCK:
        total = sum(dec._table_bytes(v) for v in dec._TABLE_CACHE.values())
        assert len(dec._TABLE_CACHE) <= 4 and total <= dec._TABLE_CACHE_MAX_BYTES


def _faint_fine_stacks():
    """The gamma-2.2 scan, its finest fringes' contrast cut to 1/8 on the right half: the
    coarse levels' share of the combination grows 64x there (the kernel keeps more of
    their series in those tiles)."""
    x, stacks = _scan_stacks(gamma=2.2, rows=48, cols=160)
    fine = stacks[2].astype(float)
    mean = fine.mean(axis=0, keepdims=True)
    fine[:, :, 80:] = mean[:, :, 80:] + (fine[:, :, 80:] - mean[:, :, 80:]) / 8
    return x, [stacks[0], stacks[1], np.round(fine).astype(np.uint8)]


@pytest.mark.parametrize("faint", [False, True], ids=["even", "faint fine level"])
def test_cut_series_stay_within_their_bounds(monkeypatch, faint):
    """The fused kernel cuts each level's correction series per tile to what the result
    needs (telefringe.fringes._kernels.fused_ladder): every level's cut moves u_p by at
    most SERIES_TAIL * L / (2 pi p_fine), and its noise factor moves sigma by at most
    NF_SERIES_TOL (relative). Against every term: u_p within 3 levels x that (6e-7 px
    here) plus a float32 ulp of the fine phase (pi: 2.4e-7 rad, 4.8e-7 px), both
    passes; sigma within 3 x NF_SERIES_TOL plus float32 rounding (2.4e-7); masks equal
    (the order prediction moved by at most ORDER_TOL). The one-period model is the paper
    rig's (27 terms: the cut matters most there)."""
    from telefringe.fringes import fast

    x, stacks = _faint_fine_stacks() if faint else _scan_stacks(gamma=2.2, rows=48, cols=160)
    fit = decode(_scan(stacks)).axes["u"].phase_errors
    models = [_PAPER_RIG_MODEL] + [m for m in fit.models if m.periods != 1]
    rig = {("u", m.periods, 4): m for m in models}
    assert [m.periods for m in models] == [1, 8, 64]
    assert len(fast._model_series(_PAPER_RIG_MODEL)[0]) == 27
    cut = decode(_scan(stacks), phase_errors=rig)
    cut_fast = decode_axis_fast(stacks, (1, 8, 64), 4, length=800, phase_errors=models)
    monkeypatch.setattr(fast, "SERIES_CUT", False)
    every = decode(_scan(stacks), phase_errors=rig)
    every_fast = decode_axis_fast(stacks, (1, 8, 64), 4, length=800, phase_errors=models)
    bound_x = 3 * fast.SERIES_TAIL * 800 / (2 * np.pi * 64) + 2.4e-7 * 800 / (2 * np.pi * 64)
    assert np.array_equal(cut.mask, every.mask) and cut.mask.mean() > 0.99
    m = cut.mask
    d = np.abs(cut.u_p - every.u_p)[m]
    assert d.max() <= bound_x, d.max()
    assert d.max() > 0  # (the series were cut)
    rel = np.abs(cut.sigma_u_p[m] / every.sigma_u_p[m] - 1)
    assert rel.max() <= 3 * fast.NF_SERIES_TOL + 2.4e-7, rel.max()
    assert np.array_equal(cut_fast.mask, every_fast.mask)
    m = cut_fast.mask
    assert np.abs(cut_fast.coordinate - every_fast.coordinate)[m].max() <= bound_x


def test_series_tails_bound_the_dropped_terms():
    """fast._series_tails: the bound on what the first n terms leave out holds at every n
    (the exact correction and noise factor, from the model, against the partial sums)."""
    from telefringe.fringes import fast

    model = _PAPER_RIG_MODEL
    ser = fast._model_series(model)
    a, b, c0, d = ser[:4]
    tg, tn, (hi, lo) = fast._series_tails(ser, 28)
    grid = np.linspace(-np.pi, np.pi, 4001)
    exact_g = grid - model._invert(grid)
    exact_nf = 1.0 / (1.0 + model.slope(model._invert(grid)))
    assert lo <= exact_nf.min() ** -2 and exact_nf.max() ** -2 <= hi
    for n in range(0, 29):
        t = np.arange(1, min(n, len(a)) + 1)
        g = c0 + (a[:t.size, None] * np.cos(d * t[:, None] * grid)
                  + b[:t.size, None] * np.sin(d * t[:, None] * grid)).sum(axis=0)
        gd = (d * t[:, None] * (-a[:t.size, None] * np.sin(d * t[:, None] * grid)
                                + b[:t.size, None] * np.cos(d * t[:, None] * grid))).sum(axis=0)
        assert np.abs(g - exact_g).max() <= tg[n]
        assert np.abs((1.0 - gd) / exact_nf - 1.0).max() <= tn[n]
    assert tg[0] > 1e-2 and tg[27] <= 1.1 * fast.SERIES_TAIL
