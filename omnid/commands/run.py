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
    parser.add_argument(
        "--record",
        metavar="FILE.mcap",
        help="record what the chair saw and decided as MCAP (record.path; rotation and budget "
        "as record.* says; needs the 'record' extra)",
    )
    parser.add_argument(
        "--view",
        nargs="?",
        const="127.0.0.1:8765",
        metavar="HOST:PORT",
        help="serve the recorded topics live over the Foxglove WebSocket protocol (default "
        "127.0.0.1:8765)",
    )
    parser.add_argument(
        "--inject-faults",
        action="store_true",
        help=argparse.SUPPRESS,  # tools/fault_figures.py only (signals inject faults)
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

    return main(
        args.config,
        stats_out=args.stats_out,
        record=args.record,
        view=args.view,
        inject_faults=args.inject_faults,
    )
