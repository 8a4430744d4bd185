"""GS311 dual-axis tilt sensor packets: encoder and incremental parser (thesis 4.2.2.1, SPEC §5).

Known from the thesis (Table 4.2): every packet is ``ID``, ``data`` (0 or more bytes, a fixed
length per ID), ``checksum`` where checksum = (ID + sum(data)) mod 256. A packet without data has
checksum = ID, so the read-angles command is ``0x50 0x50``; the reply ID is ``0xA0``.

**Assumed reply layout** (the thesis gives no figure for it; every item is a setting of
:class:`Gs311Format`, so a real unit can be matched without code changes)::

    byte 0      0xA0                      reply ID
    bytes 1-2   roll count                signed 16-bit, byte order ``byte_order`` (big default)
    bytes 3-4   pitch count               signed 16-bit, same order
    byte 5      checksum                  (0xA0 + bytes 1..4) mod 256

    roll_deg  = roll_sign  * count * deg_per_count
    pitch_deg = pitch_sign * count * deg_per_count

The readings are 12-bit (Table 4.1), so a count outside ``[-2**(count_bits-1), 2**(count_bits-1))``
cannot come from the sensor and the packet is refused as corrupted. This range check matters: the
8-bit sum alone lets about 1 in 256 random windows pass; the two range checks reject a further
255 in 256 of those. A single corrupted byte always changes the sum, so it is always rejected.

The parser is fed bytes as they arrive and returns whole, valid frames; on a bad checksum or a
count out of range it drops one byte and searches for the next ``0xA0`` (resynchronises).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Literal

from omnid.config import require
from omnid.errors import ProtocolError

CMD_READ_ANGLES = 0x50
REPLY_ANGLES = 0xA0
REPLY_LENGTH = 6  # ID + 4 data bytes + checksum


def checksum(packet_without_checksum: bytes) -> int:
    """Table 4.2 checksum: (ID + sum of data bytes) mod 256; equals ID when there is no data."""
    return sum(packet_without_checksum) & 0xFF


def encode_packet(packet_id: int, data: bytes = b"") -> bytes:
    """One packet: ID, data, checksum (thesis Table 4.2)."""
    if not 0 <= packet_id <= 0xFF:
        raise ValueError(f"packet id must be a byte, got {packet_id}")
    body = bytes((packet_id,)) + bytes(data)
    return body + bytes((checksum(body),))


READ_ANGLES_REQUEST = encode_packet(CMD_READ_ANGLES)  # b"\x50\x50"


@dataclass(frozen=True)
class Gs311Format:
    """How a reply's data bytes map to angles (see the module docstring for the layout)."""

    byte_order: Literal["big", "little"] = "big"
    deg_per_count: float = 90.0 / 4096.0  # ±45° over the 12-bit range (Table 4.1)
    roll_sign: int = 1
    pitch_sign: int = 1
    count_bits: int = 12

    def __post_init__(self) -> None:
        require(self.deg_per_count > 0.0, "deg_per_count", "must be > 0")
        require(self.roll_sign in (-1, 1), "roll_sign", "must be 1 or -1")
        require(self.pitch_sign in (-1, 1), "pitch_sign", "must be 1 or -1")
        require(2 <= self.count_bits <= 16, "count_bits", "must be in 2..16")

    @property
    def _struct(self) -> struct.Struct:
        return struct.Struct(">hh" if self.byte_order == "big" else "<hh")

    @property
    def max_abs_count(self) -> int:
        """Counts must lie in [-max_abs_count, max_abs_count - 1]."""
        return 1 << (self.count_bits - 1)

    def counts_to_deg(self, roll_count: int, pitch_count: int) -> tuple[float, float]:
        """(roll_deg, pitch_deg) from raw counts, applying scale and axis signs."""
        k = self.deg_per_count
        return (self.roll_sign * roll_count * k, self.pitch_sign * pitch_count * k)

    def deg_to_counts(self, roll_deg: float, pitch_deg: float) -> tuple[int, int]:
        """Nearest raw counts for given angles, clipped to the sensor's range (emulator side)."""
        lo, hi = -self.max_abs_count, self.max_abs_count - 1
        r = round(self.roll_sign * roll_deg / self.deg_per_count)
        p = round(self.pitch_sign * pitch_deg / self.deg_per_count)
        return (min(max(r, lo), hi), min(max(p, lo), hi))


