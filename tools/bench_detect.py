"""Benchmark of laser dot detection on rendered 640x480 captures (~870 dots per camera).

Prints, for one core (cv2.setNumThreads(1)): the renderer's time, the ``best`` detector's
median time for both cameras and its accuracy (centre RMS vs truth, recall, false positives);
trackpy.locate on the same subtracted images (speed ratio and accuracy); the vectorised thesis
detector against its direct loop transcription (tests/core/thesis_oracle.py).

Run from the repository root:  python tools/bench_detect.py [--repeats 30] [--no-oracle]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
import warnings
from pathlib import Path

import cv2
import numpy as np

from omnid.core.detect import detect_dots, to_gray
from omnid.core.geometry import StereoRig
from omnid.core.laser import DotPattern
from omnid.sim.render import RenderOptions, render_capture, visible_truth

EDGE_MARGIN_PX = 4.0


def score(found: np.ndarray, truth: np.ndarray, cam, tol_px: float = 1.5):
    """(recall, false positives, centre RMS px) with one-to-one nearest-neighbour matching."""
    found = found[cam.in_disk(found[:, :2], EDGE_MARGIN_PX)] if len(found) else found
    if len(found) == 0:
        return 0.0, 0, float("nan")
    d = np.hypot(found[:, None, 0] - truth[None, :, 0], found[:, None, 1] - truth[None, :, 1])
    j = d.argmin(axis=1)
    i = d.argmin(axis=0)
    mutual = (i[j] == np.arange(len(found))) & (d.min(axis=1) < tol_px)
    err = found[mutual, :2] - truth[j[mutual]]
    return mutual.sum() / len(truth), int((~mutual).sum()), float(np.sqrt((err**2).sum(1).mean()))


def median_ms(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return 1e3 * statistics.median(times)


def trackpy_locate(sub: np.ndarray, minmass: float) -> np.ndarray:
    import trackpy

    df = trackpy.locate(sub, 7, minmass=minmass, separation=5, engine="numba")
    return df[["y", "x", "mass"]].to_numpy(dtype=np.float64)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--no-oracle", action="store_true", help="skip the slow direct transcription")
    ap.add_argument("--no-trackpy", action="store_true")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    rig = StereoRig.nominal()
    xyz = DotPattern(rows=30, cols=34, step_slope=0.07).on_plane(rig.floor_depth_mm)
    n_disk = [int(c.in_disk(c.project(xyz)).sum()) for c in (rig.cam1, rig.cam2)]
    print(
        f"python {platform.python_version()}, numpy {np.__version__}, cv2 {cv2.__version__}, "
        f"cv2 threads 1, {platform.machine()}"
    )
    print(f"dots: {len(xyz)} cast, in disk cam1/cam2: {n_disk}")
    scenes = {
        "sensor (noise, shot, flicker)": RenderOptions.realistic(
            halo_fraction=0.0, ghost_fraction=0.0
        ),
        "sensor, BGR": RenderOptions.realistic(halo_fraction=0.0, ghost_fraction=0.0, color=True),
        "realistic (+ speckled halos, ghosts)": RenderOptions.realistic(),
    }
    first = render_capture(rig, xyz, RenderOptions.realistic(), seed=0)
    t_render = median_ms(
        lambda: render_capture(rig, xyz, RenderOptions.realistic(), seed=0),
        max(args.repeats // 3, 5),
    )
    print(f"\nrender_capture (both cameras, realistic): {t_render:.1f} ms median")
    del first

    trackpy_minmass = None
    if not args.no_trackpy:
        # Fair minmass: the one with the best recall − FP rate on a separate seed.
        cap = render_capture(rig, xyz, RenderOptions.realistic(), seed=99)
        sub = to_gray(cap.base1) - to_gray(cap.mask1)
        truth = visible_truth(rig.cam1, rig.cam1.project(xyz), EDGE_MARGIN_PX)
        best_q = -1.0
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for mm in (50, 100, 200, 300, 400, 600, 800):
                rec, fp, _ = score(trackpy_locate(sub, mm), truth, rig.cam1)
                q = rec - fp / len(truth)
                if q > best_q:
                    best_q, trackpy_minmass = q, mm
        print(f"trackpy: diameter 7, separation 5, minmass {trackpy_minmass} (tuned on seed 99)")

    print(
        f"\n{'scene':40s} {'method':8s} {'ms (2 cams)':>11s} {'RMS px':>7s} {'recall':>7s} {'FP':>4s}"
    )
    for name, opts in scenes.items():
        cap = render_capture(rig, xyz, opts, seed=3)
        pairs = [(cap.mask1, cap.base1, rig.cam1), (cap.mask2, cap.base2, rig.cam2)]
        truths = [visible_truth(c, c.project(xyz), EDGE_MARGIN_PX) for _, _, c in pairs]

        def run_best(pairs=pairs):
            return [detect_dots(m, b, "best") for m, b, _ in pairs]

        def run_thesis(pairs=pairs):
            return [detect_dots(m, b, "thesis") for m, b, _ in pairs]

        rows = [("best", run_best), ("thesis", run_thesis)]
        if trackpy_minmass is not None:
            subs = [to_gray(b) - to_gray(m) for m, b, _ in pairs]

            def run_tp(subs=subs):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    return [trackpy_locate(s, trackpy_minmass) for s in subs]

            rows.append(("trackpy", run_tp))
        times = {}
        for label, fn in rows:
            reps = args.repeats if label != "trackpy" else max(args.repeats // 5, 3)
            times[label] = median_ms(fn, reps)
            res = [score(f, t, c) for f, t, (_, _, c) in zip(fn(), truths, pairs, strict=True)]
            rms = float(np.sqrt(np.mean([r[2] ** 2 for r in res])))
            rec = float(np.mean([r[0] for r in res]))
            fp = sum(r[1] for r in res)
            print(f"{name:40s} {label:8s} {times[label]:11.2f} {rms:7.3f} {rec:7.4f} {fp:4d}")
        if "trackpy" in times:
            print(f"{'':40s} speed ratio trackpy / best: {times['trackpy'] / times['best']:.1f}x")

    if not args.no_oracle:
        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "core"))
        from thesis_oracle import oracle_detect

        from omnid.core.detect import DetectionParams

        p = DetectionParams()
        cap = render_capture(rig, xyz, RenderOptions.realistic(), seed=3)
        t = time.perf_counter()
        slow = oracle_detect(
            cap.mask1,
            cap.base1,
            block_px=p.block_px,
            block_coefficient=p.block_coefficient,
            min_peak_gray=p.min_peak_gray,
            e1=p.ring_e1_gray,
            e2=p.ring_e2_gray,
            e3=p.ring_e3_gray,
            e4=p.e4_gray,
        )
        t_slow = 1e3 * (time.perf_counter() - t)
        t_fast = median_ms(lambda: detect_dots(cap.mask1, cap.base1, "thesis"), args.repeats)
        fast = detect_dots(cap.mask1, cap.base1, "thesis")
        same = np.array_equal(np.array(slow, dtype=np.float64).reshape(-1, 3), fast)
        print(
            f"\nthesis, one camera: direct transcription {t_slow:.0f} ms, vectorised "
            f"{t_fast:.2f} ms, ratio {t_slow / t_fast:.0f}x, same dots: {same} ({len(fast)})"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
