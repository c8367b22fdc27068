"""pytest (doctests of src/): leave out the driver modules whose optional library is not
installed on this machine; importing them would raise DriverUnavailable by design (the
driver tests in tests/ say so and skip)."""

import importlib.util

from telefringe.acquisition.base import AcquisitionError

collect_ignore = []


def _importable(module: str) -> bool:
    try:
        __import__(module)
        return True
    except (ImportError, AcquisitionError):
        return False


if not _importable("telefringe.acquisition.drivers._arvlib"):
    collect_ignore += ["_arvlib.py", "aravis.py", "aravis_fake.py"]
for _module, _needs in (("window.py", "pyglet"), ("gentl.py", "harvesters"),
                        ("pylon.py", "pypylon"), ("lightcrafter.py", "hid")):
    if importlib.util.find_spec(_needs) is None:
        collect_ignore.append(_module)
