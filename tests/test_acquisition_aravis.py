"""The aravis camera driver against a real GigE Vision stack: Aravis's fake camera on
loopback (GVCP + GVSP over UDP), whose images are the virtual rig's render of the pattern
a projector is showing.

The fake camera listens on 127.0.0.1:3956, one at a time: `make test` runs the file in
one worker (``--dist loadfile``), and the fixture waits for the port if another run holds
it. Needs libaravis 0.8 (``make test`` installs ``libaravis-0.8-0`` when run as root).
"""

from __future__ import annotations

import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from telefringe.acquisition.base import DriverUnavailable, FrameStatus, Trigger, open_camera

try:
    from telefringe.acquisition.drivers import aravis
    from telefringe.acquisition.drivers.aravis_fake import FakeGigECamera
except DriverUnavailable as exc:  # pragma: no cover - only without libaravis
    pytest.skip(f"{exc} (as root, `make test` installs it)", allow_module_level=True)

from telefringe.fringes.patterns import pattern_groups, pattern_stack
from telefringe.fringes.phase import wrap, wrapped_phase
from telefringe.simulate.presets import get_preset
from telefringe.simulate.render import _integrate_many, _sensor, trace_geometry
from telefringe.simulate.scenes import make_scene

GROUPS = pattern_groups(steps=4, periods=(1, 8), axes=("u", "v"))


def _wait_for_port(timeout_s: float = 60.0) -> None:
    """Wait until nothing listens on 127.0.0.1:3956/udp (another test run's fake camera)."""
    end = time.monotonic() + timeout_s
    while True:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            s.bind(("127.0.0.1", 3956))
            return
        except OSError:
            if time.monotonic() > end:
                pytest.fail("127.0.0.1:3956/udp stays busy (another GigE Vision device or "
                            "fake camera): the fake camera cannot listen")
            time.sleep(0.5)
        finally:
            s.close()


class _Rig:
    """The virtual rig's camera images of whatever projector image is shown: the fill of
    the fake camera and, with another seed, the 'direct' render to compare with."""

    def __init__(self, bit_depth: int):
        self.vrig = get_preset("fast").with_photometry(bit_depth=bit_depth)
        self.geom = trace_geometry(self.vrig, make_scene("plate"))
        p = self.vrig.projector.intrinsics
        self.patterns = []                     # (projector image, axis, group, k)
        for g in GROUPS:
            st = pattern_stack(g, width=p.width, height=p.height, bit_depth=8)
            self.patterns += [(st[k], g.axis, g, k) for k in range(g.count)]
        top = np.full((p.height, p.width), 255, np.uint8)
        self.patterns += [(top, "u", None, 0), (np.zeros_like(top), "u", None, 1)]
        self._signal = {}
        self._served = [self.image(i, seed=1) for i in range(len(self.patterns))]

    def served(self, index: int) -> np.ndarray:
        """What the fake camera sends while pattern ``index`` is shown (rendered ahead, so
        the camera's streaming thread only copies)."""
        return self._served[index]

    def signal(self, index: int) -> np.ndarray:
        if index not in self._signal:
            img, axis, _, _ = self.patterns[index]
            line = img[0, :] if axis == "u" else img[:, 0]
            self._signal[index] = _integrate_many(self.geom, self.vrig, axis, [line])[0]
        return self._signal[index]

    def image(self, index: int, seed: int) -> np.ndarray:
        rng = np.random.default_rng([seed, index])
        return _sensor(self.signal(index), self.vrig, 1.0, rng, self.geom.pad)

    def phase_rms(self, images) -> float:
        """RMS (rad) of the wrapped phase error of every phase group, over lit pixels."""
        t = self.geom.truth
        p = self.vrig.projector.intrinsics
        errs = []
        i = 0
        for g in GROUPS:
            stack = np.stack(images[i:i + g.count]).astype(float)
            i += g.count
            wp = wrapped_phase(stack, steps=g.steps, offset=g.offset)
            coord, length = (t.u_p, p.width) if g.axis == "u" else (t.v_p, p.height)
            truth = 2 * np.pi * g.periods * coord / length
            ok = t.lit & (wp.modulation > 10 * self.vrig.photometry.max_value / 255)
            errs.append(wrap(wp.phase - truth)[ok])
        e = np.concatenate(errs)
        assert e.size > 0.5 * t.lit.size
        return float(np.sqrt(np.mean(e ** 2)))


class _Shown:
    """The projector of these tests: remembers which pattern it shows."""

    index = None


@pytest.fixture(scope="module")
def rig8():
    return _Rig(8)


