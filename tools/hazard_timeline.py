"""Where the time goes between a hazard's first laser dot and the first limited command.

One scenario of the safety suite (:mod:`omnid.sim.suite`), one rider, one seed, run with the
daemon's own core; every cloud that enters the map is logged against the simulated world's
truth (the chair's true pose at the update):

- ``dots F/O/D/-``: the cloud's dots on the hazard (within 30 mm of it) by class — floor,
  obstacle, drop-off, and drop-off dots the map's evidence rules set aside (``-``);
- ``cells O/D/U``: the map's cells over the hazard after the update: obstacle, drop-off,
  unknown (in doubt, or never seen);
- the true footprint's clearance to the hazard, the chair's speed, and the safety layer's
  decision at the next control step (limited or not, its reasons).

Usage::

    python tools/hazard_timeline.py "narrow trench" --rider joystick --seed 0
    python tools/hazard_timeline.py "wall at 35°" --every 2   # every 2nd cloud

Prints a line per cloud from the first dot on the hazard until the first stop, then a summary
(first dot in the cloud, first classified, first blocking cell, first limit).
"""

from __future__ import annotations

import argparse
import math
import sys
from typing import Any

import numpy as np

from omnid.core.freespace import FreeSpaceMap
from omnid.core.occupancy import CellState, rig_to_robot
from omnid.core.types import PointClass


def _to_world(pose: tuple[float, float, float], xy: np.ndarray) -> np.ndarray:
    x, y, th = pose
    c, s = math.cos(th), math.sin(th)
    return np.column_stack([x + c * xy[:, 0] - s * xy[:, 1], y + s * xy[:, 0] + c * xy[:, 1]])


