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


def make_core(
    rig_x_offset_mm: float = 300.0, joystick: bool = False, tilt: bool | None = None
) -> Any:
    """The daemon's ``ControlCore`` with its default configuration (``etc/omnid.yaml``
    defaults), told where the simulated rig sits on the chair. ``joystick``: the rider has a
    joystick (``rider.joystick.enabled``); ``tilt``: and the head-tilt sensor (default: only
    when there is no joystick — a silent enabled source would stop the chair)."""
    from omnid.daemon.config import OmnidConfig
    from omnid.daemon.core import ControlCore

    config = OmnidConfig()
    config = dataclasses.replace(
        config,
        perception=dataclasses.replace(config.perception, rig_x_offset_mm=rig_x_offset_mm),
    )
    if tilt is None:
        tilt = not joystick
    if joystick or not tilt:
        r = config.rider
        rider = dataclasses.replace(
            r,
            tilt=dataclasses.replace(r.tilt, enabled=tilt),
            joystick=dataclasses.replace(r.joystick, enabled=joystick),
        )
        config = dataclasses.replace(config, rider=rider)
    return ControlCore(config)


def run_and_report(args: argparse.Namespace, controller: Any, title: str) -> int:
    """Fast-mode run of ``args`` (course, duration_s, perception, seed, out, quiet)."""
    from omnid.sim.course import get_course
    from omnid.sim.report import summary_lines, write_report
    from omnid.sim.simulator import SimSettings, Simulator
    from omnid.sim.story import ReactiveRider, demo_story

    course = get_course(args.course)
    rider: ReactiveRider | None = None
    notes = [f"Course `{course.name}`, perception `{args.perception}`, seed {args.seed}."]
    if controller is None:
        controller = make_core(joystick=True, tilt=True)
        rider = demo_story()
        notes.append(
            "Driven by the daemon core (`ControlCore`) with a reactive demo rider who watches "
            "what the chair does and moves on to the next step when it is done (or after the "
            "step's timeout): head tilt forward through the wide passage and on until the "
            "narrow passage is refused; back away on the joystick (the only input that can "
            "reverse: the head-tilt commands have no 'back'); head tilt right, towards the "
            "stairs; forward until the stairs are refused; right again, towards box 3, seen on "
            "the way and now beside the chair outside the laser's field (refused from the map). "
            "The run ends when the story does."
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
    path = write_report(
        args.out, course, result, title, notes, sim.chair.settings, story=rider is not None
    )
    for line in summary_lines(result):
        print(line.replace("- ", "  ", 1))
    print(f"report: {path}  (drawing: {path.parent / 'course.png'})")
    if rider is not None and (result.collisions or result.falls):
        print(
            "the simulated chair collided or fell: the daemon failed this course", file=sys.stderr
        )
        return 1
    return 0


def write_floor_capture(directory: str, seed: int = 0) -> None:
    """The installer's captures rendered by the simulated rig (as installed: misaligned, with
    the simulator's laser), laser on: the empty floor as ``mask1/base1/mask2/base2.png`` in
    ``directory`` and the extras as ``extra_box/`` and ``extra_wall/`` in it — for
    ``omnid calibrate --floor-depth-mm <mount height> --extra DIR/extra_box ...``."""
    from pathlib import Path

    from omnid.sim.installation import write_installation
    from omnid.sim.rigs import misaligned_rig
    from omnid.sim.world import RigMount

    h = RigMount().height_mm
    rig = misaligned_rig(h)

    out = Path(directory)
    try:
        extras = write_installation(rig, out, seed=seed)
        for name in ("mask1", "base1", "mask2", "base2"):  # the floor also as plain names
            (out / f"floor_{name}.png").replace(out / f"{name}.png")
    except OSError as exc:
        raise OmnidError(f"--floor-capture {directory}: cannot write ({exc})") from exc
    print(f"extra captures: {' '.join(str(e) for e in extras)}", flush=True)
    print(f"floor capture: {out} (floor depth {h:.0f} mm)", flush=True)


def serve_real_time(args: argparse.Namespace, controller: Any) -> int:
    """Serve the simulated chair to an ``omnid run`` in another process, in real time."""
    if controller is not None:
        raise OmnidError("--serve runs the chair for an external daemon; --drive cannot be used")
    from omnid.devices.emulators.control_unit import ControlUnitEmulator
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

    import signal

    import numpy as np

    from omnid.sim.simulator import _clearance, _perimeter

    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(True))
    boxes = np.array(
        [(b.x_min_mm, b.x_max_mm, b.y_min_mm, b.y_max_mm) for b in course.world.boxes]
    ).reshape(-1, 4)
    drops = np.array(
        [(d.x_min_mm, d.x_max_mm, d.y_min_mm, d.y_max_mm) for d in course.world.dropoffs]
    ).reshape(-1, 4)
    pty = emu.open_pty()
    print(f"control unit: {pty}", flush=True)
    print(f"cameras: sim+unix://{args.serve}", flush=True)
    deadline = t0 + args.duration_s
    closest = float("inf")
    contacts = 0
    last_print = t0
    try:
        with FrameServer(args.serve, frame):
            while time.monotonic() < deadline and not stop:
                time.sleep(0.02)
                _ = emu.clocks  # advance the plant to now
                chair = sim.chair
                supports = np.array(list(chair.support_points().values()))
                closest = min(
                    closest, _clearance(_perimeter(chair), boxes), _clearance(supports, drops)
                )
                for c in chair.contacts(course.world):
                    contacts += 1
                    print(f"t={time.monotonic() - t0:.2f} s: {c.kind} ({c.part})", flush=True)
                    stop.append(True)
                now = time.monotonic()
                if now - last_print >= 0.5:
                    last_print = now
                    x, y, th = chair.pose
                    print(
                        f"t={now - t0:.2f} s chair ({x:.0f}, {y:.0f}) mm {np.degrees(th):.1f}° "
                        f"speed {chair.left_speed_mm_s:.0f}/{chair.right_speed_mm_s:.0f} mm/s "
                        f"laser {'on' if emu.laser_on else 'off'}",
                        flush=True,
                    )
    except KeyboardInterrupt:
        pass
    finally:
        emu.close()
    x, y, _ = sim.chair.pose
    print(
        f"result: contacts {contacts}, closest approach {closest:.0f} mm, "
        f"chair at ({x:.0f}, {y:.0f}) mm",
        flush=True,
    )
    return 1 if contacts else 0
