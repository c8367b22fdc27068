"""The DLPC350 controller's USB command protocol (TI DLP LightCrafter 4500), written from
TI's DLPC350 Programmer's Guide (DLPU010) and TI's own command tables.

Pure Python, no device access: it encodes commands into the 64-byte HID reports the
controller reads, decodes its replies, and keeps a small :class:`Dlpc350Emulator` (a
controller model at the report boundary) for tests. The projector driver
(:mod:`~telefringe.acquisition.drivers.lightcrafter`) sends these reports over hidapi.

Framing (one USB HID report of 64 bytes; hidapi prepends the report id 0)::

    byte 0      flags: bit 7 read (1) / write (0), bit 6 reply wanted, bit 5 error
                (set by the controller in a reply: command unknown or failed),
                bits 2:0 destination (0: projector control)
    byte 1      sequence number (echoed in the reply)
    bytes 2-3   length, little endian: the bytes that follow (command + data)
    bytes 4-5   command, little endian (e.g. 0x1A1B is sent as 1B 1A)
    bytes 6-    data (parameters little endian), zero padding to 64 bytes

A message longer than one report continues in the next reports, 64 bytes each with no
header.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass, field

__all__ = ["REPORT_SIZE", "VID", "PID", "CMD", "Dlpc350Error", "encode", "decode",
           "lut_entry", "exposure_period", "TRIGGER_DELAY_ZERO", "Dlpc350",
           "Dlpc350Emulator", "VALIDATION_BITS"]

#: bytes in one HID report (without hidapi's leading report id)
REPORT_SIZE = 64
#: USB vendor and product ids of the DLPC350 (LightCrafter 4500)
VID, PID = 0x0451, 0x6401

#: USB command codes (CMD2 << 8 | CMD3) of the commands this driver uses
CMD = {
    "power": 0x0200,             # 0 normal, 1 standby
    "version": 0x0205,           # read: 4 x uint32 (application, API, SW config, sequence)
    "status_hw": 0x1A0A,         # read: 1 byte
    "status_sys": 0x1A0B,
    "status_main": 0x1A0C,
    "led_enable": 0x1A07,
    "validate": 0x1A1A,          # write starts validation; read: bit 7 busy, bits 4:0 flags
    "display_mode": 0x1A1B,      # 0 video, 1 pattern display
    "trig_out1": 0x1A1D,         # invert, rising delay, falling delay
    "pattern_source": 0x1A22,    # 0 video port (HDMI/FPD-Link), 3 internal flash
    "trigger_mode": 0x1A23,      # 0 VSYNC, 1 internal/external trigger
    "start_stop": 0x1A24,        # 0 stop, 1 pause, 2 start
    "exposure_period": 0x1A29,   # uint32 exposure us, uint32 frame period us
    "pattern_config": 0x1A31,    # entries-1, repeat, patterns for TRIG_OUT_2 - 1, images-1
    "mailbox_address": 0x1A32,   # offset 0..127
    "mailbox_control": 0x1A33,   # 0 close, 1 image index LUT, 2 pattern LUT, 3 var. exposure
    "mailbox_data": 0x1A34,      # LUT entries (pattern LUT: 3 bytes each)
}

#: what each bit of the validation reply means (an error when set)
VALIDATION_BITS = {
    0: "exposure or frame period invalid",
    1: "pattern numbers in the LUT invalid",
    2: "continuous TRIG_OUT_1 request or overlapping black sectors",
    3: "no post vector before an externally triggered pattern",
    4: "frame period and exposure differ by less than 230 us",
}

#: TRIG_OUT delay code for 0 us (each step is 107.2 ns; 0x00 is -20.05 us)
TRIGGER_DELAY_ZERO = 0xBB


class Dlpc350Error(RuntimeError):
    """The controller refused a command, or a reply did not match its request."""


def encode(command: int, data: bytes = b"", *, read: bool = False, reply: bool = True,
           seq: int = 0) -> list[bytes]:
    """The HID reports (each ``REPORT_SIZE`` bytes) of one message.

    command : int, e.g. ``CMD["display_mode"]``. data : bytes, the parameters.
    read : a read request (the controller answers with the value). reply : ask the
    controller to acknowledge a write. seq : int 0..255, echoed in the reply.

    >>> encode(0x1A1B, bytes([1]), seq=7)[0][:7].hex(" ")
    '40 07 03 00 1b 1a 01'
    >>> encode(0x1A0A, read=True)[0][:6].hex(" ")
    'c0 00 02 00 0a 1a'
    """
    if not 0 <= command <= 0xFFFF:
        raise ValueError(f"command 0x{command:x} is not a 16-bit code")
    body = struct.pack("<H", command) + bytes(data)
    flags = (0x80 if read else 0) | (0x40 if (reply or read) else 0)
    msg = bytes([flags, seq & 0xFF]) + struct.pack("<H", len(body)) + body
    reports = [msg[:REPORT_SIZE]]
    rest = msg[REPORT_SIZE:]
    while rest:
        reports.append(rest[:REPORT_SIZE])
        rest = rest[REPORT_SIZE:]
    return [r.ljust(REPORT_SIZE, b"\0") for r in reports]


@dataclass(frozen=True)
class Reply:
    """A decoded reply: flags, sequence, data (the bytes after the header)."""

    flags: int
    seq: int
    data: bytes

    @property
    def error(self) -> bool:
        """The controller flagged the command as unknown or failed (flags bit 5)."""
        return bool(self.flags & 0x20)


def decode(report: bytes) -> Reply:
    """Decode one reply report (``REPORT_SIZE`` bytes, without a report id).

    >>> decode(bytes([0xC0, 3, 1, 0, 0x41]) + bytes(59)).data
    b'A'
    """
    report = bytes(report)
    if len(report) < 4:
        raise Dlpc350Error(f"short reply ({len(report)} bytes)")
    n = struct.unpack_from("<H", report, 2)[0]
    return Reply(report[0], report[1], report[4:4 + n])


def lut_entry(*, trigger: int, pattern: int, bit_depth: int, leds: int, invert: bool = False,
              insert_black: bool = False, buffer_swap: bool = False,
              trigger_out_prev: bool = False) -> int:
    """One 24-bit pattern LUT entry (Programmer's Guide, pattern display LUT data).

    trigger : 0 internal, 1 external positive, 2 external negative, 3 none (continue
    from the previous pattern; also what VSYNC-triggered video patterns after the first
    of a frame use). pattern : the bit plane group (8-bit: 0 = G7..G0, 1 = R7..R0,
    2 = B7..B0 of the video frame; 1-bit: 0..23). bit_depth : 1..8. leds : bit 0 red,
    bit 1 green, bit 2 blue (7 = white). invert, insert_black, buffer_swap,
    trigger_out_prev : bits 16..19.

    >>> hex(lut_entry(trigger=0, pattern=1, bit_depth=8, leds=7, buffer_swap=True))
    '0x47804'
    """
    if trigger not in (0, 1, 2, 3):
        raise ValueError("trigger must be 0, 1, 2 or 3")
    if not 0 <= pattern <= 24:
        raise ValueError("pattern number must be 0..24")
    if not 1 <= bit_depth <= 8:
        raise ValueError("bit depth must be 1..8")
    if not 0 <= leds <= 7:
        raise ValueError("leds must be 0..7")
    return (trigger | pattern << 2 | bit_depth << 8 | leds << 12 | int(invert) << 16
            | int(insert_black) << 17 | int(buffer_swap) << 18 | int(trigger_out_prev) << 19)


def exposure_period(exposure_us: int, period_us: int) -> bytes:
    """The data of the exposure-and-frame-period command, checked as the controller does:
    the exposure equals the period or is shorter by at least 230 us.

    >>> exposure_period(5000, 16667).hex(" ")
    '88 13 00 00 1b 41 00 00'
    """
    exposure_us, period_us = int(exposure_us), int(period_us)
    if not (exposure_us == period_us or 0 < exposure_us <= period_us - 230):
        raise ValueError(f"exposure {exposure_us} us must equal the period {period_us} us or "
                         f"be at least 230 us shorter")
    return struct.pack("<II", exposure_us, period_us)


class Dlpc350:
    """Commands to a DLPC350 over a transport.

    transport : an object with ``write(report: bytes)`` (``REPORT_SIZE`` bytes, no report
    id) and ``read(timeout_ms: int) -> bytes`` (one reply report, b"" on timeout).
    """

    def __init__(self, transport, *, timeout_ms: int = 1000):
        self.t = transport
        self.timeout_ms = int(timeout_ms)
        self._seq = 0

    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFF
        return self._seq

    def write(self, name: str, data: bytes = b"") -> None:
        """Send a write command and check the controller's acknowledgement."""
        seq = self._next_seq()
        for r in encode(CMD[name], data, seq=seq):
            self.t.write(r)
        self._reply(name, seq)

    def read(self, name: str, data: bytes = b"") -> bytes:
        """Send a read request; return the reply's data."""
        seq = self._next_seq()
        for r in encode(CMD[name], data, read=True, seq=seq):
            self.t.write(r)
        return self._reply(name, seq).data

    def _reply(self, name: str, seq: int) -> Reply:
        raw = self.t.read(self.timeout_ms)
        if not raw:
            raise Dlpc350Error(f"DLPC350 did not answer {name} within {self.timeout_ms} ms")
        rep = decode(raw)
        if rep.seq != seq:
            raise Dlpc350Error(f"DLPC350 answered sequence {rep.seq} to {name} (sent {seq})")
        if rep.error:
            raise Dlpc350Error(f"DLPC350 refused {name} (error flag in its reply)")
        return rep

    # ----------------------------------------------------------- composite operations
    def status(self) -> tuple[int, int, int]:
        """(hardware, system, main) status bytes (Programmer's Guide, status commands)."""
        return tuple(self.read(n)[0] for n in ("status_hw", "status_sys", "status_main"))

    def stop(self) -> None:
        """Stop the pattern sequence."""
        self.write("start_stop", bytes([0]))

    def start(self) -> None:
        """Start the validated pattern sequence."""
        self.write("start_stop", bytes([2]))

    def video_mode(self) -> None:
        """Plain video display (the HDMI input shown as is)."""
        self.stop()
        self.write("display_mode", bytes([0]))

    def load_video_patterns(self, entries: Sequence[int], *, exposure_us: int,
                            period_us: int, repeat: bool, trigger_out_delay: int = 0
                            ) -> int:
        """Pattern display from the video port: ``entries`` (24-bit LUT entries, in
        display order), each lit ``exposure_us`` every ``period_us``; TRIG_OUT_1 pulses at
        each pattern. Validates and returns the validation status (0: valid); raises
        :class:`Dlpc350Error` naming the problems otherwise.
        """
        entries = [int(e) for e in entries]
        if not 1 <= len(entries) <= 128:
            raise ValueError("a pattern LUT holds 1..128 entries")
        self.stop()
        self.write("display_mode", bytes([1]))
        self.write("pattern_source", bytes([0]))
        self.write("trigger_mode", bytes([0]))
        self.write("exposure_period", exposure_period(exposure_us, period_us))
        self.write("trig_out1", bytes([0, TRIGGER_DELAY_ZERO + int(trigger_out_delay),
                                       TRIGGER_DELAY_ZERO]))
        self.write("pattern_config", bytes([len(entries) - 1, int(bool(repeat)),
                                            len(entries) - 1, 0]))
        self.write("mailbox_control", bytes([2]))
        self.write("mailbox_address", bytes([0]))
        self.write("mailbox_data", b"".join(e.to_bytes(3, "little") for e in entries))
        self.write("mailbox_control", bytes([0]))
        return self.validate()

    def validate(self, *, polls: int = 100) -> int:
        """Run the controller's validation; return its status, raising on errors."""
        self.write("validate", bytes([0]))
        for _ in range(polls):
            st = self.read("validate")[0]
            if not st & 0x80:
                break
        else:
            raise Dlpc350Error("DLPC350 validation did not finish")
        errors = [msg for bit, msg in VALIDATION_BITS.items() if st & (1 << bit)]
        if errors:
            raise Dlpc350Error("DLPC350 rejected the pattern sequence: " + "; ".join(errors))
        return st


@dataclass
class Dlpc350Emulator:
    """A DLPC350 model at the HID report boundary (for tests): it parses every report the
    way the controller's framing says, keeps the state the commands set, validates like
    the Programmer's Guide describes, and answers with a reply per message.

    ``reports`` keeps every report written; ``triggers`` counts TRIG_OUT_1 pulses of the
    patterns run (one per LUT entry per pass).
    """

    state: dict = field(default_factory=lambda: {
        "display_mode": 0, "pattern_source": 3, "trigger_mode": 0, "start_stop": 0,
        "exposure_period": (0, 0), "pattern_config": None, "mailbox_control": 0,
        "mailbox_address": 0, "pattern_lut": [], "trig_out1": None, "validated": False})
    reports: list = field(default_factory=list)
    triggers: int = 0
    _pending: bytes = b""
    _need: int = 0
    _out: list = field(default_factory=list)
    status_bytes: tuple = (0x01, 0x01, 0x00)

    def write(self, report: bytes) -> None:
        report = bytes(report)
        if len(report) != REPORT_SIZE:
            raise Dlpc350Error(f"a report is {REPORT_SIZE} bytes, got {len(report)}")
        self.reports.append(report)
        if self._need:
            self._pending += report
            if len(self._pending) >= self._need:
                self._handle(self._pending[:self._need])
                self._pending, self._need = b"", 0
            return
        n = struct.unpack_from("<H", report, 2)[0] + 4
        if n > REPORT_SIZE:
            self._pending, self._need = report, n
            return
        self._handle(report[:n])

    def read(self, timeout_ms: int) -> bytes:
        return self._out.pop(0) if self._out else b""

    def _answer(self, flags: int, seq: int, data: bytes = b"", error: bool = False) -> None:
        f = (flags & 0xC0) | (0x20 if error else 0)
        self._out.append((bytes([f, seq]) + struct.pack("<H", len(data)) + data)
                         .ljust(REPORT_SIZE, b"\0"))

    def _handle(self, msg: bytes) -> None:
        flags, seq = msg[0], msg[1]
        cmd = struct.unpack_from("<H", msg, 4)[0]
        data = msg[6:]
        names = {v: k for k, v in CMD.items()}
        name = names.get(cmd)
        s = self.state
        if name is None:
            self._answer(flags, seq, error=True)
            return
        if flags & 0x80:                               # read
            if name in ("status_hw", "status_sys", "status_main"):
                i = ("status_hw", "status_sys", "status_main").index(name)
                self._answer(flags, seq, bytes([self.status_bytes[i]]))
            elif name == "validate":
                self._answer(flags, seq, bytes([self._validation()]))
            elif name == "exposure_period":
                self._answer(flags, seq, struct.pack("<II", *s["exposure_period"]))
            elif name in ("display_mode", "pattern_source", "trigger_mode", "start_stop"):
                self._answer(flags, seq, bytes([s[name]]))
            else:
                self._answer(flags, seq, error=True)
            return
        running = s["start_stop"] == 2
        if running and name not in ("start_stop", "status_hw"):
            self._answer(flags, seq, error=True)       # the guide: stop before changing
            return
        if name == "start_stop":
            if data[0] == 2:
                if not (s["validated"] and s["display_mode"] == 1):
                    self._answer(flags, seq, error=True)
                    return
                cfg = s["pattern_config"]
                self.triggers += cfg[0] + 1
            s["start_stop"] = data[0]
        elif name == "exposure_period":
            s[name] = struct.unpack_from("<II", data)
        elif name == "pattern_config":
            s[name] = tuple(data[:4])
        elif name == "trig_out1":
            s[name] = tuple(data[:3])
        elif name == "mailbox_data":
            if s["mailbox_control"] != 2:
                self._answer(flags, seq, error=True)
                return
            n = len(data) // 3
            lut = s["pattern_lut"]
            start = s["mailbox_address"]
            entries = [int.from_bytes(data[3 * i:3 * i + 3], "little") for i in range(n)]
            s["pattern_lut"] = lut[:start] + entries + lut[start + n:]
        elif name == "validate":
            s["validated"] = self._validation() & 0x1F == 0
        else:
            s[name] = data[0]
        if name not in ("validate", "start_stop", "mailbox_control", "mailbox_address"):
            s["validated"] = False               # any setting change needs a new validation
        self._answer(flags, seq)

    def _validation(self) -> int:
        s = self.state
        st = 0
        exp, per = s["exposure_period"]
        if not (exp == per or 0 < exp <= per - 230) or per == 0:
            st |= 1
        cfg = s["pattern_config"]
        lut = s["pattern_lut"]
        if cfg is None or len(lut) < cfg[0] + 1:
            st |= 2
        else:
            for e in lut[:cfg[0] + 1]:
                depth = (e >> 8) & 0xF
                pat = (e >> 2) & 0x3F
                if not 1 <= depth <= 8 or pat > (24 // depth - 1 if depth > 1 else 24):
                    st |= 2
        return st
