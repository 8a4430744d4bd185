"""``omnid run --config etc/omnid.yaml`` — the wheelchair control daemon (systemd: Type=notify)."""

from __future__ import annotations

import argparse
from typing import Any


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "run",
        help="run the control daemon",
        description="Run the wheelchair control daemon until SIGTERM (SIGHUP reloads the config).",
    )
    parser.add_argument(
        "--config",
        default="/etc/omnid/omnid.yaml",
        help="configuration file (default /etc/omnid/omnid.yaml, where the service installs "
        "the repository's etc/omnid.yaml)",
    )
    parser.add_argument(
        "--check",
        action="store_true",
        help="check everything `run` checks before it starts (configuration, calibration, "
        "ports, camera, teleop socket), list each finding and exit: 0 if `run` would start",
    )
    parser.add_argument(
        "--stats-out",
        metavar="JSON",
        help="at exit, write the control-loop and perception timings here (benchmarks)",
    )
    parser.set_defaults(func=handle)


def handle(args: argparse.Namespace) -> int:
    from omnid.daemon.config import load_config
    from omnid.daemon.preflight import preflight

    if args.check:
        config = load_config(args.config)
        result = preflight(config, args.config)
        for check in result.checks:
            print(check.line())
        n_err, n_warn = len(result.errors), len(result.warnings)
        verdict = "refused" if n_err else "ok"
        print(
            f"{args.config}: {verdict} ({len(result.checks)} checks, {n_err} errors, "
            f"{n_warn} warnings)"
        )
        return 2 if n_err else 0
    from omnid.daemon.run import main

    return main(args.config, stats_out=args.stats_out)
