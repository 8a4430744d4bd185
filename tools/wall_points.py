"""Where the obstacle points beside a wall lie: perception's error, or the map's (odometry).

Runs scenario-suite trials (``omnid.sim.suite.SCENARIOS``) with pipeline perception and
measures, against the simulator's true boxes, the distance of each obstacle point from the
nearest box outline (0 on a face; a point inside a box counts by its distance to the face):

* **perceived**: every cloud's obstacle points placed in the world by the chair's *true* pose at
  capture — what perception alone got wrong;
* **map**: the points the daemon's map keeps at the end of the run (robot frame by its odometry
  pose) placed by the chair's true pose at the end — what the safety layer acts on, with the
  odometry's drift since each point was entered.

A "phantom on a wall" that is a map point off the wall but a perceived point on it is the
odometry's doing, not the matcher's. Prints counts, the share beyond 15 and 50 mm, the worst,
and the odometry's final position and heading error.

    python tools/wall_points.py [--seeds 3] [--trials "along a wall at 150 mm" "doorway 850 mm"]
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math

import numpy as np
from numpy.typing import NDArray

from omnid.core.types import PointClass
from omnid.sim.suite import SCENARIOS, make_core, simulate


def outline_distance_mm(xy: NDArray[np.float64], rects: NDArray[np.float64]) -> NDArray[np.float64]:
    """Distance (mm) of points (N, 2) from the nearest outline of rectangles (R, 4: x0 x1 y0 y1)."""
    if len(xy) == 0 or len(rects) == 0:
        return np.full(len(xy), math.inf)
    x, y = xy[:, 0, None], xy[:, 1, None]
    x0, x1, y0, y1 = (rects[None, :, k] for k in range(4))
    ex = np.maximum(np.maximum(x0 - x, x - x1), 0.0)
    ey = np.maximum(np.maximum(y0 - y, y - y1), 0.0)
    outside = np.hypot(ex, ey)
    inside = np.minimum(np.minimum(x - x0, x1 - x), np.minimum(y - y0, y1 - y))
    d = np.where((ex == 0.0) & (ey == 0.0), inside, outside)
    return np.asarray(d.min(axis=1), dtype=np.float64)


def run(name: str, kind: str, seed: int, register_mm: float | None = None) -> dict[str, float]:
    trial = SCENARIOS[name](kind, seed)  # type: ignore[arg-type]
    core = make_core(trial.rider, dict(trial.config))
    if register_mm is not None:  # the map's cloud registration (freespace.register_max_step_mm)
        core.map.settings = dataclasses.replace(core.map.settings, register_max_step_mm=register_mm)
    sim, result, *_ = simulate(
        trial,
        core,
        "pipeline",
        {"record_seen": True, "worker_period_s": 0.1, "perceive_time_s": 0.01},
    )
    w = trial.course.world
    rects = np.array(
        [(b.x_min_mm, b.x_max_mm, b.y_min_mm, b.y_max_mm) for b in w.boxes if b.height_mm >= 15.0]
    ).reshape(-1, 4)
    seen = result.seen
    obstacle = seen[seen[:, 2] == PointClass.OBSTACLE]
    d_seen = outline_distance_mm(obstacle[:, :2], rects)
    px, py, th = sim.chair.pose
    robot = core.map.obstacle_points
    c, s = math.cos(th), math.sin(th)
    world = np.column_stack([px + c * robot[:, 0] - s * robot[:, 1],
                             py + s * robot[:, 0] + c * robot[:, 1]])  # fmt: skip
    d_map = outline_distance_mm(world, rects)
    ox, oy, oth = core.odometry.pose
    return {
        "seen": len(d_seen),
        "seen>15": int((d_seen > 15.0).sum()),
        "seen>50": int((d_seen > 50.0).sum()),
        "seen max": float(d_seen.max()) if len(d_seen) else 0.0,
        "map": len(d_map),
        "map>15": int((d_map > 15.0).sum()),
        "map>50": int((d_map > 50.0).sum()),
        "map max": float(d_map.max()) if len(d_map) else 0.0,
        "drift mm": math.hypot(px - ox, py - oy),
        "drift deg": math.degrees(abs(math.remainder(th - oth, 2 * math.pi))),
        "contacts": len(result.collisions),
        "registered": core.map.registrations["applied"],
        "refused": core.map.registrations["too large"],
        "few pairs": core.map.registrations["too few pairs"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument(
        "--register-mm",
        type=float,
        default=None,
        help="freespace.register_max_step_mm for the runs (default: as configured)",
    )
    ap.add_argument("--kinds", nargs="+", default=["joystick", "tilt"])
    ap.add_argument("--trials", nargs="+", default=["along a wall at 150 mm", "doorway 850 mm"])
    args = ap.parse_args()
    logging.getLogger("omnid").setLevel(logging.ERROR)
    total: dict[str, float] = {}
    for name in args.trials:
        for kind in args.kinds:
            for seed in range(args.seeds):
                r = run(name, kind, seed, args.register_mm)
                for k, v in r.items():
                    total[k] = (
                        max(total.get(k, 0.0), v)
                        if "max" in k or "drift" in k
                        else (total.get(k, 0.0) + v)
                    )
                print(f"{name:24s} {kind:8s} seed {seed}: "
                      f"perceived {r['seen']:5d} pts, >15 mm {r['seen>15']:3d}, >50 mm "
                      f"{r['seen>50']:3d}, worst {r['seen max']:5.0f} mm | map {r['map']:4d} pts, "
                      f">15 mm {r['map>15']:3d}, >50 mm {r['map>50']:3d}, worst "
                      f"{r['map max']:5.0f} mm | odometry off {r['drift mm']:4.0f} mm "
                      f"{r['drift deg']:4.1f} deg | clouds registered {r['registered']}, "
                      f"refused {r['refused']}, too few pairs {r['few pairs']}", flush=True)  # fmt: skip
    print(f"all: perceived {total['seen']:.0f} pts, >15 mm {total['seen>15']:.0f}, >50 mm "
          f"{total['seen>50']:.0f}, worst {total['seen max']:.0f} mm | map {total['map']:.0f} pts, "
          f">15 mm {total['map>15']:.0f}, >50 mm {total['map>50']:.0f}, worst "
          f"{total['map max']:.0f} mm | odometry off up to {total['drift mm']:.0f} mm "
          f"{total['drift deg']:.1f} deg; contacts {total['contacts']:.0f}")  # fmt: skip


if __name__ == "__main__":
    main()
