"""Runs behind ``omnid demo`` and ``omnid simulate``: build, run, print progress, report.

Two ways to run:

* :func:`run_and_report` — fast mode: the daemon's core (or an open-loop driver) on the
  simulator's virtual clock; writes ``report.md`` and ``course.png``.
* :func:`serve_real_time` — for ``omnid run`` in another process: the chair is the plant of a
  control-unit emulator on a pty, camera frames are served on a Unix socket (``sim+unix://``),
  and the chair is watched for collisions and falls in real time.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import time
from typing import Any

from omnid.errors import OmnidError

log = logging.getLogger(__name__)


def make_core(rig_x_offset_mm: float = 300.0) -> Any:
    """The daemon's ``ControlCore`` with its default configuration (``etc/omnid.yaml``
    defaults), told where the simulated rig sits on the chair."""
    try:
        from omnid.daemon.config import OmnidConfig  # type: ignore[import-not-found,unused-ignore]
        from omnid.daemon.core import ControlCore  # type: ignore[import-not-found,unused-ignore]
    except ImportError as exc:
        raise OmnidError(
            f"the daemon core is not available in this build ({exc}); "
            "use `omnid simulate --drive T:LEFT:RIGHT` for an open-loop run"
        ) from exc
    config = OmnidConfig()
    config = dataclasses.replace(
        config,
        perception=dataclasses.replace(config.perception, rig_x_offset_mm=rig_x_offset_mm),
    )
    return ControlCore(config)


def run_and_report(args: argparse.Namespace, controller: Any, title: str) -> int:
    """Fast-mode run of ``args`` (course, duration_s, perception, seed, out, quiet)."""
    from omnid.sim.course import demo_rider, get_course
    from omnid.sim.report import summary_lines, write_report
    from omnid.sim.simulator import SimSettings, Simulator

    course = get_course(args.course)
    rider = None
    notes = [f"Course `{course.name}`, perception `{args.perception}`, seed {args.seed}."]
    if controller is None:
        controller = make_core()
        rider = demo_rider()
        notes.append(
            "Driven by the daemon core (`ControlCore`) with the scripted demo rider "
            "(head tilts: forward towards the stairs, left, forward towards box 3, stop)."
        )
    else:
        notes.append("Open loop: fixed duties, no daemon — the chair is unguarded.")

    def progress(now_s: float, sim: Simulator) -> None:
        if args.quiet:
            return
        x, y, th = sim.chair.pose
        print(
            f"  t={now_s:5.1f} s  chair at ({x / 1000:5.2f}, {y / 1000:5.2f}) m, "
            f"heading {th * 57.2958:6.1f}°  laser {'on' if sim.control_unit.laser_on else 'off'}",
            flush=True,
        )

    settings = SimSettings(perception=args.perception, seed=args.seed)
    sim = Simulator(course, controller, settings=settings, rider=rider, progress=progress)
    if not args.quiet:
        print(f"{title}: {args.duration_s:.0f} s in course '{course.name}'", flush=True)
    result = sim.run(args.duration_s)
    path = write_report(args.out, course, result, title, notes, sim.chair.settings)
    for line in summary_lines(result):
        print(line.replace("- ", "  ", 1))
    print(f"report: {path}  (drawing: {path.parent / 'course.png'})")
    if controller is not None and rider is not None and (result.collisions or result.falls):
        print(
            "the simulated chair collided or fell: the daemon failed this course", file=sys.stderr
        )
        return 1
    return 0


def serve_real_time(args: argparse.Namespace, controller: Any) -> int:
    """Serve the simulated chair to an ``omnid run`` in another process, in real time."""
    if controller is not None:
        raise OmnidError("--serve runs the chair for an external daemon; --drive cannot be used")
    try:
        from omnid.devices.emulators.control_unit import (  # type: ignore[import-not-found,unused-ignore]
            ControlUnitEmulator,
        )
    except ImportError as exc:
        raise OmnidError(f"the control-unit emulator is not available ({exc})") from exc
    from omnid.sim.course import get_course
    from omnid.sim.frame_server import FrameServer
    from omnid.sim.simulator import SimSettings, Simulator

    course = get_course(args.course)
    sim = Simulator(course, None, settings=SimSettings(seed=args.seed))
    emu = ControlUnitEmulator(plant=sim.chair)
    t0 = time.monotonic()

    def frame() -> Any:
        laser = bool(emu.laser_on)  # advances the plant to now under the emulator's lock
        sim.now_s = time.monotonic() - t0
        cap = sim.render(laser_on=laser)
        return sim.now_s, cap.base1, cap.base2

    pty = emu.open_pty()
    print(f"control unit: {pty}", flush=True)
    print(f"cameras: sim+unix://{args.serve}", flush=True)
    deadline = t0 + args.duration_s
    try:
        with FrameServer(args.serve, frame):
            while time.monotonic() < deadline:
                time.sleep(0.02)
                _ = emu.clocks  # advance the plant to now
                for c in sim.chair.contacts(course.world):
                    print(f"t={time.monotonic() - t0:.2f} s: {c.kind} ({c.part})", flush=True)
                    return 1
    except KeyboardInterrupt:
        pass
    finally:
        emu.close()
    return 0
