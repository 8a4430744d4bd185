"""Codec of the control-unit protocol, exactly as ``docs/protocol.md`` (version 2) defines it.

Pure bytes in, frames out — no I/O — so both ends (driver and emulator) and the fuzz tests use it
with plain byte strings::

    wire = encode_command(CommandFrame(seq=7, left_duty_pm=500, right_duty_pm=500,
                                       flags=FLAG_ENABLE | FLAG_LASER_ON, cycle=812, age_ms=3))
    parser = FrameParser(accept=(TYPE_COMMAND,))
    frames = parser.feed(wire)          # -> [CommandFrame(seq=7, ...)]

The parser is incremental (feed any chunking), rejects every frame whose CRC, length, type or
field ranges are wrong, counts what it rejected, and resynchronises on the next valid frame
(rules in the protocol document, "Framing and resynchronisation").
"""

from __future__ import annotations

import binascii
import struct
from collections.abc import Iterable
from dataclasses import dataclass

from omnid.errors import ProtocolError

__all__ = [
    "COMMAND_FRAME_LEN",
    "COMMAND_LEN",
    "FAULT_NAMES",
    "FAULT_OVERCURRENT_LEFT",
    "FAULT_OVERCURRENT_RIGHT",
    "FAULT_RESET",
    "FAULT_RX_ERROR",
    "FAULT_STALE_COMMAND",
    "FAULT_UNDERVOLTAGE",
    "FAULT_WATCHDOG",
    "FLAG_ENABLE",
    "FLAG_LASER_ON",
    "FLAG_LEFT_REVERSE",
    "FLAG_RIGHT_REVERSE",
    "REPLY_FRAME_LEN",
    "REPLY_LEN",
    "START",
    "STATE_DRIVE_ENABLED",
    "STATE_LASER_IS_ON",
    "TYPE_COMMAND",
    "TYPE_REPLY",
    "CommandFrame",
    "FrameParser",
    "ReplyFrame",
    "crc16",
    "crc16_ccitt_false_table",
    "cycle_ahead",
    "decode_frame",
    "duty_to_wire",
    "encode_command",
    "encode_reply",
    "fault_names",
    "unwrap_int32",
    "wire_to_duty",
]

START = 0xA5
TYPE_COMMAND = 0x01
TYPE_REPLY = 0x81
COMMAND_LEN = 11
REPLY_LEN = 15
HEADER_LEN = 4
CRC_LEN = 2
COMMAND_FRAME_LEN = HEADER_LEN + COMMAND_LEN + CRC_LEN  # 17
REPLY_FRAME_LEN = HEADER_LEN + REPLY_LEN + CRC_LEN  # 21
_PAYLOAD_LEN = {TYPE_COMMAND: COMMAND_LEN, TYPE_REPLY: REPLY_LEN}

FLAG_LEFT_REVERSE = 0x01
FLAG_RIGHT_REVERSE = 0x02
FLAG_LASER_ON = 0x04
FLAG_ENABLE = 0x08
_FLAG_RESERVED = 0xF0

STATE_LASER_IS_ON = 0x01
STATE_DRIVE_ENABLED = 0x02
_STATE_RESERVED = 0xFC

FAULT_WATCHDOG = 0x01
FAULT_OVERCURRENT_LEFT = 0x02
FAULT_OVERCURRENT_RIGHT = 0x04
FAULT_RX_ERROR = 0x08
FAULT_UNDERVOLTAGE = 0x10
FAULT_STALE_COMMAND = 0x20
FAULT_RESET = 0x80
FAULT_NAMES = {
    FAULT_WATCHDOG: "watchdog",
    FAULT_OVERCURRENT_LEFT: "overcurrent_left",
    FAULT_OVERCURRENT_RIGHT: "overcurrent_right",
    FAULT_RX_ERROR: "rx_error",
    FAULT_UNDERVOLTAGE: "undervoltage",
    FAULT_STALE_COMMAND: "stale_command",
    FAULT_RESET: "reset",
}

