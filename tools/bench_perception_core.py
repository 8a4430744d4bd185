"""Benchmark: the whole ``best`` perception of one 640x480 stereo capture on ONE core.

``pipeline.perceive(capture, calib, "best")`` = subtract + detect (both cameras), match,
triangulate, classify; the goal of issue 2 is ≤ 10 ms median. The capture is rendered
(``RenderOptions.realistic()``: read + shot noise, 3 % flicker, speckled halos, ghosts) from
``ideal_lattice(30, 35, 0.07, 0.28)`` (``--laser ideal``) or a dense physical projector (default),
on the floor (1100 mm) with a 300 mm high box top in front. The calibration comes from a
rendered capture of the empty floor (``calibrate_from_capture``, another seed), so the run is
end to end. Everything runs with cv2.setNumThreads(1) and one BLAS thread.

Printed: min and median of each stage (each timed on its own, ``--repeats`` runs) and of the
whole ``perceive``; the number of points and how many are right (within 1.5 px of a true dot in
both images); the load average (the machine is shared: prefer the min, and the ratios).

Run from the repository root:  python tools/bench_perception_core.py [--repeats 50]
"""

from __future__ import annotations

import os

# One core: BLAS threads must be fixed before numpy is imported.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from omnid.core.calibration import calibrate_from_capture  # noqa: E402
from omnid.core.classify import classify  # noqa: E402
from omnid.core.detect import detect_dots  # noqa: E402
from omnid.core.geometry import StereoRig  # noqa: E402
from omnid.core.matching import match_dots  # noqa: E402
from omnid.core.pipeline import perceive  # noqa: E402
from omnid.core.triangulate import triangulate  # noqa: E402
from omnid.core.types import PointCloud  # noqa: E402
from omnid.sim.laser import LaserProjector, ideal_lattice  # noqa: E402
from omnid.sim.render import RenderOptions, render_capture  # noqa: E402


def timed(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    """(min, median) wall time of ``fn`` in ms over ``repeats`` runs after one warm-up."""
    fn()
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return 1e3 * min(out), 1e3 * statistics.median(out)


def scene_xyz(rig: StereoRig, pattern: LaserProjector) -> np.ndarray:
    """The pattern's dots on the floor, with a 300 mm high box top where 0.8 < X/Z < 1.2."""
    sl = pattern.rays().slopes()
    box = (sl[:, 0] > 0.8) & (sl[:, 0] < 1.2) & (np.abs(sl[:, 1]) < 0.3)
    depth = np.where(box, rig.floor_depth_mm - 300.0, rig.floor_depth_mm)
    return np.column_stack([sl * depth[:, None], depth])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument(
        "--laser",
        choices=["physical", "ideal"],
        default="physical",
        help="physical: a dense non-ideal projector (~850 dots); ideal: the old regular slope "
        "lattice from the frame origin, ideal_lattice(30, 35, 0.07, 0.28) (the degenerate case)",
    )
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    rig = StereoRig.nominal()
    opts = RenderOptions.realistic()
    if args.laser == "ideal":
        pattern = ideal_lattice(30, 35, 0.07, 0.28)
        xyz = scene_xyz(rig, pattern)
        laser: object = pattern
    else:
        from omnid.sim.world import Box, RigMount, World, cast_laser

        laser = LaserProjector(pitch_u=0.04, pitch_v=0.045, orders_u=(-16, 16), orders_v=(-22, 22))
        m = RigMount(height_mm=rig.floor_depth_mm)
        box = Box(m.x_offset_mm + 800, m.x_offset_mm + 1300, -400.0, 400.0, 300.0)
        hits = cast_laser(World((box,)), (0.0, 0.0, 0.0), m, laser, rig)
        xyz = hits.xyz[hits.visible1 | hits.visible2]
    try:
        from omnid.sim.installation import calibrate_installed
    except ImportError:  # an older checkout: the floor alone
        floor = render_capture(rig, laser.on_plane(rig.floor_depth_mm), opts, seed=99)  # type: ignore[attr-defined]
        calib = calibrate_from_capture(floor, rig.floor_depth_mm, rig.baseline_mm)
    else:
        calib = calibrate_installed(rig, laser, seed=99, options=opts)
    cap = render_capture(rig, xyz, opts, seed=3)

    print(
        f"python {platform.python_version()}, numpy {np.__version__}, cv2 {cv2.__version__}, "
        f"one core (cv2 threads {cv2.getNumThreads()}, BLAS threads 1), {platform.machine()}, "
        f"{os.cpu_count()} CPUs"
    )
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    cloud = perceive(cap, calib, "best")
    true_px = rig.project(xyz)
    d = np.hypot(
        cloud.pixels[:, None, 0] - true_px[None, :, 0],
        cloud.pixels[:, None, 1] - true_px[None, :, 1],
    )
    d2 = np.hypot(
        cloud.pixels[:, None, 2] - true_px[None, :, 2],
        cloud.pixels[:, None, 3] - true_px[None, :, 3],
    )
    right = int(((d < 1.5) & (d2 < 1.5)).any(axis=1).sum())
    n_vis = int(rig.visible(true_px).sum())
    print(
        f"dots cast {len(xyz)}; visible in both cameras {n_vis}; perceived points {len(cloud.xyz)}, "
        f"right {right}"
    )

    d1 = detect_dots(cap.mask1, cap.base1, "best")
    d2_ = detect_dots(cap.mask2, cap.base2, "best")
    pixels = match_dots(calib, d1, d2_, "best")
    xyz_b, cov_b = triangulate(calib.rig, pixels, "best", 0.3)
    pc = PointCloud(xyz_b, cov_b, pixels, np.zeros(len(pixels), np.uint8), calib.floor_depth_mm)
    stages: list[tuple[str, Callable[[], object]]] = [
        (
            "detect best, both cameras",
            lambda: (
                detect_dots(cap.mask1, cap.base1, "best"),
                detect_dots(cap.mask2, cap.base2, "best"),
            ),
        ),
        ("match best", lambda: match_dots(calib, d1, d2_, "best")),
        ("triangulate best", lambda: triangulate(calib.rig, pixels, "best", 0.3)),
        ("classify", lambda: classify(pc)),
        ("perceive(..., 'best') whole", lambda: perceive(cap, calib, "best")),
        ("perceive(..., 'thesis') whole", lambda: perceive(cap, calib, "thesis")),
    ]
    print(f"\n{'stage':32s} {'min ms':>8s} {'median ms':>10s}")
    for name, fn in stages:
        lo, med = timed(fn, args.repeats)
        print(f"{name:32s} {lo:8.2f} {med:10.2f}")
    print(f"\nload average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
