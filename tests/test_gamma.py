"""Projector nonlinearity: the periodic phase error learned from the ladder and removed
(virtual rig, gamma 2.2, patterns not pre-compensated), and the pre-compensation path."""

import numpy as np
import pytest

from telefringe.fringes import nonlinearity as nl
from telefringe.fringes.decode import decode
from telefringe.fringes.nonlinearity import (
    PhaseErrorModel,
    default_harmonics,
    fit_phase_errors,
    fit_response,
    periodic_error,
)
from telefringe.fringes.patterns import precompensate
from telefringe.fringes.phase import wrap, wrapped_phase
from telefringe.fringes.scan import PhaseGroup, Scan, ScanManifest
from telefringe.simulate.presets import get_preset
from telefringe.simulate.render import default_groups, render_scan
from telefringe.simulate.scenes import plate_at_z


@pytest.fixture(scope="module")
def fast_rig():
    return get_preset("fast")


def _scan(vrig, steps, seed):
    return render_scan(vrig, plate_at_z(0.0), default_groups(vrig, axes=("u",), steps=steps),
                       seed=seed, white=False, black=False)


def _interior(truth):
    """Lit plate pixels 2 px or more from an albedo edge (camera defocus and pixel
    integration mix the phases of both sides of a marker edge: physics, not decoding)."""
    from scipy.ndimage import binary_erosion

    return truth.lit & binary_erosion(truth.part == 0, iterations=2)


def test_three_steps_gamma_error_drops_tenfold_without_wrong_orders(fast_rig, rig_noise):
    scan, truth = _scan(fast_rig, 3, seed=3)
    width = fast_rig.projector.intrinsics.width
    lit = truth.lit & np.isin(truth.part, (0, 1))
    pc = decode(scan, noise=rig_noise(fast_rig))
    fit = pc.axes["u"].phase_errors
    fine = wrapped_phase(scan.stacks[2], steps=3).phase  # the 64-period group
    true = 2 * np.pi * 64 * truth.u_p / width
    harm = range(1, 25)
    before = periodic_error(fine[lit], true[lit], harmonics=harm)
    after = periodic_error(fit.models[2].correct(fine)[lit], true[lit], harmonics=harm)
    assert before.peak > 0.1  # gamma 2.2 seen through 3 steps (defocus shrinks it a bit)
    assert after.peak < before.peak / 10, (before.peak, after.peak)
    # unwrapping after the correction: every lit plate pixel valid, no wrong order
    # (a period is 400 / 64 = 6.25 px)
    assert pc.mask[lit].all()
    assert np.max(np.abs(pc.u_p[lit] - truth.u_p[lit])) < 6.25 / 4
    # without it, the 1 -> 8 step is off by up to 8 * 0.29 rad: most orders are untrusted
    raw = decode(scan, noise=rig_noise(fast_rig), gamma_correction=False)
    assert raw.mask[lit].mean() < 0.5
    ok = raw.mask & lit
    assert np.max(np.abs(raw.u_p[ok] - truth.u_p[ok])) < 6.25 / 2  # flagged, not wrong
    # at the noise floor on the interior
    core = _interior(truth)
    rms = np.sqrt(np.mean((pc.u_p - truth.u_p)[core] ** 2))
    pred = np.sqrt(np.mean(pc.sigma_u_p[core] ** 2))
    assert rms == pytest.approx(pred, rel=0.05)


def test_four_steps_residual_at_noise_floor(fast_rig, rig_noise):
    scan, truth = _scan(fast_rig, 4, seed=4)
    width = fast_rig.projector.intrinsics.width
    pc = decode(scan, noise=rig_noise(fast_rig))
    core = _interior(truth)
    assert pc.mask[core].all()
    err = (pc.u_p - truth.u_p)[core]
    rms, pred = np.sqrt(np.mean(err ** 2)), np.sqrt(np.mean(pc.sigma_u_p[core] ** 2))
    # n ~ 44000 pixels: relative standard error 0.3 %; the noise model itself is good to
    # about 1 % on this rig (intensity variance), so 3 %
    assert rms == pytest.approx(pred, rel=0.03), (rms, pred)
    # what is left of the periodic error is far below the noise of one pixel
    true = 2 * np.pi * 64 * truth.u_p / width
    phase = 2 * np.pi * 64 * pc.u_p / width
    resid = periodic_error(wrap(phase)[core], true[core], harmonics=range(1, 25))
    sigma_phi = pred * 2 * np.pi * 64 / width
    assert resid.rms < 0.2 * sigma_phi
    # the coarse groups' 4th-harmonic error (about 0.011 rad) is found
    m1 = pc.axes["u"].phase_errors.models[0]
    assert 0.008 < m1.peak < 0.016


