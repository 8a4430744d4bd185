"""``omnid perceive``: one stereo capture → classified 3-D laser dots (SPEC §6).

With ``--json`` it prints ONE JSON object ``{"points": [{x, y, z, h, r1, c1, r2, c2, class}, ...],
...}`` (mm in the rig frame of SPEC §2; pixel positions as floats)."""

from __future__ import annotations

import argparse
import json


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "perceive",
        help="detect, match, triangulate and classify the laser dots of one capture",
        description="Run the perception pipeline on one stereo mask/base capture.",
    )
    p.add_argument("--calib", required=True, metavar="CALIB.yaml", help="calibration file")
    for name in ("mask1", "base1", "mask2", "base2"):
        p.add_argument(f"--{name}", required=True, metavar="PNG", help=f"{name} image")
    p.add_argument("--method", choices=["thesis", "best"], default="best")
    p.add_argument(
        "--detect", choices=["thesis", "best"], default="best", help="dot detector (default best)"
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from omnid.core.calibration import Calibration
    from omnid.core.pipeline import PerceptionSettings, perceive
    from omnid.core.types import PointClass
    from omnid.io_images import read_capture

    calib = Calibration.load(args.calib)
    capture = read_capture(
        args.mask1, args.base1, args.mask2, args.base2, calib.rig.cam1.image_shape
    )
    cloud = perceive(capture, calib, args.method, PerceptionSettings(detection_method=args.detect))
    counts = {c.label: int((cloud.classes == c).sum()) for c in PointClass}
    if args.json:
        doc = {
            "method": args.method,
            "floor_depth_mm": calib.floor_depth_mm,
            "counts": counts,
            "points": cloud.to_records(),
        }
        print(json.dumps(doc))
    else:
        parts = ", ".join(f"{v} {k}" for k, v in counts.items())
        print(f"{len(cloud)} points ({parts})")
    return 0
