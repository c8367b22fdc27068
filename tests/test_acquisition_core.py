"""acquisition/: the contract (base), the sim pair's physics and clock, the verification
numerics, the latency fit and store, and scan.json's capture block."""

from __future__ import annotations

import json

import numpy as np
import pytest

from telefringe.acquisition import verify
from telefringe.acquisition.base import (
    Camera,
    DriverUnavailable,
    FrameStatus,
    Projector,
    Trigger,
    list_devices,
    load_driver,
    open_camera,
    open_projector,
    parse_spec,
    pixel_format_max,
)
from telefringe.acquisition.drivers.sim import SimConfig, next_frame_id, parse_address
from telefringe.acquisition.sequence import round_exposure, to_stored, wait_periods
from telefringe.fringes.patterns import fringe_intensity, pattern_stack
from telefringe.fringes.scan import PhaseGroup

SMALL = "sim:preset=fast,crop=96x80+112+88"
PERIOD_NS = 16_666_667


@pytest.fixture
def pair():
    proj = open_projector(SMALL)
    cam = open_camera("sim", projector=proj)
    yield cam, proj
    cam.close()
    proj.close()


# ----------------------------------------------------------------------------- registry
def test_registry_specs_and_missing_drivers():
    assert parse_spec("aravis:127.0.0.1") == ("aravis", "127.0.0.1")
    assert parse_spec("window:912x1140+1280+0") == ("window", "912x1140+1280+0")
    with pytest.raises(DriverUnavailable, match="known: .*sim"):
        open_camera("nosuch:1")
    with pytest.raises(DriverUnavailable, match="DRIVER"):
        parse_spec(":x")
    # a driver whose package is missing: one line naming the extra
    import importlib

    real_import = importlib.import_module

    def fake_import(name, *a, **k):
        if name == "telefringe.acquisition.drivers.pylon":
            raise ModuleNotFoundError("No module named 'pypylon'", name="pypylon")
        return real_import(name, *a, **k)

    importlib.import_module = fake_import
    try:
        with pytest.raises(DriverUnavailable) as exc:
            load_driver("pylon", "camera")
    finally:
        importlib.import_module = real_import
    msg = str(exc.value)
    assert "pip install 'telefringe[pylon]'" in msg and "pypylon" in msg and "\n" not in msg
    found = list_devices("camera")
    assert any(d.address == "preset=fast" for d in found["sim"])


def test_sim_pair_follows_the_protocols(pair):
    cam, proj = pair
    assert isinstance(cam, Camera) and isinstance(proj, Projector)
    assert cam.info.driver == "sim" and cam.info.serial and proj.info.sequencer
    assert pixel_format_max("Mono12") == 4095
    s = cam.configure(exposure_s=0.0123456789, gain_db=6.0, pixel_format="Mono12",
                      roi=(4, 2, 40, 30))
    # the values actually set: us steps, no analogue gain in the virtual camera
    assert s.exposure_s == pytest.approx(0.012346) and s.gain_db == 0.0
    assert s.roi == (4, 2, 40, 30) and s.max_value == 4095
    cam.start()
    with pytest.raises(Exception, match="stop acquisition"):
        cam.configure(exposure_s=0.01)
    shown = proj.show(np.zeros((300, 400), np.uint8))
    proj.clock.wait_until(shown.t_ns + 3 * PERIOD_NS)
    cam.fire()
    f = cam.grab(1.0)
    assert f.ok and f.image.shape == (30, 40) and f.image.dtype == np.uint16
    assert f.image.max() <= 4095
    # nothing triggered: a timeout, never the previous frame again
    t = proj.clock.now_ns()
    g = cam.grab(0.5)
    assert g.status is FrameStatus.TIMEOUT and g.image is None
    assert proj.clock.now_ns() - t == 500_000_000          # virtual: no sleep
    with pytest.raises(Exception, match="2-D"):
        proj.show(np.eye(300, 400, dtype=np.uint8))
    with pytest.raises(Exception, match="belongs to the sim camera"):
        parse_address("drop=0.1", kind="projector")


