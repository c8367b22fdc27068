"""ctypes bindings to libaravis 0.8 (the C library of the Aravis project, LGPL-2.1+).

Why ctypes and not PyGObject: PyGObject is a source-only package that needs the
GObject-introspection development files and a compiler, and its recent releases need a
newer GLib than Debian 12 has; Debian's ``python3-gi`` serves only the system Python. The
handful of C functions a camera driver needs are stable across Aravis 0.8.x, so binding
them directly works in any virtual environment with nothing but the shared library
(Debian/Ubuntu: ``apt-get install libaravis-0.8-0``).

Only this module and :mod:`~telefringe.acquisition.drivers.aravis` /
:mod:`~telefringe.acquisition.drivers.aravis_fake` touch the library. Every call that
takes a ``GError **`` goes through :func:`call`, which turns a set error into
:class:`~telefringe.acquisition.base.DeviceError` carrying Aravis's own message.
"""

from __future__ import annotations

import ctypes as C
import ctypes.util
import os

from telefringe.acquisition.base import DeviceError, DriverUnavailable

__all__ = ["lib", "gobject", "call", "INSTALL_HINT", "BUFFER_STATUS", "PIXEL_FORMATS"]

#: what to install when the library is missing (one line)
INSTALL_HINT = ("the aravis driver needs the Aravis 0.8 library (libaravis-0.8.so.0); "
                "install it: apt-get install libaravis-0.8-0 (Debian/Ubuntu), or build Aravis "
                "0.8 from its sources; set TELEFRINGE_LIBARAVIS to its path if elsewhere")

#: ArvBufferStatus values (arvbuffer.h, 0.8)
BUFFER_STATUS = {-1: "unknown", 0: "success", 1: "cleared",
                 2: "packets still missing when the frame timed out",
                 3: "missing packets", 4: "wrong packet id", 5: "size mismatch",
                 6: "filling", 7: "aborted", 8: "payload not supported"}

#: GenICam PFNC codes of the monochrome formats telefringe reads (name -> (code, bytes/px))
PIXEL_FORMATS = {"Mono8": (0x01080001, 1), "Mono10": (0x01100003, 2),
                 "Mono12": (0x01100005, 2), "Mono14": (0x01100025, 2),
                 "Mono16": (0x01100007, 2)}


class _GError(C.Structure):
    _fields_ = [("domain", C.c_uint32), ("code", C.c_int), ("message", C.c_char_p)]


def _load(names):
    for name in names:
        if not name:
            continue
        try:
            return C.CDLL(name)
        except OSError:
            continue
    return None


_explicit = os.environ.get("TELEFRINGE_LIBARAVIS", "")
lib = _load([_explicit, "libaravis-0.8.so.0", ctypes.util.find_library("aravis-0.8")])
if lib is None:
    # DriverUnavailable (an AcquisitionError) travels unchanged through the registry's
    # lazy import: the user sees this one line
    raise DriverUnavailable(INSTALL_HINT)
gobject = _load(["libgobject-2.0.so.0", ctypes.util.find_library("gobject-2.0")])
_glib = _load(["libglib-2.0.so.0", ctypes.util.find_library("glib-2.0")])
if gobject is None or _glib is None:
    raise DriverUnavailable(INSTALL_HINT + " (GLib/GObject not found)")

_P = C.c_void_p
_ERR = C.POINTER(C.POINTER(_GError))
_I = C.POINTER(C.c_int)
_D = C.POINTER(C.c_double)


def _proto(name, restype, *argtypes):
    fn = getattr(lib, name)
    fn.restype = restype
    fn.argtypes = list(argtypes)


# device list
_proto("arv_update_device_list", None)
_proto("arv_get_n_devices", C.c_uint)
for _n in ("arv_get_device_id", "arv_get_device_address", "arv_get_device_vendor",
           "arv_get_device_model", "arv_get_device_serial_nbr", "arv_get_device_protocol"):
    _proto(_n, C.c_char_p, C.c_uint)
# camera
_proto("arv_camera_new", _P, C.c_char_p, _ERR)
for _n in ("arv_camera_get_vendor_name", "arv_camera_get_model_name",
           "arv_camera_get_device_serial_number", "arv_camera_get_pixel_format_as_string"):
    _proto(_n, C.c_char_p, _P, _ERR)
_proto("arv_camera_get_sensor_size", None, _P, _I, _I, _ERR)
_proto("arv_camera_set_region", None, _P, C.c_int, C.c_int, C.c_int, C.c_int, _ERR)
_proto("arv_camera_get_region", None, _P, _I, _I, _I, _I, _ERR)
_proto("arv_camera_set_pixel_format_from_string", None, _P, C.c_char_p, _ERR)
_proto("arv_camera_dup_available_pixel_formats_as_strings", C.POINTER(C.c_char_p), _P,
       C.POINTER(C.c_uint), _ERR)