def _ladder_phases(steps, gamma, rng, n=30000, sigma=0.01):
    """Synthetic measured phases of the 1, 8, 64 ladder for random projector x."""
    x = rng.uniform(0, 1, n)
    out = []
    for p in (1, 8, 64):
        phi = 2 * np.pi * p * x
        d = 2 * np.pi * np.arange(steps)[:, None] / steps
        imgs = (0.5 + 0.5 * np.cos(phi[None] + d)) ** gamma
        imgs = imgs + rng.normal(0, sigma, imgs.shape)
        out.append(wrapped_phase(imgs, steps=steps).phase)
    return x, out


def test_fit_recovers_synthetic_gamma_error_and_leaves_linear_alone():
    rng = np.random.default_rng(0)
    x, ph = _ladder_phases(3, 2.2, rng)
    fit = fit_phase_errors(ph, [1, 8, 64], steps=[3, 3, 3])
    assert fit.coverage == (1.0, 1.0, 1.0) and fit.warnings == ()
    for p, m, meas in zip((1, 8, 64), fit.models, ph, strict=True):
        true = 2 * np.pi * p * x
        before = periodic_error(meas, true, harmonics=range(1, 25)).peak
        after = periodic_error(m.correct(meas), true, harmonics=range(1, 25)).peak
        assert before == pytest.approx(0.291, abs=0.01)
        assert after < 0.01
    x, ph = _ladder_phases(4, 1.0, rng)
    fit = fit_phase_errors(ph, [1, 8, 64], steps=[4, 4, 4])
    assert all(not m.harmonics for m in fit.models)  # nothing significant: no noise added


def test_fit_needs_absolute_phase_for_non_integer_ratios():
    rng = np.random.default_rng(1)
    x, ph = _ladder_phases(4, 1.0, rng, n=2000)
    with pytest.raises(ValueError, match="integer ratio"):
        fit_phase_errors([ph[1], ph[2]], [8, 60], steps=[4, 4])
    single = fit_phase_errors([ph[0]], [1], steps=[4])
    assert single.models[0].harmonics == ()


def test_model_helpers():
    m = PhaseErrorModel(8, (3,), np.array([0.0]), np.array([0.1]))
    phi = np.linspace(-np.pi, np.pi, 7)
    assert np.allclose(m.error(phi), 0.1 * np.sin(3 * phi))
    assert np.allclose(m.slope(phi), 0.3 * np.cos(3 * phi))
    c = m.correct(phi)
    assert np.all((c > -np.pi) & (c <= np.pi))
    assert m.rms == pytest.approx(0.1 / np.sqrt(2))
    assert m.peak == pytest.approx(0.1, rel=1e-3)
    assert default_harmonics(3) == (3, 6, 9, 12, 15, 18, 21, 24)
    assert default_harmonics(12) == (12, 24)


def _strong_model():
    """A 3-step-like error of 0.15 rad with harmonics up to 24 (orders sharing divisor 3)."""
    harm = (3, 6, 9, 12, 18, 24)
    return PhaseErrorModel(64, harm, np.array([0.02, -0.01, 0.004, 0.002, -0.001, 0.0005]),
                           np.array([-0.12, 0.015, -0.006, 0.003, 0.001, -0.0004]))


def test_inversion_cold_and_warm_start_solve_the_model_to_1e_14():
    m = _strong_model()
    x = np.random.default_rng(5).uniform(-np.pi, np.pi, 20_000)
    cold = m._invert(x)
    assert np.max(np.abs(cold + m.error(cold) - x)) < 1e-13  # the equation, not a proxy
    # warm start from the solution of a nearby model (as the Gauss-Newton loop does)
    near = PhaseErrorModel(64, m.harmonics, m.cos_coef * 1.01, m.sin_coef * 0.99)
    warm = m._invert(x, near._invert(x))
    assert np.max(np.abs(warm - cold)) < 1e-13
    # orders 1..24 without a common divisor go through the same recurrence
    odd = PhaseErrorModel(1, (1, 5, 7), np.array([0.01, 0.0, 0.002]),
                          np.array([0.05, -0.004, 0.001]))
    sol = odd._invert(x)
    assert np.max(np.abs(sol + odd.error(sol) - x)) < 1e-13


