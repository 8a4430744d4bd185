#!/usr/bin/env python3
"""Trace a suite trial's safety stops to the evidence that made them (docs/benchmarks.md,
"Where the remaining passage stops came from").

    python tools/trace_stops.py "doorway 850 mm" joystick 0 [--set KEY=VALUE] [--map KEY=VALUE]

Runs one trial of the scenario suite (pipeline perception unless ``--perception truth``) and,
for the first step of every safety stop before the chair got through (the rider asked to move,
the safety layer limited the command to zero), prints what refused the request itself:

- the blocking evidence the leading face meets within the stop distance, or the swing within
  its buffer and stopping distance: robot frame, an exact dot (grow 0) or a cell centre (grow
  its half-diagonal), its true distance to the nearest thing in the world (a phantom lies
  outside every box), and how many captures had an obstacle dot within 5 mm of it;
- for ``unknown_stop``, the never-seen cells the swing meets by their extent;
- for every cell named, its history in the map (its state after each capture, and
  "re-anchored" where the stored grid had just been moved), and the obstacle dots that fell
  in it.

Positions are in the odometry frame (the daemon's), turned into the world by the true start
pose for the truth distances. ``--set`` changes a safety setting, ``--map`` a free-space map
setting (``--map obstacle_max_edge_mm=0``: no fill between obstacle dots).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from typing import Any

import numpy as np

from omnid.core.occupancy import CellState, rig_to_robot
from omnid.core.types import PointClass
from omnid.sim import suite


def _rect_distance(xy: np.ndarray, rects: np.ndarray) -> np.ndarray:
    """Distance (mm) of world points to the nearest rectangle (negative inside)."""
    out = np.full(len(xy), np.inf)
    for x0, x1, y0, y1 in rects:
        dx = np.maximum(x0 - xy[:, 0], xy[:, 0] - x1)
        dy = np.maximum(y0 - xy[:, 1], xy[:, 1] - y1)
        outside = np.hypot(np.maximum(dx, 0.0), np.maximum(dy, 0.0))
        out = np.minimum(out, np.where((dx > 0) | (dy > 0), outside, np.maximum(dx, dy)))
    return out


def _to_world(xy: np.ndarray, pose: Any) -> np.ndarray:
    x, y, th = pose
    c, s = math.cos(th), math.sin(th)
    return np.column_stack([x + c * xy[:, 0] - s * xy[:, 1], y + s * xy[:, 0] + c * xy[:, 1]])


def _value(text: str) -> Any:
    if text in ("true", "false"):
        return text == "true"
    try:
        return float(text)
    except ValueError:
        return text


class Tracer:
    """Hooks on one core: the safety layer's refused checks and the map after each capture."""

    def __init__(self, core: Any) -> None:
        self.core = core
        self.stops: list[dict[str, Any]] = []
        self.dots: list[tuple[float, np.ndarray]] = []  # capture time, obstacle dots (odometry)
        self.history: list[tuple[float, Any, Any, Any, Any]] = []  # after each map change
        self._check, self._perceive = core.safety.check, core.on_perception
        core.safety.check = self.check
        core.on_perception = self.on_perception

    def _odometry(self) -> tuple[float, float, float]:
        p = self.core._poses
        return tuple(p[-1][1:4]) if p else (0.0, 0.0, 0.0)

    def check(self, grid, v, w, age, now_s=0.0, evidence=None, key=None, unseen=None):
        layer = self.core.safety
        sf = layer.settings
        d = self._check(grid, v, w, age, now_s, evidence, key, unseen)
        if not d.stopped or (v == 0.0 and w == 0.0) or evidence is None:
            return d
        xy, grow, _ = evidence
        u = abs(v) + abs(w) * layer.r_max_mm
        s_mm = layer._contact(xy[:, 0], xy[:, 1], grow, v, w, u)
        lead = layer._leading(xy[:, 0], xy[:, 1], s_mm, v, w, u)
        swing_mm = layer._swing_refuse_mm
        hit = (lead & (s_mm <= sf.stop_distance_mm)) | (
            ~lead & (s_mm <= sf.swing_buffer_mm + swing_mm)
        )
        reasons = [r.value for r in d.reasons]
        cells = np.zeros((0, 3))
        if "unknown_stop" in reasons:  # the never-seen cells the swing meets (as _unknown_sweep)
            if unseen is None:
                xs, ys = grid.cell_centers()
                ii, jj = np.nonzero(grid.states == CellState.UNKNOWN)
                px, py = xs[ii], ys[jj]
                h = 0.5 * grid.settings.resolution_mm * math.sqrt(2.0)
            else:  # the map's own never-seen cells, moved exactly (what the layer reads)
                if isinstance(unseen, tuple):  # (centres (N, 2), half-diagonal)
                    uxy, h = unseen
                    px, py = uxy[:, 0], uxy[:, 1]
                else:  # an UnseenCells view
                    px, py = unseen.within(-math.inf, math.inf, -math.inf, math.inf)
                    h = unseen.grow_mm
            near = np.hypot(px, py) < layer.r_max_mm + 200.0
            px, py = px[near], py[near]
            s_ext = layer._contact(px, py, h, v, w, u, False)
            # a cell the chair surely overlaps now (its trail's edge) is met by its centre
            edge = layer._rect_distance(px, py) < h / math.sqrt(2.0)
            centre = layer._contact(px[edge], py[edge], 0.0, v, w, u, False)
            s_ext[edge] = np.where(centre == 0.0, math.inf, centre)  # under it: its trail
            bad = s_ext <= swing_mm
            cells = np.column_stack([px[bad], py[bad], s_ext[bad]])
        self.stops.append(dict(t=now_s, v=v, w=w, reasons=reasons, odo=self._odometry(),
                               xy=xy[hit], grow=grow[hit], s=s_mm[hit], lead=lead[hit],
                               cells=cells))  # fmt: skip
        return d

    def on_perception(self, cloud, t_cap):
        m = self.core.map
        version = m.version
        self._perceive(cloud, t_cap)
        if m.version == version:
            return
        self.history.append((t_cap, self._odometry(), m._anchor.states.copy(),
                             m._anchor_settings, m.pose_in_anchor))  # fmt: skip
        at = self.core._pose_at(t_cap)
        obstacle = cloud.classes == PointClass.OBSTACLE
        if at is not None and np.any(obstacle):
            xy = rig_to_robot(cloud.xyz[obstacle], self.core.config.perception.rig_x_offset_mm)
            self.dots.append((t_cap, _to_world(xy, at[:3])))

    def cell_history(self, xy: np.ndarray, until_s: float) -> str:
        """The map's state at an odometry-frame point after each capture (its changes)."""
        out: list[str] = []
        last, prev = None, None
        for t, (px, py, pth), states, a, anchor in self.history:
            if t > until_s:
                break
            dx, dy = xy[0] - px, xy[1] - py
            c, sn = math.cos(pth), math.sin(pth)
            rx, ry = c * dx + sn * dy, -sn * dx + c * dy
            ax = anchor[0] + math.cos(anchor[2]) * rx - math.sin(anchor[2]) * ry
            ay = anchor[1] + math.sin(anchor[2]) * rx + math.cos(anchor[2]) * ry
            i = math.floor((ax - a.x_min_mm) / a.resolution_mm)
            j = math.floor((ay - a.y_min_mm) / a.resolution_mm)
            state = CellState(int(states[i, j])).name
            if state != last:
                moved = prev is not None and math.hypot(*anchor[:2]) < math.hypot(*prev[:2]) - 1.0
                out.append(f"{t:.2f} {state}{' (re-anchored)' if moved else ''}")
                last = state
            prev = anchor
        return ", ".join(out[-8:])

    def dots_near(
        self, xy: np.ndarray, radius_mm: float, until_s: float
    ) -> list[tuple[float, np.ndarray]]:
        """(capture time, its obstacle dots within ``radius_mm`` of ``xy``), odometry frame."""
        out = []
        for t, dots in self.dots:
            if t <= until_s:
                near = np.hypot(*(dots - xy).T) < radius_mm
                if np.any(near):
                    out.append((t, dots[near]))
        return out


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("scenario", choices=sorted(suite.SCENARIOS))
    ap.add_argument("rider", choices=suite.RIDERS)
    ap.add_argument("seed", type=int)
    ap.add_argument("--perception", default="pipeline", choices=("pipeline", "truth"))
    ap.add_argument("--set", action="append", default=[], help="safety KEY=VALUE")
    ap.add_argument("--map", action="append", default=[], help="free-space map KEY=VALUE")
    ap.add_argument(
        "--perceive-time-s",
        type=float,
        default=None,
        help="charge this much virtual time per cloud instead of perceive's wall time, so "
        "that the run is the same however loaded the machine is (SimSettings.perceive_time_s)",
    )
    args = ap.parse_args()
    trial = suite.SCENARIOS[args.scenario](args.rider, args.seed)
    changes = {k: _value(v) for k, v in (kv.split("=", 1) for kv in args.set)}
    core = suite.make_core(trial.rider, {**trial.config, **changes})
    for k, v in (kv.split("=", 1) for kv in args.map):
        kind = type(getattr(core.map.settings, k))
        core.map.settings = dataclasses.replace(core.map.settings, **{k: kind(_value(v))})
    tracer = Tracer(core)
    sim_changes = (
        None if args.perceive_time_s is None else {"perceive_time_s": args.perceive_time_s}
    )
    _, _, _, st, _ = suite.simulate(trial, core, args.perception, sim_changes)
    rects = suite._rects(trial.course)
    start = trial.course.start_pose

    def truth(xy: np.ndarray) -> np.ndarray:
        return _rect_distance(_to_world(xy, start), rects)

    def explain(xy: np.ndarray, t: float) -> None:
        print(f"      its history: {tracer.cell_history(xy, t)}")
        for tc, dots in tracer.dots_near(xy, 36.0, t):
            for p, d in zip(dots, truth(dots), strict=True):
                print(
                    f"      capture {tc:.2f}: obstacle dot ({p[0]:.0f}, {p[1]:.0f}), true {d:.1f} mm"
                )

    goal = np.flatnonzero(st[:, 2] > (trial.goal_x_mm or math.inf))
    t_end = float(st[goal[0], 0]) if len(goal) else math.inf
    print(f"{args.scenario}, {args.rider}, seed {args.seed}: through at {t_end:.2f} s; "
          f"{len(tracer.stops)} refused checks")  # fmt: skip
    last = -1.0
    for e in tracer.stops:
        if e["t"] > t_end:
            break
        first, last = e["t"] - last > 0.05, e["t"]
        if not first:
            continue
        true_pose = st[min(int(np.searchsorted(st[:, 0], e["t"] - 1e-9)), len(st) - 1), 2:5]
        pose = e["odo"]
        print(f"\n t {e['t']:.2f} s  odometry ({pose[0]:.0f}, {pose[1]:.0f}, "
              f"{math.degrees(pose[2]):.1f}°)  asked v {e['v']:.0f} mm/s ω {e['w']:.3f} rad/s  "
              f"{'+'.join(e['reasons'])}  true clearance "
              f"{suite.footprint_clearance_mm(true_pose, rects):.0f} mm")  # fmt: skip
        cells = e["cells"]
        for k in np.argsort(cells[:, 2])[:8]:
            w = _to_world(cells[k : k + 1, :2], pose)
            print(f"   never-seen cell: robot ({cells[k, 0]:.0f}, {cells[k, 1]:.0f}) swing "
                  f"{cells[k, 2]:.1f} mm, odometry ({w[0, 0]:.0f}, {w[0, 1]:.0f}), its centre "
                  f"{truth(w)[0]:.0f} mm from the nearest thing")  # fmt: skip
            explain(w[0], e["t"])
        if len(e["xy"]):
            w = _to_world(e["xy"], pose)
            d = truth(w)
            for k in np.argsort(e["s"])[:12]:
                seen = len(tracer.dots_near(w[k], 5.0, e["t"]))
                print(f"   {'lead ' if e['lead'][k] else 'swing'} at {e['s'][k]:6.1f} mm: robot "
                      f"({e['xy'][k, 0]:.0f}, {e['xy'][k, 1]:.0f}) grow {e['grow'][k]:.1f}, "
                      f"odometry ({w[k, 0]:.0f}, {w[k, 1]:.0f}), true {d[k]:.1f} mm, "
                      f"dots of {seen} captures within 5 mm")  # fmt: skip
                if e["grow"][k] > 0.0:
                    explain(w[k], e["t"])


if __name__ == "__main__":
    main()
