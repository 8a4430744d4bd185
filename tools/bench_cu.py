"""Benchmark of the control-unit link: codec rates and command→reply round trip over a real pty.

Run from the repository root::

    python tools/bench_cu.py [--exchanges 2000] [--baudrate 115200]

Prints encode/decode rates (frames/s) of the codec next to a reference measured in the same run
(a bare ``struct.pack`` of the same fields, and ``binascii.crc_hqx`` alone), and the round-trip
time of one command → reply through ``ControlUnitLink``'s transport and the emulator on a pty
(median / p99 / max), next to the bytes' time on the wire at the configured baud rate.
A pty has no baud rate: the wire time is what a real RS-485 line adds.
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import struct
import sys
import tempfile
import time
from pathlib import Path

from omnid.devices import cu_codec as codec
from omnid.devices.control_unit import WheelCommand
from omnid.devices.emulators.control_unit import ControlUnitEmulator
from omnid.devices.transport import open_transport


def rate(fn, n: int) -> float:
    t0 = time.perf_counter()
    for _ in range(n):
        fn()
    return n / (time.perf_counter() - t0)


def bench_codec(n: int) -> None:
    cmd = codec.CommandFrame(7, 500, 250, codec.FLAG_ENABLE | codec.FLAG_LASER_ON, 250)
    rep = codec.ReplyFrame(7, 123456, -654321, 500, -250, 3, 0, 0)
    wire_c, wire_r = codec.encode_command(cmd), codec.encode_reply(rep)
    stream = wire_r * 100
    ref = rate(lambda: struct.pack(">HHBH", 500, 250, 12, 250), n)
    crc = rate(lambda: codec.crc16(wire_r[1:19]), n)
    crc_py = rate(lambda: codec.crc16_ccitt_false_table(wire_r[1:19]), n // 10)
    enc_c = rate(lambda: codec.encode_command(cmd), n)
    enc_r = rate(lambda: codec.encode_reply(rep), n)
    dec = rate(lambda: codec.decode_frame(wire_c), n)
    p = codec.FrameParser()
    parse = rate(lambda: p.feed(stream), n // 100) * 100
    print(f"reference struct.pack (command fields)  {ref:12,.0f} /s")
    print(f"crc16 (binascii, 18 B)                  {crc:12,.0f} /s   ({crc / ref:.2f}x ref)")
    print(f"crc16 table-driven Python (18 B)        {crc_py:12,.0f} /s   ({crc_py / ref:.3f}x ref)")
    print(f"encode_command                          {enc_c:12,.0f} /s   ({enc_c / ref:.2f}x ref)")
    print(f"encode_reply                            {enc_r:12,.0f} /s   ({enc_r / ref:.2f}x ref)")
    print(f"decode_frame (command)                  {dec:12,.0f} /s   ({dec / ref:.2f}x ref)")
    print(f"FrameParser.feed, reply frames in bulk  {parse:12,.0f} /s   ({parse / ref:.2f}x ref)")


async def bench_round_trip(exchanges: int, baudrate: int) -> None:
    emu = ControlUnitEmulator()
    with tempfile.TemporaryDirectory() as d:
        path = emu.open_pty(Path(d) / "ttyCU")
        t = open_transport(path, baudrate=baudrate)
        parser = codec.FrameParser(accept=(codec.TYPE_REPLY,))
        cmd = WheelCommand(0.5, 0.5, laser_on=True, enable=True)
        rtts = []
        lost = 0
        for i in range(exchanges):
            seq = i & 0xFF
            wire = codec.encode_command(cmd.to_frame(seq, 250, cycle=i & 0xFFFF))
            t0 = time.perf_counter()
            await t.write(wire)
            got = False
            deadline = t0 + 0.05
            while not got and time.perf_counter() < deadline:
                data = await t.read_some(64, deadline - time.perf_counter())
                got = any(f.seq == seq for f in parser.feed(data))
            if got:
                rtts.append(time.perf_counter() - t0)
            else:
                lost += 1
        t.close()
        emu.close()
    rtts.sort()
    wire_ms = (codec.COMMAND_FRAME_LEN + codec.REPLY_FRAME_LEN) * 10 / baudrate * 1000
    med = statistics.median(rtts) * 1000
    p99 = rtts[int(0.99 * (len(rtts) - 1))] * 1000
    print(f"round trip over pty, {exchanges} exchanges ({lost} lost):")
    print(f"  median {med:.3f} ms   p99 {p99:.3f} ms   max {rtts[-1] * 1000:.3f} ms")
    print(
        f"  wire time at {baudrate} baud ({codec.COMMAND_FRAME_LEN} + {codec.REPLY_FRAME_LEN} "
        f"bytes, 8N1): {wire_ms:.3f} ms"
    )
    print(f"  estimated on RS-485: median {med + wire_ms:.3f} ms, p99 {p99 + wire_ms:.3f} ms")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0] if __doc__ else None)
    ap.add_argument("--exchanges", type=int, default=2000)
    ap.add_argument("--codec-n", type=int, default=100_000)
    ap.add_argument("--baudrate", type=int, default=115200)
    args = ap.parse_args(argv)
    bench_codec(args.codec_n)
    asyncio.run(bench_round_trip(args.exchanges, args.baudrate))
    return 0


if __name__ == "__main__":
    sys.exit(main())
