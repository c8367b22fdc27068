"""What the aravis driver costs per frame: software trigger + grab of a 320 x 256 Mono8
frame over GigE Vision on loopback, from Aravis's fake camera in another process.

Prints the driver's CPU time per frame (process_time, the minimum of 3 runs of 100
frames: load-independent) and the wall time per frame (which the fake camera paces: it
looks for triggers every 5 ms). Needs libaravis-0.8 (Debian: libaravis-0.8-0) and a free
127.0.0.1:3956/udp.

    .venv/bin/python benchmarks/acquisition_aravis.py
"""

import subprocess
import sys
import time

from telefringe.acquisition.base import Trigger
from telefringe.acquisition.drivers import aravis


def main() -> None:
    server = subprocess.Popen([sys.executable, "-m", "telefringe.acquisition.drivers.aravis_fake",
                               "--lifetime", "120"], stdout=subprocess.PIPE, text=True)
    try:
        assert server.stdout.readline().startswith("ready")
        with aravis.open_camera("127.0.0.1") as cam:
            cam.configure(exposure_s=0.001, roi=(0, 0, 320, 256), trigger=Trigger.SOFTWARE)
            cam.start()
            for _ in range(5):
                cam.fire()
                cam.grab(1.0)
            runs = []
            for _ in range(3):
                c0, w0, n = time.process_time(), time.perf_counter(), 100
                for _ in range(n):
                    cam.fire()
                    assert cam.grab(1.0).ok
                runs.append(((time.process_time() - c0) / n, (time.perf_counter() - w0) / n))
        cpu = min(r[0] for r in runs) * 1e3
        wall = min(r[1] for r in runs) * 1e3
        print(f"aravis driver, 320 x 256 Mono8 over loopback GigE Vision: CPU {cpu:.3f} ms per "
              f"frame (min of 3 x 100), wall {wall:.2f} ms (paced by the fake camera)")
    finally:
        server.terminate()
        server.communicate(timeout=30)


if __name__ == "__main__":
    main()
