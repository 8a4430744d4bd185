"""Perception over random rigs × scenes × seeds: recall, wrong pairs, error, classification.

What is drawn and scored is described in :mod:`omnid.experiments.rigs`. Prints, per scene class,
the median and the worst decile over rigs, the pooled rates, and how calibration went.

    python tools/eval_rigs.py                  # 30 rigs x 7 scene classes x 2 seeds
    python tools/eval_rigs.py --quick          # 10 rigs x 7 classes x 1 seed
    python tools/eval_rigs.py --floor-only     # calibrate on the floor capture alone
    python tools/eval_rigs.py --old-root /path/to/older/checkout   # score an older pipeline
                                               # (same draws; it calibrates on the floor only)
    python tools/eval_rigs.py --approach       # phantoms driving up to a passage and a wall:
                                               # 30 rigs x 2 scenes x 65 poses (25 mm apart)
    python tools/eval_rigs.py --misses         # what the empty floor's misses are (30 rigs x 2)
    python tools/eval_rigs.py --split-blends   # any of the above with the experimental blend
                                               # split in the detector (detect._split_blends)
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def _load_experiments(old_root: str | None):
    """The evaluation module, run against this checkout or against ``old_root``'s omnid."""
    if old_root:
        sys.path.insert(0, str(Path(old_root).resolve()))
    path = HERE.parent / "omnid" / "experiments" / "rigs.py"
    spec = importlib.util.spec_from_file_location("eval_rigs_experiments", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--rigs", type=int, default=30, help="number of random rigs (30)")
    ap.add_argument("--seeds", type=int, default=2, help="scene draws per class and rig (2)")
    ap.add_argument("--scenes", default=None, help="comma-separated scene classes (all)")
    ap.add_argument("--quick", action="store_true", help="10 rigs, 1 seed")
    ap.add_argument("--floor-only", action="store_true", help="calibrate without extra captures")
    ap.add_argument("--old-root", default=None, help="score the omnid found in this checkout")
    ap.add_argument("--seed", type=int, default=0, help="draws the rigs (0)")
    ap.add_argument("--json", action="store_true", help="also print the scores as JSON")
    ap.add_argument(
        "--approach",
        action="store_true",
        help="closed-loop-like sweep: phantom points per 1000 clouds approaching a passage/wall",
    )
    ap.add_argument(
        "--misses",
        action="store_true",
        help="the empty floor's misses: separation, doubled twin, the blob's point",
    )
    ap.add_argument("--step-mm", type=float, default=25.0, help="--approach: pose step (25 mm)")
    ap.add_argument(
        "--split-blends",
        action="store_true",
        help="the detector splits blends of two spots (experimental, detect._split_blends)",
    )
    args = ap.parse_args(argv)
    import cv2

    cv2.setNumThreads(1)
    ex = _load_experiments(args.old_root)
    if args.split_blends:
        import functools

        from omnid.core import detect

        detect._detect_best = functools.partial(detect._detect_best, split_blends=True)
    import omnid

    n_rigs = 10 if args.quick else args.rigs
    seeds = list(range(1 if args.quick else args.seeds))
    scenes = args.scenes.split(",") if args.scenes else list(ex.SCENE_CLASSES)
    if args.approach:
        return _approach(ex, n_rigs, args)
    if args.misses:
        return _misses(ex, n_rigs, seeds, args)
    scores = []
    refused: list[str] = []
    src_err = []
    cal_s = []
    t_all = time.perf_counter()
    for r in range(n_rigs):
        case = ex.rig_case(r, args.seed)
        t0 = time.perf_counter()
        try:
            calib = ex.calibrate_case(case, args.seed, args.floor_only)
        except Exception as exc:
            refused.append(f"rig {r} ({case.kind}): {type(exc).__name__}: {exc}")
            scores.extend(ex.refused_scores(case, scenes, seeds))
            continue
        cal_s.append(time.perf_counter() - t0)
        laser = getattr(calib, "laser", None)
        if laser is not None and getattr(laser, "source_known", False):
            src_err.append(math.dist(tuple(laser.source_mm), tuple(case.laser.source_mm)))
        scores.extend(ex.evaluate_case(case, calib, scenes, seeds))
    print(f"omnid from {Path(omnid.__file__).resolve().parent.parent}")
    print(
        f"{n_rigs} rigs x {len(scenes)} scene classes x {len(seeds)} seeds; "
        f"calibration {'floor only' if args.floor_only or args.old_root else 'floor + 2 extras'}; "
        f"{time.perf_counter() - t_all:.0f} s"
    )
    print(ex.format_summary(scores))
    pooled = ex.pooled(scores)
    print(
        "pooled: "
        + ", ".join(
            f"{k} {100 * v:.3f} %" if k != "ms_median" else f"perceive median {v:.1f} ms"
            for k, v in pooled.items()
        )
    )
    n_clouds = sum(s.clouds for s in scores)
    print(
        f"not understood: {sum(s.not_understood for s in scores)} dots in {n_clouds} clouds; "
        f"clouds withheld from the map (>= 3 such dots: the chair stops) "
        f"{sum(s.clouds_withheld for s in scores)}"
    )
    if cal_s:
        print(
            f"calibration: {len(cal_s)} of {n_rigs} rigs, median {sorted(cal_s)[len(cal_s) // 2]:.2f} s"
        )
    if src_err:
        src_err.sort()
        print(
            f"laser source found on {len(src_err)} rigs: error median {src_err[len(src_err) // 2]:.2f} mm, "
            f"worst {src_err[-1]:.2f} mm"
        )
    for line in refused:
        print("refused:", line)
    if args.json:
        print(json.dumps([{**vars(s), "err_sum": list(s.err_sum)} for s in scores]))
    return 0


def _misses(ex, n_rigs: int, seeds: list[int], args: argparse.Namespace) -> int:
    """The empty floor's misses (``omnid.experiments.rigs.floor_misses``), binned."""
    import omnid

    t_all = time.perf_counter()
    seen, misses = 0, []
    for r in range(n_rigs):
        case = ex.rig_case(r, args.seed)
        calib = ex.calibrate_case(case, args.seed, args.floor_only)
        n, m = ex.floor_misses(case, calib, seeds)
        seen += n
        misses.extend(m)
    print(f"omnid from {Path(omnid.__file__).resolve().parent.parent}")
    print(f"{n_rigs} rigs x {len(seeds)} seeds, {time.perf_counter() - t_all:.0f} s")
    print(ex.format_misses(seen, misses))
    return 0


def _approach(ex, n_rigs: int, args: argparse.Namespace) -> int:
    """The approach sweep (``omnid.experiments.rigs.evaluate_approach``): per rig and in sum."""
    import omnid

    t_all = time.perf_counter()
    scores = []
    print(f"omnid from {Path(omnid.__file__).resolve().parent.parent}")
    print(
        "| rig | kind | clouds | points | wrong pairs | phantom points | rows | worst cloud (at mm) |"
    )
    print("|---:|---|---:|---:|---:|---:|---:|---|")
    for r in range(n_rigs):
        case = ex.rig_case(r, args.seed)
        try:
            calib = ex.calibrate_case(case, args.seed, args.floor_only)
        except Exception as exc:
            print(f"| {r} | {case.kind} | refused: {type(exc).__name__}: {exc} |")
            continue
        sc = ex.evaluate_approach(case, calib, args.seed, step_mm=args.step_mm)
        scores.append(sc)
        print(
            f"| {r} | {case.kind} | {sc.clouds} | {sc.points} | {sc.wrong} | {sc.phantom_points} "
            f"| {sc.phantom_rows} | {sc.worst_cloud} ({sc.worst_front_mm:.0f}) |",
            flush=True,
        )
    summ = ex.summarise_phantoms(scores)
    ms = [m for s in scores for m in s.ms]
    print(
        f"{len(scores)} rigs, {summ['clouds']:.0f} clouds ({time.perf_counter() - t_all:.0f} s): "
        f"phantom points per 1000 clouds median {summ['median_per_1000']:.1f}, worst decile "
        f"{summ['worst_decile_per_1000']:.1f}, pooled {summ['pooled_per_1000']:.1f}; clouds with "
        f"a phantom row (>= {ex.PHANTOM_ROW_POINTS} points) {summ['rows']:.0f}; wrong pairs "
        f"{100 * summ['wrong_share']:.3f} % of points; perceive median "
        f"{sorted(ms)[len(ms) // 2] if ms else float('nan'):.1f} ms"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
