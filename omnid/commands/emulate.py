"""``omnid emulate NAME [options]`` — serve an emulated device on a pty for bench use.

Examples::

    omnid emulate control-unit --pty             # prints the pty path, serves until Ctrl-C
    omnid emulate control-unit --pty --link /tmp/ttyCU
    omnid emulate gs311 --help

Emulators are listed in :data:`omnid.devices.emulators.EMULATORS` and imported only when chosen;
each module's ``add_arguments(parser)`` defines its options and ``run(args)`` serves.
"""

from __future__ import annotations

import argparse
from typing import Any

EMULATOR_NAMES = ("control-unit", "gs311")  # kept in step with omnid.devices.emulators.EMULATORS


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "emulate",
        help="serve an emulated device (control unit, tilt sensor) on a pseudo-terminal",
        description="Serve an emulated device on a pty; prints the path, runs until interrupted.",
        add_help=True,
    )
    parser.add_argument("device", metavar="DEVICE", help=f"one of: {', '.join(EMULATOR_NAMES)}")
    parser.add_argument(
        "options", nargs=argparse.REMAINDER, help="options of that emulator (DEVICE --help)"
    )
    parser.set_defaults(func=handle)


def handle(args: argparse.Namespace) -> int:
    from omnid.devices import emulators

    module = emulators.load(args.device)
    sub = argparse.ArgumentParser(
        prog=f"omnid emulate {args.device}", description=(module.__doc__ or "").split("\n")[0]
    )
    module.add_arguments(sub)
    sub_args = sub.parse_args(args.options)
    import contextlib
    import os
    import signal

    def interrupted(signum: int, frame: object) -> None:
        raise KeyboardInterrupt  # the emulator's finally closes the pty and removes --link

    # SIGTERM (kill, systemd, a bench script) and SIGHUP (terminal closed) end the emulator as
    # Ctrl-C does, so no dangling --link symlink is left behind
    previous = {s: signal.signal(s, interrupted) for s in (signal.SIGTERM, signal.SIGHUP)}
    try:
        return int(module.run(sub_args) or 0)
    except KeyboardInterrupt:
        return 0
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        # a signal before the emulator's own cleanup was armed: its pty is gone with this
        # process, so is the link to it (only ever a symlink, never a file)
        link = getattr(sub_args, "link", None)
        if link and os.path.islink(link):
            with contextlib.suppress(OSError):
                os.unlink(link)
