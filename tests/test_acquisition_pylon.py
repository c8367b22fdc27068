"""The pylon camera driver against pylon's own camera emulation (``PYLON_CAMEMU``), which
ships inside the pypylon wheel: software trigger, our images from a folder (the emulator
shows them in name order, one per frame, like a DLP sequence), and failed buffers on
demand. pypylon (about 90 MB) is an optional extra, not in the test extra: without it
these tests skip."""

from __future__ import annotations

import os

import numpy as np
import pytest

os.environ.setdefault("PYLON_CAMEMU", "1")
with __import__("warnings").catch_warnings():  # pypylon's SWIG types warn on import
    __import__("warnings").simplefilter("ignore", DeprecationWarning)
    pytest.importorskip("pypylon", reason="pypylon is not installed (optional: pip install "
                        "'telefringe[pylon]', about 90 MB)")

import cv2  # noqa: E402

import telefringe.acquisition.drivers.pylon as drv  # noqa: E402
from telefringe.acquisition.base import FrameStatus, Trigger, open_camera  # noqa: E402
from telefringe.fringes.patterns import pattern_groups, pattern_stack  # noqa: E402
from telefringe.fringes.phase import wrapped_phase  # noqa: E402
from telefringe.simulate.presets import get_preset  # noqa: E402
from telefringe.simulate.render import _integrate_many, _sensor, trace_geometry  # noqa: E402
from telefringe.simulate.scenes import make_scene  # noqa: E402


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    vrig = get_preset("fast")
    geom = trace_geometry(vrig, make_scene("plate"))
    p = vrig.projector.intrinsics
    (g,) = pattern_groups(steps=4, periods=(8,), axes=("u",))
    lines = [im[0, :] for im in pattern_stack(g, width=p.width, height=p.height)]
    sig = _integrate_many(geom, vrig, "u", lines)
    rng = np.random.default_rng(3)
    images = [_sensor(s, vrig, 1.0, rng, geom.pad) for s in sig]
    folder = tmp_path_factory.mktemp("camemu")
    for k, im in enumerate(images):
        cv2.imwrite(str(folder / f"{k:03d}.png"), im)
    return folder, images, g


def test_emulated_basler_captures_our_images_by_software_trigger(rendered):
    folder, images, g = rendered
    assert any(d.model == "Emulation" for d in drv.list_cameras())
    with open_camera("pylon:") as cam:
        h, w = images[0].shape
        s = cam.configure(exposure_s=0.004, pixel_format="Mono8", roi=(0, 0, w, h),
                          trigger=Trigger.SOFTWARE)
        assert (s.roi, s.pixel_format) == ((0, 0, w, h), "Mono8")
        assert abs(s.exposure_s - 0.004) < 1e-6
        cam.feature("TestImageSelector").Value = "Off"
        cam.feature("ImageFileMode").Value = "On"
        cam.feature("ImageFilename").Value = str(folder)
        cam.start()
        got = []
        for _ in images:
            cam.fire()
            f = cam.grab(2.0)
            assert f.ok, f.message
            got.append(f)
        # a failed buffer comes back INCOMPLETE with pylon's words, never as an image
        cam.feature("ForceFailedBufferCount").Value = 1
        cam.feature("ForceFailedBuffer").Execute()
        cam.fire()
        bad = cam.grab(2.0)
        assert bad.status is FrameStatus.INCOMPLETE and bad.image is None
        assert "incompletely grabbed" in bad.message
        cam.fire()
        again = cam.grab(2.0)                    # the next frame after it is fine
        assert again.ok and again.frame_id == bad.frame_id + 1
    assert [f.frame_id for f in got] == list(range(got[0].frame_id, got[0].frame_id + 4))
    assert all(np.array_equal(f.image, im) for f, im in zip(got, images, strict=True))
    wp = wrapped_phase(np.stack([f.image for f in got]).astype(float), steps=g.steps)
    ref = wrapped_phase(np.stack(images).astype(float), steps=g.steps)
    assert np.array_equal(wp.phase, ref.phase)
