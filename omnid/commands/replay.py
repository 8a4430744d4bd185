"""``omnid replay FILE.mcap [...]`` — this build's perception and safety layer on a recording.

Feeds the recorded inputs, in the recorded order, to a fresh daemon core built from the
recorded configuration, re-runs perception on the recorded camera captures, and reports where
this build decides otherwise (commands on the wire, reasons) — so a recorded incident becomes a
regression test. Exit status: 0 every decision as recorded, 1 some differ, 2 bad input (a file
that is not an omnid recording, another format version or rig: one line).
"""

from __future__ import annotations

import argparse
from typing import Any


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "replay",
        help="run this build's perception and safety layer on a recording; report differences",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("files", nargs="+", metavar="FILE.mcap", help="the segments, oldest first")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="change a recorded configuration key (what would this setting have done?), e.g. "
        "safety.stop_distance_mm=300 (repeatable)",
    )
    p.add_argument("--calib", metavar="CALIB.yaml", help="perceive with this calibration instead")
    p.add_argument(
        "--no-perception",
        action="store_true",
        help="feed the recorded clouds only (do not re-run perception on the captures)",
    )
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")
    p.set_defaults(func=handle)


def handle(args: argparse.Namespace) -> int:
    import json
    import logging

    from omnid.record.reader import read_recording
    from omnid.record.replay import as_json, replay, summary_lines

    rec = read_recording(args.files)
    calib = None
    if args.calib:
        from omnid.core.calibration import Calibration

        calib = Calibration.load(args.calib)
    daemon_log = logging.getLogger("omnid.daemon")
    level = daemon_log.level
    daemon_log.setLevel(logging.ERROR)  # the replayed core's refusals are the report, not logs
    try:
        result = replay(rec, args.set, calibration=calib, perception=not args.no_perception)
    finally:
        daemon_log.setLevel(level)
    if args.json:
        print(json.dumps(as_json(rec, result), default=str))
    else:
        for line in summary_lines(rec, result):
            print(line)
    return 0 if result.same else 1