def _fake(rig: _Rig, shown: _Shown, **kw) -> FakeGigECamera:
    _wait_for_port()

    def fill(w, h, fmt, exposure_s, gain):
        if shown.index is None:
            return None
        img = rig.served(shown.index)
        if fmt == "Mono8" and img.dtype != np.uint8:
            raise ValueError("the rig renders 16-bit images; configure Mono16")
        return img

    return FakeGigECamera(fill, **kw)


def _configure(cam, rig: _Rig):
    k = rig.vrig.camera.intrinsics
    fmt = "Mono8" if rig.vrig.photometry.bit_depth == 8 else "Mono16"
    return cam.configure(exposure_s=0.004, pixel_format=fmt, roi=(0, 0, k.width, k.height),
                         trigger=Trigger.SOFTWARE)


def _capture(cam, rig, shown, *, retries: int, timeout_s: float = 1.0):
    """Show each pattern, fire, grab; retry a bad frame after a flush. Returns the
    images, ids, and the number of retries; raises after ``retries`` failures of one."""
    images, ids, n_retry = [], [], 0
    for i in range(len(rig.patterns)):
        shown.index = i
        for _attempt in range(retries + 1):
            cam.fire()
            f = cam.grab(timeout_s)
            if f.ok:
                break
            n_retry += 1
            cam.flush()
        else:
            raise RuntimeError(f"pattern {i}: no complete frame in {retries + 1} tries "
                               f"({f.status.value}: {f.message})")
        images.append(f.image)
        ids.append(f.frame_id)
    return images, ids, n_retry


def test_id_gap_wraps_like_gige_vision():
    assert aravis.id_gap(65535, 1, wrap16=True) == 1
    assert aravis.id_gap(65535, 2, wrap16=True) == 2
    assert aravis.id_gap(65535, 65536, wrap16=False) == 1
    assert aravis.id_gap(3, 2, wrap16=True) == 65534     # an old frame is far "ahead"


def test_which_frame_answers_a_trigger():
    """The decision table of the software-trigger bookkeeping, case by case (the fake
    camera cannot produce every case on demand)."""
    cam = aravis.AravisCamera.__new__(aravis.AravisCamera)
    cam._gv, cam.discarded = True, 0
    img = np.zeros((2, 2), np.uint8)

    def judge(owed, last, fid, *, status=0, arrived=2_000, t_fire=1_000):
        cam._reset_counts()
        cam._owed, cam._last_id, cam._t_fire_ns = owed, last, t_fire
        return cam._judge(status, fid, 0, arrived, img if status == 0 else None, True)

    assert judge(0, 10, 11) is None                           # nothing was asked for
    assert judge(1, None, 5, arrived=500) is None             # began before the trigger
    assert judge(1, None, 5).ok                               # first after start
    assert judge(1, 65535, 1).ok                              # the GigE Vision wrap
    jump = judge(1, 10, 12)
    assert not jump.ok and "jumped by 2" in jump.message
    assert judge(1, 10, 10) is None                           # an id already seen
    assert not judge(1, 10, 9).ok                             # an older id: never OK
    late = judge(1, 10, 11, arrived=500)
    assert not late.ok and "before the trigger" in late.message
    lost = judge(1, 10, 11, status=3, arrived=500)            # leader lost: stale id/time
    assert lost.status is FrameStatus.INCOMPLETE and lost.frame_id == -1
    assert lost.image is None and cam._last_id is None
    # two triggers outstanding: the first frame arrived before the second trigger
    cam._reset_counts()
    cam._owed, cam._last_id, cam._t_fire_ns = 2, 10, 1_000
    assert cam._judge(0, 11, 0, 500, img, True).ok
    assert cam._judge(0, 12, 0, 2_000, img, True).ok and cam._owed == 0


