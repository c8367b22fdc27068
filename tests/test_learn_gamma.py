"""The learned projector gamma (fringes.nonlinearity) made fast: its compiled evaluation
against the formulas, its early stop against the converged fit, and the 1e5-pixel subsample
against the fit on every pixel (accuracy first: each bound stated from the noise)."""

import numpy as np
import pytest

from telefringe.fringes import nonlinearity as nl
from telefringe.fringes.decode import decode
from telefringe.fringes.nonlinearity import fit_phase_errors, periodic_error
from telefringe.fringes.phase import wrap, wrapped_phase
from telefringe.simulate.presets import get_preset
from telefringe.simulate.render import default_groups, render_scan
from telefringe.simulate.scenes import plate_at_z


def _h(x, orders):
    """(n, 2 k): cos, sin of each order, interleaved (NumPy, no recurrence)."""
    m = np.asarray(orders, dtype=float)
    out = np.empty((x.size, 2 * m.size))
    out[:, 0::2] = np.cos(np.outer(x, m))
    out[:, 1::2] = np.sin(np.outer(x, m))
    return out


def _ladder_case():
    """A 1, 8, 64 ladder of 3000 random samples with random forward models (4 mrad) and
    noise (5-40 mrad): (per, harm, offs, harm_arr, coef, samp, pairs, sig, models)."""
    rng = np.random.default_rng(11)
    per = [1, 8, 64]
    harm = [(4, 8, 12), (4, 8, 12, 16, 20, 24), (4, 8, 24)]
    offs = np.cumsum([0] + [2 * len(h) for h in harm])
    harm_arr = [np.asarray(h, dtype=np.int64) for h in harm]
    coef = 0.004 * rng.standard_normal(int(offs[-1]))
    models = nl._models(per, harm, offs, coef)
    n = 3000
    x = rng.uniform(0, 1, n)
    sig = [rng.uniform(0.005, 0.01, n), rng.uniform(0.02, 0.04, n), rng.uniform(0.005, 0.01, n)]
    samp = []
    for p, m, s in zip(per, models, sig, strict=True):
        t = wrap(2 * np.pi * p * x)
        samp.append(wrap(t + m.error(t) + s * rng.standard_normal(n)))
    pairs = [(0, 1, 8, sig[0], sig[1], None, None), (1, 2, 8, sig[1], sig[2], None, None)]
    return per, harm, offs, harm_arr, coef, samp, pairs, sig, models


def test_one_compiled_evaluation_equals_its_definition():
    """One Gauss-Newton evaluation (two compiled passes over every group and pair) against
    its definition written out in NumPy: Newton inverses, gains 1 / (1 + e'), weights, the
    errors-in-variables mean bias and Stein's sums (the harmonics whose dilution is too
    large left uncorrected: some are, here), the normal equations. Same arithmetic in
    another order: agreement to 1e-9 of the step."""
    per, harm, offs, harm_arr, coef, samp, pairs, sig, models = _ladder_case()
    n = samp[0].size
    # one evaluation gives the normal matrix; two give the step solved from it
    _, _, kept, ata, chi2 = nl._gauss_newton(samp, per, harm, harm_arr, offs, pairs, coef, 1,
                                             np.inf, tol=0.0, reject_first=False)
    out = nl._gauss_newton(samp, per, harm, harm_arr, offs, pairs, coef, 2, np.inf,
                           tol=np.inf, reject_first=False)
    step = out[0] - coef

    est = [wrap(m._invert(s)) for m, s in zip(models, samp, strict=True)]
    gain = [1.0 / (1.0 + m.slope(e)) for m, e in zip(models, est, strict=True)]
    n_par = int(offs[-1])
    res, wts = [], []
    for a, b, r, sa, sb, *_ in pairs:
        res.append(wrap(r * est[a] - est[b]))
        wts.append(1.0 / ((r * sa * gain[a]) ** 2 + (sb * gain[b]) ** 2))
    chi2_ref = sum(float(np.sum(w * q * q)) for w, q in zip(wts, res, strict=True))
    s2 = chi2_ref / (2 * n - n_par)
    tau2 = [s2 * (s * g) ** 2 for s, g in zip(sig, gain, strict=True)]
    fix = [0.5 * h.astype(float) ** 2 * np.median(t) <= nl._EIV_DILUTION
           for h, t in zip(harm_arr, tau2, strict=True)]
    assert not fix[1].all() and fix[1].any()  # both kinds of harmonic are exercised
    curv = [nl._curvature(m, e, t, f) for m, e, t, f in zip(models, est, tau2, fix,
                                                           strict=True)]
    ata_ref = np.zeros((n_par, n_par))
    atb_ref = np.zeros(n_par)
    for (a, b, r, sa, sb, *_), q, w in zip(pairs, res, wts, strict=True):
        mean_bias = 0.5 * s2 * (r * sa ** 2 * -gain[a] ** 3 * curv[a]
                                - sb ** 2 * -gain[b] ** 3 * curv[b])
        jac = np.zeros((n, n_par))
        jac[:, offs[a]:offs[a + 1]] = -r * gain[a][:, None] * _h(est[a], harm[a])
        jac[:, offs[b]:offs[b + 1]] = gain[b][:, None] * _h(est[b], harm[b])
        ata_ref += jac.T @ (w[:, None] * jac)
        atb_ref += jac.T @ (w * -(q - mean_bias))
        for g, fac in ((a, r * r * (sa * gain[a]) ** 2), (b, (sb * gain[b]) ** 2)):
            atb_ref[offs[g]:offs[g + 1]] -= s2 * nl._stein_sum(models[g], est[g], gain[g],
                                                               curv[g], w * fac, fix[g])
    assert kept == 2 * n
    assert chi2 == pytest.approx(chi2_ref, rel=1e-12)
    np.testing.assert_allclose(ata, ata_ref, rtol=0, atol=1e-11 * np.abs(ata_ref).max())
    ridge = 1e-9 * np.trace(ata_ref) / n_par + 1e-300
    step_ref = np.linalg.solve(ata_ref + ridge * np.eye(n_par), atb_ref)
    np.testing.assert_allclose(step, step_ref, rtol=0, atol=1e-9 * np.abs(step_ref).max())


