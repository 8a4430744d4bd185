"""``omnid calibrate``: find mirror centres, scale, rotation and the matching polynomials from
one stereo capture of an empty floor at a known depth (SPEC §6), and write CALIB.yaml."""

from __future__ import annotations

import argparse
import json
import logging

log = logging.getLogger("omnid.calibrate")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "calibrate",
        help="calibrate the stereo rig from one capture of an empty floor",
        description="Calibrate the rig (mirror centres, f/K, rotation, thesis polynomials) from "
        "one stereo mask/base capture of an empty floor at a known depth; no manual clicking.",
    )
    for name in ("mask1", "base1", "mask2", "base2"):
        p.add_argument(f"--{name}", required=True, metavar="PNG", help=f"{name} image")
    p.add_argument("--floor-depth-mm", type=float, required=True, help="floor depth H, mm")
    p.add_argument("--baseline-mm", type=float, default=200.0, help="baseline D, mm")
    p.add_argument("--out", required=True, metavar="CALIB.yaml", help="calibration file")
    p.add_argument("--json", action="store_true", help="print the residuals as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from omnid.core.calibration import calibrate_from_capture
    from omnid.io_images import read_capture

    capture = read_capture(args.mask1, args.base1, args.mask2, args.base2)
    calib = calibrate_from_capture(capture, args.floor_depth_mm, args.baseline_mm)
    calib.save(args.out)
    r = calib.residuals
    if args.json:
        print(json.dumps({"out": str(args.out), "residuals": r}))
    else:
        c1, c2 = calib.rig.cam1, calib.rig.cam2
        print(
            f"wrote {args.out}: {int(r.get('inliers', 0))} floor pairs, "
            f"row rms {r['row_rms_px']:.3f} px, disparity rms {r['disparity_rms_px']:.3f} px, "
            f"f/K {c1.f_over_k_px:.2f}/{c2.f_over_k_px:.2f} px"
        )
    return 0
