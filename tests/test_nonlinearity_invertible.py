"""``PhaseErrorModel.invertible`` is a proof, not a sample: a model it passes can be
inverted everywhere (the decoder's table never fails), a model that dips below a monotonic
mapping between sample points is refused."""

from __future__ import annotations

import numpy as np

from telefringe.fringes.nonlinearity import PhaseErrorModel

#: Learned by the decoder from the tilted plane of a tiny acceptance scan (6 % of the
#: circle covered): the old 64-samples-per-period check passed it, and its inversion then
#: raised "phase error model is not invertible" inside `telefringe accept`.
_LEARNED_ON_A_TINY_PLANE = PhaseErrorModel(
    1, (4, 12, 20, 24), np.array([-0.00131648, 0.00358584, -0.00644912, 0.00519531]),
    np.array([-0.06604705, -0.01836919, -0.03520623, 0.01680904]))


def _fine_min(model, n=2 ** 21):
    return float(np.min(1.0 + model.slope(np.linspace(-np.pi, np.pi, n, endpoint=False))))


def test_a_model_that_dips_between_samples_is_not_invertible():
    m = _LEARNED_ON_A_TINY_PLANE
    grid = np.linspace(-np.pi, np.pi, 64 * max(m.harmonics), endpoint=False)
    assert np.min(1.0 + m.slope(grid)) > 0  # what the sampled check saw
    assert _fine_min(m) < 0  # what is there
    assert not m.invertible


def test_invertible_models_invert_everywhere_and_the_rest_are_not_monotonic():
    rng = np.random.default_rng(7)
    seen = {True: 0, False: 0}
    for _ in range(60):
        harm = tuple(sorted(rng.choice(np.arange(1, 13), size=3, replace=False).tolist()))
        a, b = rng.normal(size=3), rng.normal(size=3)
        # scale so that the slope's amplitude bound sits near 1: both outcomes occur
        scale = rng.uniform(0.6, 1.6) / np.sum(np.array(harm) * np.hypot(a, b))
        m = PhaseErrorModel(1, harm, a * scale, b * scale)
        ok = m.invertible
        seen[ok] += 1
        if ok:
            assert _fine_min(m, 2 ** 16) > 0
            g, err = m.correction_table(4096)  # raised on non-invertible models
            assert np.all(np.isfinite(g)) and np.isfinite(err)
        else:
            # refused only when not monotonic or too close to it to prove at 2^22 points
            assert _fine_min(m, 2 ** 18) < 1e-3
    assert seen[True] >= 10 and seen[False] >= 10


def test_a_three_step_scan_learns_its_gamma_without_a_traceback(tmp_path, monkeypatch):
    """A 3-step scan's gamma fit prunes harmonics and restarts from the pruned model,
    which dropping harmonics can leave non-invertible: the restart is made invertible
    (halved, reported) instead of raising inside Gauss-Newton. Plate of the cropped fast
    rig (a bare rig, so residuals include its nominal geometry).

    Both fits converge: on this crop the 1-period phase covers 28 % (u) and 33 % (v) of
    its circle, and at the solution that group's higher orders are nearly collinear
    (variance inflations 1e3-7e6), so Gauss-Newton on every harmonic stalled with steps
    halved 2^7-fold and more to stay invertible (Newton's method after it did not help:
    its matrix by differences of 0.01 and 0.001 standard errors differed by 10x its size,
    the iterate being where the 1-period model was nearly non-invertible, residual RMS
    0.54 rad, 5x the noise). The fit restarts from each group's orders 3 and 6 and adds
    the higher ones only while they can be told apart there. Measured one more
    Gauss-Newton step from the models returned: 0.0060 (u) and 0.0021 (v) standard errors
    (60 and 4e-5 before, u warned); bounds 2x. Reconstructed: every pixel valid (76 %
    before), the plane-fit residual over sigma_z 1.54 RMS (5.8 before; 4 steps give 1.7
    on the same scene); bounds 2x (for the valid fraction: a 1 % loss fails)."""
    import json
    import warnings

    from test_reconstruct_virtual import _next_step

    from telefringe.cli import main
    from telefringe.fringes import decode as decode_module
    from telefringe.io.rig_json import bare_rig_json
    from telefringe.io.scan_json import write_scan
    from telefringe.simulate.presets import crop_camera, get_preset
    from telefringe.simulate.render import default_groups, render_scan
    from telefringe.simulate.scenes import plate_at_z

    vr = crop_camera(get_preset("fast"), col0=100, row0=80, width=120, height=100)
    (tmp_path / "rig.json").write_text(json.dumps(bare_rig_json(vr.rig,
                                                                reference_pose="truth")))
    scan, _ = render_scan(vr, plate_at_z(0.0), default_groups(vr, steps=3), seed=3)
    write_scan(tmp_path / "three", scan)
    out = tmp_path / "out"
    fits = {}
    learn = decode_module.fit_phase_errors

    def kept(*args, **kwargs):
        fit = learn(*args, **kwargs)
        fits[tuple(int(p) for p in args[1])] = (args, kwargs, fit)
        return fit

    monkeypatch.setattr(decode_module, "fit_phase_errors", kept)
    with warnings.catch_warnings():
        # a fit that did not converge warns: an error here
        warnings.filterwarnings("error", message="fit_phase_errors", category=RuntimeWarning)
        assert main(["reconstruct", str(tmp_path / "three"), "--rig",
                     str(tmp_path / "rig.json"), "-o", str(out), "--no-ply",
                     "--noise-model", "default"]) == 0
    assert sorted(fits) == [(1, 8, 48), (1, 8, 64)]
    for periods, bound in (((1, 8, 64), 0.012), ((1, 8, 48), 0.0042)):
        args, kwargs, fit = fits[periods]
        assert _next_step(args, kwargs, fit) < bound
        # (the restart's harmonics left out are said)
        assert any("Gauss-Newton on every harmonic stalled" in w for w in fit.warnings)
    pts = np.load(out / "points.npz")
    xyz, sz = pts["xyz"].reshape(-1, 3), pts["sigma_z"].ravel()
    ok = np.isfinite(xyz).all(axis=1) & np.isfinite(sz)
    assert ok.mean() > 0.99  # 1.0 (0.74 unconverged; 6 % without the gamma correction)
    a = np.c_[xyz[ok, :2], np.ones(ok.sum())]
    coef, *_ = np.linalg.lstsq(a, xyz[ok, 2], rcond=None)
    z = (xyz[ok, 2] - a @ coef) / sz[ok]
    assert np.sqrt(np.mean(z ** 2)) < 3.1