def test_correction_and_noise_tables_are_bounded_against_the_exact_inverse():
    m = _strong_model()
    x = np.random.default_rng(6).uniform(-np.pi, np.pi, 50_000)
    exact = m._invert(x)
    assert m.table_error <= 1e-8
    assert m._table[0].size % 4096 == 0
    got = m.correct(x)
    assert np.max(np.abs(wrap(got - exact))) <= m.table_error + 1e-15
    nf = 1.0 / (1.0 + m.slope(exact))
    assert m.noise_table_error <= 1e-6
    assert np.max(np.abs(m.noise_factor(x) / nf - 1.0)) <= m.noise_table_error + 1e-15
    # NaN stays NaN (invalid pixels) in both look-ups
    assert np.isnan(m.correct(np.array([np.nan]))[0])
    assert np.isnan(m.noise_factor(np.array([np.nan]))[0])


def test_precompensation_with_a_measured_response():
    # a projector with gamma 2.2 and black level 0.02, measured with uniform frames
    levels = np.linspace(0, 1, 33)
    captured = 10 + 200 * (0.02 + 0.98 * levels ** 2.2)
    resp = fit_response(levels, captured)
    want = np.linspace(0, 1, 101)
    shown = precompensate(want, inverse_response=resp.inverse)
    emitted = 0.02 + 0.98 * shown ** 2.2
    # linear in the wanted value (piecewise-linear inverse over 33 levels)
    assert np.max(np.abs((emitted - 0.02) / 0.98 - want)) < 0.01
    assert np.allclose(precompensate(want, gamma=2.2) ** 2.2, want)
    with pytest.raises(ValueError):
        precompensate(want)
    with pytest.raises(ValueError):
        fit_response([0.2, 0.5, 1.0], [1, 2, 3])


def test_gauss_newton_normal_matrix_matches_finite_differences():
    """_gauss_newton's normal matrix J^T W J (one iteration, no rejection) against J from
    central differences of the pair residual r phi_a(c) - phi_b(c), phi_g(c) the true
    phase the model c implies for each measured phase (solved here by the model's own
    Newton inverse, which is tested separately against the forward series)."""
    rng = np.random.default_rng(8)
    per, r = (8, 64), 8
    harm = [(1, 2, 3), (2, 3, 4)]
    offs = np.cumsum([0] + [2 * len(h) for h in harm])
    harm_arr = [np.asarray(h, dtype=np.int64) for h in harm]
    coef = 0.03 * rng.standard_normal(int(offs[-1]))
    models = nl._models(per, harm, offs, coef)
    x = rng.uniform(0, 800, 400)  # projector pixels
    true = [wrap(2 * np.pi * p * x / 800) for p in per]
    samp = [wrap(t + m.error(t)) for t, m in zip(true, models, strict=True)]
    sig = [np.full(x.size, 0.01), np.full(x.size, 0.02)]
    pairs = [(0, 1, r, sig[0], sig[1], None, None)]
    _, _, kept, ata, _ = nl._gauss_newton(samp, per, harm, harm_arr, offs, pairs, coef, 1,
                                          np.inf, tol=0.0, reject_first=False)
    assert kept == x.size

    def phases(c):
        return [m._invert(s, start=t) for m, s, t in
                zip(nl._models(per, harm, offs, c), samp, true, strict=True)]

    h = 1e-6
    J = np.empty((x.size, coef.size))
    for k in range(coef.size):
        up, dn = coef.copy(), coef.copy()
        up[k] += h
        dn[k] -= h
        pu, pd = phases(up), phases(dn)
        J[:, k] = ((r * pu[0] - pu[1]) - (r * pd[0] - pd[1])) / (2 * h)
    # the residual's weight, 1 / var with var from each phase's noise times its gain
    # 1 / (1 + e'(phi))
    gain = [1 / (1 + m.slope(t)) for m, t in zip(models, true, strict=True)]
    w = 1 / ((r * sig[0] * gain[0]) ** 2 + (sig[1] * gain[1]) ** 2)
    ref = J.T @ (w[:, None] * J)
    # central differences of a smooth function, h = 1e-6 on coefficients of 0.03 rad:
    # error ~1e-10 relative (the Newton inverse's 1e-14 rad / h); measured 1.4e-11. Leaving
    # out the gain 1 / (1 + e') would be a 10 % error.
    err = np.max(np.abs(ata - ref)) / np.max(np.abs(ref))
    assert err < 1e-7, err


