"""Benchmark: the whole ``best`` perception of one 640x480 stereo capture on ONE core.

``pipeline.perceive(capture, calib, "best")`` = subtract + detect (both cameras), match,
triangulate, classify; the goals: ≤ 10 ms per frame pair (issue 11) and no slower than the
thesis-era pipeline on the same captures (issue 9). Two lasers, each on the floor (1100 mm) with
a 300 mm high box 800–1300 mm ahead: the default physical projector (``LaserProjector()``, ~190
dots seen by both cameras) and a dense one (pitch 0.032 × 0.036, ~840 dots). Captures are rendered
with ``RenderOptions.realistic()`` (read + shot noise, 3 % flicker, speckled halos, ghosts); the
calibration comes from the simulated installer's captures (floor + extras, other seeds), so the
run is end to end. Everything runs with cv2.setNumThreads(1) and one BLAS thread.

Printed per laser: median and p90 (and min) of each stage (each timed on its own over
``--repeats`` runs, called as ``pipeline.perceive_detailed`` calls it: ``match_triples`` and
``triangulate_on_beams``), what the whole ``perceive`` spends beyond them (min − the stages'
mins), and of the whole ``perceive``, next to the same-run reference: the thesis
pipeline (``perceive(..., "thesis")``) and, with ``--old-root DIR`` (a checkout of the thesis-era
omnid, e.g. ``git archive 80b18a4 | tar -x -C DIR``), that checkout's ``best`` on the same
captures (its own floor calibration, in a subprocess); the number of points and how many are
right (within 1.5 px of a true dot in both images); the load average (the machine may be shared:
prefer the ratios).

With ``--split-blends``, also the whole ``perceive`` with the detector's experimental blend split
(``detect._split_blends``) against the default, interleaved run by run in this process (same
captures, same calibration), and how many points each gets right.

Run from the repository root:  python tools/bench_perception_core.py [--repeats 50] [--split-blends]
"""

from __future__ import annotations

import os

# One core: BLAS threads must be fixed before numpy is imported.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from omnid.core.classify import classify  # noqa: E402
from omnid.core.detect import detect_dots  # noqa: E402
from omnid.core.geometry import StereoRig  # noqa: E402
from omnid.core.matching import _tracks, match_triples  # noqa: E402
from omnid.core.pipeline import perceive  # noqa: E402
from omnid.core.triangulate import triangulate_on_beams  # noqa: E402
from omnid.core.types import PointCloud, StereoCapture  # noqa: E402
from omnid.experiments.machine import load_average, one_core  # noqa: E402
from omnid.sim.installation import calibrate_installed  # noqa: E402
from omnid.sim.laser import LaserProjector  # noqa: E402
from omnid.sim.render import RenderOptions, render_capture  # noqa: E402


def timed(fn: Callable[[], object], repeats: int) -> tuple[float, float, float]:
    """(min, median, p90) wall time of ``fn`` in ms over ``repeats`` runs after one warm-up."""
    fn()
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    ms = 1e3 * np.array(out)
    return float(ms.min()), float(np.median(ms)), float(np.percentile(ms, 90))


LASERS = {
    "default": lambda: LaserProjector(),
    "dense": lambda: LaserProjector(
        pitch_u=0.032, pitch_v=0.036, orders_u=(-24, 24), orders_v=(-30, 30)
    ),
}


def scene(rig: StereoRig, laser: LaserProjector) -> np.ndarray:
    """The laser's dots (seen by either camera) on the floor with a 300 mm high box ahead."""
    from omnid.sim.world import Box, RigMount, World, cast_laser

    m = RigMount(height_mm=rig.floor_depth_mm)
    box = Box(m.x_offset_mm + 800, m.x_offset_mm + 1300, -400.0, 400.0, 300.0)
    hits = cast_laser(World((box,)), (0.0, 0.0, 0.0), m, laser, rig)
    return hits.xyz[hits.visible1 | hits.visible2]


