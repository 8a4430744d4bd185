"""Benchmark of the map path: ray casting, classification, free-space update and motion.

    python tools/bench_map.py [--points 1500] [--repeats 50]

Runs on one core (BLAS and OpenCV threads pinned to 1) and prints the minimum and the median
wall time of N calls in ms (the minimum is the figure least disturbed by other load on the
machine; the load average is printed too), each with its ratio to a reference measured in the
same run: the thesis-style map — marking only the cells under the dots (``OccupancyGrid.mark``
per class), no free-area filling, no memory. ``FreeSpaceMap.update`` is measured both ways:
neighbours from the laser lattice (the default) and from a Delaunay triangulation (the method it
replaced, still the fallback).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import math  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402

import cv2  # noqa: E402

from omnid.core.classify import classify, with_classes  # noqa: E402
from omnid.core.freespace import FreeSpaceMap, FreeSpaceSettings  # noqa: E402
from omnid.core.geometry import StereoRig  # noqa: E402
from omnid.core.occupancy import CellState, OccupancyGrid, rig_to_robot  # noqa: E402
from omnid.core.types import PointClass  # noqa: E402
from omnid.sim import scenes  # noqa: E402
from omnid.sim.laser import ideal_lattice  # noqa: E402
from omnid.sim.world import cast_laser, observe  # noqa: E402


def timed_ms(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    """(minimum, median) wall time of ``repeats`` calls, ms."""
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * min(times), 1e3 * statistics.median(times)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=1500, help="laser rays (approximately)")
    ap.add_argument("--repeats", type=int, default=50)
    args = ap.parse_args()
    cv2.setNumThreads(1)

    cols = 51
    rows = max(1, round(args.points / cols))
    pattern = ideal_lattice(rows=rows, cols=cols, step_slope=0.06, forward_min_slope=0.3)
    rig = StereoRig.nominal()
    sc = scenes.three_boxes()
    hits = cast_laser(sc.world, sc.pose, sc.mount, pattern, rig)
    cloud, _ = observe(hits, rig, 0.2, 0, sc.mount.height_mm)
    cloud = with_classes(cloud)
    off = sc.mount.x_offset_mm
    print(f"scene three_boxes, {len(hits)} rays, {len(cloud)} points seen by both mirrors")

    def reference() -> None:
        g = OccupancyGrid()
        xy = rig_to_robot(cloud.xyz, off)
        for cls, state in (
            (PointClass.FLOOR, CellState.FREE),
            (PointClass.DROPOFF, CellState.DROPOFF),
            (PointClass.OBSTACLE, CellState.OBSTACLE),
        ):
            g.mark(xy[cloud.classes == cls], state)

    fmap = FreeSpaceMap()
    fmap.update(cloud, off)
    dmap = FreeSpaceMap(FreeSpaceSettings(neighbours="delaunay"))

    def update() -> None:
        fmap.update(cloud, off, now_s=time.monotonic())

    def update_delaunay() -> None:
        dmap.update(cloud, off, now_s=time.monotonic())

    # A drive through the scene: 25 mm and 0.01 rad per capture, so boxes occlude other rays in
    # every capture and the map must rebuild its lattice strips each time.
    drive = []
    for k in range(40):
        h = cast_laser(sc.world, (k * 25.0, 0.0, 0.01 * k), sc.mount, pattern, rig)
        drive.append(with_classes(observe(h, rig, 0.2, k, sc.mount.height_mm)[0]))
    step = iter(range(10**9))
    drive_map = FreeSpaceMap()

    def update_driving() -> None:
        drive_map.update(drive[next(step) % len(drive)], off, now_s=time.monotonic())

    def move_small() -> None:
        fmap.move(10.0, 0.0, 0.01)
        fmap.move(-10.0, 0.0, -0.01)

    def move_reanchor() -> None:
        fmap.move(1200.0, 0.0, 0.3)  # beyond reanchor_distance_mm: resamples the grid
        fmap.move(0.0, 0.0, -0.3)
        fmap.move(-1200.0, 0.0, 0.0)

    def update_and_move() -> None:
        update()
        fmap.move(10.0, 0.0, 0.01)

    def grid_view() -> None:
        fmap.move(1.0, 0.0, 0.0)  # invalidates the cached robot-frame grid
        _ = fmap.grid

    def corridor() -> None:
        fmap.nearest_blocking_distance_mm(350.0, 3000.0, curvature_per_mm=1.0 / 2000.0)

    n = args.repeats
    ref = timed_ms(reference, n)
    rows_out = [
        ("reference: mark dot cells only", ref),
        ("cast_laser", timed_ms(lambda: cast_laser(sc.world, sc.pose, sc.mount, pattern, rig), n)),
        ("observe (noise + triangulate + cov)", timed_ms(lambda: observe(hits, rig, 0.2, 0), n)),
        ("classify", timed_ms(lambda: classify(cloud), n)),
        ("FreeSpaceMap.update (lattice, strips kept)", timed_ms(update, n)),
        ("FreeSpaceMap.update (lattice, driving)", timed_ms(update_driving, n)),
        ("FreeSpaceMap.update (delaunay)", timed_ms(update_delaunay, n)),
        ("FreeSpaceMap.move x2 (small)", timed_ms(move_small, n)),
        ("FreeSpaceMap.move x3 (one re-anchor)", timed_ms(move_reanchor, n)),
        ("update + move", timed_ms(update_and_move, n)),
        ("grid view (resample to robot frame)", timed_ms(grid_view, n)),
        ("nearest_blocking_distance_mm (arc, 3 m)", timed_ms(corridor, n)),
    ]
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores, {n} calls each")
    print(f"{'step':44s} {'min ms':>8s} {'median ms':>10s} {'x ref (min)':>12s}")
    for name, (lo, med) in rows_out:
        ratio = lo / ref[0] if ref[0] > 0 and math.isfinite(lo) else float("nan")
        print(f"{name:44s} {lo:8.3f} {med:10.3f} {ratio:12.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