DUTY_FULL_SCALE = 1000  # ‰
WATCHDOG_MIN_MS = 20
WATCHDOG_MAX_MS = 2000
MAX_AGE_DEFAULT_MS = 40  # the unit's freshness limit when a command says MAX_AGE_MS = 0
AGE_SATURATED_MS = 255  # AGE_MS of a command 255 ms old or older
CYCLE_MODULUS = 1 << 16

_CMD = struct.Struct(">HHBHHBB")
_REPLY = struct.Struct(">iihhBBB")
_HEADER = struct.Struct(">BBBB")
_CRC = struct.Struct(">H")


def _make_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return tuple(table)


_TABLE = _make_table()


def crc16_ccitt_false_table(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no xorout), table-driven.

    The reference a firmware port copies; :func:`crc16` is the same function in C.
    """
    crc = 0xFFFF
    for b in bytes(data):
        crc = ((crc << 8) & 0xFFFF) ^ _TABLE[(crc >> 8) ^ b]
    return crc


def crc16(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (``binascii.crc_hqx`` with init 0xFFFF; check 0x29B1)."""
    return binascii.crc_hqx(data, 0xFFFF)


@dataclass(frozen=True, slots=True)
class CommandFrame:
    """A command, master → unit (protocol table "Command payload"). Duties are ‰ magnitudes.

    ``cycle``: number of the control cycle that computed the command (+1 per computed command,
    mod 2¹⁶); ``age_ms``: how old the command was when this frame was sent (255 = 255 ms or
    more); ``max_age_ms``: the unit drives only on commands at most this old and holds one
    cycle's command at most this long (0 = the unit's default 40 ms).
    """

    seq: int
    left_duty_pm: int
    right_duty_pm: int
    flags: int
    watchdog_ms: int = 0
    cycle: int = 0
    age_ms: int = 0
    max_age_ms: int = 0

    def __post_init__(self) -> None:
        if not 0 <= self.seq <= 0xFF:
            raise ProtocolError(f"command seq {self.seq} outside 0..255")
        for name in ("left_duty_pm", "right_duty_pm"):
            v = getattr(self, name)
            if not 0 <= v <= DUTY_FULL_SCALE:
                raise ProtocolError(f"command {name} {v} outside 0..{DUTY_FULL_SCALE}")
        if self.flags & ~0xFF or self.flags & _FLAG_RESERVED:
            raise ProtocolError(f"command flags 0x{self.flags:02x} use reserved bits")
        if self.watchdog_ms != 0 and not WATCHDOG_MIN_MS <= self.watchdog_ms <= WATCHDOG_MAX_MS:
            raise ProtocolError(
                f"command watchdog_ms {self.watchdog_ms} outside {WATCHDOG_MIN_MS}..{WATCHDOG_MAX_MS}"
            )
        if not 0 <= self.cycle < CYCLE_MODULUS:
            raise ProtocolError(f"command cycle {self.cycle} outside 0..{CYCLE_MODULUS - 1}")
        if not 0 <= self.age_ms <= AGE_SATURATED_MS or not 0 <= self.max_age_ms <= 255:
            raise ProtocolError("command age_ms/max_age_ms outside one byte")

    @property
    def enabled(self) -> bool:
        """``ENABLE`` set: the unit may drive (still subject to the freshness rules)."""
        return bool(self.flags & FLAG_ENABLE)

    @property
    def left_duty(self) -> float:
        """Signed left duty in [-1, 1]."""
        return wire_to_duty(self.left_duty_pm, bool(self.flags & FLAG_LEFT_REVERSE))

    @property
    def right_duty(self) -> float:
        """Signed right duty in [-1, 1]."""
        return wire_to_duty(self.right_duty_pm, bool(self.flags & FLAG_RIGHT_REVERSE))


