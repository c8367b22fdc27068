"""The LightCrafter 4500 (DLPC350) driver at the USB HID report boundary.

This machine has no USB: the reports are checked against the framing examples of TI's
programmer's guides (the DLPC350 and DLPC900 use the same HID framing) and the command
codes and bit layouts of TI's DLPC350 documentation, and run against a controller model
(:class:`Dlpc350Emulator`) that parses them the way the controller does. What only the
hardware can tell is in docs/acquisition_hardware.md.
"""

from __future__ import annotations

import numpy as np
import pytest

from telefringe.acquisition.base import NotSupported, ProjectorInfo, Shown
from telefringe.acquisition.drivers import dlpc350 as d


def test_framing_matches_the_guides_read_and_write_examples():
    # read request, sequence 0x11, command 0x1100: 00 | C0 11 02 00 00 11
    assert d.encode(0x1100, read=True, seq=0x11)[0][:6] == bytes.fromhex("C0 11 02 00 00 11")
    # write without reply, sequence 0x12, 3 x 511: 00 | 00 12 08 00 00 11 FF 01 FF 01 FF 01
    r = d.encode(0x1100, bytes.fromhex("FF01FF01FF01"), reply=False, seq=0x12)
    assert r[0][:12] == bytes.fromhex("00 12 08 00 00 11 FF 01 FF 01 FF 01")
    assert len(r) == 1 and len(r[0]) == 64 and not any(r[0][12:])
    # the reply of the read example: flags echoed, length 6, data LSB first
    rep = d.decode(bytes.fromhex("C0 11 06 00 FF 01 FF 01 FF 01").ljust(64, b"\0"))
    assert (rep.seq, rep.data, rep.error) == (0x11, bytes.fromhex("FF01FF01FF01"), False)
    assert d.decode(bytes([0xE0, 1, 0, 0]).ljust(64, b"\0")).error


def test_dlpc350_commands_and_layouts():
    # DLPC350 USB codes: display mode 0x1A1B, start/stop 0x1A24, mailbox data 0x1A34 ...
    assert d.encode(d.CMD["display_mode"], b"\x01", seq=3)[0][:7] == \
        bytes.fromhex("40 03 03 00 1B 1A 01")
    assert d.encode(d.CMD["start_stop"], b"\x02", seq=4)[0][:7] == \
        bytes.fromhex("40 04 03 00 24 1A 02")
    # exposure and frame period: two uint32 LSB first (5000 us in 16667 us)
    assert d.exposure_period(5000, 16667) == bytes.fromhex("88130000 1B410000")
    with pytest.raises(ValueError, match="230 us"):
        d.exposure_period(16600, 16667)
    # pattern LUT entry: trigger [1:0], pattern [7:2], depth [11:8], LEDs [14:12],
    # invert 16, black 17, buffer swap 18, trigger out previous 19
    assert d.lut_entry(trigger=0, pattern=0, bit_depth=8, leds=7, buffer_swap=True) == 0x47800
    assert d.lut_entry(trigger=3, pattern=2, bit_depth=8, leds=7) == 0x07808 | 0x3
    assert d.lut_entry(trigger=1, pattern=23, bit_depth=1, leds=2, invert=True,
                       insert_black=True, trigger_out_prev=True) == 0xB215D
    with pytest.raises(ValueError):
        d.lut_entry(trigger=0, pattern=0, bit_depth=9, leds=7)


def test_a_long_message_continues_in_headerless_reports():
    entries = [d.lut_entry(trigger=0, pattern=k % 24, bit_depth=1, leds=7) for k in range(30)]
    data = b"".join(e.to_bytes(3, "little") for e in entries)
    reports = d.encode(d.CMD["mailbox_data"], data, seq=9)
    assert len(reports) == 2                      # 4 + 2 + 90 bytes
    assert reports[0][2:4] == (92).to_bytes(2, "little")
    assert reports[0][6:] == data[:58] and reports[1][:32] == data[58:]
    emu = d.Dlpc350Emulator()
    ctl = d.Dlpc350(emu)
    ctl.write("mailbox_control", b"\x02")
    ctl.write("mailbox_address", b"\x00")
    ctl.write("mailbox_data", data)
    assert emu.state["pattern_lut"] == entries


def _entries(n):
    return [d.lut_entry(trigger=0 if k == 0 else 3, pattern=k, bit_depth=8, leds=7,
                        buffer_swap=k == 0) for k in range(n)]