def test_an_exposure_integrates_what_the_projector_shows(pair):
    """A pattern change inside the exposure mixes the two patterns in proportion to
    their times (the signal is linear in the emitted light)."""
    cam, proj = pair
    rig = proj.rig
    white = np.full((300, 400), 255, np.uint8)
    black = np.zeros((300, 400), np.uint8)
    t0 = 10 * 1_000_000_000
    rig.emit(t0, black)
    rig.emit(t0 + 10_000_000, white)
    w = rig.weights(t0, t0 + 40_000_000)
    assert [round(a, 6) for a, _ in w] == [0.25, 0.75]
    mix = rig._signal(w[0][1]) * 0.25 + rig._signal(w[1][1]) * 0.75
    rig.noise_rng = np.random.default_rng(1)
    img = rig.render(t0, t0 + 40_000_000).astype(float)
    from telefringe.simulate import render

    rig.noise_rng = np.random.default_rng(1)
    ref = render._sensor(mix, rig.vrig, 0.04 / SimConfig().exposure_ref, rig.noise_rng,
                         rig._geom.pad).astype(float)
    assert np.array_equal(img, ref)
    # and in the streamed timing: a trigger before the light arrives sees the old pattern
    cam.configure(exposure_s=1 / 60)
    cam.start()
    proj.show(black)
    proj.clock.wait_until(proj.clock.now_ns() + 10 * PERIOD_NS)
    sh = proj.show(white)
    cam.fire()                                  # at the flip: latency 25 ms not waited
    early = cam.grab(1.0).image.astype(float).mean()
    proj.clock.wait_until(sh.t_ns + 2 * PERIOD_NS)
    cam.fire()
    late = cam.grab(1.0).image.astype(float).mean()
    assert early < 0.1 * late


def test_frame_ids_wrap_like_gige_vision():
    assert next_frame_id(65535) == 1 and next_frame_id(1) == 2
    assert verify.id_gap(65535, 1) == 1 and verify.id_gap(65534, 2) == 3
    ok = verify.check_ids([65534, 65535, 1, 2])
    assert ok.ok and list(ok.gaps) == [1, 1, 1]
    bad = verify.check_ids([65534, 65535, 2, 2])
    assert not bad.ok and list(np.flatnonzero(bad.bad)) == [2, 3]
    assert "missing" in bad.message and "repeats" in bad.message
    assert verify.check_ids([10, 12], allowed_extra=[0, 1]).ok


def test_spacing_and_duplicates():
    ts = [0, 16_666_667, 33_333_333, 66_666_667]
    sp = verify.check_spacing(ts, period_s=1 / 60)
    assert not sp.ok and list(np.flatnonzero(sp.bad)) == [3]
    rng = np.random.default_rng(0)
    a = rng.integers(0, 255, (20, 20), dtype=np.uint8)
    b = rng.integers(0, 255, (20, 20), dtype=np.uint8)
    flat = np.zeros((20, 20), np.uint8)
    assert verify.duplicate_frames([a, b, a.copy(), flat, flat.copy()]) == [(0, 2)]


def _synthetic(n, *, w=0.0, bad=None, gamma=2.2, periods=7.3, noise=1.0, seed=0):
    """N-step frames of a gamma-distorted fringe over a field seeing many periods, frame
    ``bad`` mixed with its predecessor's pattern in proportion ``w``."""
    rng = np.random.default_rng(seed)
    x = np.linspace(0, 1, 200)[None, :] * np.ones((60, 1))
    alb = 0.6 + 0.3 * np.sin(3 * x + np.linspace(0, 1, 60)[:, None])

    def frame(k):
        lv = fringe_intensity(x * 400, periods=periods * 40, steps=n, k=k, length=400)
        return 10 + 200 * alb * lv ** gamma

    st = np.stack([frame(k) for k in range(n)])
    if bad is not None:
        st[bad] = (1 - w) * frame(bad) + w * frame(bad - 1)
    return st + noise * rng.standard_normal(st.shape)