@dataclass(frozen=True, slots=True)
class ReplyFrame:
    """A reply, unit → master (protocol table "Reply payload"). Clocks are raw int32."""

    seq: int
    left_clocks: int
    right_clocks: int
    left_applied_pm: int
    right_applied_pm: int
    state: int
    faults: int
    rx_errors: int

    def __post_init__(self) -> None:
        if not 0 <= self.seq <= 0xFF:
            raise ProtocolError(f"reply seq {self.seq} outside 0..255")
        for name in ("left_clocks", "right_clocks"):
            if not -(2**31) <= getattr(self, name) < 2**31:
                raise ProtocolError(f"reply {name} outside int32")
        for name in ("left_applied_pm", "right_applied_pm"):
            if not -DUTY_FULL_SCALE <= getattr(self, name) <= DUTY_FULL_SCALE:
                raise ProtocolError(f"reply {name} outside ±{DUTY_FULL_SCALE}")
        if self.state & ~0xFF or self.state & _STATE_RESERVED:
            raise ProtocolError(f"reply state 0x{self.state:02x} uses reserved bits")
        if not 0 <= self.faults <= 0xFF or not 0 <= self.rx_errors <= 0xFF:
            raise ProtocolError("reply faults/rx_errors outside one byte")


def duty_to_wire(duty: float) -> tuple[int, bool]:
    """Signed duty in [-1, 1] → (magnitude ‰ 0..1000, reverse flag)."""
    if not -1.0 <= duty <= 1.0:  # also false for NaN
        raise ProtocolError(f"duty {duty!r} outside [-1, 1]")
    return round(abs(duty) * DUTY_FULL_SCALE), duty < 0


def wire_to_duty(magnitude_pm: int, reverse: bool) -> float:
    """(magnitude ‰, reverse flag) → signed duty in [-1, 1]."""
    d = magnitude_pm / DUTY_FULL_SCALE
    return -d if reverse else d


def _frame(ftype: int, seq: int, payload: bytes) -> bytes:
    body = _HEADER.pack(START, ftype, len(payload), seq)[1:] + payload
    return bytes((START,)) + body + _CRC.pack(crc16(body))


def encode_command(cmd: CommandFrame) -> bytes:
    """The 17 wire bytes of a command frame."""
    return _frame(
        TYPE_COMMAND,
        cmd.seq,
        _CMD.pack(
            cmd.left_duty_pm,
            cmd.right_duty_pm,
            cmd.flags,
            cmd.watchdog_ms,
            cmd.cycle,
            cmd.age_ms,
            cmd.max_age_ms,
        ),
    )


def encode_reply(rep: ReplyFrame) -> bytes:
    """The 21 wire bytes of a reply frame."""
    return _frame(
        TYPE_REPLY,
        rep.seq,
        _REPLY.pack(
            rep.left_clocks,
            rep.right_clocks,
            rep.left_applied_pm,
            rep.right_applied_pm,
            rep.state,
            rep.faults,
            rep.rx_errors,
        ),
    )


def decode_frame(frame: bytes | bytearray | memoryview) -> CommandFrame | ReplyFrame:
    """Decode one complete frame; :class:`ProtocolError` says what is wrong with it."""
    frame = bytes(frame)
    if len(frame) < HEADER_LEN + CRC_LEN or frame[0] != START:
        raise ProtocolError("frame: no start byte / too short")
    ftype, length, seq = frame[1], frame[2], frame[3]
    expected = _PAYLOAD_LEN.get(ftype)
    if expected is None:
        raise ProtocolError(f"frame: unknown type 0x{ftype:02x}")
    if length != expected or len(frame) != HEADER_LEN + length + CRC_LEN:
        raise ProtocolError(f"frame: length {length}/{len(frame)} wrong for type 0x{ftype:02x}")
    body = frame[1 : HEADER_LEN + length]
    (crc,) = _CRC.unpack_from(frame, HEADER_LEN + length)
    if crc16(body) != crc:
        raise ProtocolError("frame: CRC mismatch")
    payload = frame[HEADER_LEN : HEADER_LEN + length]
    if ftype == TYPE_COMMAND:
        return CommandFrame(seq, *_CMD.unpack(payload))
    return ReplyFrame(seq, *_REPLY.unpack(payload))


