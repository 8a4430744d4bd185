"""``omnid simulate`` — a custom closed-loop run on the simulator's virtual clock.

Examples::

    omnid simulate --course builtin --duration-s 45 --out ./sim-run
    omnid simulate --course empty-room --drive "0:0.6:0.6" --duration-s 20   # open loop
    omnid simulate --perception pipeline --duration-s 10                      # full vision
    omnid simulate --serve /tmp/omnid-frames.sock --duration-s 60             # frames for omnid run

Without ``--drive`` the daemon's core (``omnid.daemon.core.ControlCore``) drives, with the demo
rider's head-motion script. ``--drive`` replaces it with fixed duties ``T:LEFT:RIGHT`` (several
allowed, each held until the next) — the chair unguarded, to see what the daemon prevents.
"""

from __future__ import annotations

import argparse
from typing import Any

from omnid.commands._args import positive_float


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "simulate",
        help="run the chair in a simulated course (faster than real time) and write a report",
        description=__doc__.split("\n")[0] if __doc__ else None,
    )
    add_run_arguments(p, default_out="./omnid-sim")
    p.add_argument(
        "--drive",
        action="append",
        metavar="T:LEFT:RIGHT",
        help="open loop: from time T s hold these duties (repeatable); no daemon",
    )
    p.add_argument(
        "--serve",
        metavar="SOCKET",
        help="real time for an external `omnid run`: a control-unit pty (printed) and camera "
        "frames on this Unix socket (sim+unix://) until SIGTERM/Ctrl-C (or --duration-s)",
    )
    p.add_argument(
        "--link",
        metavar="PATH",
        help="with --serve: a stable symlink to the control unit's pty (control_unit.port)",
    )
    p.add_argument(
        "--floor-capture",
        metavar="DIR",
        help="write mask1/base1/mask2/base2.png of an empty floor as the simulated rig sees it "
        "(for `omnid calibrate`, floor depth = the rig's mount height) before running",
    )
    p.set_defaults(func=handle)


def add_run_arguments(
    p: argparse.ArgumentParser,
    default_out: str,
    default_duration_s: float = 45.0,
    duration_help: str = "simulated seconds",
) -> None:
    """Options shared by ``simulate`` and ``demo``."""
    p.add_argument("--course", default="builtin", help="builtin (default), empty-room or box-ahead")
    p.add_argument(
        "--duration-s",
        type=positive_float,
        default=None,
        help=f"{duration_help} ({default_duration_s:g})",
    )
    p.set_defaults(default_duration_s=default_duration_s)
    p.add_argument(
        "--perception",
        choices=["truth", "pipeline", "off"],
        default="pipeline",
        help="pipeline: rendered mask/base frames of the misaligned rig, calibrated at install, "
        "through omnid.core.pipeline.perceive (default); truth: cast laser dots with their true "
        "classes (fast); off: no perception",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (0)")
    p.add_argument("--out", default=default_out, help=f"report directory ({default_out})")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.add_argument(
        "--record",
        metavar="FILE.mcap",
        help="record the run as MCAP: what the daemon saw and decided, and the simulator's "
        "truth on /sim/* (needs the 'record' extra)",
    )
    p.add_argument(
        "--view",
        nargs="?",
        const="127.0.0.1:8765",
        metavar="HOST:PORT",
        help="serve the same topics live over the Foxglove WebSocket protocol (default "
        "127.0.0.1:8765), the run paced to real time",
    )


def parse_drive(items: list[str]) -> list[tuple[float, float, float]]:
    from omnid.errors import InputError

    out = []
    for item in items:
        parts = item.split(":")
        try:
            t, left, right = (float(x) for x in parts)
        except ValueError:
            raise InputError(f"--drive {item!r}: expected T:LEFT:RIGHT numbers") from None
        if not (-1 <= left <= 1 and -1 <= right <= 1 and t >= 0):
            raise InputError(f"--drive {item!r}: duties must be in [-1, 1] and T ≥ 0")
        out.append((t, left, right))
    return out


def handle(args: argparse.Namespace) -> int:
    from omnid.sim import scenario

    controller = None
    if args.drive:
        from omnid.sim.simulator import OpenLoopDriver

        controller = OpenLoopDriver(parse_drive(args.drive))
    if getattr(args, "floor_capture", None):
        scenario.write_floor_capture(args.floor_capture, args.seed)
    if args.serve:
        return scenario.serve_real_time(args, controller)  # --duration-s None: until stopped
    args.duration_s = args.default_duration_s if args.duration_s is None else args.duration_s
    return scenario.run_and_report(args, controller, title="omnid simulate")