@dataclass(frozen=True)
class AnglesFrame:
    """One decoded read-angles reply: raw counts and angles, deg."""

    roll_count: int
    pitch_count: int
    roll_deg: float
    pitch_deg: float


def encode_angles_reply(roll_count: int, pitch_count: int, fmt: Gs311Format) -> bytes:
    """The sensor's reply to ``0x50 0x50`` carrying the given counts (emulator side)."""
    return encode_packet(REPLY_ANGLES, fmt._struct.pack(roll_count, pitch_count))


def decode_angles_reply(packet: bytes, fmt: Gs311Format) -> AnglesFrame:
    """Decode exactly one reply packet; raises :class:`ProtocolError` naming what is wrong."""
    if len(packet) != REPLY_LENGTH:
        raise ProtocolError(f"GS311 reply: expected {REPLY_LENGTH} bytes, got {len(packet)}")
    if packet[0] != REPLY_ANGLES:
        raise ProtocolError(f"GS311 reply: expected ID 0xA0, got 0x{packet[0]:02X}")
    if checksum(packet[:5]) != packet[5]:
        raise ProtocolError(
            f"GS311 reply: checksum 0x{packet[5]:02X} != 0x{checksum(packet[:5]):02X}"
        )
    roll, pitch = fmt._struct.unpack_from(packet, 1)
    m = fmt.max_abs_count
    if not (-m <= roll < m and -m <= pitch < m):
        raise ProtocolError(
            f"GS311 reply: count out of {fmt.count_bits}-bit range ({roll}, {pitch})"
        )
    roll_deg, pitch_deg = fmt.counts_to_deg(roll, pitch)
    return AnglesFrame(roll, pitch, roll_deg, pitch_deg)


class Gs311Parser:
    """Incremental parser of read-angles replies: ``feed(bytes) -> [AnglesFrame, ...]``.

    Rejects bad checksums and out-of-range counts, and resynchronises on the next ``0xA0``.
    Counters: ``frames``, ``checksum_errors``, ``range_errors``, ``bytes_discarded``.
    """

    def __init__(self, fmt: Gs311Format | None = None) -> None:
        self.fmt = fmt or Gs311Format()
        self._buf = bytearray()
        self._unpack = self.fmt._struct.unpack_from
        self._max = self.fmt.max_abs_count
        self.frames = 0
        self.checksum_errors = 0
        self.range_errors = 0
        self.bytes_discarded = 0

    def reset(self) -> None:
        """Forget buffered bytes (e.g. before a new half-duplex request)."""
        self.bytes_discarded += len(self._buf)
        self._buf.clear()

    @property
    def buffered(self) -> int:
        """Bytes held waiting for the rest of a packet."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[AnglesFrame]:
        """Add received bytes; return every valid frame completed by them, in order."""
        buf = self._buf
        buf += data
        out: list[AnglesFrame] = []
        start = 0
        n = len(buf)
        m = self._max
        while True:
            i = buf.find(REPLY_ANGLES, start)
            if i < 0:
                self.bytes_discarded += n - start
                start = n
                break
            self.bytes_discarded += i - start
            if n - i < REPLY_LENGTH:
                start = i
                break
            if (sum(buf[i : i + 5]) & 0xFF) != buf[i + 5]:
                self.checksum_errors += 1
                self.bytes_discarded += 1
                start = i + 1
                continue
            roll, pitch = self._unpack(buf, i + 1)
            if not (-m <= roll < m and -m <= pitch < m):
                self.range_errors += 1
                self.bytes_discarded += 1
                start = i + 1
                continue
            roll_deg, pitch_deg = self.fmt.counts_to_deg(roll, pitch)
            out.append(AnglesFrame(roll, pitch, roll_deg, pitch_deg))
            self.frames += 1
            start = i + REPLY_LENGTH
        del buf[:start]
        return out