def test_full_scan_by_software_trigger_measures_like_direct_render(rig8):
    """A full scan (2 axes x 2 periods x 4 steps + white + black) through GigE Vision:
    every frame is bit-identical to the rig's render of the pattern shown, the ids run on
    across the 65535 -> 1 wrap, and the decoded phase error is that of the same images
    rendered directly (independent noise) within 1.1x."""
    shown = _Shown()
    with _fake(rig8, shown) as fake, aravis.open_camera("127.0.0.1") as cam:
        s = _configure(cam, rig8)
        assert (s.pixel_format, s.roi[2:], s.max_value) == ("Mono8", (320, 256), 255)
        assert abs(s.exposure_s - 0.004) < 1e-6
        cam.start()
        # the fake's ids start at 65401: run on past the wrap first
        while True:
            shown.index = 0
            cam.fire()
            f = cam.grab(1.0)
            assert f.ok, f.message
            if f.frame_id > 65525:
                break
        images, ids, n_retry = _capture(cam, rig8, shown, retries=0)
        assert fake.errors == []
    n = len(rig8.patterns)
    assert n_retry == 0
    assert 65535 in ids and 1 in ids
    assert all(aravis.id_gap(a, b, wrap16=True) == 1 for a, b in zip(ids, ids[1:], strict=False))
    same = [np.array_equal(im, rig8.image(i, seed=1)) for i, im in enumerate(images)]
    assert sum(same) == n
    captured = rig8.phase_rms(images)
    direct = rig8.phase_rms([rig8.image(i, seed=2) for i in range(n)])
    print(f"phase RMS: captured {captured:.5f} rad, direct {direct:.5f} rad, "
          f"ratio {captured / direct:.4f}")
    assert captured <= 1.1 * direct


def test_mono16_frames_carry_the_12_bit_render():
    rig = _Rig(12)
    shown = _Shown()
    with _fake(rig, shown), aravis.open_camera("127.0.0.1") as cam:
        s = _configure(cam, rig)
        assert (s.pixel_format, s.max_value) == ("Mono16", 65535)
        cam.start()
        for i in (0, 5):
            shown.index = i
            cam.fire()
            f = cam.grab(1.0)
            assert f.ok and f.image.dtype == np.uint16
            assert np.array_equal(f.image, rig.image(i, seed=1))
            assert f.image.max() > 4095          # MSB-aligned 12-bit data in 16 bits


def _served(fake, n: int, timeout_s: float = 5.0) -> None:
    """Wait until the fake camera has filled ``n`` frames (so the test's projector may
    move on without racing the camera's thread)."""
    end = time.monotonic() + timeout_s
    while fake.frames_served < n:
        assert time.monotonic() < end, "the fake camera stopped serving frames"
        time.sleep(0.001)


def test_late_frames_are_never_taken_for_the_next_pattern(rig8):
    """Grab with a timeout too short for the frame: it arrives late, after the next
    pattern is shown; the next grab must return the next pattern, never the late one."""
    shown = _Shown()
    with _fake(rig8, shown) as fake, aravis.open_camera("127.0.0.1") as cam:
        _configure(cam, rig8)
        cam.start()
        n_timeouts = 0
        for i in range(6):
            shown.index = i
            n = fake.frames_served
            cam.fire()
            f = cam.grab(0.0)                    # too short: the frame comes later
            if f.status is FrameStatus.TIMEOUT:
                n_timeouts += 1
                _served(fake, n + 1)             # the late frame is on its way ...
                time.sleep(0.02)
                shown.index = i + 1              # ... and the projector moves on
                cam.fire()
                f = cam.grab(1.0)
                assert f.ok, f.message
                assert np.array_equal(f.image, rig8.image(i + 1, seed=1))
            else:
                assert np.array_equal(f.image, rig8.image(i, seed=1))
        assert n_timeouts >= 3
        assert cam.resyncs == n_timeouts
        # several triggers before grabbing: frames come back in order, each once
        for i in (2, 3, 4):
            shown.index = i
            n = fake.frames_served
            cam.fire()
            _served(fake, n + 1)
        got = [cam.grab(1.0) for _ in range(3)]
        assert [g.ok for g in got] == [True] * 3
        assert all(np.array_equal(g.image, rig8.image(i, seed=1))
                   for g, i in zip(got, (2, 3, 4), strict=True))
        assert cam.grab(0.1).status is FrameStatus.TIMEOUT


def test_one_percent_packet_loss_retries_then_succeeds_or_fails_clearly(rig8):
    """1 % of GVSP packets lost (about half the frames incomplete, the fake never resends):
    incomplete frames come back INCOMPLETE, never OK; retries after a flush recover; no
    accepted frame is ever another pattern's; or the capture stops with one clear error."""
    shown = _Shown()
    with _fake(rig8, shown, loss_ratio=0.01), aravis.open_camera("127.0.0.1") as cam:
        _configure(cam, rig8)
        cam.start()
        try:
            images, ids, n_retry = _capture(cam, rig8, shown, retries=12, timeout_s=0.5)
        except RuntimeError as exc:               # the one clear error (p ~ 1e-3)
            assert "no complete frame in 13 tries" in str(exc)
            return
        stats = cam.statistics()
    n = len(rig8.patterns)
    print(f"1 % packet loss: {n} frames accepted after {n_retry} retries; Aravis stream "
          f"statistics {stats}")
    assert n_retry >= 1 and stats["failures"] >= 1
    assert all(np.array_equal(im, rig8.image(i, seed=1)) for i, im in enumerate(images))


