"""Benchmark: matching + triangulation + grid update of ~1500 laser dots (target ≤ 5 ms).

A dense lattice (30 x 50 rays, slope step 0.06) on the floor with a box top 300 mm high is
projected into a misaligned rig, pixel noise σ = 0.2 px added, and the calibration is built from
the true rig (so the figures time the algorithms, not calibration quality). Each camera keeps
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

from omnid.core.calibration import Calibration, LaserLattice
from omnid.core.classify import classify
from omnid.core.freespace import FreeSpaceMap
from omnid.core.matching import fit_thesis_polynomials, match_dots
from omnid.core.triangulate import triangulate
from omnid.core.types import PointCloud
from omnid.sim.laser import ideal_lattice
from omnid.sim.rigs import misaligned_rig


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
    pat = ideal_lattice(rows=30, cols=51, step_slope=0.06, forward_min_slope=0.24)
    sl = pat.rays().slopes()
    box = (sl[:, 0] > 0.8) & (sl[:, 0] < 1.2) & (np.abs(sl[:, 1]) < 0.3)
    depth = np.where(box, H - 300.0, H)
    xyz = np.column_stack([sl * depth[:, None], depth])
    px = rig.project(xyz)
    rng = np.random.default_rng(0)
    noisy = px + rng.normal(0, 0.2, px.shape)
    # each camera shows the dots inside its own mirror disk (as a real capture does)
    in1 = rig.cam1.in_disk(px[:, :2], margin_px=2.0)
    in2 = rig.cam2.in_disk(px[:, 2:], margin_px=2.0)
    floor_px = rig.project(pat.on_plane(H))
    floor_px = floor_px[rig.visible(floor_px)]
    poly = fit_thesis_polynomials(floor_px, floor_px[:, :2], floor_px[:, 2:])
    lat = LaserLattice(0.24, 0.06, -0.06 * 25, 0.06, (0, 29), (0, 50))
    # the dots' scatter (0.2 px) as a calibration measures it (the best matcher's label walk
    # is as strict as that scatter allows)
    calib = Calibration(
        rig, poly.row_coeffs, poly.col_coeffs, floor_px, lat, residuals={"row_rms_px": 0.2}
    )
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
