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
    """The daemon's ``ControlCore`` with the shipped configuration (``etc/omnid.yaml`` = the
    built-in defaults) except for what a scripted rider cannot do: hold the head still for the
    neutral-pose calibration at start (``rider.tilt.neutral_calibration_s: 0``: the scripted
    head's neutral is level) and release a command after a fault (``control.rearm_after_fault:
    false``: the scripts hold their command through faults). Told where the simulated rig sits
    on the chair. ``joystick``: the rider has a joystick (``rider.joystick.enabled``); ``tilt``:
    and the head-tilt sensor (default: only when there is no joystick — a silent enabled source
    would stop the chair)."""
    from omnid.daemon.config import OmnidConfig
    from omnid.daemon.core import ControlCore

    config = OmnidConfig()
    config = dataclasses.replace(
        config,
        control=dataclasses.replace(config.control, rearm_after_fault=False),
        rider=dataclasses.replace(
            config.rider,
            tilt=dataclasses.replace(config.rider.tilt, neutral_calibration_s=0.0),
        ),
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

    recording = None
    if getattr(args, "record", None) or getattr(args, "view", None):
        from omnid.record.session import SimRecording

        recording = SimRecording(controller, args.record, args.view, pace=bool(args.view))
        controller = recording.core
    settings = SimSettings(perception=args.perception, seed=args.seed)
    sim = Simulator(course, controller, settings=settings, rider=rider, progress=progress)
    if recording is not None:
        recording.attach(sim)
    if not args.quiet:
        print(f"{title}: {args.duration_s:.0f} s in course '{course.name}'", flush=True)
    try:
        result = sim.run(args.duration_s)
    finally:
        if recording is not None:
            for segment in recording.close():
                print(f"recording: {segment}", flush=True)
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
        for name in ("mask1", "base1", "mask2", "base2"):  # the floor under the plain names
            (out / f"floor_{name}.png").replace(out / f"{name}.png")
    except OSError as exc:
        raise OmnidError(f"--floor-capture {directory}: cannot write ({exc})") from exc
    print(f"extra captures: {' '.join(str(e) for e in extras)}", flush=True)
    print(f"floor capture: {out} (floor depth {h:.0f} mm)", flush=True)


def serve_real_time(args: argparse.Namespace, controller: Any) -> int:
    """Serve the simulated chair to an ``omnid run`` in another process, in real time, until
    SIGTERM/Ctrl-C (or ``--duration-s``): :class:`omnid.sim.bench.RealTimeChair`."""
    if controller is not None:
        raise OmnidError("--serve runs the chair for an external daemon; --drive cannot be used")
    import signal

    from omnid.sim.bench import RealTimeChair

    chair = RealTimeChair(
        args.course, args.seed, frames_path=args.serve, cu_link=getattr(args, "link", None)
    )
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(True))
    chair.start(tilt=False)
    print(f"control unit: {chair.cu_path}", flush=True)
    print(f"cameras: sim+unix://{args.serve}", flush=True)
    duration = getattr(args, "duration_s", None)
    deadline = None if duration is None else chair.t0 + duration
    last_print = chair.t0
    try:
        while (deadline is None or time.monotonic() < deadline) and not stop:
            time.sleep(0.02)
            for text in chair.poll():
                print(f"t={time.monotonic() - chair.t0:.2f} s: {text}", flush=True)
                stop.append(True)
            if time.monotonic() - last_print >= 0.5:
                last_print = time.monotonic()
                print(chair.status_line(), flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        chair.close()
    x, y, _ = chair.sim.chair.pose
    print(
        f"result: contacts {len(chair.contacts)}, closest approach {chair.closest_mm:.0f} mm, "
        f"chair at ({x:.0f}, {y:.0f}) mm",
        flush=True,
    )
    return 1 if chair.contacts else 0
