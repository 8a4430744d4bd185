"""``omnid demo`` — the daemon on the simulator, no hardware needed.

Runs the daemon's core in the built-in course (a room with three boxes, a wide and a narrow
passage and stairs down) with a reactive rider (head tilt; the joystick only to back away) who
drives through the wide passage, is refused at the narrow one, turns towards the stairs until
refused, then towards a box seen on the way (refused from the map); prints progress and writes ``report.md`` and ``course.png`` (the path, what
perception saw, where commands were refused) into ``./omnid-demo/``. About a minute or less.
"""

from __future__ import annotations

import argparse
from typing import Any

from omnid.commands.simulate import add_run_arguments


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "demo",
        help="drive the simulated chair through the built-in course and write a report",
        description=__doc__.split("\n")[0] if __doc__ else None,
    )
    # at most: every step of the reactive story to its timeout; the run ends with the story
    add_run_arguments(
        p,
        default_out="./omnid-demo",
        default_duration_s=130.0,
        duration_help="simulated seconds at most; the run ends when the rider's story does, "
        "usually after about 60",
    )
    p.set_defaults(func=handle)


def handle(args: argparse.Namespace) -> int:
    from omnid.sim import scenario

    args.duration_s = args.default_duration_s if args.duration_s is None else args.duration_s
    return scenario.run_and_report(args, None, title="omnid demo")