_OLD_BEST = """
import os, sys, time, json
for v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[v] = "1"
sys.path.insert(0, sys.argv[1])
import cv2, numpy as np
cv2.setNumThreads(1)
from omnid.core.calibration import calibrate_from_capture
from omnid.core.pipeline import perceive
from omnid.core.types import StereoCapture
z = np.load(sys.argv[2])
cap = lambda p: StereoCapture(z[p + "m1"], z[p + "b1"], z[p + "m2"], z[p + "b2"])
calib = calibrate_from_capture(cap("floor_"), float(z["H"]), float(z["B"]))
c = cap("")
perceive(c, calib, "best")
out = []
for _ in range(int(sys.argv[3])):
    t0 = time.perf_counter(); cloud = perceive(c, calib, "best"); out.append(time.perf_counter() - t0)
ms = 1e3 * np.array(out)
print(json.dumps([float(ms.min()), float(np.median(ms)), float(np.percentile(ms, 90)), len(cloud.xyz)]))
"""


def old_best(
    old_root: str, rig: StereoRig, floor: StereoCapture, cap: StereoCapture, repeats: int
) -> tuple[float, float, float, int] | str:
    """(min, median, p90 ms, points) of ``old_root``'s ``best`` on ``cap``, or why not."""
    import json
    import subprocess
    import sys
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "caps.npz")
        arrays = {"H": np.array(rig.floor_depth_mm), "B": np.array(rig.baseline_mm)}
        for prefix, c in (("floor_", floor), ("", cap)):
            arrays.update(
                {prefix + "m1": c.mask1, prefix + "b1": c.base1}
                | {prefix + "m2": c.mask2, prefix + "b2": c.base2}
            )
        np.savez(path, **arrays)  # type: ignore[arg-type]
        res = subprocess.run(
            [sys.executable, "-c", _OLD_BEST, old_root, path, str(repeats)],
            capture_output=True,
            text=True,
            timeout=600,
        )
    if res.returncode != 0:
        return (res.stderr.strip().splitlines() or ["failed"])[-1]
    lo, med, p90, n = json.loads(res.stdout.strip().splitlines()[-1])
    return lo, med, p90, int(n)


def interleaved(
    fa: Callable[[], object], fb: Callable[[], object], repeats: int
) -> tuple[tuple[float, float], tuple[float, float]]:
    """((min, median) of fa, (min, median) of fb) in ms, the two called in turn ``repeats``
    times each after one warm-up each (the machine's load falls on both alike)."""
    fa()
    fb()
    ta: list[float] = []
    tb: list[float] = []
    for _ in range(repeats):
        for fn, out in ((fa, ta), (fb, tb)):
            t0 = time.perf_counter()
            fn()
            out.append(time.perf_counter() - t0)
    a, b = 1e3 * np.array(ta), 1e3 * np.array(tb)
    return (float(a.min()), float(np.median(a))), (float(b.min()), float(np.median(b)))


def right_points(rig: StereoRig, xyz: np.ndarray, cloud: PointCloud) -> int:
    """Points of ``cloud`` within 1.5 px of a true dot in both images."""
    true_px = rig.project(xyz)
    d = np.hypot(
        cloud.pixels[:, None, 0] - true_px[None, :, 0],
        cloud.pixels[:, None, 1] - true_px[None, :, 1],
    )
    d2 = np.hypot(
        cloud.pixels[:, None, 2] - true_px[None, :, 2],
        cloud.pixels[:, None, 3] - true_px[None, :, 3],
    )
    return int(((d < 1.5) & (d2 < 1.5)).any(axis=1).sum())


def bench_split(rig: StereoRig, xyz: np.ndarray, cap: StereoCapture, calib, repeats: int) -> None:
    """The whole ``perceive`` with the experimental blend split against without, interleaved."""
    import functools

    from omnid.core import detect

    plain = detect._detect_best
    split = functools.partial(plain, split_blends=True)

    def run(fn: Callable[..., np.ndarray]) -> Callable[[], PointCloud]:
        def go() -> PointCloud:
            detect._detect_best = fn
            try:
                return perceive(cap, calib, "best")
            finally:
                detect._detect_best = plain

        return go

    (s_lo, s_med), (p_lo, p_med) = interleaved(run(split), run(plain), repeats)
    n_s, n_p = right_points(rig, xyz, run(split)()), right_points(rig, xyz, run(plain)())
    print(
        f"{'perceive best + blend split':34s} {s_lo:8.2f} {s_med:10.2f}  ({n_s} points right)\n"
        f"{'perceive best (interleaved ref)':34s} {p_lo:8.2f} {p_med:10.2f}  ({n_p} points right)\n"
        f"ratio split / default: {s_lo / p_lo:.2f} (min), {s_med / p_med:.2f} (median)"
    )