def test_hardware_trigger_and_free_run(rig8):
    """HARDWARE: the line is set, fire() sends nothing, and with no pulse on the line
    (the fake has no trigger input) grab says TIMEOUT, never an old image. FREE_RUN: every
    frame once, oldest first, ids consecutive."""
    shown = _Shown()
    shown.index = 3
    with _fake(rig8, shown), aravis.open_camera("127.0.0.1") as cam:
        k = rig8.vrig.camera.intrinsics
        s = cam.configure(exposure_s=0.004, roi=(0, 0, k.width, k.height),
                          trigger=Trigger.HARDWARE)
        assert (s.trigger, s.trigger_line) == (Trigger.HARDWARE, "Line0")
        cam.start()
        cam.fire()
        f = cam.grab(0.3)
        assert f.status is FrameStatus.TIMEOUT and f.image is None
        cam.stop()
        cam.configure(exposure_s=0.004, roi=(0, 0, k.width, k.height),
                      trigger=Trigger.FREE_RUN)
        cam.start()
        frames = [cam.grab(1.0) for _ in range(6)]
        cam.stop()
    assert all(f.ok and f.message == "" for f in frames)
    assert all(aravis.id_gap(a.frame_id, b.frame_id, wrap16=True) == 1
               for a, b in zip(frames, frames[1:], strict=False))
    assert all(np.array_equal(f.image, rig8.image(3, seed=1)) for f in frames)


def test_registry_opens_the_camera_by_address_and_by_serial(rig8):
    shown = _Shown()
    with _fake(rig8, shown, serial="TF777"):
        listed = aravis.list_cameras()
        assert any(d.serial == "TF777" and d.address == "127.0.0.1" for d in listed)
        for spec in ("aravis:127.0.0.1", "aravis:TF777"):
            with open_camera(spec) as cam:
                assert (cam.info.serial, cam.info.model, cam.info.vendor) == \
                    ("TF777", "Fake", "Aravis")
                assert "Mono8" in cam.info.pixel_formats
        with pytest.raises(Exception, match="no Aravis camera 'NOPE'"):
            open_camera("aravis:NOPE")


