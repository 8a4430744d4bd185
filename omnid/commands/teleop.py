"""``omnid teleop --socket PATH``: drive the chair from a terminal's arrow keys.

Up/left/right/down = forward/left/right/stop (thesis 4.2.1), space also stops, ``q`` quits. The
terminal is put in raw mode while the client runs and restored on exit, whatever happens.
"""

from __future__ import annotations

import argparse
from typing import Any

from omnid.commands._args import positive_float


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "teleop",
        help="drive with the arrow keys through the daemon's teleop socket",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--socket",
        default="/run/omnid/teleop.sock",
        help="the daemon's teleop socket (default /run/omnid/teleop.sock)",
    )
    parser.add_argument(
        "--reply-timeout-s",
        type=positive_float,
        default=1.0,
        help="give up when the daemon is silent",
    )
    parser.set_defaults(func=handler)


def handler(args: argparse.Namespace) -> int:
    import asyncio
    import contextlib
    import os
    import stat
    import sys
    import termios
    import tty

    from omnid.devices.teleop import run_client
    from omnid.errors import InputError

    fd = sys.stdin.fileno()
    mode = os.fstat(fd).st_mode
    if not (os.isatty(fd) or stat.S_ISFIFO(mode) or stat.S_ISSOCK(mode)):
        raise InputError(
            "standard input is not a terminal (nor a pipe): run omnid teleop in a terminal "
            "to drive with the arrow keys (or pipe the keys' bytes into it)"
        )
    saved = None
    if os.isatty(fd):
        saved = termios.tcgetattr(fd)
        tty.setraw(fd)

    def echo(text: str) -> None:
        # raw mode: the terminal does not turn \n into \r\n
        sys.stdout.write(text + ("\r\n" if saved is not None else "\n"))
        sys.stdout.flush()

    try:
        if saved is not None:
            echo("omnid teleop: arrows drive (down/space = stop), q quits")
        return asyncio.run(run_client(args.socket, fd, echo, args.reply_timeout_s))
    finally:
        if saved is not None:
            with contextlib.suppress(termios.error):
                termios.tcsetattr(fd, termios.TCSADRAIN, saved)