@pytest.mark.parametrize("n", [4, 5, 8])
def test_phase_step_check_clean_and_mixed(n):
    clean = verify.phase_step_check(_synthetic(n), max_value=255)
    assert clean.possible and not clean.flagged.any(), clean.message
    # the tolerance's floor (2 mrad) is far above what a clean group shows here
    assert np.max(np.abs(clean.step_error)) < 0.5e-3
    for w in (0.03, 0.1, 0.5, 1.0):
        r = verify.phase_step_check(_synthetic(n, w=w, bad=2), max_value=255)
        assert r.flagged[2], (w, r.message)
        # the mixed frame is the worst one (N = 4 cannot tell frame 2 from frame 0)
        assert np.argmax(np.abs(r.step_error)) in ((0, 2) if n == 4 else (2,))


def test_phase_step_check_says_when_it_cannot():
    r = verify.phase_step_check(_synthetic(3), max_value=255)
    assert not r.possible and "3 steps" in r.message and not r.flagged.any()
    r = verify.phase_step_check(_synthetic(4, periods=0.008), max_value=255)
    assert not r.possible and "of a fringe period" in r.message


def test_gray_check_flags_a_mixed_bit_frame():
    rng = np.random.default_rng(0)
    bits = rng.integers(0, 2, (3, 40, 40)).astype(float)
    lo, hi = np.full((40, 40), 10.0), np.full((40, 40), 210.0)
    st = lo + bits * (hi - lo)
    st[2] = 0.5 * st[2] + 0.5 * st[1]
    r = verify.gray_check(st, dark=lo, bright=hi, min_contrast=20)
    assert list(np.flatnonzero(r.flagged)) == [2]


def test_exposure_latency_and_storage_helpers(tmp_path, monkeypatch):
    assert wait_periods(0.025, 1 / 60) == 2 and wait_periods(0.0, 1 / 60) == 1
    e, warn = round_exposure(0.02, 1 / 60)
    assert e == pytest.approx(1 / 60) and "rounded" in warn
    e, warn = round_exposure(0.004, 1 / 60)
    assert e == 0.004 and "shorter than one refresh" in warn
    assert to_stored(np.array([4095, 0, 2048], np.uint16), "Mono12").tolist() == \
        [65535, 0, 32776]
    assert to_stored(np.array([1023], np.uint16), "Mono10").tolist() == [65535]
    from telefringe.acquisition.latency import (
        ENV_LATENCY_FILE,
        fit_latency,
        latency_file,
        load_latency,
        save_latency,
    )

    d = np.arange(0, 0.05, 0.002)
    f = np.clip((d + 0.004 - 0.025) / 0.004, 0, 1)
    lat, half = fit_latency(d, f, exposure_s=0.004)
    assert lat == pytest.approx(0.026) and lat >= 0.025 and half == pytest.approx(0.025)
    with pytest.raises(Exception, match="never saw"):
        fit_latency(d, 0 * f, exposure_s=0.004)
    monkeypatch.setenv(ENV_LATENCY_FILE, str(tmp_path / "lat.json"))
    assert latency_file() == tmp_path / "lat.json"
    assert load_latency("a") is None
    save_latency("a", {"latency_s": 0.03})
    save_latency("b", {"latency_s": 0.01})
    assert load_latency("a")["latency_s"] == 0.03 and load_latency("b")["latency_s"] == 0.01
    (tmp_path / "lat.json").write_text("{broken")
    with pytest.raises(Exception, match="lat.json"):
        load_latency("a")


def test_sequenced_mode_hardware_triggers(pair):
    cam, proj = pair
    from telefringe.acquisition.sequence import Policy, capture_sequenced

    g = PhaseGroup("u", 8, 4)
    imgs = list(pattern_stack(g, width=400, height=300))
    s = cam.configure(exposure_s=1 / 120, trigger=Trigger.HARDWARE)
    assert s.trigger_line == "Line0"
    cam.start()
    cam.fire()                                     # a no-op under the hardware trigger
    assert cam.grab(0.1).status is FrameStatus.TIMEOUT
    res = capture_sequenced(cam, proj, imgs, settings=s, exposure_s=1 / 120,
                            layout=[("phase", g)], policy=Policy())
    ts = [sh.timestamp_ns for sh in res.shots]
    # exposure 8.3 ms: one refresh period for it plus one wasted (SLStudio's advice)
    assert np.allclose(np.diff(ts), 2 * PERIOD_NS, atol=1000) and res.retries == 0
    assert verify.check_ids([sh.frame_id for sh in res.shots]).ok


