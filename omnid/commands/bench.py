"""``omnid bench`` — the whole chair on the bench in one command, no hardware.

Starts the simulated chair in real time (its chair is the control-unit emulator's motor plant,
its cameras the frame server's, a GS311 emulator with the head at rest), calibrates the
simulated rig, writes a configuration for them and runs the real daemon (``omnid run``) as a
child process; prints how to drive it (``omnid teleop`` on the teleop socket) and what the
chair does; Ctrl-C (or SIGTERM) stops the daemon, the emulators and the simulator, and removes
the links. Everything lives in one folder (``--dir``, default a new temporary one).
"""

from __future__ import annotations

import argparse
from typing import Any

from omnid.commands._args import positive_float


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "bench",
        help="simulator + emulators + daemon together in real time; drive with omnid teleop",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--course", default="builtin", help="builtin (default), empty-room, box-ahead")
    p.add_argument("--seed", type=int, default=0, help="random seed (0)")
    p.add_argument("--dir", metavar="DIR", help="working folder (default: a new temporary one)")
    p.add_argument(
        "--duration-s",
        type=positive_float,
        default=None,
        help="stop by itself after this long (tests)",
    )
    p.add_argument("--record", metavar="FILE.mcap", help="the daemon records (omnid run --record)")
    p.add_argument(
        "--view",
        nargs="?",
        const="127.0.0.1:8765",
        metavar="HOST:PORT",
        help="the daemon serves the live Foxglove view (omnid run --view)",
    )
    p.add_argument(
        "--quiet", action="store_true", help="no status lines; the daemon's log goes to DIR"
    )
    p.set_defaults(func=handle)


def bench_config(folder: Any, chair: Any) -> str:
    """The daemon's configuration for the bench (everything else as shipped)."""
    m = chair.sim.mount
    return (
        "# written by omnid bench: the simulated chair's devices in this folder\n"
        f"control_unit:\n  port: {folder / 'ttyCU'}\n"
        f"tilt_sensor:\n  port: {folder / 'ttyTilt'}\n"
        f"camera:\n  url: sim+unix://{folder / 'frames.sock'}\n"
        f"teleop:\n  socket_path: {folder / 'teleop.sock'}\n"
        "perception:\n"
        f"  calibration_path: {folder / 'calib.yaml'}\n"
        f"  rig_x_offset_mm: {m.x_offset_mm:g}\n"
        "rider:\n  tilt:\n    neutral_calibration_s: 0.0   # the emulated head is at rest\n"
    )


def handle(args: argparse.Namespace) -> int:
    import signal
    import subprocess
    import sys
    import tempfile
    import time
    from pathlib import Path

    from omnid.errors import InputError
    from omnid.sim.bench import RealTimeChair

    folder = Path(args.dir) if args.dir else Path(tempfile.mkdtemp(prefix="omnid-bench-"))
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{folder}: cannot create the folder ({exc.strerror or exc})") from None
    folder = folder.resolve()
    say = print if not args.quiet else (lambda *a, **k: None)
    print(f"omnid bench: calibrating the simulated rig in {folder} ...", flush=True)
    chair = RealTimeChair(
        args.course,
        args.seed,
        frames_path=folder / "frames.sock",
        cu_link=folder / "ttyCU",
        tilt_link=folder / "ttyTilt",
        calibrate=True,
    )
    chair.save_calibration(folder / "calib.yaml")
    config = folder / "omnid.yaml"
    config.write_text(bench_config(folder, chair))
    stop: list[str] = []

    def on_signal(signum: int, frame: object) -> None:
        stop.append(signal.Signals(signum).name)

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    chair.start()
    cmd = [sys.executable, "-m", "omnid.cli", "run", "--config", str(config)]
    if args.record:
        cmd += ["--record", str(Path(args.record).resolve())]
    if args.view:
        cmd += ["--view", args.view]
    log_path = folder / "daemon.log"
    err = open(log_path, "w") if args.quiet else None  # noqa: SIM115 - closed below
    daemon = subprocess.Popen(cmd, stderr=err, stdout=err, start_new_session=True)
    rc_daemon: int | None = None
    try:
        teleop = folder / "teleop.sock"
        deadline = time.monotonic() + 30.0
        while not teleop.exists() and daemon.poll() is None and not stop:
            if time.monotonic() > deadline:
                raise InputError(f"the daemon did not open {teleop} within 30 s (log: {log_path})")
            chair.poll()
            time.sleep(0.02)
        if daemon.poll() is not None:
            raise InputError(
                f"the daemon exited with status {daemon.returncode} at start"
                + (f" (log: {log_path})" if args.quiet else "")
            )
        print(
            f"bench running: course '{chair.course.name}', the daemon's pid {daemon.pid}\n"
            f"  control unit  {chair.cu_path}   (the simulated chair is its motor plant)\n"
            f"  tilt sensor   {chair.tilt_path}   (head at rest)\n"
            f"  cameras       sim+unix://{chair.frames_path}\n"
            f"  daemon        omnid run --config {config}"
            + (f"   (log: {log_path})" if args.quiet else "")
            + "\n"
            f"drive it from another terminal:\n"
            f"  omnid teleop --socket {teleop}      (arrows: forward/left/right, down or space "
            "stops)\n"
            + (f"live view: Foxglove, open connection ws://{args.view}\n" if args.view else "")
            + "Ctrl-C stops the daemon, the emulators and the simulator.",
            flush=True,
        )
        end = None if args.duration_s is None else time.monotonic() + args.duration_s
        last = time.monotonic()
        while not stop and daemon.poll() is None and (end is None or time.monotonic() < end):
            time.sleep(0.02)
            for text in chair.poll():
                print(f"the simulated chair: {text} — {chair.status_line()}", flush=True)
            if time.monotonic() - last >= 2.0:
                last = time.monotonic()
                say(chair.status_line(), flush=True)
    finally:
        if daemon.poll() is None:
            daemon.send_signal(signal.SIGTERM)  # the daemon stops the chair, then exits
            t_end = time.monotonic() + 15.0
            while daemon.poll() is None and time.monotonic() < t_end:
                chair.poll()  # the plant keeps running while the daemon brakes
                time.sleep(0.02)
            if daemon.poll() is None:
                daemon.kill()
        rc_daemon = daemon.wait()
        if err is not None:
            err.close()
        chair.close()
        for s, h in previous.items():
            signal.signal(s, h)
    x, y, _ = chair.sim.chair.pose
    print(
        f"bench stopped{' (' + stop[0] + ')' if stop else ''}: daemon exit status {rc_daemon}, "
        f"chair at ({x:.0f}, {y:.0f}) mm, contacts {len(chair.contacts)}, closest approach "
        f"{chair.closest_mm:.0f} mm",
        flush=True,
    )
    return 1 if chair.contacts or rc_daemon not in (0, None) else 0
