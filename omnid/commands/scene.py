"""``omnid scene NAME --out DIR``: the captures a user needs to try the perception pipeline
without hardware, for any rig, laser and spot model.

Writes into DIR:

- ``floor_mask1.png … floor_base2.png``: the empty floor at the rig's depth (``omnid calibrate``);
- ``mask1.png … base2.png``: the named scene of :mod:`omnid.sim.scenes` (``omnid perceive``);
- ``extra1/ … extraK/`` (one per ``--extra SCENE``): an installer's further captures of the same
  rig and laser with something standing in view (SPEC §6, ``omnid calibrate --extra DIR``),
  each with ``mask1.png … base2.png`` and its own ``truth.json``;
- ``truth.json``: what drew them — the rig, the laser, the spot model and sensor, and every laser
  dot of the scene (``dots``) and of the floor capture (``floor_dots``): its beam, diffraction
  order, rig-frame position, class, which mirror sees it and its true image positions (the
  projection of its 3-D centre, the point a detector is scored against).

``--rig``, ``--laser`` and ``--spots`` take a preset, a random draw (from ``--seed``) or a file
(a YAML mapping of fields or a truth.json written here); ``--laser-param`` / ``--spot-param``
``key=value`` change single fields (see :mod:`omnid.sim.specs`). ``--list`` prints the scenes.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "scene",
        help="render a named scene's captures (and an empty floor to calibrate on)",
        description="Render the stereo captures of a named scene (three_boxes, dropoff, "
        "passage, the Table 7.4 planes, ...) and of the empty floor, plus truth.json, so the "
        "pipeline can be tried without hardware: scene → calibrate → perceive. The rig, the "
        "laser and the spot model can be chosen, drawn at random or read from a file.",
        epilog="examples:  omnid scene three_boxes --out D --rig random --laser random --seed 4"
        "  |  omnid scene floor --out D --laser default --laser-param source_mm=[0,0,-120] "
        "--laser-param law=angle --extra wall --extra box"
        "  |  omnid scene passage --out E --laser D/truth.json --rig D/truth.json",
    )
    p.add_argument("name", nargs="?", metavar="NAME", help="scene name (see --list)")
    p.add_argument("--out", metavar="DIR", help="folder for the PNGs and truth.json")
    p.add_argument("--list", action="store_true", help="list the scenes and exit")
    p.add_argument(
        "--rig",
        default=None,
        metavar="SPEC",
        help="nominal (default), misaligned (centres a few px off, f/K +3 %%/-2 %%, rotations "
        "1.5°/-1°), random (centres ±6 px, f/K ±4 %%, roll ±1.5°) or a truth.json / YAML file",
    )
    p.add_argument(
        "--misaligned", action="store_true", help="the same as --rig misaligned (older spelling)"
    )
    p.add_argument(
        "--laser",
        default="ideal",
        metavar="SPEC",
        help="ideal (default: the regular slope lattice from the rig origin), default (a "
        "plausible real laser: source 90 mm above the mirror plane, sine-law grating), random "
        "(every parameter drawn, docs/laser.md) or a truth.json / YAML file",
    )
    p.add_argument(
        "--laser-param",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="change one LaserProjector field (e.g. law=angle, source_mm=[0,0,-120], "
        "axis_tilt_deg=38; *_deg keys set the *_rad field); repeatable",
    )
    p.add_argument(
        "--spots",
        default=None,
        metavar="SPEC",
        help="clean (default: round Gaussians), realistic (speckled halos, ghosts), random, one "
        "family drawn at random (gaussian, halo, saturated, rim, speckle, mixed) or a file",
    )
    p.add_argument(
        "--spot-param",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="change one SpotModel field (e.g. sigma_px=2.5, peak_gray=600); repeatable",
    )
    p.add_argument(
        "--sensor",
        choices=("clean", "realistic"),
        default=None,
        help="sensor: clean (read noise only; default) or realistic (shot noise, 3 %% flicker)",
    )
    p.add_argument(
        "--realistic",
        action="store_true",
        help="the same as --sensor realistic --spots realistic (older spelling)",
    )
    p.add_argument(
        "--extra",
        action="append",
        default=[],
        metavar="SCENE",
        help="also write OUT/extraK/ (K = 1, 2, ...): a capture of the same rig and laser with "
        "SCENE in view, for calibrate --extra: wall or box (drawn at random from the seed), "
        "random (either) or a scene name; repeatable",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the noise and random draws")
    p.set_defaults(func=run)


def _num(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def _dots(hits: Any, rays: Any, floor_depth_mm: float) -> list[dict[str, Any]]:
    """truth.json's record of every beam's dot (one per beam, in the laser's beam order)."""
    from omnid.core.types import PointClass

    return [
        {
            "beam": i,
            "order": [int(o[0]), int(o[1])],
            "twin": int(tw),
            "brightness": float(b),
            "x": float(p[0]),
            "y": float(p[1]),
            "z": float(p[2]),
            "h": float(floor_depth_mm - p[2]),
            "class": PointClass(int(c)).label,
            "visible1": bool(v1),
            "visible2": bool(v2),
            "r1": _num(q[0]),
            "c1": _num(q[1]),
            "r2": _num(q[2]),
            "c2": _num(q[3]),
        }
        for i, (p, c, v1, v2, q, b, o, tw) in enumerate(
            zip(
                hits.xyz,
                hits.truth,
                hits.visible1,
                hits.visible2,
                hits.pixels,
                hits.brightness,
                rays.orders,
                rays.twin,
                strict=True,
            )
        )
    ]


def _capture_files(folder: Path, capture: Any, prefix: str = "") -> list[tuple[Path, bytes]]:
    """The four PNGs of ``capture`` as (path, encoded bytes), written later with the rest."""
    from omnid.io_images import png_bytes

    paths = [folder / f"{prefix}{name}.png" for name in ("mask1", "base1", "mask2", "base2")]
    return [(p, png_bytes(p, getattr(capture, p.stem.removeprefix(prefix)))) for p in paths]


def _json_file(path: Path, doc: dict[str, Any]) -> tuple[Path, bytes]:
    return path, (json.dumps(doc, indent=1) + "\n").encode()


def _mkdir(folder: Path) -> None:
    from omnid.errors import InputError

    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{folder}: cannot create the folder ({exc.strerror or exc})") from exc


def run(args: argparse.Namespace) -> int:
    from omnid.errors import InputError
    from omnid.sim.scenes import RANDOM_EXTRAS, get_scene, scene_names

    if args.list:
        for name in scene_names():
            print(f"{name:18s} {get_scene(name).description}")
        extras = ", ".join(RANDOM_EXTRAS)
        print(f"(for --extra also: {extras} — a wall or a box drawn at random from the seed)")
        return 0
    if not args.name or not args.out:
        raise InputError("give a scene NAME and --out DIR (or --list)")
    scene = get_scene(args.name)  # an unknown name is a one-line InputError listing the known
    for name in args.extra:
        if name not in RANDOM_EXTRAS:
            get_scene(name)

    from omnid.config import to_mapping
    from omnid.experiments.scenes import scene_hits
    from omnid.sim import specs
    from omnid.sim.render import RenderOptions, render_hits
    from omnid.sim.scenes import extra_scene, floor_hits

    H = scene.mount.height_mm
    if args.misaligned and args.rig not in (None, "misaligned"):
        raise InputError("--misaligned contradicts --rig " + args.rig)
    rig_spec = args.rig or ("misaligned" if args.misaligned else "nominal")
    rig = specs.rig_from_spec(rig_spec, args.seed, H)
    laser = specs.laser_from_spec(args.laser, args.seed, specs.parse_params(args.laser_param))
    spots_spec = args.spots or ("realistic" if args.realistic else "clean")
    spots = specs.spots_from_spec(spots_spec, args.seed, specs.parse_params(args.spot_param))
    sensor = args.sensor or ("realistic" if args.realistic else "clean")
    options = (
        RenderOptions.realistic(spots=spots) if sensor == "realistic" else RenderOptions(spots)
    )
    rays = laser.rays()
    out = Path(args.out)
    # everything is rendered first and written at the end, all files or none (a refusal
    # half-way must not leave a capture without its truth.json, or one of another seed)
    files: list[tuple[Path, bytes]] = []
    folders = [out]

    floor = floor_hits(rig, laser, scene.mount)
    hits = scene_hits(scene, rig, laser)
    files += _capture_files(out, render_hits(rig, floor, args.seed, options), "floor_")
    files += _capture_files(out, render_hits(rig, hits, args.seed + 1, options))
    common = {
        "floor_depth_mm": H,
        "baseline_mm": rig.baseline_mm,
        "rig_x_offset_mm": scene.mount.x_offset_mm,
        "seed": args.seed,
        "rig_spec": rig_spec,
        "misaligned": rig_spec != "nominal",
        "realistic": sensor == "realistic",
        "rig": specs.rig_mapping(rig),
        "laser_spec": args.laser,
        "laser": to_mapping(laser),
        "spots_spec": spots_spec,
        "spots": to_mapping(spots),
        "sensor": specs.sensor_mapping(options),
    }
    written: list[str] = []
    for k, name in enumerate(args.extra, start=1):
        ex = extra_scene(name, specs.stream(args.seed, "extra", k), scene.mount)
        ex_hits = scene_hits(ex, rig, laser)
        folder = out / f"extra{k}"
        folders.append(folder)
        files += _capture_files(folder, render_hits(rig, ex_hits, args.seed + 1 + k, options))
        doc = {
            "scene": ex.name,
            "description": ex.description,
            **common,
            "visible_both": int(ex_hits.visible.sum()),
            "off_floor_both": int((ex_hits.visible & (ex_hits.truth != 0)).sum()),
            "dots": _dots(ex_hits, rays, H),
        }
        files.append(_json_file(folder / "truth.json", doc))
        written.append(f"{folder}/ ({ex.description})")
    truth = {
        "scene": scene.name,
        "description": scene.description,
        **common,
        "visible_both": int(hits.visible.sum()),
        "extras": [f"extra{k}" for k in range(1, len(args.extra) + 1)],
        "dots": _dots(hits, rays, H),
        "floor_dots": _dots(floor, rays, H),
    }
    files.append(_json_file(out / "truth.json", truth))
    from omnid.io_images import write_files_atomic

    for folder in folders:
        _mkdir(folder)
    write_files_atomic(files)
    print(
        f"wrote {out}/floor_{{mask,base}}{{1,2}}.png, {out}/{{mask,base}}{{1,2}}.png and "
        f"{out}/truth.json: {scene.description}, {int(hits.visible.sum())} dots seen by both "
        f"cameras, floor {H:g} mm below the mirrors; rig {rig_spec}, laser {args.laser} "
        f"({laser.law} law, source at {', '.join(f'{v:.0f}' for v in laser.source_mm)} mm), "
        f"spots {spots.kind}"
    )
    for line in written:
        print(f"wrote {line}")
    return 0
