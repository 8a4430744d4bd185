"""``omnid perceive``: one stereo capture → classified 3-D laser dots (SPEC §6).

With ``--json`` it prints ONE JSON object ``{"points": [{x, y, z, h, r1, c1, r2, c2, class}, ...],
"calibration_health": {explained, residual_ratio, dots, ok}, ...}`` (mm in the rig frame of
SPEC §2; pixel positions as floats); without it a short summary for a person: points per class,
the matched fraction, how well the capture fits the calibration, the nearest obstacle and
drop-off ahead. A capture that does not fit the calibration (the rig knocked, another rig's
captures) is refused with one line, nothing written.
``--ply`` and ``--png`` also write the cloud (PLY) and a top-down picture of the free-space map
built from this capture with the points over it; both are written atomically.
"""

from __future__ import annotations

import argparse
import json
import math
from typing import TYPE_CHECKING

from omnid.commands._args import finite_float, positive_float

if TYPE_CHECKING:
    from omnid.core.types import PointCloud


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "perceive",
        help="detect, match, triangulate and classify the laser dots of one capture",
        description="Run the perception pipeline on one stereo mask/base capture.",
    )
    p.add_argument("--calib", required=True, metavar="CALIB.yaml", help="calibration file")
    for name in ("mask1", "base1", "mask2", "base2"):
        p.add_argument(f"--{name}", required=True, metavar="PNG", help=f"{name} image")
    p.add_argument(
        "--method",
        choices=["thesis", "best"],
        default="best",
        help="thesis: the thesis' detector, matching and triangulation end to end; best: ours",
    )
    p.add_argument(
        "--detect",
        choices=["thesis", "best"],
        default=None,
        help="dot detector (default: the one of --method)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--ply", metavar="PATH", help="also write the classified cloud as PLY")
    p.add_argument(
        "--png", metavar="PATH", help="also write a top-down picture of the free space and dots"
    )
    p.add_argument(
        "--half-width-mm",
        type=positive_float,
        default=350.0,
        help="half width of the corridor ahead in which the nearest obstacle is sought (350)",
    )
    p.add_argument(
        "--rig-x-offset-mm",
        type=finite_float,
        default=300.0,
        help="how far the vision rig sits ahead of the wheel axle, for --png (300)",
    )
    p.set_defaults(func=run)