_proto("arv_camera_set_exposure_time", None, _P, C.c_double, _ERR)
_proto("arv_camera_get_exposure_time", C.c_double, _P, _ERR)
_proto("arv_camera_get_exposure_time_bounds", None, _P, _D, _D, _ERR)
_proto("arv_camera_set_exposure_time_auto", None, _P, C.c_int, _ERR)
_proto("arv_camera_set_gain", None, _P, C.c_double, _ERR)
_proto("arv_camera_get_gain", C.c_double, _P, _ERR)
_proto("arv_camera_get_gain_bounds", None, _P, _D, _D, _ERR)
_proto("arv_camera_set_gain_auto", None, _P, C.c_int, _ERR)
_proto("arv_camera_set_acquisition_mode", None, _P, C.c_int, _ERR)
_proto("arv_camera_set_trigger", None, _P, C.c_char_p, _ERR)
_proto("arv_camera_clear_triggers", None, _P, _ERR)
_proto("arv_camera_software_trigger", None, _P, _ERR)
_proto("arv_camera_set_frame_rate", None, _P, C.c_double, _ERR)
_proto("arv_camera_get_payload", C.c_uint, _P, _ERR)
_proto("arv_camera_is_gv_device", C.c_int, _P)
_proto("arv_camera_gv_set_packet_size", None, _P, C.c_int, _ERR)
_proto("arv_camera_gv_auto_packet_size", C.c_uint, _P, _ERR)
_proto("arv_camera_create_stream", _P, _P, _P, _P, _ERR)
_proto("arv_camera_start_acquisition", None, _P, _ERR)
_proto("arv_camera_stop_acquisition", None, _P, _ERR)
# stream and buffers
_proto("arv_stream_push_buffer", None, _P, _P)
_proto("arv_stream_try_pop_buffer", _P, _P)
_proto("arv_stream_timeout_pop_buffer", _P, _P, C.c_uint64)
_proto("arv_stream_get_statistics", None, _P, C.POINTER(C.c_uint64), C.POINTER(C.c_uint64),
       C.POINTER(C.c_uint64))
_proto("arv_buffer_new_allocate", _P, C.c_size_t)
_proto("arv_buffer_get_status", C.c_int, _P)
_proto("arv_buffer_get_payload_type", C.c_int, _P)
_proto("arv_buffer_get_frame_id", C.c_uint64, _P)
_proto("arv_buffer_get_timestamp", C.c_uint64, _P)
_proto("arv_buffer_get_system_timestamp", C.c_uint64, _P)
_proto("arv_buffer_get_image_data", _P, _P, C.POINTER(C.c_size_t))
_proto("arv_buffer_get_data", _P, _P, C.POINTER(C.c_size_t))
_proto("arv_buffer_get_image_width", C.c_int, _P)
_proto("arv_buffer_get_image_height", C.c_int, _P)
_proto("arv_buffer_get_image_pixel_format", C.c_uint32, _P)
# the fake GigE Vision camera (aravis_fake)
_proto("arv_gv_fake_camera_new", _P, C.c_char_p, C.c_char_p)
_proto("arv_gv_fake_camera_is_running", C.c_int, _P)
_proto("arv_gv_fake_camera_get_fake_camera", _P, _P)
_proto("arv_fake_camera_set_fill_pattern", None, _P, _P, _P)
_proto("arv_fake_camera_set_trigger_frequency", None, _P, C.c_double)

gobject.g_object_unref.restype = None
gobject.g_object_unref.argtypes = [_P]
gobject.g_object_set.restype = None        # variadic: (obj, name, value, NULL)
_glib.g_error_free.restype = None
_glib.g_error_free.argtypes = [C.POINTER(_GError)]
_glib.g_free.restype = None
_glib.g_free.argtypes = [_P]


def call(fn_name: str, *args):
    """Call ``lib.fn_name(*args, &error)``; raise DeviceError with Aravis's message when
    the call set an error. Returns the C function's result."""
    err = C.POINTER(_GError)()
    out = getattr(lib, fn_name)(*args, C.byref(err))
    if err:
        msg = err.contents.message.decode("utf-8", "replace") if err.contents.message else ""
        _glib.g_error_free(err)
        raise DeviceError(f"Aravis {fn_name.removeprefix('arv_')}: {msg or 'failed'}")
    return out


def g_free(ptr) -> None:
    """Free memory Aravis allocated for the caller (``dup_*`` results)."""
    _glib.g_free(ptr)


def set_double_property(obj, name: str, value: float) -> None:
    """``g_object_set(obj, name, (double) value, NULL)``."""
    gobject.g_object_set(C.c_void_p(obj), name.encode(), C.c_double(value), C.c_void_p(None))