def main(argv: list[str] | None = None) -> int:
    from omnid.sim.settings import SimSettings
    from omnid.sim.simulator import Simulator
    from omnid.sim.suite import SCENARIOS, _rects, footprint_clearance_mm, make_core

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0] if __doc__ else None)
    ap.add_argument("scenario", choices=sorted(SCENARIOS))
    ap.add_argument("--rider", choices=("joystick", "tilt"), default="joystick")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--perception", choices=("pipeline", "truth"), default="pipeline")
    ap.add_argument("--every", type=int, default=1, help="print every n-th cloud")
    ap.add_argument("--set", action="append", default=[], help="freespace KEY=VALUE")
    args = ap.parse_args(argv)
    import dataclasses
    import logging

    logging.disable(logging.ERROR)
    trial = SCENARIOS[args.scenario](args.rider, args.seed)
    core = make_core(trial.rider, trial.config)
    if args.set:
        changes = {k: type(getattr(core.map.settings, k))(v) for k, _, v in
                   (s.partition("=") for s in args.set)}  # fmt: skip
        core.map = FreeSpaceMap(dataclasses.replace(core.map.settings, **changes))
    settings = SimSettings(perception=args.perception, seed=trial.seed, record_seen=False,
                           stop_on_contact=False, record_period_s=0.1)  # fmt: skip
    kw: dict[str, Any] = {}
    from omnid.sim.rider import JoystickScript

    kw["joystick" if isinstance(trial.rider_input, JoystickScript) else "rider"] = trial.rider_input
    sim = Simulator(trial.course, core, settings, chair_settings=trial.chair, **kw)
    hz = _rects(trial.course, trial.hazard)
    fmap: FreeSpaceMap = core.map
    offset = core.config.perception.rig_x_offset_mm
    log: list[dict[str, Any]] = []
    kept: dict[str, np.ndarray] = {}
    evidence = fmap._dropoff_evidence

    def spy_evidence(*a: Any, **k: Any) -> Any:
        out = evidence(*a, **k)
        kept["cls"] = out
        return out

    fmap._dropoff_evidence = spy_evidence  # type: ignore[method-assign]
    update = fmap.update

    def spy_update(cloud: Any, *a: Any, **k: Any) -> Any:
        kept.pop("cls", None)
        update(cloud, *a, **k)
        pose = sim.chair.pose
        rec: dict[str, Any] = {"t": sim.now_s, "clear": footprint_clearance_mm(pose, hz)}
        if len(cloud):
            w = _to_world(pose, rig_to_robot(cloud.xyz, offset))
            on = np.zeros(len(w), dtype=bool)
            for x0, x1, y0, y1 in hz:
                on |= ((w[:, 0] >= x0 - 30) & (w[:, 0] <= x1 + 30)
                       & (w[:, 1] >= y0 - 30) & (w[:, 1] <= y1 + 30))  # fmt: skip
            cls = cloud.classes[on]
            after = kept.get("cls", cloud.classes)[on] if "cls" in kept else cls
            rec["F"] = int(np.sum(cls == PointClass.FLOOR))
            rec["O"] = int(np.sum(cls == PointClass.OBSTACLE))
            rec["D"] = int(np.sum(after == PointClass.DROPOFF))
            rec["x"] = int(np.sum((cls == PointClass.DROPOFF) & (after != PointClass.DROPOFF)))
            h = cloud.height_mm[on]
            rec["h"] = (float(np.min(h)), float(np.max(h))) if len(h) else None
        grid = fmap.grid
        xs, ys = grid.cell_centers()
        gx, gy = np.meshgrid(xs, ys, indexing="ij")
        w = _to_world(pose, np.column_stack([gx.ravel(), gy.ravel()]))
        inz = np.zeros(len(w), dtype=bool)
        for x0, x1, y0, y1 in hz:
            inz |= (w[:, 0] >= x0) & (w[:, 0] <= x1) & (w[:, 1] >= y0) & (w[:, 1] <= y1)
        # only the part of the hazard within 1.5 m ahead of the chair's front
        rx, ry = gx.ravel(), gy.ravel()
        inz &= (rx < 350 + 1500) & (np.abs(ry) < 600)
        sts = grid.states.ravel()[inz]
        rec["cO"] = int(np.sum(sts == CellState.OBSTACLE))
        rec["cD"] = int(np.sum(sts == CellState.DROPOFF))
        rec["cU"] = int(np.sum(sts == CellState.UNKNOWN))
        rec["cF"] = int(np.sum(sts == CellState.FREE))
        rec["n"] = int(inz.sum())
        log.append(rec)

    fmap.update = spy_update  # type: ignore[method-assign]
    result = sim.run(trial.duration_s)
    trace = np.array(core.trace).reshape(len(core.trace), -1)
    st = result.steps[: len(trace)]

    def decision_at(t: float) -> tuple[bool, str, float]:
        i = int(np.searchsorted(trace[:, 0], t + 1e-9))
        if i >= len(trace):
            return False, "", math.nan
        return bool(trace[i, 5]), "+".join(result.reasons_at(i)), float(abs(st[i, 5]))

    first: dict[str, float] = {}
    print(f"{args.scenario} / {args.rider} / seed {args.seed} / {args.perception}")
    print("    t   clear  speed | dots F  O  D  - | h min..max | cells O  D  U  F /n | limited")
    for k, rec in enumerate(log):
        dots = rec.get("F", 0) + rec.get("O", 0) + rec.get("D", 0) + rec.get("x", 0)
        if dots and "dot" not in first:
            first["dot"] = rec["t"]
        if (rec.get("O", 0) or rec.get("D", 0) or rec.get("x", 0)) and "labelled" not in first:
            first["labelled"] = rec["t"]
        if (rec["cO"] or rec["cD"]) and "cell" not in first:
            first["cell"] = rec["t"]
        lim, why, v = decision_at(rec["t"])
        if lim and "limit" not in first and "dot" in first:
            first["limit"] = rec["t"]
        if "stop" in why and "stop" not in first:
            first["stop"] = rec["t"]
        shown = "dot" in first and ("stop" not in first or rec["t"] - first["stop"] < 0.3)
        if shown and (k % args.every == 0 or lim):
            h = rec.get("h")
            hs = f"{h[0]:5.0f}..{h[1]:4.0f}" if h else "    —     "
            print(f"{rec['t']:6.2f} {rec['clear']:6.0f} {v:5.0f} | "
                      f"{rec.get('F', 0):6d} {rec.get('O', 0):2d} {rec.get('D', 0):2d} "
                      f"{rec.get('x', 0):2d} | {hs} | {rec['cO']:7d} {rec['cD']:2d} "
                      f"{rec['cU']:2d} {rec['cF']:2d} /{rec['n']} | {why}")  # fmt: skip
    print("first:", ", ".join(f"{k} {v:.2f} s" for k, v in first.items()))
    print(f"closest {result.min_clearance_mm:.0f} mm, end clearance "
          f"{footprint_clearance_mm(sim.chair.pose, hz):.0f} mm")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
