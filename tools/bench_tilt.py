"""Benchmark of the GS311 tilt-sensor link: codec rates and request→reply round trip over a pty.

Run from the repository root::

    python tools/bench_tilt.py [--frames 200000] [--exchanges 2000] [--poll-s 3]

Prints, with a reference measured in the same run:

* parser throughput on a clean reply stream and on a stream with garbage, against
  ``struct.iter_unpack`` of the same bytes (the floor of any Python decoder of this layout);
* encoder rate;
* request → reply round trip over a real pty with the emulator (median, p99), against a plain
  echo device on a pty (the cost of the pty and its reader thread alone);
* the poll rate and error counters :class:`TiltSensorLink` achieves against the emulator.
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import random
import statistics
import struct
import sys
import time

from omnid.devices import gs311_codec as codec
from omnid.devices.emulators.gs311 import Gs311Emulator
from omnid.devices.pty import PtyPort
from omnid.devices.tilt import TiltSensorLink, TiltSettings
from omnid.devices.transport import open_transport


def _best_of(fn, repeat: int = 3) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def bench_codec(n_frames: int) -> None:
    rng = random.Random(1)
    fmt = codec.Gs311Format()
    values = [(rng.randint(-2048, 2047), rng.randint(-2048, 2047)) for _ in range(n_frames)]
    clean = b"".join(codec.encode_angles_reply(r, p, fmt) for r, p in values)
    noisy = bytearray()
    for k in range(0, len(clean), 6 * 10):
        noisy += clean[k : k + 60] + rng.randbytes(6)  # ~10 % garbage between runs of frames
    noisy = bytes(noisy)

    def parse(data: bytes) -> int:
        p = codec.Gs311Parser(fmt)
        n = 0
        for k in range(0, len(data), 4096):  # chunks as a serial read would deliver them
            n += len(p.feed(data[k : k + 4096]))
        return n

    assert parse(clean) == n_frames
    n_noisy = parse(noisy)
    t_clean = _best_of(lambda: parse(clean))
    t_noisy = _best_of(lambda: parse(noisy))
    st = struct.Struct(">Bhhb")
    t_ref = _best_of(lambda: sum(1 for _ in st.iter_unpack(clean)))
    t_enc = _best_of(lambda: [codec.encode_angles_reply(r, p, fmt) for r, p in values])
    print(f"codec: {n_frames} frames ({len(clean) / 1e6:.2f} MB)")
    print(
        f"  parse clean   {n_frames / t_clean / 1e6:6.2f} M frames/s  "
        f"({len(clean) / t_clean / 1e6:.1f} MB/s)"
    )
    print(
        f"  parse +10% garbage {n_noisy / t_noisy / 1e6:6.2f} M frames/s  "
        f"({len(noisy) / t_noisy / 1e6:.1f} MB/s, {n_noisy} of {n_frames} frames kept)"
    )
    print(
        f"  reference struct.iter_unpack {n_frames / t_ref / 1e6:6.2f} M frames/s "
        f"-> parser/reference time ratio {t_clean / t_ref:.1f}x"
    )
    print(f"  encode        {n_frames / t_enc / 1e6:6.2f} M frames/s")
    print(f"  at 100 Hz the parser needs {100 / (n_frames / t_clean) * 100:.4f} % of one core")


async def _round_trips(path: str, request: bytes, reply_len: int, n: int) -> list[float]:
    t = open_transport(path, baudrate=115200)
    out = []
    try:
        for _ in range(n):
            t.reset_input()
            t0 = time.perf_counter()
            await t.write(request)
            await t.read_exactly(reply_len, 0.1)
            out.append(time.perf_counter() - t0)
    finally:
        t.close()
    return out


def _summary(xs: list[float]) -> tuple[float, float]:
    xs = sorted(xs)
    return statistics.median(xs), xs[min(len(xs) - 1, int(0.99 * len(xs)))]


def bench_round_trip(n: int) -> None:
    emu = Gs311Emulator([(0, -10.0, 5.0), (10, 10.0, -5.0)])
    path = emu.open_pty()
    try:
        rtt = asyncio.run(_round_trips(path, codec.READ_ANGLES_REQUEST, 6, n))
    finally:
        emu.close()
    port: PtyPort

    def echo(data: bytes) -> None:
        port.write(data * 3)  # 2 bytes in, 6 bytes out: same sizes as the GS311 exchange

    port = PtyPort(echo, name="echo")
    path = port.open()
    try:
        ref = asyncio.run(_round_trips(path, b"\x50\x50", 6, n))
    finally:
        port.close()
    med, p99 = _summary(rtt)
    rmed, rp99 = _summary(ref)
    print(f"round trip over a pty, {n} exchanges (request 2 B, reply 6 B):")
    print(f"  GS311 emulator  median {med * 1e3:.3f} ms  p99 {p99 * 1e3:.3f} ms")
    print(
        f"  echo reference  median {rmed * 1e3:.3f} ms  p99 {rp99 * 1e3:.3f} ms "
        f"-> ratio {med / rmed:.2f}x"
    )
    print(
        f"  budget: poll period 10 ms, request timeout 8 ms; a real 115200-baud line adds "
        f"{8 * 10 / 115200 * 1e3:.2f} ms of wire time"
    )


def bench_poll(duration_s: float) -> None:
    emu = Gs311Emulator([(0, -10.0, 5.0), (10, 10.0, -5.0)], noise_deg=0.1)
    path = emu.open_pty()
    stamps: list[float] = []

    async def go():
        link = TiltSensorLink(
            TiltSettings(port=path), on_reading=lambda r: stamps.append(r.timestamp_s)
        )
        await link.start()
        await asyncio.sleep(duration_s)
        h = link.health
        await link.stop()
        return h

    try:
        h = asyncio.run(go())
    finally:
        emu.close()
    gaps = [b - a for a, b in itertools.pairwise(stamps)]
    med, p99 = _summary(gaps)
    print(f"TiltSensorLink vs emulator for {duration_s:g} s:")
    print(
        f"  {len(stamps) / duration_s:.1f} readings/s (sensor: 100), gap between readings "
        f"median {med * 1e3:.2f} ms, p99 {p99 * 1e3:.2f} ms, max {max(gaps) * 1e3:.2f} ms"
    )
    print(
        f"  requests {h.requests}, ok {h.replies_ok}, timeouts {h.timeouts}, "
        f"checksum errors {h.checksum_errors}, stale episodes {h.stale_episodes}"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=200_000)
    ap.add_argument("--exchanges", type=int, default=2000)
    ap.add_argument("--poll-s", type=float, default=3.0)
    args = ap.parse_args(argv)
    print(f"python {sys.version.split()[0]}")
    bench_codec(args.frames)
    bench_round_trip(args.exchanges)
    bench_poll(args.poll_s)
    return 0


if __name__ == "__main__":
    sys.exit(main())