def test_the_right_hand_side_alone_is_the_same_bit_for_bit():
    """Newton's matrix by differences and its step acceptance evaluate the estimating
    equations' right-hand side alone (no normal matrix, its O(n_par^2) per sample): the
    same numbers, bit for bit, as the full evaluation's, and so the same Newton matrix as
    by full evaluations (an iteration whose success can hang on small differences in that
    matrix, e.g. the 3-step scan of test_nonlinearity_invertible, keeps its iterates)."""
    per, harm, offs, harm_arr, coef, samp, pairs, *_ = _ladder_case()
    lad = nl._Ladder(samp, per, harm, harm_arr, offs, pairs)
    first = lad.evaluate(coef, 4.0, True)
    assert not all(f.all() for f in first.fix)  # (some harmonics left uncorrected)
    # (each evaluation starts the phases' inversion from the last one's: the same start)
    warm = first.unwrapped
    ev = lad.evaluate(coef, 0.0, False, keep=first.keep, fix=first.fix)
    lad.start = warm
    rhs = lad.evaluate(coef, 0.0, False, keep=first.keep, fix=first.fix, with_gram=False)
    assert np.array_equal(rhs.atb, ev.atb) and rhs.chi2 == ev.chi2
    assert not rhs.ata.any()
    se = np.sqrt(ev.chi2 / (ev.n_keep - coef.size) * np.diag(np.linalg.inv(ev.ata)))
    h = 1e-2 * se
    by_full = np.empty((coef.size, coef.size))
    lad.start = warm
    for i in range(coef.size):
        c = coef.copy()
        c[i] += h[i]
        by_full[:, i] = -(lad.evaluate(c, 0.0, False, keep=ev.keep, fix=ev.fix).atb
                          - ev.atb) / h[i]
    lad.start = warm
    assert np.array_equal(nl._newton_matrix(lad, ev, h), by_full)


@pytest.fixture(scope="module")
def fast_scan():
    vrig = get_preset("fast")
    scan, truth = render_scan(vrig, plate_at_z(0.0), default_groups(vrig, axes=("u",)),
                              seed=21, white=False, black=False)
    return scan, truth


