"""``omnid calibrate``: find mirror centres, scale, rotation, the matching polynomials and the
laser (every beam's floor dot and the source they leave from) from one stereo capture of an
empty floor at a known depth plus ``--extra`` captures of something standing in view (SPEC §6),
and write CALIB.yaml. Prints the residuals reached; refuses with one line saying what to capture
when the captures cannot determine the laser."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from omnid.commands._args import positive_float

log = logging.getLogger("omnid.calibrate")

NAMES = ("mask1", "base1", "mask2", "base2")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "calibrate",
        help="calibrate the stereo rig and the laser from captures of the floor and obstacles",
        description="Calibrate the rig (mirror centres, f/K, rotation, thesis polynomials) from "
        "one stereo mask/base capture of an empty floor at a known depth, and the laser from it "
        "and --extra captures in which some dots fall on a box or a wall; no manual clicking.",
    )
    for name in NAMES:
        p.add_argument(f"--{name}", required=True, metavar="PNG", help=f"{name} image")
    p.add_argument("--floor-depth-mm", type=positive_float, required=True, help="floor depth H, mm")
    p.add_argument("--baseline-mm", type=positive_float, default=200.0, help="baseline D, mm")
    p.add_argument("--out", required=True, metavar="CALIB.yaml", help="calibration file")
    p.add_argument(
        "--extra",
        action="append",
        default=[],
        metavar="DIR",
        help="a further capture of the same rig with dots on a box or a wall (DIR holds "
        "mask1.png, base1.png, mask2.png, base2.png); repeatable; at least one is needed to "
        "place the laser's source",
    )
    p.add_argument("--json", action="store_true", help="print the residuals as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from omnid.core.calibration import calibrate_from_capture
    from omnid.io_images import read_capture, refuse_clobbering

    inputs = {f"--{n}": getattr(args, n) for n in NAMES}
    for k, folder in enumerate(args.extra, 1):
        inputs |= {f"--extra #{k} {n}.png": str(Path(folder) / f"{n}.png") for n in NAMES}
    refuse_clobbering({"--out": args.out}, inputs)
    capture = read_capture(args.mask1, args.base1, args.mask2, args.base2)
    extras = []
    for folder in args.extra:
        d = Path(folder)
        m1, b1, m2, b2 = (str(d / f"{n}.png") for n in NAMES)
        extras.append(read_capture(m1, b1, m2, b2, capture.shape))
    calib = calibrate_from_capture(capture, args.floor_depth_mm, args.baseline_mm, extras=extras)
    calib.save(args.out)
    r = calib.residuals
    if not extras:  # the floor is fine, but it cannot place the laser's source
        import sys

        print(
            "calibrate: note: floor only, so the laser's source is unknown (assumed near the "
            "baseline's midpoint, |O_Z| <= 200 mm): floor dots are read as usual, other dots "
            "only where the capture itself places the source, else reported as not understood; "
            "an --extra capture of a box or a wall 0.5-1.5 m ahead makes the source known",
            file=sys.stderr,
        )
    if args.json:
        print(json.dumps({"out": str(args.out), "residuals": r}))
        return 0
    c1, c2 = calib.rig.cam1, calib.rig.cam2
    las = calib.laser
    assert las is not None
    ox, oy, oz = las.source_mm
    sx, sy, sz = las.source_sigma_mm
    print(
        f"wrote {args.out}: {int(r.get('inliers', 0))} floor pairs, "
        f"row rms {r['row_rms_px']:.3f} px, disparity rms {r['disparity_rms_px']:.3f} px, "
        f"f/K {c1.f_over_k_px:.2f}/{c2.f_over_k_px:.2f} px"
    )
    where = (
        f"source at ({ox:.1f}, {oy:.1f}, {oz:.1f}) mm ± ({sx:.1f}, {sy:.1f}, {sz:.1f}) from "
        f"{int(r.get('source_dots', 0))} dots off the floor"
        if las.source_known
        else "source unknown (no --extra)"
    )
    doubled = int(las.doubled().sum())
    print(
        f"laser: {len(las)} beams ({int(r.get('beams_one_camera', 0))} seen by one camera on "
        f"the floor, {int(r.get('beams_off_floor', 0))} only off it, {doubled} doubled: "
        f"their blobs are split), {where}: line residual "
        f"{r.get('source_line_rms_mm', 0.0):.2f} mm rms, track residual "
        f"{r.get('extra_track_rms_px', 0.0):.3f} px rms, "
        f"{100 * r.get('extra_matched_fraction', 0.0):.0f} % of the extras' dots matched"
    )
    return 0
