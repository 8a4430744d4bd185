"""``omnid scene NAME --out DIR``: the captures a user needs to try the perception pipeline
without hardware.

Writes ``floor_mask1.png … floor_base2.png`` (the empty floor at the rig's depth, for
``omnid calibrate``), ``extra_box/`` and ``extra_wall/`` (the installer's extra captures, for
``omnid calibrate --extra``), ``mask1.png … base2.png`` of the named scene of :mod:`omnid.sim.scenes`
(for ``omnid perceive``) and ``truth.json`` (the rig that drew them and every laser dot: its
rig-frame position, class, which mirror sees it and its ideal image positions). ``--list``
prints the scenes.
"""

from __future__ import annotations

import argparse
import json
import math
from typing import Any

NAMES = ("mask1", "base1", "mask2", "base2")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "scene",
        help="render a named scene's captures (and an empty floor to calibrate on)",
        description="Render the stereo captures of a named scene (three_boxes, dropoff, "
        "passage, the Table 7.4 planes, ...) and of the empty floor, plus truth.json, so the "
        "pipeline can be tried without hardware: scene → calibrate → perceive.",
    )
    p.add_argument("name", nargs="?", metavar="NAME", help="scene name (see --list)")
    p.add_argument("--out", metavar="DIR", help="folder for the PNGs and truth.json")
    p.add_argument("--list", action="store_true", help="list the scenes and exit")
    p.add_argument(
        "--misaligned",
        action="store_true",
        help="cameras misaligned (centres off by a few px, f/K +3 %%/-2 %%, rotations 1.5°/-1°)",
    )
    p.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    p.add_argument("--realistic", action="store_true", help="halos, ghosts, flicker and shot noise")
    p.set_defaults(func=run)


def _camera(cam: Any) -> dict[str, Any]:
    return {
        "center_row_px": cam.center_row_px,
        "center_col_px": cam.center_col_px,
        "y_mm": cam.y_mm,
        "f_over_k_px": cam.f_over_k_px,
        "rotation_rad": cam.rotation_rad,
        "disk_radius_px": cam.disk_radius_px,
        "image_shape": list(cam.image_shape),
    }


def _num(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from omnid.errors import InputError
    from omnid.sim.scenes import get_scene, scene_names

    if args.list:
        for name in scene_names():
            print(f"{name:18s} {get_scene(name).description}")
        return 0
    if not args.name or not args.out:
        raise InputError("omnid scene: give a scene NAME and --out DIR (or --list)")
    scene = get_scene(args.name)  # an unknown name is a one-line InputError listing the known

    from omnid.core.geometry import StereoRig
    from omnid.core.types import PointClass
    from omnid.experiments.scenes import render_hits, scene_hits
    from omnid.io_images import write_bytes_atomic, write_png
    from omnid.sim.render import RenderOptions
    from omnid.sim.rigs import misaligned_rig

    H = scene.mount.height_mm
    rig = misaligned_rig(H) if args.misaligned else StereoRig.nominal(floor_depth_mm=H)
    options = RenderOptions.realistic() if args.realistic else RenderOptions()
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{out}: cannot create the folder ({exc.strerror or exc})") from exc
    from omnid.sim.installation import installation_captures, write_capture

    floor, extras = installation_captures(rig, seed=args.seed, options=options)
    try:
        for name, extra in extras.items():
            write_capture(extra, out / f"extra_{name}")
    except OSError as exc:
        raise InputError(f"{out}: cannot write the extra captures ({exc})") from exc
    hits = scene_hits(scene, rig)
    cap = render_hits(rig, hits, args.seed + 1, options)
    for prefix, capture in (("floor_", floor), ("", cap)):
        for name in NAMES:
            write_png(out / f"{prefix}{name}.png", getattr(capture, name))
    dots = [
        {
            "x": float(p[0]),
            "y": float(p[1]),
            "z": float(p[2]),
            "h": float(H - p[2]),
            "class": PointClass(int(c)).label,
            "visible1": bool(v1),
            "visible2": bool(v2),
            "r1": _num(q[0]),
            "c1": _num(q[1]),
            "r2": _num(q[2]),
            "c2": _num(q[3]),
        }
        for p, c, v1, v2, q in zip(
            hits.xyz, hits.truth, hits.visible1, hits.visible2, hits.pixels, strict=True
        )
    ]
    truth = {
        "scene": scene.name,
        "description": scene.description,
        "floor_depth_mm": H,
        "baseline_mm": rig.baseline_mm,
        "rig_x_offset_mm": scene.mount.x_offset_mm,
        "misaligned": bool(args.misaligned),
        "realistic": bool(args.realistic),
        "seed": args.seed,
        "rig": {"cam1": _camera(rig.cam1), "cam2": _camera(rig.cam2)},
        "visible_both": int(hits.visible.sum()),
        "dots": dots,
    }
    write_bytes_atomic(out / "truth.json", (json.dumps(truth, indent=1) + "\n").encode())
    print(
        f"wrote {out}/floor_{{mask,base}}{{1,2}}.png, {out}/extra_{{box,wall}}/ (for "
        f"`omnid calibrate --extra`), {out}/{{mask,base}}{{1,2}}.png and "
        f"{out}/truth.json: {scene.description}, {int(hits.visible.sum())} dots seen by both "
        f"cameras, floor {H:g} mm below the mirrors"
    )
    return 0