def test_video_pattern_sequence_is_configured_validated_and_started():
    emu = d.Dlpc350Emulator()
    ctl = d.Dlpc350(emu)
    assert ctl.status() == emu.status_bytes
    assert ctl.load_video_patterns(_entries(3), exposure_us=5000, period_us=5555,
                                   repeat=True) == 0
    s = emu.state
    assert (s["display_mode"], s["pattern_source"], s["trigger_mode"]) == (1, 0, 0)
    assert s["exposure_period"] == (5000, 5555)
    assert s["pattern_config"] == (2, 1, 2, 0)
    assert s["pattern_lut"] == _entries(3) and s["validated"]
    assert s["trig_out1"] == (0, d.TRIGGER_DELAY_ZERO, d.TRIGGER_DELAY_ZERO)
    ctl.start()
    assert emu.triggers == 3
    # settings cannot change while the sequence runs: the controller flags an error
    with pytest.raises(d.Dlpc350Error, match="refused trigger_mode"):
        ctl.write("trigger_mode", b"\x01")
    ctl.stop()
    # every message got exactly one reply, with its own sequence number
    assert emu.read(0) == b""


def test_controller_errors_are_reported_not_ignored():
    emu = d.Dlpc350Emulator()
    ctl = d.Dlpc350(emu)
    # a pattern number an 8-bit LUT cannot have: the controller's validation says so
    bad = [d.lut_entry(trigger=0, pattern=5, bit_depth=8, leds=7)]
    with pytest.raises(d.Dlpc350Error, match="pattern numbers in the LUT invalid"):
        ctl.load_video_patterns(bad, exposure_us=5000, period_us=5555, repeat=True)
    with pytest.raises(d.Dlpc350Error, match="refused start_stop"):
        ctl.start()                               # not validated: it refuses to start

    class Silent:
        def write(self, r):
            pass

        def read(self, ms):
            return b""

    with pytest.raises(d.Dlpc350Error, match="did not answer"):
        d.Dlpc350(Silent(), timeout_ms=5).stop()

    class WrongSeq(d.Dlpc350Emulator):
        def read(self, ms):
            r = bytearray(super().read(ms))
            r[1] ^= 0xFF
            return bytes(r)

    with pytest.raises(d.Dlpc350Error, match="answered sequence"):
        d.Dlpc350(WrongSeq()).stop()


class _Window:
    """Records what a window projector would put on the LightCrafter's HDMI input."""

    def __init__(self):
        from telefringe.acquisition.base import SYSTEM_CLOCK

        self.clock = SYSTEM_CLOCK
        self.info = ProjectorInfo("window", "HDMI", "", 912, 1140, 60.0)
        self.shown = []
        self.closed = False

    def show(self, image):
        self.shown.append(("grey", np.array(image)))
        return Shown(self.clock.now_ns())

    def show_rgb(self, image):
        self.shown.append(("rgb", np.array(image)))
        return Shown(self.clock.now_ns())

    def close(self):
        self.closed = True


def test_lightcrafter_packs_three_patterns_into_one_hdmi_frame():
    pytest.importorskip("hid", reason="hidapi is not installed (pip install -e '.[test]')")
    from telefringe.acquisition.drivers import lightcrafter as lc
    emu = d.Dlpc350Emulator()
    win = _Window()
    rng = np.random.default_rng(1)
    pats = [rng.integers(0, 256, (1140, 912), dtype=np.uint8) for _ in range(3)]
    with lc.LightCrafterProjector(d.Dlpc350(emu), win, serial="X1") as p:
        assert p.info.sequencer and (p.info.width, p.info.height) == (912, 1140)
        got = p.load_sequence(pats, exposure_s=0.005)
        assert (got.count, got.exposure_s) == (3, 0.005)
        assert got.period_s == pytest.approx(5555e-6)
        p.start_sequence()
        kind, frame = win.shown[-1]
        assert kind == "rgb"
        # LUT entry k shows pattern number k: 8-bit pattern 0 = G, 1 = R, 2 = B
        for k, (entry, pat) in enumerate(zip(emu.state["pattern_lut"], pats, strict=True)):
            number = (entry >> 2) & 0x3F
            assert number == k
            assert np.array_equal(frame[..., lc.PLANE_OF_PATTERN[number]], pat)
        assert emu.triggers == 3
        with pytest.raises(NotSupported, match="--mode streamed"):
            p.load_sequence(pats + pats[:1], exposure_s=0.005)
        p.stop_sequence()
        p.show(pats[0])                            # streamed mode: plain video
        assert emu.state["display_mode"] == 0 and win.shown[-1][0] == "grey"
    assert win.closed
