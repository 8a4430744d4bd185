"""Throughput of triangulation (points/s) for both methods, against a reference in the same run.

    python tools/bench_triangulation.py [--points N] [--repeats R]

The reference is the bare projection ``StereoRig.project`` of the same points (the cheapest
vectorised numpy pass over them), so the ratios say how many projections one triangulation
costs, whatever the machine. A per-point Python loop of the ``best`` method is timed too, to show
what vectorisation buys.
"""

from __future__ import annotations

import argparse
import platform
import time
from collections.abc import Callable

import numpy as np

from omnid.core.geometry import StereoRig
from omnid.core.triangulate import ray_residual_px, triangulate


def _best_of(fn: Callable[[], object], repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=100_000)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    n = args.points
    rig = StereoRig.nominal()
    P = np.column_stack(
        [rng.uniform(200, 2000, n), rng.uniform(-1500, 1500, n), rng.uniform(400, 1100, n)]
    )
    px = rig.project(P) + rng.normal(0.0, 0.3, (n, 4))

    t_ref = _best_of(lambda: rig.project(P), args.repeats)
    rows = [("reference: StereoRig.project", t_ref, n)]
    for method in ("thesis", "best"):
        t = _best_of(lambda m=method: triangulate(rig, px, method=m), args.repeats)
        rows.append((f"triangulate method={method} (xyz + cov)", t, n))
    rows.append(("ray_residual_px", _best_of(lambda: ray_residual_px(rig, px), args.repeats), n))
    m = min(n, 2000)
    t_loop = _best_of(lambda: [triangulate(rig, px[i], method="best") for i in range(m)], 3)
    rows.append(("best, one call per point (Python loop)", t_loop, m))

    print(
        f"machine: {platform.machine()}, {platform.python_implementation()} "
        f"{platform.python_version()}, numpy {np.__version__}; {n} points, best of "
        f"{args.repeats}"
    )
    print(f"{'what':45s} {'points/s':>14s} {'x reference time':>18s}")
    ref_rate = n / t_ref
    for name, t, count in rows:
        rate = count / t
        print(f"{name:45s} {rate:14,.0f} {ref_rate / rate:18.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