def nearest_ahead_mm(cloud: PointCloud, label: int, half_width_mm: float) -> float:
    """Smallest X (mm ahead of the vision system) of the points of class ``label`` within
    ``half_width_mm`` of the rig's X axis; ``inf`` when there is none. A drop-off point below
    the floor counts where its ray crossed floor level (X·H/Z): the floor ends before there."""
    import numpy as np

    xyz = cloud.xyz[cloud.classes == label]
    if len(xyz) == 0:
        return math.inf
    x = xyz[:, 0].copy()
    H = cloud.floor_depth_mm
    below = xyz[:, 2] > H
    x[below] = x[below] * H / xyz[below, 2]
    ahead = (x > 0) & (np.abs(xyz[:, 1]) <= half_width_mm)
    return float(x[ahead].min()) if ahead.any() else math.inf


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from omnid.core.calibration import Calibration
    from omnid.core.pipeline import PerceptionSettings, perceive_detailed
    from omnid.core.types import PointClass
    from omnid.errors import InputError
    from omnid.io_images import png_bytes, read_capture, refuse_clobbering, write_files_atomic

    refuse_clobbering(
        {"--ply": args.ply, "--png": args.png},
        {f"--{n}": getattr(args, n) for n in ("calib", "mask1", "base1", "mask2", "base2")},
    )

    calib = Calibration.load(args.calib)
    capture = read_capture(
        args.mask1, args.base1, args.mask2, args.base2, calib.rig.cam1.image_shape
    )
    for cam, mask, base in ((1, capture.mask1, capture.base1), (2, capture.mask2, capture.base2)):
        if np.array_equal(mask, base) and mask.min() != mask.max():  # blank: no dots, said below
            raise InputError(
                f"--mask{cam} and --base{cam} are the same picture: the dots are found in base "
                f"(laser on) minus mask (laser off), so give the two exposures of camera {cam}"
            )
    result = perceive_detailed(
        capture, calib, args.method, PerceptionSettings(detection_method=args.detect)
    )
    cloud = result.cloud
    health = result.health
    if health is not None and not health.ok:
        raise InputError(
            f"{health.describe()}: the rig has moved since calibration, or the captures are "
            f"of another rig; recalibrate ({args.calib})"
        )
    outputs: list[tuple[str, bytes]] = []  # written together below: both or neither
    if args.ply:
        from omnid.core.export import ply_bytes

        outputs.append((args.ply, ply_bytes(cloud)))
    if args.png:
        from omnid.core.export import render_topdown, with_legend
        from omnid.core.freespace import FreeSpaceMap

        fmap = FreeSpaceMap()
        fmap.update(cloud, args.rig_x_offset_mm)
        top = render_topdown(fmap, cloud, rig_x_offset_mm=args.rig_x_offset_mm)
        title = f"omnid perceive: {len(cloud)} points, forward up, chair's left on the left"
        outputs.append((args.png, png_bytes(args.png, with_legend(top, title))))
    write_files_atomic(outputs)
    counts = {c.label: int((cloud.classes == c).sum()) for c in PointClass}
    nearest = {
        c.label: nearest_ahead_mm(cloud, int(c), args.half_width_mm)
        for c in (PointClass.OBSTACLE, PointClass.DROPOFF)
    }
    # a camera with fewer dots than a capture can be judged by has no laser in it: a spot or
    # two of sensor noise in base minus mask is not a laser pattern (hundreds of dots)
    few = PerceptionSettings().health.min_dots
    dark = [(i, len(d)) for i, d in ((1, result.dots1), (2, result.dots2)) if len(d) < few]
    if dark:
        import sys

        print(
            "perceive: no laser dots found in camera "
            + " or ".join(f"{i}" + (f" (only {n} spots)" if n else "") for i, n in dark)
            + ": is the laser on in the base pictures and off in the mask ones (not swapped)?",
            file=sys.stderr,
        )
    if args.json:
        doc = {
            "method": args.method,
            "detector": result.detection_method,
            "floor_depth_mm": calib.floor_depth_mm,
            "counts": counts,
            "dots1": len(result.dots1),
            "dots2": len(result.dots2),
            "matched_fraction": result.matched_fraction,
            "calibration_health": None
            if health is None
            else {
                "explained": None if math.isnan(health.explained) else health.explained,
                "residual_ratio": None
                if math.isnan(health.residual_ratio)
                else health.residual_ratio,
                "dots": health.dots,
                "ok": health.ok,
            },
            "not_understood": result.not_understood,
            "source_estimate": None
            if result.source_estimate is None
            else {"source_mm": result.source_estimate[0], "sigma_mm": result.source_estimate[1]},
            "nearest_obstacle_mm": None if math.isinf(nearest["obstacle"]) else nearest["obstacle"],
            "nearest_dropoff_mm": None if math.isinf(nearest["dropoff"]) else nearest["dropoff"],
            "points": cloud.to_records(),
        }
        print(json.dumps(doc))
        return 0
    parts = ", ".join(f"{v} {k}" for k, v in counts.items())
    print(
        f"{len(cloud)} points ({parts}); method {args.method}, detector {result.detection_method}"
    )
    print(
        f"matched {100 * result.matched_fraction:.0f} % "
        f"({len(cloud)} pairs of {len(result.dots1)} / {len(result.dots2)} dots found)"
    )
    if health is not None:
        print(health.describe())
    if result.not_understood:
        print(
            f"{result.not_understood} dots off the floor not understood (the calibration does "
            "not know the laser's source and this capture could not place it): not free space; "
            "recalibrate with --extra to read them"
        )
    for label, what in (("obstacle", "obstacle"), ("dropoff", "drop-off")):
        d = nearest[label]
        where = f"{d:.0f} mm" if math.isfinite(d) else "none seen"
        print(f"nearest {what} ahead (within ±{args.half_width_mm:g} mm): {where}")
    for path in (args.ply, args.png):
        if path:
            print(f"wrote {path}")
    return 0
