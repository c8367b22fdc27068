"""Unusual but legitimate inputs a user's rig or capture tool produces: each either works
or stops with a message naming the file / option and what is expected (never a silently
wrong result)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from telefringe.fringes.decode import decode
from telefringe.fringes.fast import decode_axis_fast
from telefringe.fringes.scan import PhaseGroup, Scan, ScanManifest
from telefringe.io.errors import InputError
from telefringe.io.scan_json import read_scan, write_scan


def _fringe_scan(top: int, *, shape=(12, 20), clip: int | None = None) -> Scan:
    """A 4-step, one-period scan along u in 16-bit integers reaching about ``top`` (a
    camera's full scale), its brightest samples clipped at ``clip`` (a saturated pixel in
    the top-left corner)."""
    rows, cols = shape
    x = np.linspace(0.0, 2 * np.pi, cols, endpoint=False)[None, :] * np.ones((rows, 1))
    k = np.arange(4)[:, None, None]
    stack = top * (0.45 + 0.35 * np.cos(x[None] + 2 * np.pi * k / 4))
    stack[:, 0, 0] = 1.5 * top      # far above the full scale: clipped
    stack = np.round(np.minimum(stack, top if clip is None else clip)).astype(np.uint16)
    man = ScanManifest(projector_width=20, projector_height=10,
                       groups=(PhaseGroup(axis="u", periods=1, steps=4),))
    return Scan(manifest=man, stacks=(stack,), max_value=65535.0)


def _set_saturation(folder, value) -> None:
    path = folder / "scan.json"
    doc = json.loads(path.read_text())
    doc["saturation"] = value
    path.write_text(json.dumps(doc))


def test_16bit_scan_of_a_12bit_camera_needs_its_saturation(tmp_path):
    # 12-bit values stored as they are (LSB-aligned, 0..4095): read as 16-bit data, the
    # clipped pixels (4095) were never flagged and every pixel's modulation fell below
    # the default threshold (2 % of 65535)
    write_scan(tmp_path / "lsb", _fringe_scan(4095))
    with pytest.raises(InputError, match=r"never exceed 4095 .*\"saturation\" in scan.json"):
        read_scan(tmp_path / "lsb")
    _set_saturation(tmp_path / "lsb", 4095)
    scan = read_scan(tmp_path / "lsb")
    assert scan.max_value == 4095.0
    pc = decode(scan, gamma_correction=False)
    assert pc.saturated[0, 0] and not pc.mask[0, 0]
    assert pc.mask.sum() == pc.mask.size - 1       # the rest decodes
    # a saturation below the values found is refused
    _set_saturation(tmp_path / "lsb", 4000)
    with pytest.raises(InputError, match="pixel values reach 4095, above .*'saturation' 4000"):
        read_scan(tmp_path / "lsb")
    for bad in (0, 70000, 4095.5, "4095"):
        _set_saturation(tmp_path / "lsb", bad)
        with pytest.raises(InputError, match="'saturation' must be an integer in 1..65535"):
            read_scan(tmp_path / "lsb")


def test_16bit_scan_of_values_shifted_left_needs_its_saturation(tmp_path):
    # a 12-bit camera's values shifted left by 4 (low bits 0) saturate at 65520, which a
    # full scale of 65535 never flags
    sc = _fringe_scan(4095)
    shifted = Scan(sc.manifest, (sc.stacks[0] << 4,), max_value=65535.0)
    write_scan(tmp_path / "msb", shifted)
    with pytest.raises(InputError, match=r"lowest 4 bits .* are 0.*\(e\.g\. 65520\)"):
        read_scan(tmp_path / "msb")
    _set_saturation(tmp_path / "msb", 65520)
    scan = read_scan(tmp_path / "msb")
    assert decode(scan, gamma_correction=False).saturated[0, 0]


def test_full_range_16bit_scan_and_saturation_round_trip(tmp_path):
    # values using the whole 16-bit range read as before (full scale 65535)
    write_scan(tmp_path / "full", _fringe_scan(65535))
    assert read_scan(tmp_path / "full").max_value == 65535.0
    # a scan whose camera saturates below its images' maximum keeps it through write_scan
    sc = _fringe_scan(4095)
    write_scan(tmp_path / "kept", Scan(sc.manifest, sc.stacks, max_value=4095.0))
    assert json.loads((tmp_path / "kept" / "scan.json").read_text())["saturation"] == 4095
    assert read_scan(tmp_path / "kept").max_value == 4095.0


def test_lone_one_period_group_decodes_the_whole_projector():
    # a scan of one one-period group per axis (no ladder): the fused kernel returned NaN
    # for every pixel whose wrapped phase was negative (the projector's second half);
    # the default decode goes through it (fast.decode_axis_fast too)
    sc = _fringe_scan(65535)
    for gamma in (True, False):
        fast = decode(sc, gamma_correction=gamma)
        exact = decode(sc, gamma_correction=gamma, exact=True)
        assert fast.mask.sum() == fast.mask.size - 1      # all but the clipped pixel
        np.testing.assert_array_equal(fast.mask, exact.mask)
        cols = np.arange(20.0) * np.ones((12, 1))
        # the true coordinate is the column (noise-free, rounded to integers: 0.003 px
        # measured)
        assert np.nanmax(np.abs(fast.u_p - cols)) < 0.01
        np.testing.assert_allclose(fast.u_p, exact.u_p, atol=1e-9)
    bare = decode_axis_fast(sc.stacks, [1], 4, length=20, max_value=sc.max_value)
    np.testing.assert_array_equal(bare.mask, fast.mask)
    np.testing.assert_allclose(bare.coordinate, fast.u_p, atol=1e-9)


def test_global_flags_work_after_the_command(tmp_path, capsys):
    # the README promises -q / -v / --debug for every command; after the command's
    # arguments they were refused ("No such option: -q")
    from telefringe.cli import main
    from telefringe.cli._common import state

    write_scan(tmp_path / "scan", _fringe_scan(65535))
    capsys.readouterr()
    try:
        assert main(["decode", str(tmp_path / "scan"), "-o", str(tmp_path / "c.npz"),
                     "-q"]) == 0
        assert (tmp_path / "c.npz").exists() and capsys.readouterr().out == ""
        assert main(["decode", str(tmp_path / "scan"), "-o", str(tmp_path / "c.npz"),
                     "--force", "-v"]) == 0
        assert "median modulation" in capsys.readouterr().out
        # --debug after the command shows the traceback (the error is raised)
        with pytest.raises(InputError, match="already exists"):
            main(["decode", str(tmp_path / "scan"), "-o", str(tmp_path / "c.npz"),
                  "--debug"])
        # a sub-command of a group too
        assert main(["simulate", "scan", "-h", "-q"]) == 0
    finally:
        state.quiet = state.verbose = state.debug = False


def test_noise_estimate_is_not_taken_from_a_rounding_dominated_exposure(rig_noise):
    # HDR exposures 0.1 / 0.6 / 4 of the fast rig (8 bit): the 0.1 exposure's values
    # (2-3 DN, noise 0.3 DN before rounding) vary less than a + b I says, so its groups
    # passed as the quietest, the others were left out as noisier, and the line through
    # their one narrow range had a gain 8-50x too low with a standard error 5-20x too
    # small (seeds 0-3): sigma_z 2.3x too small, silently
    import telefringe.simulate.render as sim
    from telefringe.fringes.noise import NoiseEstimateError, estimate_noise
    from telefringe.simulate import scenes
    from telefringe.simulate.presets import crop_camera, get_preset

    vr = crop_camera(get_preset("fast"), col0=100, row0=80, width=96, height=77)
    geom = sim.trace_geometry(vr, scenes.plate_at_z(0.0))
    gain = rig_noise(vr).gain
    scans = [sim.render_scan(vr, None, sim.default_groups(vr), exposures=(0.1, 0.6, 4.0),
                             seed=seed, geometry=geom)[0] for seed in (0, 1)]
    e = estimate_noise(scans[0])
    # measured 0.0176 +- 0.0047 against the true 0.0196, from the 4x exposure's groups
    assert abs(e.b - gain) < 3 * np.sqrt(e.covariance[1, 1]), (e.b, gain)
    assert all(g[3] > 0.1 for g in e.groups), e.groups
    # seed 1: the groups that agree with the quietest span one narrow range: said so
    with pytest.raises(NoiseEstimateError, match="too narrow an intensity range"):
        estimate_noise(scans[1])


def test_bga_on_a_flat_part_says_no_ball_was_found():
    # a plate with specks measured as a BGA: the message was "no ball could be fitted ()"
    from telefringe.metrology import BGANominal, MetrologyError, measure_bga
    from telefringe.reconstruction.cloud import PointCloud

    rows, cols = 60, 80
    yy, xx = np.mgrid[0:rows, 0:cols] * 0.05
    rng = np.random.default_rng(0)
    xyz = np.dstack([xx, yy, 0.002 * rng.standard_normal((rows, cols))])
    xyz[10:50:10, 10:70:15, 2] += 0.2         # specks far smaller than a ball
    cloud = PointCloud(xyz, np.ones((rows, cols), bool), np.full((rows, cols), 0.002),
                       np.zeros((rows, cols)), np.zeros((rows, cols), np.uint8),
                       np.array([0.0, 0.0, 1.0]))
    with pytest.raises(MetrologyError, match=r"no ball found: no region of ball size stands "
                                             r"0\.09 mm \(a fifth of the diameter\)"):
        measure_bga(cloud, BGANominal(rows=4, cols=4, pitch_mm=0.8, ball_diameter_mm=0.45))


def test_force_never_replaces_an_output_that_is_or_holds_an_input(tmp_path, capfd):
    # 'reconstruct scans/a -o scans/a --force' (or -o scans) replaced the scan folder by
    # the reconstruction, deleting the images; a batch whose scans sit in OUT/scans/NAME
    # did so even without --force
    from telefringe.cli import main
    from telefringe.io.atomic import atomic_dir, atomic_file

    scan = tmp_path / "scans" / "a"
    scan.mkdir(parents=True)
    (scan / "scan.json").write_text("{}")
    for out, what in ((scan, "is"), (tmp_path / "scans", "holds")):
        with pytest.raises(InputError, match=f"{what} the input .*write the output "
                                             "somewhere else"):
            with atomic_dir(out, force=True, inputs=(None, scan)):
                pass
    with pytest.raises(InputError, match="is the input"):
        with atomic_file(scan / "scan.json", force=True, inputs=(scan / "scan.json",)):
            pass
    assert (scan / "scan.json").read_text() == "{}"
    # an output beside the input, or a new one inside it, is fine
    with atomic_dir(tmp_path / "out", force=True, inputs=(scan,)) as tmp:
        (tmp / "x").write_text("1")
    with atomic_dir(scan / "rec", force=True, inputs=(scan,)):
        pass
    # the calibration report refused before anything is computed
    assert main(["calibrate", str(scan), "-o", str(tmp_path / "rig.json"), "--report",
                 str(tmp_path / "scans"), "--force"]) == 2
    assert "holds the input" in capfd.readouterr().err
    assert (scan / "scan.json").read_text() == "{}"


def test_a_lone_period_count_says_the_nonlinearity_stays(tmp_path, capsys):
    # one period count per axis: gamma correction (the default) silently did nothing
    from telefringe.cli import main

    write_scan(tmp_path / "scan", _fringe_scan(65535))
    capsys.readouterr()
    out = str(tmp_path / "c.npz")
    assert main(["decode", str(tmp_path / "scan"), "-o", out]) == 0
    assert ("axis u: one period count (1): the projector nonlinearity cannot be learned"
            in " ".join(capsys.readouterr().out.split()))
    assert main(["decode", str(tmp_path / "scan"), "-o", out, "--force",
                 "--no-gamma-correction"]) == 0
    assert "nonlinearity" not in capsys.readouterr().out


def test_patterns_refuse_periods_finer_than_2_px(tmp_path, capfd):
    # 300 periods across 400 px: a traceback from write_scan before
    from telefringe.cli import main

    assert main(["patterns", str(tmp_path / "p"), "--width", "400", "--height", "300",
                 "--periods", "1,8,300"]) == 2
    assert "at most 200 periods along u" in capfd.readouterr().err
    assert not (tmp_path / "p").exists()
    assert main(["patterns", str(tmp_path / "p"), "--width", "400", "--height", "300",
                 "--periods", "1,8,200", "--axes", "u", "--no-white-black"]) == 0


def test_decode_force_never_replaces_an_image_or_the_manifest(tmp_path, capfd):
    from telefringe.cli import main

    write_scan(tmp_path / "scan", _fringe_scan(65535))
    image = tmp_path / "scan" / "u_001_4s_00.png"
    before = image.read_bytes()
    for target in (image, tmp_path / "scan" / "scan.json"):
        assert main(["decode", str(tmp_path / "scan"), "-o", str(target), "--force"]) == 2
        assert "is the input" in capfd.readouterr().err
    assert image.read_bytes() == before
    assert main(["decode", str(tmp_path / "scan"), "-o", str(tmp_path / "scan" / "c.npz"),
                 "--force"]) == 0


def test_nonlinearity_kept_messages():
    # the batch's row and the CLI both say it (one message per axis of one period count)
    from telefringe.fringes.decode import nonlinearity_kept

    sc = _fringe_scan(65535)
    pc = decode(sc)
    assert [m[:28] for m in nonlinearity_kept(pc.axes, True)] == ["axis u: one period count (1)"]
    assert nonlinearity_kept(pc.axes, False) == []
