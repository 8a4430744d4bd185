"""The ``omnid`` command line.

Subcommands live one per module in :mod:`omnid.commands`; each module defines
``register(subparsers)`` which adds its parser and sets ``func`` (``args -> exit code``).
Modules are discovered by name, and import their heavy dependencies inside ``func`` so that
``omnid --help`` stays fast and a missing optional library only fails the command that needs it.

Errors derived from :class:`~omnid.errors.OmnidError` (and ``OSError``) print one line
``omnid <command>: error: ...`` and exit with status 2 — never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import re
import sys
from collections.abc import Sequence

from omnid import __version__
from omnid.errors import OmnidError


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with every subcommand found in :mod:`omnid.commands`."""
    parser = argparse.ArgumentParser(
        prog="omnid",
        description="Control daemon of a powered wheelchair with omni-directional stereo vision.",
    )
    parser.add_argument("--version", action="version", version=f"omnid {__version__}")
    parser.add_argument(
        "--log-level",
        default="INFO",
        choices=["DEBUG", "INFO", "WARNING", "ERROR"],
        help="logging threshold (default INFO)",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    import omnid.commands as commands_pkg

    for info in sorted(pkgutil.iter_modules(commands_pkg.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"omnid.commands.{info.name}")
        module.register(subparsers)
    _plain_help(parser)
    return parser


_ROLE = re.compile(r":[a-z]+:`~?([^`<]*?)\s*(?:<[^`]*>)?`")


def plain_text(text: str) -> str:
    """reST markup of module docstrings as a terminal shows it: ````omnid run```` → omnid run,
    ``:class:`~omnid.x.Name``` → Name, a literal-block ``Examples::`` → ``Examples:``."""

    def role(m: re.Match[str]) -> str:
        target = m.group(1)
        return target.rsplit(".", 1)[-1] if "~" in m.group(0) else target

    text = _ROLE.sub(role, text)
    text = text.replace("``", "").replace("`", "")
    return re.sub(r"(\w)::$", r"\1:", text, flags=re.M)


def _plain_help(parser: argparse.ArgumentParser) -> None:
    """Strip reST markup from every description and help text, subcommands included."""
    if parser.description:
        parser.description = plain_text(parser.description)
    if parser.epilog:
        parser.epilog = plain_text(parser.epilog)
    for action in parser._actions:
        if isinstance(action.help, str):
            action.help = plain_text(action.help)
        if isinstance(action, argparse._SubParsersAction):
            for choice in action._choices_actions:
                if isinstance(choice.help, str):
                    choice.help = plain_text(choice.help)
            for sub in action.choices.values():
                _plain_help(sub)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``omnid`` console script; returns the process exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    logging.basicConfig(
        level=getattr(logging, args.log_level),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except (OmnidError, OSError) as exc:
        print(f"omnid {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
