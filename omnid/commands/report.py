"""``omnid report FILE.mcap [...] --out DIR`` — a recording as two pictures.

Writes ``top.png`` (the path seen from above, the obstacles and drop-offs perception reported,
where motion was refused; the course and the true path for a simulator recording) and
``timeline.png`` (the rider's demand, the speed, the limit scale with a band per reason, the
faults) into DIR.
"""

from __future__ import annotations

import argparse
from typing import Any


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "report",
        help="draw a recording: top-down picture and timeline (PNG)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("files", nargs="+", metavar="FILE.mcap", help="the segments, oldest first")
    p.add_argument("--out", default="omnid-report", metavar="DIR", help="folder (omnid-report)")
    p.set_defaults(func=handle)


def handle(args: argparse.Namespace) -> int:
    from omnid.record.plots import write_report
    from omnid.record.reader import read_recording

    rec = read_recording(args.files)
    if rec.truncated:
        print(f"note: {rec.truncated}; drawing what is complete")
    for path in write_report(rec, args.out):
        print(f"wrote {path}")
    return 0
