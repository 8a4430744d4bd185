"""Benchmark: matching + triangulation + grid update of ~1500 laser dots (target ≤ 5 ms).

A dense physical laser (finer grating than the simulator's default) on the floor with a box top
300 mm high is ray-cast into a misaligned rig, pixel noise σ = 0.05 px added; the calibration is
the installer's (floor + extras, rendered).  Each camera keeps
the dots inside its own mirror disk. Reported: minimum and median wall time of each stage over
``--repeat`` runs, one thread, and the ratio of each stage's minimum to that of a reference
measured in the same run (a plain numpy N×M distance matrix of the same dots, the cost
of the most naive nearest-neighbour matcher).

Run:  python tools/bench_perception.py [--repeat 50]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable

import numpy as np

from omnid.core.classify import classify
from omnid.core.freespace import FreeSpaceMap
from omnid.core.matching import match_dots
from omnid.core.triangulate import triangulate
from omnid.core.types import PointCloud
from omnid.experiments.scenes import misaligned_rig
from omnid.sim.installation import calibrate_installed
from omnid.sim.laser import LaserProjector
from omnid.sim.world import Box, RigMount, World, cast_laser

#: A dense physical laser (~1400 beams): finer grating pitch than the simulator's default.
DENSE_LASER = LaserProjector(pitch_u=0.035, pitch_v=0.04, orders_u=(-16, 16), orders_v=(-22, 22))


def timed(fn: Callable[[], object], repeat: int) -> tuple[float, float]:
    """(minimum, median) wall time of ``fn`` over ``repeat`` runs, ms."""
    fn()
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return 1e3 * min(out), 1e3 * statistics.median(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeat", type=int, default=50)
    args = ap.parse_args(argv)
    rig = misaligned_rig()
    H = rig.floor_depth_mm
    laser = DENSE_LASER
    calib = calibrate_installed(rig, laser, seed=0)
    m = RigMount(height_mm=H)
    box = Box(m.x_offset_mm + 800, m.x_offset_mm + 1300, -400.0, 400.0, 300.0)
    hits = cast_laser(World((box,)), (0.0, 0.0, 0.0), m, laser, rig)
    xyz = hits.xyz
    px = rig.project(xyz)
    rng = np.random.default_rng(0)
    noisy = px + rng.normal(0, 0.05, px.shape)
    # each camera shows the dots inside its own mirror disk (as a real capture does)
    in1 = hits.visible1 & rig.cam1.in_disk(px[:, :2], margin_px=2.0)
    in2 = hits.visible2 & rig.cam2.in_disk(px[:, 2:], margin_px=2.0)
    strength = np.full((len(noisy), 1), 100.0)
    d1 = np.hstack([noisy[in1, :2], strength[in1]])
    d2 = np.hstack([noisy[in2, 2:], strength[in2]])
    rng.shuffle(d2)
    n = int((in1 & in2).sum())
    best = match_dots(calib, d1, d2, "best")
    thesis = match_dots(calib, d1, d2, "thesis")
    xyz_b, cov_b = triangulate(rig, best, "best")
    cloud = PointCloud(xyz_b, cov_b, best, np.zeros(len(best), np.uint8), H)
    classes = classify(cloud)
    cloud = PointCloud(xyz_b, cov_b, best, classes, H)
    fmap = FreeSpaceMap()

    ref = timed(
        lambda: np.hypot(d1[:, None, 0] - d2[None, :, 0], d1[:, None, 1] - d2[None, :, 1]),
        args.repeat,
    )
    t_best = timed(lambda: match_dots(calib, d1, d2, "best"), args.repeat)
    t_thesis = timed(lambda: match_dots(calib, d1, d2, "thesis"), args.repeat)
    t_tri = timed(lambda: triangulate(rig, best, "best"), args.repeat)
    t_cls = timed(lambda: classify(cloud), args.repeat)
    t_map = timed(lambda: fmap.update(cloud, 300.0), args.repeat)
    total = tuple(a + b + c + d for a, b, c, d in zip(t_best, t_tri, t_cls, t_map, strict=True))
    print(
        f"dots: {len(d1)} / {len(d2)} in camera 1 / 2, {n} seen by both; "
        f"best matched {len(best)}, thesis matched {len(thesis)}"
    )
    print(f"reference (N x M distance matrix): min {ref[0]:.2f} ms, median {ref[1]:.2f} ms")
    print(f"{'stage':40s} {'min ms':>8s} {'median ms':>10s}  min / reference min")
    for name, t in (
        ("match best", t_best),
        ("match thesis", t_thesis),
        ("triangulate best", t_tri),
        ("classify", t_cls),
        ("grid update", t_map),
        ("best: match+triangulate+classify+grid", total),
    ):
        print(f"{name:40s} {t[0]:8.2f} {t[1]:10.2f}  {t[0] / ref[0]:6.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
