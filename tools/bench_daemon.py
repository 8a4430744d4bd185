"""Benchmark of the daemon: control-loop jitter, cycle cost, rider → wire and perception → safety.

Run from the repository root:  python tools/bench_daemon.py [--seconds 5]

Prints, each against a reference measured in the same run:
- control-loop lateness p50/p99 at 50 Hz of the real ``Daemon`` (control-unit emulator on a pty,
  teleop keyboard input) while a worker thread burns CPU like ``perceive``; reference: a bare
  asyncio loop sleeping to the same deadlines;
- ``ControlCore.step`` cost p99 with the real free-space map;
- rider input → wheel command on the wire: teleop line sent → emulator sees non-zero duty, p99;
- perception result → safety: ``on_perception`` (map update) + the next ``step``, p99.
"""

from __future__ import annotations

import argparse
import asyncio
import tempfile
import threading
import time
from pathlib import Path

import numpy as np


def pct(xs, q):
    return float(np.percentile(np.asarray(xs) * 1e3, q)) if len(xs) else float("nan")


async def bare_loop(seconds: float, period: float) -> list[float]:
    t0, k, late = time.monotonic(), 0, []
    while time.monotonic() - t0 < seconds:
        deadline = t0 + k * period
        await asyncio.sleep(max(0.0, deadline - time.monotonic()))
        late.append(time.monotonic() - deadline)
        k += 1
    return late


def burn(stop: threading.Event) -> None:
    a = np.random.default_rng(0).random((480, 640)).astype(np.float32)
    while not stop.is_set():
        import cv2

        cv2.GaussianBlur(a, (21, 21), 3.0)


async def daemon_run(seconds: float, tmp: Path):
    from omnid.daemon.config import ConfigHolder
    from omnid.daemon.run import Daemon
    from omnid.devices.emulators.control_unit import ControlUnitEmulator, MotorPlant

    emu = ControlUnitEmulator(MotorPlant())
    pty = emu.open_pty()
    cfg = tmp / "omnid.yaml"
    cfg.write_text(
        f"control_unit:\n  port: {pty}\nteleop:\n  socket_path: {tmp / 't.sock'}\n"
        "perception:\n  enabled: false\nrider:\n  tilt:\n    enabled: false\n"
    )
    d = Daemon(ConfigHolder(cfg))
    task = asyncio.create_task(d.run())
    await asyncio.sleep(1.0)
    reader, writer = await asyncio.open_unix_connection(str(tmp / "t.sock"))
    wire: list[float] = []
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        # wait for standstill, then press "left" and time until the unit applies a duty
        while emu.applied_duty != (0.0, 0.0):
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.2)
        t0 = time.monotonic()
        writer.write(b"left\n")
        await writer.drain()
        await reader.readline()
        while emu.applied_duty == (0.0, 0.0) and time.monotonic() - t0 < 2.0:
            await asyncio.sleep(0.001)
        wire.append(time.monotonic() - t0)
    writer.close()
    d.request_stop()
    await task
    emu.close()
    return d.stats, wire


def core_costs(n: int = 300):
    from omnid.core.types import PointClass, PointCloud
    from omnid.daemon.config import OmnidConfig
    from omnid.daemon.core import ControlCore
    from omnid.daemon.rider import RiderSettings, TiltSettings

    # keyboard only, so that every cycle sweeps the footprint (a stale tilt would stop early)
    core = ControlCore(OmnidConfig(rider=RiderSettings(tilt=TiltSettings(enabled=False))))

    class St:
        def __init__(self, t):
            self.seq, self.left_clocks, self.right_clocks = 0, 0, 0
            self.laser_on, self.faults, self.timestamp_s = True, 0, t

    xs, ys = np.meshgrid(np.arange(0, 2500, 60.0), np.arange(-1200, 1200, 60.0), indexing="ij")
    xyz = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, 1100.0)])
    cls = np.where(xyz[:, 0] > 1800, PointClass.OBSTACLE, PointClass.FLOOR).astype(np.uint8)
    cloud = PointCloud(xyz, np.zeros((len(xyz), 3, 3)), np.zeros((len(xyz), 4)), cls)
    step, perc = [], []
    for k in range(n):
        t = k * 0.02
        core.on_status(St(t))
        core.on_key("left" if k % 2 else "forward", t)
        if k % 25 == 0:
            w0 = time.perf_counter()
            core.on_perception(cloud, t)
            core.step(t)
            perc.append(time.perf_counter() - w0)
            continue
        w0 = time.perf_counter()
        core.step(t)
        step.append(time.perf_counter() - w0)
    assert core.last_report is not None and core.last_report.decision is not None
    return step, perc, len(xyz)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=5.0)
    a = ap.parse_args()
    import logging

    logging.basicConfig(level=logging.ERROR)
    stop = threading.Event()
    th = threading.Thread(target=burn, args=(stop,), daemon=True)
    ref = asyncio.run(bare_loop(a.seconds, 0.02))
    th.start()
    ref_loaded = asyncio.run(bare_loop(a.seconds, 0.02))
    with tempfile.TemporaryDirectory() as tmp:
        stats, wire = asyncio.run(daemon_run(a.seconds, Path(tmp)))
    stop.set()
    step, perc, npts = core_costs()
    print("control loop at 50 Hz, worker thread burning CPU (perceive stand-in):")
    print(
        f"  bare asyncio loop, idle:    lateness p50 {pct(ref, 50):.2f} ms  p99 {pct(ref, 99):.2f} ms"
    )
    print(
        f"  bare asyncio loop, loaded:  lateness p50 {pct(ref_loaded, 50):.2f} ms  p99 {pct(ref_loaded, 99):.2f} ms"
    )
    print(
        f"  omnid Daemon, loaded:       lateness p50 {pct(stats.lateness_s, 50):.2f} ms  p99 "
        f"{pct(stats.lateness_s, 99):.2f} ms  ({stats.cycles} cycles, {stats.skipped} skipped)"
        f"  ratio p99 daemon/bare {pct(stats.lateness_s, 99) / pct(ref_loaded, 99):.2f}"
    )
    print(
        f"rider key → duty applied by the emulated unit (pty): p50 {pct(wire, 50):.1f} ms  "
        f"p99 {pct(wire, 99):.1f} ms  (n={len(wire)}; control period 20 ms, link period 20 ms)"
    )
    print(
        f"ControlCore.step (real map): p50 {pct(step, 50):.2f} ms  p99 {pct(step, 99):.2f} ms"
        f"  = {pct(step, 99) / 20.0 * 100:.1f} % of the 20 ms period"
    )
    print(
        f"perception result → safety decision (map update {npts} dots + step): "
        f"p50 {pct(perc, 50):.2f} ms  p99 {pct(perc, 99):.2f} ms"
    )


if __name__ == "__main__":
    main()