def bench_laser(name: str, repeats: int, old_root: str | None, split: bool = False) -> None:
    rig = StereoRig.nominal()
    opts = RenderOptions.realistic()
    laser = LASERS[name]()
    xyz = scene(rig, laser)
    calib = calibrate_installed(rig, laser, seed=99, options=opts)
    cap = render_capture(rig, xyz, opts, seed=3)
    cloud = perceive(cap, calib, "best")
    right = right_points(rig, xyz, cloud)
    n_vis = int(rig.visible(rig.project(xyz)).sum())
    print(
        f"\n## laser {name}: dots cast {len(xyz)}; visible in both cameras {n_vis}; "
        f"perceived points {len(cloud.xyz)}, right {right}"
    )
    # each stage as pipeline.perceive_detailed calls it (calibration with a known source)
    assert calib.laser is not None and calib.laser.source_known
    model, sigma = calib.laser, calib.pixel_sigma_px
    d1 = detect_dots(cap.mask1, cap.base1, "best")
    d2_ = detect_dots(cap.mask2, cap.base2, "best")
    m = match_triples(calib.rig, model, sigma, d1, d2_)
    pixels = np.hstack([np.take(d1[:, :2], m.i1, axis=0), np.take(d2_[:, :2], m.i2, axis=0)])
    tr = _tracks(calib.rig, model)

    def on_beams() -> tuple[np.ndarray, np.ndarray]:
        slope, cross = np.take(tr.slope, m.beam, axis=0), np.take(tr.cross_mm, m.beam, axis=0)
        slope_sigma = tr.slope_sigma(m.beam, m.inv_depth)
        return triangulate_on_beams(calib.rig, pixels, slope, cross, slope_sigma, sigma)

    xyz_b, cov_b = on_beams()
    pc = PointCloud(xyz_b, cov_b, pixels, np.zeros(len(pixels), np.uint8), calib.floor_depth_mm)
    stages: list[tuple[str, Callable[[], object]]] = [
        (
            "detect best, both cameras",
            lambda: (
                detect_dots(cap.mask1, cap.base1, "best"),
                detect_dots(cap.mask2, cap.base2, "best"),
            ),
        ),
        ("match best (triples)", lambda: match_triples(calib.rig, model, sigma, d1, d2_)),
        ("triangulate on beams", on_beams),
        ("classify", lambda: classify(pc)),
        ("perceive best, whole", lambda: perceive(cap, calib, "best")),
        ("perceive thesis, whole (ref)", lambda: perceive(cap, calib, "thesis")),
    ]
    print(f"{'stage':34s} {'min ms':>8s} {'median ms':>10s} {'p90 ms':>8s}")
    whole: dict[str, float] = {}
    mins: dict[str, float] = {}
    for label, fn in stages:
        lo, med, p90 = timed(fn, repeats)
        whole[label], mins[label] = med, lo
        print(f"{label:34s} {lo:8.2f} {med:10.2f} {p90:8.2f}")
    rest = mins["perceive best, whole"] - sum(mins[label] for label, _ in stages[:4])
    print(f"{'rest of perceive (whole - stages)':34s} {rest:8.2f}")
    ref = whole["perceive thesis, whole (ref)"]
    best = whole["perceive best, whole"]
    print(f"ratio thesis / best (median): {ref / best:.2f}")
    if old_root:
        floor = render_capture(rig, laser.on_plane(rig.floor_depth_mm), opts, seed=99)
        old = old_best(old_root, rig, floor, cap, repeats)
        if isinstance(old, str):
            print(f"old best ({old_root}): not run: {old}")
        else:
            lo, med, p90, n = old
            print(f"{'old best, whole (ref)':34s} {lo:8.2f} {med:10.2f} {p90:8.2f}  ({n} points)")
            print(f"ratio old best / best (median): {med / best:.2f}")
            print(f"ratio old best / best (min): {lo / mins['perceive best, whole']:.2f}")
    if split:
        bench_split(rig, xyz, cap, calib, repeats)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--laser", choices=[*LASERS, "all"], default="all")
    ap.add_argument(
        "--old-root", default=None, help="also time this checkout's best (same captures)"
    )
    ap.add_argument(
        "--split-blends",
        action="store_true",
        help="also time perceive with the experimental blend split, interleaved with the default",
    )
    args = ap.parse_args(argv)
    print(one_core(cv2))
    for name in LASERS if args.laser == "all" else [args.laser]:
        bench_laser(name, args.repeats, args.old_root, args.split_blends)
    print(f"\nload average after: {load_average()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