def _uneven_scan(seed, drift, gamma=1.0):
    """Fringes at L = 3840 px, 1/4/16/64/256, 4 steps, 8-bit, noise 1.2 DN, on camera
    columns ``drift`` * 3820 / 255 px apart (about one fine period of 15 px): the fine
    phase drifts slowly across the image and covers its circle unevenly. Returns the
    true projector coordinate (rows, cols) and the scan."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:48, 0:256].astype(float)
    x = 10 + xx * (3820 / 255 * drift) + 0.037 * yy
    groups, stacks = [], []
    for p in (1, 4, 16, 64, 256):
        k = np.arange(4)[:, None, None]
        pat = (0.5 + 0.5 * np.cos(2 * np.pi * p * x / 3840 + 2 * np.pi * k / 4)) ** gamma
        img = 40 + 160 * pat + rng.normal(0, 1.2, (4, *x.shape))
        groups.append(PhaseGroup("u", p, 4))
        stacks.append(np.clip(np.round(img), 0, 255).astype(np.uint8))
    return x, Scan(ScanManifest(3840, 2160, tuple(groups)), tuple(stacks))


def _rms(pc, x):
    return float(np.sqrt(np.nanmean((pc.u_p - x) ** 2)))


#: one pixel's phase noise in the scans above: sqrt(2 / N) sigma_I / B with sigma_I^2 =
#: 1.2^2 + 1/12 DN^2 (noise and rounding), B = 80 DN
_SIGMA_PHI = np.sqrt(2 / 4) * np.sqrt(1.2 ** 2 + 1 / 12) / 80


def test_no_correction_learned_from_an_uneven_phase_coverage():
    """Ideal sinusoidal fringes (no gamma), columns 0.998 of a fine period apart: the fine
    phase covers 27 of 36 10-degree bins. The fit used to learn 0.045 rad of harmonics
    here (tripling the u_p error, 0.025 -> 0.080 px): its regressors, evaluated at the
    noisy measured phase, are correlated with the residual's noise, so least squares
    learned the shrinkage ``sigma^2 d log p / dphi`` of an uneven phase density. The
    estimating equation is now corrected for it (Stein's lemma)."""
    x, scan = _uneven_scan(0, 0.999)
    raw = decode(scan, gamma_correction=False, exact=True)
    fit = decode(scan, exact=True)
    pe = fit.axes["u"].phase_errors
    assert pe.coverage[:3] == (1.0, 1.0, 1.0)
    assert pe.coverage[4] == pytest.approx(27 / 36)
    # a harmonic that passes the p = 0.001 test by chance is about 4 of its standard
    # errors (0.0006 rad for the finest group): below a quarter of one pixel's noise
    assert max(m.peak for m in pe.models) < 0.25 * _SIGMA_PHI
    # a correction learned from noise alone may cost a few % of the noise, not more
    # (measured: 1.0000)
    assert _rms(fit, x) < 1.05 * _rms(raw, x), (_rms(fit, x), _rms(raw, x))


def test_harmonics_an_uneven_coverage_cannot_decide_are_flagged():
    """Columns a whole fine period apart (to 0.13 %): the 64-period phase sits in four
    narrow clusters (67 % of its 10-degree bins) on which its 8th harmonic is a
    combination of the others (variance inflation ~3e4): not learned, and said so."""
    x, scan = _uneven_scan(1, 1.0)
    raw = decode(scan, gamma_correction=False, exact=True)
    fit = decode(scan, exact=True)
    pe = fit.axes["u"].phase_errors
    assert pe.coverage[3] == pytest.approx(24 / 36)
    flagged = [w for w in pe.warnings if w.startswith("periods 64: harmonic 8 not learned")]
    assert flagged and "too unevenly" in flagged[0], pe.warnings
    assert 8 not in pe.models[3].harmonics
    assert _rms(fit, x) < 1.05 * _rms(raw, x), (_rms(fit, x), _rms(raw, x))


def test_real_gamma_is_still_learned_on_an_uneven_coverage():
    """Gamma 2.2 on the uneven coverage of the first test: the 4th-harmonic error is
    learned in every group and the u_p error comes down to the ideal fringes' noise
    floor (measured: raw 1.22, corrected 1.016 times the ideal fringes' error)."""
    x, ideal = _uneven_scan(0, 0.999)
    floor = _rms(decode(ideal, gamma_correction=False, exact=True), x)
    x, scan = _uneven_scan(0, 0.999, gamma=2.2)
    raw = decode(scan, gamma_correction=False, exact=True)
    fit = decode(scan, exact=True)
    pe = fit.axes["u"].phase_errors
    assert all(4 in m.harmonics for m in pe.models)
    assert _rms(raw, x) > 1.15 * floor  # the gamma error is there to be learned
    assert _rms(fit, x) < 1.035 * floor, (_rms(fit, x), floor)  # 2x the measured excess


def test_a_zero_start_and_a_stalled_iteration_are_reported(monkeypatch):
    """When no scaled start is invertible the fit starts from zero, and when no halved
    Gauss-Newton step is invertible it stops: both used to happen silently."""
    rng = np.random.default_rng(2)
    _, ph = _ladder_phases(3, 2.2, rng, n=3000)
    monkeypatch.setattr(PhaseErrorModel, "invertible", property(lambda self: not self.harmonics))
    fit = fit_phase_errors(ph, [1, 8, 64], steps=[3, 3, 3])
    assert any("started from zero" in w for w in fit.warnings), fit.warnings
    assert any(w.startswith("Gauss-Newton stopped") for w in fit.warnings), fit.warnings
    assert all(not m.harmonics for m in fit.models)  # nothing learned, and said why


def test_a_singular_covariance_is_reported(monkeypatch):
    """A harmonic whose covariance block is singular used to get chi2 = 0 and vanish
    silently; it is still left out (the data cannot decide it), with a warning."""
    rng = np.random.default_rng(3)
    _, ph = _ladder_phases(3, 2.2, rng, n=3000)
    solve = nl._solve

    def singular(*args, **kwargs):
        models, rms, kept, cov = solve(*args, **kwargs)
        if cov is not None and kwargs.get("start") is None:
            cov = cov.copy()
            cov[:2, :] = cov[:, :2] = 0.0  # group 1's first harmonic (3)
        return models, rms, kept, cov

    monkeypatch.setattr(nl, "_solve", singular)
    # (the refit does not converge, and says so: Newton's method took over and its steps
    # were damped short, which passed the convergence test until that test took the full
    # step; its last is 21 standard errors)
    with pytest.warns(RuntimeWarning, match=r"\(not converged\)"):
        fit = fit_phase_errors(ph, [1, 8, 64], steps=[3, 3, 3], max_inflation=np.inf,
                               iterations=8)
    assert "periods 1: harmonic 3 dropped, its covariance is singular" in fit.warnings[0]
    assert 3 not in fit.models[0].harmonics
    assert 3 in fit.models[1].harmonics  # the others are judged as before


def test_compiled_curvature_and_stein_sums_equal_their_definition():
    """The compiled errors-in-variables terms against their formulas written out in NumPy
    (cos/sin of m x per harmonic, no recurrence), with noise damping per sample."""
    from telefringe.fringes.nonlinearity import PhaseErrorModel, _curvature, _stein_sum

    rng = np.random.default_rng(5)
    model = PhaseErrorModel(64, (4, 8, 12, 20), (0.01, -0.004, 0.002, 0.001),
                            (-0.006, 0.003, 0.0015, -0.0007))
    x = rng.uniform(-np.pi, np.pi, 5000)
    tau2 = rng.uniform(0.0, 0.003, x.size)
    fix = np.array([True, True, False, True])
    m = np.asarray(model.harmonics, dtype=float)
    c, s = np.cos(np.outer(x, m)), np.sin(np.outer(x, m))
    damp = np.exp(-0.5 * np.outer(tau2, m * m))
    cc, sc = np.asarray(model.cos_coef), np.asarray(model.sin_coef)
    curv_ref = -((damp * m * m * (c * cc + s * sc)) * fix).sum(axis=1)
    curv = _curvature(model, x, tau2, fix)
    np.testing.assert_allclose(curv, curv_ref, rtol=0, atol=1e-14 * np.abs(curv_ref).max())
    gain = 1.0 / (1.0 + rng.uniform(-0.05, 0.05, x.size))
    w = rng.uniform(0.0, 2.0, x.size)
    dg = -gain * gain * curv_ref
    ref = np.empty(2 * m.size)
    ref[0::2] = (w * dg) @ c - (w * gain) @ (s * m)
    ref[1::2] = (w * dg) @ s + (w * gain) @ (c * m)
    ref[0::2] *= fix
    ref[1::2] *= fix
    got = _stein_sum(model, x, gain, curv_ref, w, fix)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    assert np.all(got[4:6] == 0.0)  # the harmonic not selected
