"""The window projector against a real X server: Xvfb with two RandR monitors (a desktop
and a projector, declared with ``xrandr --setmonitor``), pyglet drawing through Mesa's
software GL, read back from the X server with mss: what is shown must be the image, pixel
for pixel, on the projector's monitor and nowhere else.

Needs Xvfb and xrandr (``make test`` installs ``xvfb x11-xserver-utils`` when run as root)
and pyglet + mss (the test extra). Xvfb runs under ``timeout`` so that it stops by itself
even if the test run is killed.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("pyglet", reason="pyglet is not installed (pip install -e '.[test]')")
mss = pytest.importorskip("mss", reason="mss is not installed (pip install -e '.[test]')")

from telefringe.acquisition.base import NotSupported, open_projector  # noqa: E402
from telefringe.acquisition.drivers import window  # noqa: E402
from telefringe.fringes.patterns import pattern_groups, pattern_stack  # noqa: E402

MAIN = (640, 480, 0, 0)
PROJ = (400, 300, 640, 0)


@pytest.fixture(scope="module")
def xserver():
    for tool in ("Xvfb", "xrandr"):
        if shutil.which(tool) is None:
            pytest.skip(f"{tool} is not installed (as root, `make test` installs xvfb and "
                        f"x11-xserver-utils)")
    r, w = os.pipe()
    width = MAIN[0] + PROJ[0]
    proc = subprocess.Popen(["timeout", "600", "Xvfb", "-displayfd", str(w), "-screen", "0",
                             f"{width}x{MAIN[1]}x24", "-nolisten", "tcp", "-noreset"],
                            pass_fds=(w,), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    os.close(w)
    with os.fdopen(r) as f:
        number = f.readline().strip()
    if not number:
        proc.kill()
        pytest.fail("Xvfb did not start")
    display = f":{number}"
    old = os.environ.get("DISPLAY")
    os.environ["DISPLAY"] = display
    try:
        for name, (w_, h_, x_, y_) in (("MAIN", MAIN), ("PROJECTOR", PROJ)):
            subprocess.run(["xrandr", "--setmonitor", name,
                            f"{w_}/{w_ // 4}x{h_}/{h_ // 4}+{x_}+{y_}", "none"], check=True,
                           timeout=30)
        yield display
    finally:
        if old is None:
            os.environ.pop("DISPLAY", None)
        else:
            os.environ["DISPLAY"] = old
        proc.terminate()
        proc.wait(timeout=30)


def _grab(box):
    w, h, x, y = box
    with mss.MSS() as m:
        return np.array(m.grab({"left": x, "top": y, "width": w, "height": h}))


def test_monitors_are_the_randr_monitors(xserver):
    mons = window.list_monitors()
    geo = {m.name: (m.width, m.height, m.x, m.y) for m in mons}
    assert geo["MAIN"] == MAIN and geo["PROJECTOR"] == PROJ
    listed = window.list_projectors()
    assert [d.model for d in listed][:2] == ["MAIN", "PROJECTOR"]


@pytest.mark.parametrize("spec", ["window:1", "window:PROJECTOR", "window:400x300+640+0"])
def test_shown_images_are_on_the_projector_pixel_for_pixel(xserver, spec):
    w, h = PROJ[:2]
    g = pattern_groups(steps=4, periods=(7,), axes=("u", "v"))
    images = [im for grp in g for im in pattern_stack(grp, width=w, height=h)]
    images.append(np.random.default_rng(0).integers(0, 256, (h, w), dtype=np.uint8))
    before = _grab(MAIN)
    with open_projector(spec) as p:
        assert (p.info.width, p.info.height, p.info.sequencer) == (w, h, False)
        for img in images:
            t0 = p.clock.now_ns()
            shown = p.show(img)
            assert shown.t_ns >= t0
            got = _grab(PROJ)
            for c in range(3):                   # BGRA: every colour channel is the image
                assert np.array_equal(got[..., c], img), f"channel {c} differs"
            assert np.array_equal(_grab(MAIN), before)    # nothing drawn on the desktop
        with pytest.raises(ValueError, match="400 x 300"):
            p.show(np.zeros((h, w + 1), np.uint8))
        with pytest.raises(ValueError, match="8-bit"):
            p.show(np.zeros((h, w), np.uint16))
        with pytest.raises(NotSupported, match="no sequencer"):
            p.load_sequence(images[:2], exposure_s=0.01)
    assert _grab(PROJ)[..., :3].max() == 0      # closing blanks it


def test_unknown_monitor_names_the_monitors(xserver):
    with pytest.raises(Exception, match=r"no monitor named 'HDMI-9'.*PROJECTOR 400x300\+640\+0"):
        open_projector("window:HDMI-9")
    with pytest.raises(Exception, match="no monitor 7"):
        open_projector("window:7")


def test_missing_pyglet_is_one_line_saying_what_to_install():
    code = ("import sys\n"
            "sys.modules['pyglet'] = None\n"
            "from telefringe.acquisition.base import load_driver, DriverUnavailable\n"
            "try:\n"
            "    load_driver('window', 'projector')\n"
            "except DriverUnavailable as e:\n"
            "    print(e)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    line = out.stdout.strip()
    assert "\n" not in line and "pip install 'telefringe[window]'" in line


def test_refresh_rate_from_xrandr_and_options(xserver):
    text = ("Screen 0: minimum 320 x 200, current 2832 x 1140, maximum 16384 x 16384\n"
            "eDP-1 connected primary 1920x1080+0+0 (normal left inverted) 344mm x 194mm\n"
            "   1920x1080     60.02*+  59.97    48.00\n"
            "   1280x720      60.00\n"
            "HDMI-1 connected 912x1140+1920+0 (normal left inverted) 0mm x 0mm\n"
            "   912x1140      59.94*+\n"
            "   800x600       60.32    56.25\n"
            "DP-1 disconnected (normal left inverted right x axis y axis)\n")
    assert window.refresh_from_xrandr(text, (1920, 0, 912, 1140)) == 59.94
    assert window.refresh_from_xrandr(text, (0, 0, 1920, 1080)) == 60.02
    assert window.refresh_from_xrandr(text, (100, 0, 1920, 1080)) == 0.0   # spans two
    # Xvfb's mode has no clock: unknown, not invented; refresh= states it
    with open_projector("window:PROJECTOR") as p:
        assert p.info.refresh_hz == 0.0
    with open_projector("window:PROJECTOR,refresh=60,vsync=0") as p:
        assert p.info.refresh_hz == 60.0 and p.info.address == "PROJECTOR,refresh=60,vsync=0"
    with pytest.raises(Exception, match="unknown option 'fps=60'"):
        open_projector("window:PROJECTOR,fps=60")