# ----------------------------------------------------------------------------- scan.json
def test_capture_block_is_validated(tmp_path):
    from telefringe.fringes.patterns import pattern_scan
    from telefringe.io.errors import InputError
    from telefringe.io.scan_json import load_scan_manifest, read_capture, write_scan

    scan = pattern_scan(width=40, height=30, steps=4, periods=[1, 4], axes=("u",))
    names = [f"u_{p:03d}_4s_{k:02d}.png" for p in (1, 4) for k in range(4)]
    block = {"version": 1, "mode": "streamed",
             "camera": {"driver": "sim", "model": "m", "serial": "s"},
             "projector": {"driver": "sim"},
             "settings": [{"exposure_s": 0.0333, "pixel_format": "Mono8",
                           "roi": [0, 0, 40, 30]}],
             "latency": {"latency_s": 0.025}, "retries": 2,
             "frames": [{"image": n, "id": i + 1, "timestamp_ns": 10 * i, "attempts": 1}
                        for i, n in enumerate(names)]}
    write_scan(tmp_path / "ok", scan, capture=block)
    assert read_capture(tmp_path / "ok")["retries"] == 2
    load_scan_manifest(tmp_path / "ok")
    doc = json.loads((tmp_path / "ok" / "scan.json").read_text())
    doc["capture"]["frames"][0]["image"] = "nope.png"
    doc["capture"]["frames"][1]["id"] = "7"
    doc["capture"]["settings"][0]["exposure_s"] = -1
    doc["capture"]["mode"] = "magic"
    (tmp_path / "ok" / "scan.json").write_text(json.dumps(doc))
    with pytest.raises(InputError) as exc:
        load_scan_manifest(tmp_path / "ok")
    msg = str(exc.value)
    for token in ("4 problems", "frames[0].image", "frames[1].id", "exposure_s", "mode"):
        assert token in msg, (token, msg)
    # a scan without the block still reads (the block is optional)
    write_scan(tmp_path / "plain", scan)
    assert read_capture(tmp_path / "plain") is None


def test_a_camera_that_sees_no_fringes_is_one_clear_error():
    from telefringe.acquisition.sequence import (
        CaptureFailed,
        GroupReport,
        Policy,
        check_modulation,
    )

    seen = [GroupReport("phase", modulated=0.004), GroupReport("phase", modulated=0.2)]
    check_modulation(seen, Policy())
    with pytest.raises(CaptureFailed, match="does not see the projected patterns"):
        check_modulation([GroupReport("phase", modulated=0.004)], Policy())


def test_gray_frames_mixed_or_repeating_the_previous_pattern_are_flagged():
    """A Gray-code frame with most of the previous frame's light (late) is flagged by the
    repeat test, one half-and-half by the mid-grey test; a clean group passes."""
    from telefringe.acquisition.sequence import Policy, check_groups
    from telefringe.fringes.patterns import gray_code_bits
    from telefringe.fringes.scan import GrayGroup

    phase = _synthetic(4)                                  # (4, 60, 200), dark 10
    x = (np.arange(200) * 2)[None, :] * np.ones((60, 1), dtype=int)
    g = GrayGroup("u", 3, complementary=True)
    bits = gray_code_bits(x, bits=3, length=400, complementary=True).astype(float)
    gray = 10 + 200 * 0.75 * bits                          # lit like the fringes' peak
    layout = [("phase", PhaseGroup("u", 29, 4)), ("gray", g)]

    def flagged(gray_frames):
        imgs = [*phase, *gray_frames]
        reports, fl = check_groups(imgs, layout, max_value=255, policy=Policy(),
                                   saturation_limit=True)
        return sorted(i - 4 for i in fl), reports[1].message

    assert flagged(list(gray))[0] == []
    late = gray.copy()
    late[2] = 0.85 * gray[1] + 0.15 * gray[2]
    f, msg = flagged(list(late))
    assert f == [2] and "previous pattern" in msg, msg
    mixed = gray.copy()
    mixed[2] = 0.5 * gray[1] + 0.5 * gray[2]
    f, msg = flagged(list(mixed))
    assert f == [2] and "mid-grey" in msg, msg