class FrameParser:
    """Incremental parser: ``feed(bytes) -> [frames]``; rejects and counts bad frames, resyncs.

    ``accept`` lists the frame types this end receives (the unit: commands; the master: replies);
    a well-formed frame of another type is counted in ``unexpected`` and skipped.

    Counters (cumulative): ``frames`` accepted, ``crc_errors``, ``malformed`` (bad type/length or
    field out of range), ``unexpected``, ``truncated`` (an incomplete frame overtaken by a complete
    valid one), ``discarded_bytes`` (bytes skipped while searching).
    """

    def __init__(
        self, accept: Iterable[int] = (TYPE_COMMAND, TYPE_REPLY), max_buffer: int = 4096
    ) -> None:
        self._accept = frozenset(accept)
        self._buf = bytearray()
        self._max_buffer = max_buffer
        self.frames = 0
        self.crc_errors = 0
        self.malformed = 0
        self.unexpected = 0
        self.truncated = 0
        self.discarded_bytes = 0

    @property
    def pending(self) -> int:
        """Bytes held waiting for the rest of a frame."""
        return len(self._buf)

    def reset(self) -> None:
        """Forget a partial frame (e.g. after a reply deadline or a reconnect)."""
        self.discarded_bytes += len(self._buf)
        self._buf.clear()

    def _skip(self, n: int) -> None:
        del self._buf[:n]
        self.discarded_bytes += n

    def _complete_frame_after(self, start: int) -> int:
        """Index of the first complete, valid frame starting at or after ``start``; -1 if none."""
        buf = self._buf
        j = buf.find(START, start)
        while j >= 0:
            length = _PAYLOAD_LEN.get(buf[j + 1]) if j + 2 < len(buf) else None
            if length is not None and buf[j + 2] == length:
                total = HEADER_LEN + length + CRC_LEN
                if j + total <= len(buf):
                    try:
                        decode_frame(buf[j : j + total])
                        return j
                    except ProtocolError:
                        pass
            j = buf.find(START, j + 1)
        return -1

    def feed(self, data: bytes | bytearray | memoryview) -> list[CommandFrame | ReplyFrame]:
        buf = self._buf
        buf += data
        out: list[CommandFrame | ReplyFrame] = []
        while True:
            i = buf.find(START)
            if i < 0:
                self._skip(len(buf))
                break
            if i:
                self._skip(i)
            if len(buf) < HEADER_LEN:
                break
            ftype, length = buf[1], buf[2]
            expected = _PAYLOAD_LEN.get(ftype)
            if expected is None or length != expected:
                self.malformed += 1
                self._skip(1)
                continue
            total = HEADER_LEN + length + CRC_LEN
            if len(buf) < total:
                # Incomplete — unless a complete valid frame already starts later in the buffer:
                # then this candidate was a truncated frame or a false start, and waiting for
                # more bytes would hold the good frame back.
                j = self._complete_frame_after(1)
                if j < 0:
                    break
                self.truncated += 1
                self._skip(j)
                continue
            body = bytes(buf[1 : HEADER_LEN + length])
            if crc16(body) != (buf[total - 2] << 8 | buf[total - 1]):
                self.crc_errors += 1
                self._skip(1)
                continue
            try:
                frame = decode_frame(buf[:total])
            except ProtocolError:  # CRC fine but a field out of range (duty > 1000, reserved)
                self.malformed += 1
                self._skip(1)
                continue
            del buf[:total]
            if ftype not in self._accept:
                self.unexpected += 1
                continue
            self.frames += 1
            out.append(frame)
        if len(buf) > self._max_buffer:  # cannot happen with LEN ≤ 15, kept as a guard
            self._skip(len(buf))
        return out


def unwrap_int32(previous_raw: int, raw: int) -> int:
    """Signed difference of two int32 counters across wrap-around (protocol "wrap-around").

    ``delta = ((raw - previous_raw + 2**31) mod 2**32) - 2**31``.
    """
    return ((raw - previous_raw + 2**31) % 2**32) - 2**31


def cycle_ahead(previous: int, cycle: int) -> int:
    """How many cycles ``cycle`` is ahead of ``previous`` (mod 2¹⁶): 0 = a repeat, 1 … 32767
    newer, negative = older (a replayed or reordered command)."""
    d = (cycle - previous) % CYCLE_MODULUS
    return d if d < CYCLE_MODULUS // 2 else d - CYCLE_MODULUS


def fault_names(faults: int) -> tuple[str, ...]:
    """Names of the set fault bits (``FAULT_NAMES``), unknown bits as ``bit<N>``."""
    return tuple(FAULT_NAMES.get(1 << b, f"bit{b}") for b in range(8) if faults & (1 << b))
