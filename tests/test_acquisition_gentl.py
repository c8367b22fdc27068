"""The gentl camera driver against a real GenTL producer: ``viky.cti``, MVTec's simulated
producer shipped in the ``genicam`` wheel (three free-running 400 x 400 devices, Mono8 or
RGBa8; no exposure, no trigger, no time stamps). So this tests the plumbing: producer
loading, enumeration, node-map access, refusal of what the device cannot do, streaming and
buffer-to-array conversion, clean shutdown. Triggered capture is tested on the aravis
driver (a real GigE Vision stack)."""

from __future__ import annotations

import math
import os
import subprocess
import sys

import numpy as np
import pytest

genicam = pytest.importorskip("genicam", reason="genicam is not installed (pip install -e "
                              "'.[test]')")
pytest.importorskip("harvesters", reason="harvesters is not installed (pip install -e "
                    "'.[test]')")

from telefringe.acquisition.base import NotSupported, Trigger, open_camera  # noqa: E402
from telefringe.acquisition.drivers import gentl  # noqa: E402

CTI = os.path.join(os.path.dirname(genicam.__file__), "viky.cti")


def test_enumerates_the_producers_devices():
    listed = gentl.list_cameras(CTI)
    assert [d.serial for d in listed] == ["0", "1", "2"]
    assert all(d.model == "Viky" and d.address == f"{CTI}#{i}" for i, d in enumerate(listed))


def test_streams_free_running_frames_and_refuses_what_it_cannot_do():
    with open_camera(f"gentl:{CTI}#VikyTL_DEV_green") as cam:
        assert (cam.info.serial, cam.info.width, cam.info.height) == ("1", 400, 400)
        assert cam.info.pixel_formats == ("Mono8",)
        with pytest.raises(NotSupported, match="no ExposureTime"):
            cam.configure(exposure_s=0.01, trigger=Trigger.SOFTWARE)
        with pytest.raises(NotSupported, match="offers Mono8, not Mono16"):
            cam.configure(exposure_s=0.01, pixel_format="Mono16", trigger=Trigger.FREE_RUN)
        s = cam.configure(exposure_s=0.01, trigger=Trigger.FREE_RUN)
        assert math.isnan(s.exposure_s)             # unknown, never pretended
        assert (s.pixel_format, s.roi, s.max_value) == ("Mono8", (0, 0, 400, 400), 255)
        cam.start()
        frames = [cam.grab(3.0) for _ in range(3)]
        cam.stop()
    assert all(f.ok for f in frames), [f.message for f in frames]
    ids = [f.frame_id for f in frames]
    assert ids == list(range(ids[0], ids[0] + 3))
    for f in frames:
        assert f.image.shape == (400, 400) and f.image.dtype == np.uint8
        assert f.image.std() > 1 and f.timestamp_ns is None


def test_unknown_device_names_the_found_ones():
    with pytest.raises(Exception, match="no GenTL device 'nope'; found 0: VikyTL_DEV_red"):
        open_camera(f"gentl:{CTI}#nope")
    with pytest.raises(Exception, match="no GenTL producer file"):
        open_camera("gentl:/nonexistent.cti")


def test_missing_harvesters_is_one_line_saying_what_to_install():
    code = ("import sys\n"
            "sys.modules['harvesters'] = None\n"
            "from telefringe.acquisition.base import load_driver, DriverUnavailable\n"
            "try:\n"
            "    load_driver('gentl', 'camera')\n"
            "except DriverUnavailable as e:\n"
            "    print(e)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    assert "pip install 'telefringe[gentl]'" in out.stdout.strip()
