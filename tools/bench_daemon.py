"""Benchmark of the whole daemon on emulated links, with perception running.

Run from the repository root:  python tools/bench_daemon.py [--presses 200] [--period-s 0.3]
                               python tools/bench_daemon.py --step-cost [--minutes 3]

``--step-cost``: the cost of one ``ControlCore.step`` in the CI soak's setup (cluttered room,
random joystick rider, 50 Hz, truth perception; tests/scenarios/test_soak.py), with the
closed-form safety sweep and — reference, same run — with the sampled ``sweep_reference``.

Starts the real ``omnid run --config FILE --stats-out JSON`` process as systemd would, against
(in this process) the control-unit emulator on a pty, the GS311 emulator on a pty (head at
rest), and a frame server (``sim+unix://``) showing a rendered empty floor whose laser dots
appear only while the emulated unit has switched the laser on; the calibration comes from
``calibrate_from_capture`` on that floor. Perception therefore runs for real: laser switching
through the serial link, frames over the socket, ``perceive`` in the daemon's worker process.

Prints, each beside a reference measured in the same run:

- control-loop lateness p50/p99 at 50 Hz (from the daemon's own stats) — reference: a bare
  asyncio loop in its own process, sleeping to the same deadlines under the same load;
- rider input → wheel command on the wire: a teleop key line sent → the first command frame
  with a non-zero duty received by the emulated unit (many presses, each from standstill) —
  reference: key line sent → the teleop server's acknowledgement (socket + event loop only);
- perception: base frame → cloud in the map (and + one control period → the safety decision),
  the perceive time in the worker, the capture time (laser off → base pair in hand).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import types
from pathlib import Path

import numpy as np

from omnid.experiments.machine import bare_loop_lateness, start_bare_loop


def pct(xs, q) -> float:
    return float(np.percentile(np.asarray(xs) * 1e3, q)) if len(xs) else float("nan")


def step_cost(minutes: float) -> None:
    """Per-step wall time of ``ControlCore.step`` in the soak, fast sweep vs the reference."""
    import logging

    from omnid.sim.rider import random_ride
    from omnid.sim.simulator import Simulator
    from omnid.sim.suite import soak_core, soak_course, soak_settings

    logging.disable(logging.CRITICAL)
    duration = 60.0 * minutes
    print(f"machine: {os.cpu_count()} cores; soak setup, {minutes:g} simulated min each")
    rows = {}
    for name in ("reference (sampled sweep)", "closed-form sweep"):
        core = soak_core()
        if name.startswith("reference"):
            core.safety.sweep = core.safety.sweep_reference  # type: ignore[method-assign]
        times: list[float] = []
        inner = core.step

        def timed(now_s: float, inner=inner, times=times):  # type: ignore[no-untyped-def]
            t0 = time.perf_counter()
            out = inner(now_s)
            times.append(time.perf_counter() - t0)
            return out

        core.step = timed  # type: ignore[method-assign]
        sim = Simulator(soak_course(), core, soak_settings(), joystick=random_ride(7, duration))
        w0 = time.perf_counter()
        r = sim.run(duration)
        wall = time.perf_counter() - w0
        t = np.asarray(times) * 1e3
        rows[name] = float(t.mean())
        print(
            f"  {name:27s} step mean {t.mean():.3f} ms  p50 {np.median(t):.3f}  p99 "
            f"{np.percentile(t, 99):.3f}  p99.9 {np.percentile(t, 99.9):.2f}  max {t.max():.2f} ms"
            f"  ({len(t)} steps; run {wall:.1f} s wall, {r.distance_mm / 1000:.1f} m, "
            f"{len(r.collisions)} collisions)"
        )
    ref, fast = rows.values()
    print(f"  mean step cost ratio reference / closed-form: {ref / fast:.1f}x")


def bench_setup(a: argparse.Namespace) -> types.SimpleNamespace:
    """The emulated chair for a daemon process: control-unit and GS311 emulators on ptys, a
    rendered floor on a frame server's socket, a calibration, the daemon's config file."""
    from omnid.core.geometry import StereoRig
    from omnid.devices.emulators.control_unit import ControlUnitEmulator, MotorPlant
    from omnid.devices.emulators.gs311 import Gs311Emulator
    from omnid.sim.installation import calibrate_installed, installation_captures
    from omnid.sim.render import LiveSensor

    class TimedUnit(ControlUnitEmulator):
        """Records when the first command with a non-zero duty arrives after ``arm()``."""

        armed = False
        first_move_s: float | None = None

        def arm(self) -> None:
            self.first_move_s, self.armed = None, True

        def _obey(self, cmd, now):  # type: ignore[no-untyped-def]
            if self.armed and (cmd.left_duty != 0 or cmd.right_duty != 0):
                self.first_move_s, self.armed = time.monotonic(), False
            return super()._obey(cmd, now)

    tmp = Path(tempfile.mkdtemp(prefix="omnid-bench-"))
    rig = StereoRig.nominal(floor_depth_mm=1100.0)
    cap = installation_captures(rig, seed=1)[0]
    calib_path = tmp / "calib.yaml"
    calibrate_installed(rig, seed=1).save(calib_path)
    cu = TimedUnit(MotorPlant())
    gs = Gs311Emulator([(0.0, 0.0, 0.0)], noise_deg=0.2)
    frames = tmp / "frames.sock"
    teleop = tmp / "teleop.sock"
    stats_path = tmp / "stats.json"
    cfg = tmp / "omnid.yaml"
    cfg.write_text(
        f"control_unit:\n  port: {cu.open_pty()}\n"
        f"tilt_sensor:\n  port: {gs.open_pty()}\n"
        f"camera:\n  url: sim+unix://{frames}\n"
        f"teleop:\n  socket_path: {teleop}\n"
        f"perception:\n  calibration_path: {calib_path}\n  period_s: {a.period_s}\n"
    )

    sensor = LiveSensor(seed=1)  # fresh read noise per frame: a still capture is no frozen camera

    def provider():
        on = cu.laser_on
        return (
            time.monotonic(),
            sensor(cap.base1 if on else cap.mask1),
            sensor(cap.base2 if on else cap.mask2),
        )

    return types.SimpleNamespace(
        tmp=tmp,
        cu=cu,
        gs=gs,
        cap=cap,
        frames=frames,
        teleop=teleop,
        stats_path=stats_path,
        cfg=cfg,
        provider=provider,
    )


def record_cost(a: argparse.Namespace) -> None:
    """Control-loop lateness of ``omnid run --record`` against the same daemon without it,
    **at the same time**: two emulated chairs, two daemons, one of them recording — swapped
    every round — so the machine's load (shared with other work) hits both alike. Perception
    runs in both; a capture is recorded every 2 s (5x the shipped rate); both chairs turn left
    and right on teleop keys so every topic carries data."""
    import contextlib

    from omnid.record.reader import read_recording
    from omnid.sim.frame_server import FrameServer

    rigs = [bench_setup(a), bench_setup(a)]
    for b in rigs:
        b.cfg.write_text(b.cfg.read_text() + "record:\n  capture_period_s: 2.0\n")
    late: dict[str, list[float]] = {"without": [], "with --record": []}
    writer: list[dict] = []
    stop = threading.Event()

    def drive(teleop: Path) -> None:  # keys every 0.3 s: left, right, stop, ...
        k = 0
        while not stop.is_set():
            if teleop.exists():
                try:
                    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as c:
                        c.connect(str(teleop))
                        c.settimeout(1.0)
                        while not stop.is_set():
                            c.sendall([b"left\n", b"right\n", b"stop\n"][k % 3])
                            c.recv(64)
                            k += 1
                            stop.wait(0.3)
                except OSError:
                    pass
            stop.wait(0.2)

    with contextlib.ExitStack() as stack:
        for b in rigs:
            stack.enter_context(FrameServer(b.frames, b.provider))
        for r in range(a.rounds):
            procs, logs, roles = [], [], []
            stop.clear()
            for i, b in enumerate(rigs):
                recording = (r + i) % 2 == 0
                roles.append("with --record" if recording else "without")
                extra = ["--record", str(b.tmp / f"rec-{r}.mcap")] if recording else []
                b.stats_path.unlink(missing_ok=True)
                err = open(b.tmp / f"daemon-{r}.log", "w")  # noqa: SIM115
                logs.append(err)
                procs.append(
                    subprocess.Popen(
                        [
                            sys.executable,
                            "-m",
                            "omnid.cli",
                            "run",
                            "--config",
                            str(b.cfg),
                            "--stats-out",
                            str(b.stats_path),
                            *extra,
                        ],
                        stderr=err,
                        stdout=subprocess.DEVNULL,
                    )
                )
            drivers = [threading.Thread(target=drive, args=(b.teleop,), daemon=True) for b in rigs]
            for d in drivers:
                d.start()
            time.sleep(a.seconds)
            stop.set()
            for proc in procs:
                proc.send_signal(signal.SIGTERM)
            for proc, err in zip(procs, logs, strict=True):
                proc.wait(timeout=30)
                err.close()
            for d in drivers:
                d.join(timeout=5)
            for b, role in zip(rigs, roles, strict=True):
                st = json.loads(b.stats_path.read_text())
                xs = st["lateness_s"][int(3.0 * 50) :]  # after start-up
                late[role] += xs
                note = ""
                if role != "without":
                    path = b.tmp / f"rec-{r}.mcap"
                    rec = read_recording([path], topics={"/recorder"})
                    last = rec.messages[-1].doc if rec.messages else {}
                    writer.append(last)
                    note = (
                        f"  {last.get('written', 0)} messages, {path.stat().st_size / 1e6:.1f} MB, "
                        f"dropped {last.get('dropped', 0)}, writer busy "
                        f"{100 * last.get('busy_s', 0) / a.seconds:.1f} %, longest stretch without a GIL hand-back "
                        f"{last.get('slice_max_ms', 0):.2f} ms (wall, preemption included; "
                        f"{last.get('slices_over_half_ms', 0)} over 0.5 ms)"
                    )
                print(
                    f"  round {r + 1} {role:14s} p50 {pct(xs, 50):.2f} ms  p99 {pct(xs, 99):.2f} ms"
                    f"  max {pct(xs, 100):.2f} ms  ({len(xs)} cycles, {st['skipped']} skipped)"
                    + note,
                    flush=True,
                )
    for b in rigs:
        b.gs.close()
        b.cu.close()
    p0, p1 = pct(late["without"], 99), pct(late["with --record"], 99)
    print(
        f"machine: {os.cpu_count()} cores; {a.rounds} rounds of {a.seconds:g} s, two daemons at "
        "once (one recording, swapped each round), 50 Hz"
    )
    for name, xs in late.items():
        print(
            f"  {name:14s} lateness p50 {pct(xs, 50):.2f} ms  p99 {pct(xs, 99):.2f} ms  "
            f"max {pct(xs, 100):.2f} ms  ({len(xs)} cycles)"
        )
    print(f"  p99 with --record minus without: {p1 - p0:+.2f} ms (goal: within 0.5 ms)")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--presses", type=int, default=200)
    ap.add_argument("--period-s", type=float, default=0.3, help="perception.period_s")
    ap.add_argument("--step-cost", action="store_true", help="ControlCore.step cost only")
    ap.add_argument(
        "--record-cost",
        action="store_true",
        help="control-loop lateness with and without --record (alternating rounds, same run)",
    )
    ap.add_argument("--rounds", type=int, default=3, help="rounds of each for --record-cost")
    ap.add_argument("--seconds", type=float, default=30.0, help="seconds per --record-cost run")
    ap.add_argument("--minutes", type=float, default=3.0, help="soak length for --step-cost")
    a = ap.parse_args()
    if a.step_cost:
        step_cost(a.minutes)
        return

    from omnid.sim.frame_server import FrameServer

    if a.record_cost:
        record_cost(a)
        return
    b = bench_setup(a)
    tmp, cu, gs, frames, teleop = b.tmp, b.cu, b.gs, b.frames, b.teleop
    stats_path, cfg, provider = b.stats_path, b.cfg, b.provider
    wire: list[float] = []
    ack: list[float] = []
    with FrameServer(frames, provider):
        err = open(tmp / "daemon.log", "w")  # noqa: SIM115
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "omnid.cli",
                "run",
                "--config",
                str(cfg),
                "--stats-out",
                str(stats_path),
            ],
            stderr=err,
            stdout=subprocess.DEVNULL,
        )
        try:
            deadline = time.monotonic() + 20
            while not teleop.exists() and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(2.5)  # worker up, first clouds in
            seconds = max(10.0, a.presses * 0.2)
            bare = start_bare_loop(seconds)
            client = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            client.connect(str(teleop))
            client.settimeout(2.0)
            rnd = random.Random(0)
            t_end = time.monotonic() + seconds
            while time.monotonic() < t_end or len(wire) < a.presses:
                while cu.applied_duty != (0.0, 0.0):
                    time.sleep(0.002)
                time.sleep(0.05 + rnd.uniform(0.0, 0.02))  # de-phase from the 20 ms periods
                cu.arm()
                t0 = time.monotonic()
                client.sendall(rnd.choice([b"left\n", b"right\n"]))
                client.recv(64)
                ack.append(time.monotonic() - t0)
                while cu.first_move_s is None and time.monotonic() - t0 < 2.0:
                    time.sleep(0.0005)
                if cu.first_move_s is not None:
                    wire.append(cu.first_move_s - t0)
                client.sendall(b"stop\n")
                client.recv(64)
            client.close()
            bare_late = bare_loop_lateness(bare, seconds)
        finally:
            proc.send_signal(signal.SIGTERM)
            rc = proc.wait(timeout=20)
            err.close()
    gs.close()
    cu.close()
    st = json.loads(stats_path.read_text())
    late = st["lateness_s"]
    period_ms = 20.0
    print(f"machine: {os.cpu_count()} cores; daemon exit code {rc}; log {tmp / 'daemon.log'}")
    print(
        f"control loop at 50 Hz with perception in its worker process "
        f"(period {a.period_s:g} s, {st['perception_cycles']} cycles, "
        f"{st['perception_errors']} failed):"
    )
    print(
        f"  omnid run:            lateness p50 {pct(late, 50):.2f} ms  p99 {pct(late, 99):.2f} ms"
        f"  max {pct(late, 100):.2f} ms  ({st['cycles']} cycles, {st['skipped']} skipped)"
    )
    print(
        f"  bare asyncio process: lateness p50 {pct(bare_late, 50):.2f} ms  p99 "
        f"{pct(bare_late, 99):.2f} ms  (same time, same load)  ratio p99 "
        f"{pct(late, 99) / pct(bare_late, 99):.2f}"
    )
    print(
        f"rider key → first non-zero duty on the wire: p50 {pct(wire, 50):.1f} ms  "
        f"p99 {pct(wire, 99):.1f} ms  max {pct(wire, 100):.1f} ms  (n={len(wire)}); "
        f"reference key → teleop ack p99 {pct(ack, 99):.1f} ms; periods: loop {period_ms:.0f} ms, "
        f"link 20 ms"
    )
    pl, ps, cs = st["perception_latency_s"], st["perception_s"], st["capture_s"]
    mb = st["mask_to_base_s"]
    print(
        f"perception: base frame → cloud in the map p50 {pct(pl, 50):.1f} ms  p99 "
        f"{pct(pl, 99):.1f} ms (+ ≤ {period_ms:.0f} ms to the next safety decision); "
        f"perceive in the worker p50 {pct(ps, 50):.1f} ms  p99 {pct(ps, 99):.1f} ms; "
        f"capture (laser off → base pair) p50 {pct(cs, 50):.1f} ms  p99 {pct(cs, 99):.1f} ms; "
        f"mask → base p50 {pct(mb, 50):.1f} ms  p99 {pct(mb, 99):.1f} ms"
    )


if __name__ == "__main__":
    main()