def test_missing_library_is_one_line_saying_what_to_install():
    code = ("import ctypes\n"
            "real = ctypes.CDLL\n"
            "def cdll(name, *a, **k):\n"
            "    if name and 'aravis' in str(name):\n"
            "        raise OSError('not found')\n"
            "    return real(name, *a, **k)\n"
            "ctypes.CDLL = cdll\n"
            "from telefringe.acquisition.base import load_driver, DriverUnavailable\n"
            "try:\n"
            "    load_driver('aravis', 'camera')\n"
            "except DriverUnavailable as e:\n"
            "    print(e)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    line = out.stdout.strip()
    assert "\n" not in line and "apt-get install libaravis-0.8-0" in line


def _xvfb_with_projector(width: int, height: int):
    """Start Xvfb with a MAIN monitor and a PROJECTOR monitor of ``width`` x ``height``;
    returns (process, display) or skips saying what is missing."""
    import os
    import shutil

    for tool in ("Xvfb", "xrandr"):
        if shutil.which(tool) is None:
            pytest.skip(f"{tool} is not installed (as root, `make test` installs xvfb and "
                        f"x11-xserver-utils)")
    r, w = os.pipe()
    proc = subprocess.Popen(["timeout", "300", "Xvfb", "-displayfd", str(w), "-screen", "0",
                             f"{640 + width}x{max(480, height)}x24", "-nolisten", "tcp",
                             "-noreset"], pass_fds=(w,), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    os.close(w)
    with os.fdopen(r) as f:
        display = ":" + f.readline().strip()
    env = dict(os.environ, DISPLAY=display)
    for name, geo in (("MAIN", "640/160x480/120+0+0"),
                      ("PROJECTOR", f"{width}/100x{height}/75+640+0")):
        subprocess.run(["xrandr", "--setmonitor", name, geo, "none"], check=True, env=env,
                       timeout=30)
    return proc, env


def test_capture_cli_through_an_x_server_and_gige_vision(tmp_path):
    """The whole chain, every part real but the optics: `telefringe capture scan` shows
    each pattern in a window projector on an X server (Xvfb); a fake GigE Vision camera
    (another process) sees that monitor through the virtual rig and streams over GVSP;
    the capture verifies and writes the scan. Its phase error is that of the sim pair's
    capture of the same scan (a direct render) within 1.1x."""
    pytest.importorskip("pyglet", reason="pyglet is not installed (pip install -e '.[test]')")
    pytest.importorskip("mss", reason="mss is not installed (pip install -e '.[test]')")
    _wait_for_port()
    vrig = get_preset("fast")
    p = vrig.projector.intrinsics
    xvfb, env = _xvfb_with_projector(p.width, p.height)
    server = None
    try:
        common = ["--periods", "1,8", "--axes", "u,v", "--exposure", "0.0333",
                  "--latency", "0.01"]
        tf = [sys.executable, "-m", "telefringe.cli"]
        roi = f"{vrig.camera.intrinsics.width}x{vrig.camera.intrinsics.height}+0+0"
        runs = {}
        for name, loss in (("real", "0"), ("lossy", "0.01")):
            server = subprocess.Popen(
                [sys.executable, "-m", "telefringe.acquisition.drivers.aravis_fake",
                 "--monitor", "PROJECTOR", "--loss", loss, "--lifetime", "240"], env=env,
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            line = server.stdout.readline()
            assert line.startswith("ready"), server.stderr.read()
            runs[name] = subprocess.run(
                tf + ["capture", "scan", str(tmp_path / name), "--camera", "aravis:127.0.0.1",
                      "--projector", "window:PROJECTOR", "--roi", roi, "--retries", "10"]
                + common, env=env, capture_output=True, text=True, timeout=240)
            server.terminate()
            server.communicate(timeout=30)
            server = None
        real = runs["real"]
        assert real.returncode == 0, real.stdout + real.stderr
        # 1 % of the packets lost: re-shoots then success, or one clear error and nothing
        # written (10 re-shoots per frame: that happens with p ~ 0.4 %)
        lossy = runs["lossy"]
        if lossy.returncode != 0:
            assert lossy.returncode == 1 and not (tmp_path / "lossy").exists()
            assert lossy.stderr.strip().count("\n") == 0 and "attempts failed" in lossy.stderr
        direct = subprocess.run(tf + ["capture", "scan", str(tmp_path / "direct"),
                                      "--camera", "sim", "--projector",
                                      "sim:preset=fast,latency=0.01"] + common,
                                env=env, capture_output=True, text=True, timeout=240)
        assert direct.returncode == 0, direct.stdout + direct.stderr
    finally:
        if server is not None:
            server.terminate()
            server.communicate(timeout=30)      # closes its pipes
        xvfb.terminate()
        xvfb.wait(timeout=30)
    import json

    import cv2

    block = json.loads((tmp_path / "real" / "scan.json").read_text())["capture"]
    assert (block["camera"]["driver"], block["projector"]["driver"]) == ("aravis", "window")
    ids = [f["id"] for f in block["frames"]]
    assert all(aravis.id_gap(a, b, wrap16=True) >= 1 for a, b in zip(ids, ids[1:],
                                                                    strict=False))
    t = trace_geometry(vrig, make_scene("plate")).truth

    def rms(folder):
        errs = []
        for axis, coord, length in (("u", t.u_p, p.width), ("v", t.v_p, p.height)):
            for per in (1, 8):
                ims = np.stack([cv2.imread(str(folder / f"{axis}_{per:03d}_4s_{k:02d}.png"),
                                           cv2.IMREAD_UNCHANGED) for k in range(4)])
                wp = wrapped_phase(ims.astype(float), steps=4)
                ok = t.lit & (wp.modulation > 10)
                errs.append(wrap(wp.phase - 2 * np.pi * per * coord / length)[ok])
        e = np.concatenate(errs)
        return float(np.sqrt(np.mean(e ** 2)))

    r_real, r_direct = rms(tmp_path / "real"), rms(tmp_path / "direct")
    print(f"capture CLI, window on Xvfb + aravis fake camera: phase RMS {r_real:.5f} rad; "
          f"sim pair {r_direct:.5f} rad; ratio {r_real / r_direct:.4f}; retries "
          f"{block['retries']}")
    assert r_real <= 1.1 * r_direct
    if lossy.returncode == 0:
        b = json.loads((tmp_path / "lossy" / "scan.json").read_text())["capture"]
        r_lossy = rms(tmp_path / "lossy")
        print(f"  with 1 % packet loss: {b['retries']} re-shoots, phase RMS {r_lossy:.5f} rad,"
              f" ratio {r_lossy / r_direct:.4f}")
        assert b["retries"] >= 1 and r_lossy <= 1.1 * r_direct
