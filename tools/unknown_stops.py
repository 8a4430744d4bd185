"""What the clutter run's ``unknown_stop`` false stops really are (issue 13, docs/benchmarks.md).

Runs the scenario suite's ``dense clutter`` trial (:func:`omnid.sim.suite.clutter`) with the
daemon core at its default configuration and, at every control step refused with
``unknown_stop``, takes the UNKNOWN cells the refused sweep meets within the stop distance
(centres against the footprint, as :meth:`SafetyLayer.unknown_clearance` tests them) and asks,
in a 25 mm raster of the odometry frame that never forgets, where each came from:

- ``never``  never seen: no capture's floor dots surrounded it (outside the convex hull of
  every capture's floor dots), no capture marked it, the chair never stood on it;
- ``forgot`` known once in the map's own cells, UNKNOWN now: forgotten
  (``forget_after_travel_mm``), a capture's doubt (an obstacle or drop-off not yet confirmed
  overwrites what the cell held), carved;
- ``lost``   known once by the world raster (a capture marked it, or the chair's trail) but
  not by the map's own cells: resampled away at a reanchor, or off the robot grid;
- ``hole``   inside some capture's floor-dot hull yet never marked: a gap between seen dots
  that the fill (``free_max_edge_mm``) left open.

The footprint's margin plays no part in the unknown test (the module says so); a class for it
would always be empty. Only the steps that are false stops by truth (the chair at a standstill,
its outline free to move 500 mm in the asked direction with 50 mm to spare) are counted, and
events as in the suite (a run of consecutive false steps is one event).

Usage: ``python tools/unknown_stops.py [--rider joystick|tilt] [--seed 0] [--minutes 5]
[--perception truth|pipeline]``; truth perception takes about 1 min for 5 min, pipeline 5 min.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import logging
import math
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from omnid.core.freespace import FreeSpaceMap, _affine, _to_frame
from omnid.core.occupancy import CellState, OccupancyGrid, rig_to_robot
from omnid.core.types import PointClass, PointCloud
from omnid.daemon.safety import Reason, contact_path_s
from omnid.sim import suite

RES_MM = 10.0
HALF_MM = 15000.0
N = int(2 * HALF_MM / RES_MM)
Pose = tuple[float, float, float]


def _compose(a: Pose, b: Pose) -> Pose:
    x, y, t = a
    c, s = math.cos(t), math.sin(t)
    return (x + c * b[0] - s * b[1], y + s * b[0] + c * b[1], t + b[2])


def _inverse(p: Pose) -> Pose:
    x, y, t = p
    c, s = math.cos(t), math.sin(t)
    return (-c * x - s * y, s * x - c * y, -t)


def _raster(xy: NDArray[np.float64]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    i = np.clip(np.floor((xy[:, 0] + HALF_MM) / RES_MM), 0, N - 1).astype(np.intp)
    j = np.clip(np.floor((xy[:, 1] + HALF_MM) / RES_MM), 0, N - 1).astype(np.intp)
    return i, j


class WitnessMap(FreeSpaceMap):
    """The daemon's map, unchanged, that also writes what it was shown into world rasters."""

    def __init__(self, settings: Any, core: Any) -> None:
        super().__init__(settings)
        self.core = core
        self.seen = np.zeros((N, N), np.uint8)  # a capture marked it
        self.trail = np.zeros((N, N), np.uint8)  # the chair stood on it
        self.hull = np.zeros((N, N), np.uint8)  # inside a capture's floor-dot hull
        self.ever = np.zeros(self._anchor.states.shape, np.uint8)  # anchor cells ever known

    def _remember(self) -> None:
        self.ever |= (self._anchor.states != CellState.UNKNOWN).astype(np.uint8)

    def _reanchor(self) -> None:
        a = self._anchor_settings
        M = _affine(self.pose_in_anchor, a, a)
        flags = cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP
        self.ever = cv2.warpAffine(self.ever, M, self.ever.shape[::-1], flags=flags)
        super()._reanchor()

    def ever_known(self, xy_robot_mm: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Whether the anchor cell under each robot-frame point was ever known (resampled with
        the map at each reanchor, as its cells are)."""
        g = OccupancyGrid(self._anchor_settings)
        i, j, inside = g.cell_index(_to_frame(self.pose_in_anchor, xy_robot_mm))
        return inside & (self.ever[i, j] > 0)

    def _anchor_in_world(self) -> Pose:
        odo = tuple(float(v) for v in self.core.odometry.pose)
        return _compose((odo[0], odo[1], odo[2]), _inverse(self.pose_in_anchor))

    def _stamp(self, layer: NDArray[np.uint8]) -> None:
        a = self._anchor_settings
        ii, jj = np.nonzero(self._seen_travel == self.travel_mm)
        q = 0.25 * a.resolution_mm  # the cell's inner half, so a pixel marked lies in the cell
        for dx, dy in ((u * q, w * q) for u in (-1, 0, 1) for w in (-1, 0, 1)):
            xy = np.column_stack([a.x_min_mm + (ii + 0.5) * a.resolution_mm + dx,
                                  a.y_min_mm + (jj + 0.5) * a.resolution_mm + dy])  # fmt: skip
            layer[_raster(_to_frame(self._anchor_in_world(), xy))] = 1

    def update(
        self,
        cloud: PointCloud,
        rig_x_offset_mm: float = 0.0,
        now_s: float | None = None,
        source_mm: tuple[float, float, float] | None = None,
    ) -> None:
        self._seen_travel[self._seen_travel == self.travel_mm] -= 1e-6  # this capture's own
        super().update(cloud, rig_x_offset_mm, now_s, source_mm)
        self._remember()
        self._stamp(self.seen)
        floor = cloud.classes == PointClass.FLOOR
        if floor.sum() >= 3:
            xy = _to_frame(self.pose_in_anchor, rig_to_robot(cloud.xyz[floor], rig_x_offset_mm))
            i, j = _raster(_to_frame(self._anchor_in_world(), xy))
            cv2.fillConvexPoly(
                self.hull, cv2.convexHull(np.column_stack([j, i]).astype(np.int32)), 1
            )

    def occupy(self, x0_mm: float, x1_mm: float, y0_mm: float, y1_mm: float) -> int:
        n = super().occupy(x0_mm, x1_mm, y0_mm, y1_mm)
        if n:
            self._remember()
            self._stamp(self.trail)
        return n


def unseen_hits(core: Any, grid: OccupancyGrid, v: float, w: float) -> NDArray[np.float64]:
    """Robot-frame centres (M, 2) of the UNKNOWN cells (off the grid included) the sweep (v, ω)
    meets within the stop distance, outside the blind band."""
    sf = core.safety
    s = sf.settings
    res = grid.settings.resolution_mm
    u = abs(v) + abs(w) * sf.r_max_mm
    g = grid.settings
    xs = g.x_min_mm + (np.arange(math.floor((-2000 - g.x_min_mm) / res),
                                 math.ceil((2000 - g.x_min_mm) / res)) + 0.5) * res  # fmt: skip
    ys = g.y_min_mm + (np.arange(math.floor((-2000 - g.y_min_mm) / res),
                                 math.ceil((2000 - g.y_min_mm) / res)) + 0.5) * res  # fmt: skip
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    p = np.column_stack([X.ravel(), Y.ravel()])
    p = p[grid.state_at(p) == CellState.UNKNOWN]
    body = (sf._fx0, sf._fx1, sf._fy0, sf._fy1)
    hit = contact_path_s(p[:, 0], p[:, 1], v, w, body, u, s.horizon_mm)
    ok = (hit > 0.0) & (hit <= s.stop_distance_mm)
    if v > 0 and s.front_blind_mm > 0:
        h = res * math.sqrt(0.5)
        blind = (p[:, 0] > sf._fx1) & (p[:, 0] <= sf._x1 + s.front_blind_mm + h)
        ok &= ~(blind & (np.abs(p[:, 1]) <= sf._y1 + h))
    return p[ok]


def classify(core: Any, grid: OccupancyGrid, v: float, w: float) -> collections.Counter[str]:
    """Counts of ``never`` / ``lost`` / ``hole`` among the unseen cells the sweep (v, ω) meets."""
    m: WitnessMap = core.map
    p = unseen_hits(core, grid, v, w)
    odo = tuple(float(q) for q in core.odometry.pose)
    i, j = _raster(_to_frame((odo[0], odo[1], odo[2]), p))
    forgot = m.ever_known(p)
    lost = ~forgot & ((m.seen[i, j] > 0) | (m.trail[i, j] > 0))
    hole = ~forgot & ~lost & (m.hull[i, j] > 0)
    names = np.where(forgot, "forgot", np.where(lost, "lost", np.where(hole, "hole", "never")))
    return collections.Counter(names.tolist())


def run(
    rider: str,
    seed: int,
    minutes: float,
    perception: str,
    map_changes: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """One clutter trial with the witness map (``map_changes``: FreeSpaceSettings fields); the
    classes of its false unknown stops."""
    logging.disable(logging.WARNING)
    trial = suite.clutter(rider, seed, minutes * 60.0)  # type: ignore[arg-type]
    core = suite.make_core(rider)  # type: ignore[arg-type]
    fs = dataclasses.replace(core.config.freespace, **(map_changes or {}))
    core.map = WitnessMap(fs, core)
    refused: list[tuple[float, collections.Counter[str], float]] = []
    check = core.safety.check

    def witnessed(grid: OccupancyGrid, v: float, w: float, *args: Any) -> Any:
        d = check(grid, v, w, *args)
        if Reason.UNKNOWN_STOP in d.reasons:
            refused.append((args[1] if len(args) > 1 else 0.0, classify(core, grid, v, w),
                            core.path_mm))  # fmt: skip
        return d

    core.safety.check = witnessed
    _, result, trace, st, wall = suite.simulate(trial, core, perception)
    false = suite.false_stop_steps(trace, st, suite._outline(suite._rects(trial.course)), core)
    events: collections.Counter[str] = collections.Counter()
    cells: collections.Counter[str] = collections.Counter()
    early = 0
    last_k = -2
    for now, counts, path_mm in refused:
        k = min(int(np.searchsorted(st[:, 0], now - 1e-9)), len(st) - 1)
        if not false[k]:
            continue
        cells.update(counts)
        if k > last_k + 1:  # a new event
            events["+".join(sorted(counts)) or "none"] += 1
            early += path_mm < 1000.0
        last_k = k
    return {"rider": rider, "seed": seed, "perception": perception, "minutes": minutes,
            "events": dict(events), "cells": dict(cells), "early": early,
            "distance_m": result.distance_mm / 1000.0, "wall_s": wall}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rider", choices=("joystick", "tilt"), default="joystick")
    ap.add_argument("--seed", type=int, nargs="+", default=[0])
    ap.add_argument("--minutes", type=float, default=5.0)
    ap.add_argument("--perception", choices=("truth", "pipeline"), default="truth")
    ap.add_argument("--set-map", action="append", default=[], metavar="KEY=VALUE",
                    help="a freespace setting for the run (forget_after_travel_mm=0)")  # fmt: skip
    a = ap.parse_args()
    changes = {k: float(v) for k, v in (kv.split("=", 1) for kv in a.set_map)}
    for seed in a.seed:
        r = run(a.rider, seed, a.minutes, a.perception, changes)
        n = sum(r["events"].values())
        print(f"{r['rider']} seed {seed} {r['perception']} {r['minutes']:g} min: {n} false "
              f"unknown stops ({10 * n / r['minutes']:.0f} per 10 min), by the classes of the "
              f"cells they met {r['events']}; cells {r['cells']}; {r['early']} before the chair "
              f"had driven 1 m; driven {r['distance_m']:.1f} m; wall {r['wall_s']:.0f} s",
              flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
