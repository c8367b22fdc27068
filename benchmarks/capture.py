"""The capture loop's own cost per frame, beyond exposure and display latency.

A device pair that costs nothing stands in for the camera and the projector: the
projector flips at once, the camera hands back frames made beforehand (the virtual rig's
renders of the patterns, at the paper rig's 1280 x 1024 or the fast rig's 320 x 256), and
both run on a virtual clock, so no time is spent waiting for exposures or latency. What is
timed is then exactly what telefringe adds per frame: show/fire/grab bookkeeping, the
per-frame checks (status, ids, stuck buffers) and the group checks (saturation, phase
steps, backgrounds, duplicates), amortised over a whole scan (4 steps, periods 1/8/64,
axes u and v, white and black: 26 frames). Target: < 5 ms per frame.

    .venv/bin/python benchmarks/capture.py [--rig fast|paper] [--repeat 5]

Prints wall and process times (the minimum of the repeats; the machine may be shared,
the process time is the less disturbed figure).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from telefringe.acquisition.base import (
    CameraInfo,
    CameraSettings,
    Frame,
    FrameStatus,
    ProjectorInfo,
    Shown,
    Trigger,
)
from telefringe.acquisition.capture import LatencyUsed, capture_scan, pass_images
from telefringe.acquisition.drivers.sim import VirtualClock, next_frame_id
from telefringe.fringes.patterns import pattern_groups


class _Projector:
    def __init__(self, w, h, clock):
        self.info = ProjectorInfo("null", "null", "0", w, h, 60.0)
        self.clock = clock
        self.shown = None

    def show(self, image):
        self.shown = image
        return Shown(self.clock.now_ns())

    def close(self):
        pass


class _Camera:
    """Returns the prepared frame of the pattern last shown, at once."""

    def __init__(self, frames_by_pattern, projector, shape):
        self.info = CameraInfo("null", "null", "0", width=shape[1], height=shape[0])
        self._frames = frames_by_pattern
        self._proj = projector
        self._id = 1
        self._queue = []
        self.settings = None

    def configure(self, *, exposure_s, gain_db=0.0, pixel_format="Mono8", roi=None,
                  trigger=Trigger.SOFTWARE, trigger_line=None):
        self.settings = CameraSettings(exposure_s, 0.0, pixel_format,
                                       (0, 0, self.info.width, self.info.height), trigger,
                                       max_value=255)
        return self.settings

    def start(self, n_buffers=8):
        self._queue.clear()

    def stop(self):
        pass

    def flush(self):
        return 0

    def fire(self):
        img = self._frames[id(self._proj.shown)]
        self._queue.append(Frame(img, self._id, self._proj.clock.now_ns(), FrameStatus.OK))
        self._id = next_frame_id(self._id)

    def grab(self, timeout_s):
        return self._queue.pop(0)

    def close(self):
        pass


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rig", default="paper", choices=("paper", "fast"))
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    from telefringe.acquisition.drivers.sim import SimConfig, SimRig

    rig = SimRig(SimConfig(preset=args.rig))
    W, H = rig.panel_shape[1], rig.panel_shape[0]
    groups = pattern_groups(steps=4, periods=[1, 8, 64], axes=("u", "v"))
    images, _, _ = pass_images(groups, width=W, height=H, white_black=True)
    # the camera's view of each pattern, rendered once by the virtual rig
    rendered = {}
    t = 10 * 10**9
    for k, img in enumerate(images):
        rig.emit(t + k * 10**8, img)
        rendered[k] = rig.render(t + k * 10**8, t + k * 10**8 + 33_333_333)
    best_wall = best_cpu = np.inf
    for _ in range(args.repeat):
        clock = VirtualClock()
        proj = _Projector(W, H, clock)
        # the pass re-creates its images: map them by content to the rendered frames
        frames = {}
        orig = pass_images

        def mapped(*a, _orig=orig, _frames=frames, **k):
            imgs, layout, wb = _orig(*a, **k)
            for j, im in enumerate(imgs):
                _frames[id(im)] = rendered[j]
            return imgs, layout, wb

        import telefringe.acquisition.capture as cap_mod

        cap_mod.pass_images = mapped
        cam = _Camera(frames, proj, rendered[0].shape)
        w0, c0 = time.perf_counter(), time.process_time()
        res = capture_scan(cam, proj, groups=groups, white_black=True, exposure_s=1 / 30,
                           latency=LatencyUsed(0.025, "option"))
        w1, c1 = time.perf_counter(), time.process_time()
        cap_mod.pass_images = orig
        assert res.capture["retries"] == 0, res.capture["events"]
        n = len(res.capture["frames"])
        best_wall = min(best_wall, (w1 - w0) / n)
        best_cpu = min(best_cpu, (c1 - c0) / n)
    rows, cols = rendered[0].shape
    print(f"capture loop overhead, {args.rig} rig ({cols} x {rows} frames, {n} frames per "
          f"scan, best of {args.repeat}): {best_wall * 1e3:.2f} ms wall, "
          f"{best_cpu * 1e3:.2f} ms process time per frame (target < 5 ms)")


if __name__ == "__main__":
    main()