def test_early_stop_agrees_with_the_converged_fit(fast_scan, rig_noise, monkeypatch):
    """The Gauss-Newton iterations stop once the steps still to come (extrapolated) are
    below 2 % of each coefficient's standard error, and refits start from the linearised
    solution. Against the same fit iterated until the step is below 1e-7 rad: the models
    and the decoded coordinates agree to 1e-3 of the phase noise (RMS; 1e-2 at worst), and
    the error against the truth does not change (measured: 4e-7 sigma RMS, 2e-5 at
    worst)."""
    scan, truth = fast_scan
    noise = rig_noise(get_preset("fast"))
    fast = decode(scan, noise=noise).axes["u"]
    monkeypatch.setattr(nl, "_REMAINING", 1e-12)
    monkeypatch.setattr(nl, "_MAX_CONTRACTION", 0.0)
    slow = decode(scan, noise=noise).axes["u"]
    grid = np.linspace(-np.pi, np.pi, 4096, endpoint=False)
    width = get_preset("fast").projector.intrinsics.width
    sig_px = float(np.median(slow.sigma[slow.valid]))
    for m_fast, m_slow in zip(fast.phase_errors.models, slow.phase_errors.models,
                              strict=True):
        assert m_fast.harmonics == m_slow.harmonics
        # the phase noise (rad; about the same in every group: same contrast and steps) at
        # the median pixel, from the decoded sigma (the finest group's)
        sig_phi = sig_px * 2 * np.pi * max(fast.periods) / width
        diff = m_fast.error(grid) - m_slow.error(grid)
        assert np.sqrt(np.mean(diff ** 2)) < 1e-3 * sig_phi
    assert np.array_equal(fast.valid, slow.valid)
    ok = fast.valid
    d = (fast.coordinate - slow.coordinate)[ok] / slow.sigma[ok]
    assert np.sqrt(np.mean(d ** 2)) < 1e-3 and np.max(np.abs(d)) < 1e-2
    ok &= np.isfinite(truth.u_p)
    assert ok.mean() > 0.5
    e_fast = np.sqrt(np.mean((fast.coordinate - truth.u_p)[ok] ** 2))
    e_slow = np.sqrt(np.mean((slow.coordinate - truth.u_p)[ok] ** 2))
    assert e_fast == pytest.approx(e_slow, rel=1e-4)


def _gamma_ladder(rng, n, steps=4, gamma=2.2, sigma=0.01):
    """Measured wrapped phases of the 1, 8, 64 ladder (gamma on the projected intensity,
    Gaussian intensity noise) and the true phases, for n random projector positions."""
    x = rng.uniform(0, 1, n)
    meas, true = [], []
    for p in (1, 8, 64):
        phi = 2 * np.pi * p * x
        d = 2 * np.pi * np.arange(steps)[:, None] / steps
        imgs = (0.5 + 0.5 * np.cos(phi[None] + d)) ** gamma + rng.normal(0, sigma, (steps, n))
        meas.append(wrapped_phase(imgs, steps=steps).phase)
        true.append(wrap(phi))
    return meas, true


def test_a_subsample_of_1e5_pixels_determines_the_model():
    """The fit uses 1e5 pixels at most (a regular subsample). With ~12 coefficients per
    group the model's own uncertainty moves a corrected phase by about sigma sqrt(12 / n),
    1 % of the phase noise at n = 1e5. Against the model fitted to all 3e5 pixels (gamma
    2.2, 4 steps: a gamma error of half the phase noise, RMS), the subsample's corrected
    phase differs by less than 5 % of the phase noise (RMS over the circle; measured 0.3,
    0.4 and 1.6 % for the 1, 8, 64 groups), and both leave a periodic error against the
    truth below 5 % of it (measured 1.2-2.4 %; the fit of 48 harmonics to the noise alone
    is 1.3 %): the subsample costs nothing a pixel's noise would show."""
    rng = np.random.default_rng(3)
    meas, true = _gamma_ladder(rng, 300_000)
    sub = fit_phase_errors(meas, [1, 8, 64], steps=[4, 4, 4])
    full = fit_phase_errors(meas, [1, 8, 64], steps=[4, 4, 4], max_samples=300_000)
    assert sub.n_samples <= 200_000 and full.n_samples > 500_000  # two pairs each
    grid = np.linspace(-np.pi, np.pi, 4096, endpoint=False)
    for g, (ms, mf) in enumerate(zip(sub.models, full.models, strict=True)):
        assert ms.harmonics == mf.harmonics
        corrected = mf.correct(meas[g])
        sig_phi = float(np.std(wrap(corrected - true[g])))  # noise dominated
        before = periodic_error(meas[g], true[g], harmonics=range(1, 25))
        assert before.rms > 0.4 * sig_phi  # there is a gamma error to learn
        diff = wrap(ms.correct(grid) - mf.correct(grid))
        assert np.sqrt(np.mean(diff ** 2)) < 0.05 * sig_phi, (g, diff.std() / sig_phi)
        for m in (ms, mf):
            left = periodic_error(m.correct(meas[g]), true[g], harmonics=range(1, 25))
            assert left.rms < 0.05 * sig_phi, (g, left.rms / sig_phi)
