"""Benchmark of laser dot detection: accuracy per spot model, and speed, on ONE core.

1. Spot models (the issue-9 goal: centres ≤ 0.05 px RMS, median over spot models, ≤ 0.08 px in
   the worst): for every family of omnid.sim.render.SPOT_KINDS, ``--draws`` cases, each a
   random rig, a random laser, a spot model drawn from the family and the realistic sensor
   (omnid.experiments.detection). Per family: the pooled centre RMS over all its cases, the
   median and the worst case's RMS, the smallest recall, the false dots, the "floor" (the
   centre error of the model's own noise-free isolated spots: speckle and halo grains, which no
   detector removes) and the time of both cameras; for ``best`` now, ``best`` at ``--before``
   (loaded from git) and, on ``--trackpy-draws`` cases per family, trackpy.locate.
2. Speed on the standard scene of earlier runs (a dense regular lattice, ~870 dots per camera,
   realistic options): min and median of ``--repeats`` runs of best now / before / thesis /
   trackpy, and ratios measured in the same run; the renderer's time.
3. The vectorised thesis detector against its loop transcription (tests/core/thesis_oracle.py).

Everything runs on one core (cv2.setNumThreads(1), one BLAS thread); the load average is
printed (the machine may be shared: prefer the mins and the same-run ratios).

Run from the repository root (``pip install -e '.[test,bench]'``):
    python tools/bench_detect.py [--draws 10] [--repeats 30] [--before REV] [--no-oracle]
                                 [--learned-shape] [--split-blends]
"""

from __future__ import annotations

import os

# One core: BLAS threads must be fixed before numpy is imported.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import types  # noqa: E402
import warnings  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from omnid.core.detect import DetectionParams, _detect_best, detect_dots, to_gray  # noqa: E402
from omnid.core.geometry import StereoRig  # noqa: E402
from omnid.experiments import detection  # noqa: E402
from omnid.experiments.machine import load_average, one_core  # noqa: E402
from omnid.sim.laser import ideal_lattice  # noqa: E402
from omnid.sim.render import SPOT_KINDS, RenderOptions, render_capture, visible_truth  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: The detector before the spot-model work (issue 9), for the same-run comparison.
DEFAULT_BEFORE = "df0ce50"
Detector = Callable[[np.ndarray, np.ndarray], np.ndarray]


def timed(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    """(min, median) wall time of ``fn`` in ms over ``repeats`` runs after one warm-up."""
    fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return 1e3 * min(times), 1e3 * statistics.median(times)


def load_module_at(rev: str, path: str, name: str) -> types.ModuleType | None:
    """The module at ``path`` as it was at git revision ``rev`` (None outside a checkout)."""
    try:
        src = subprocess.run(
            ["git", "show", f"{rev}:{path}"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    mod = types.ModuleType(name)
    mod.__file__ = f"{rev}:{path}"
    sys.modules[name] = mod  # dataclasses look their module up
    exec(compile(src, mod.__file__, "exec"), mod.__dict__)
    return mod


def trackpy_detector(minmass: float) -> Detector:
    """trackpy.locate (diameter 7, separation 5, numba) on the float subtracted image."""
    import trackpy

    def locate(mask: np.ndarray, base: np.ndarray) -> np.ndarray:
        sub = to_gray(base) - to_gray(mask)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            df = trackpy.locate(sub, 7, minmass=minmass, separation=5, engine="numba")
        return df[["y", "x", "mass"]].to_numpy(dtype=np.float64)

    return locate


def tune_trackpy() -> float:
    """The minmass with the best recall − false-dot rate on a separate case of each family."""
    best_q, best_mm = -np.inf, 200.0
    cases = [detection.case(kind, 99) for kind in SPOT_KINDS]
    for mm in (50.0, 100.0, 200.0, 300.0, 400.0, 600.0):
        locate = trackpy_detector(mm)
        q = 0.0
        for cs in cases:
            t, iso = cs.truth(1)
            s = detection.score(locate(cs.capture.mask1, cs.capture.base1), t, iso, cs.rig.cam1)
            q += s.recall - s.false_dots / max(s.dots, 1)
        if q > best_q:
            best_q, best_mm = q, mm
    return best_mm


def spot_models(
    draws: int,
    detectors: dict[str, Detector],
    trackpy_draws: int,
    trackpy: Detector | None,
    bound_dots: int = 40,
) -> None:
    """Section 1: per family, every detector on the same cases."""
    names = [*detectors, *(["trackpy"] if trackpy is not None else [])]
    print(
        f"\n1. Spot models: {draws} cases per family (random rig, random laser, the family's "
        "random spot model, realistic sensor; floor and three boxes alternate)."
    )
    print(
        "   RMS: centre error over isolated matched dots, px (pooled over the family's cases; "
        "median and worst case); recall: the smallest of any image; FP: false dots in all its "
        "images; floor: the model's irreducible error; ms: both cameras, median."
    )
    print(
        "   Achievable, for best: 'floor' is the RMS shift of the noise-free centroid of the "
        "model's own isolated spots (speckle grains on the dot and in its halo; 0 without "
        "grains), median over the cases; 'no grains' is best on the same cases rendered "
        "without grains (sensor noise and neighbours only); 'ref' = floor ⊕ no grains per "
        "case (an estimate of what a detector can reach, not a bound); 'CRLB' is the "
        "Cramér–Rao lower bound of the centre error from the rendered spot model, the noise, "
        "the pixel integration, clipping and the grains (omnid.experiments.detection."
        "centre_bound_px), as an RMS over --bound-dots isolated dots per camera, the "
        "neighbours known; 'CRLB joint': the same with every neighbour in the dot's window "
        "unknown too (centre, brightness, blur; half the dots) — what crowding costs."
    )
    head = f"   {'family':10s} {'detector':12s} {'pooled':>7s} {'median':>7s} {'worst':>7s} "
    print(head + f"{'recall':>7s} {'FP':>5s} {'floor':>6s} {'ms':>6s}")
    pooled: dict[str, list[float]] = {n: [] for n in names}
    every_case: dict[str, list[float]] = {n: [] for n in names}
    reference: list[float] = []
    bound: list[float] = []
    bound_joint: list[float] = []
    for kind in SPOT_KINDS:
        cases = [detection.case(kind, k) for k in range(draws)]
        floors = [detection.spot_floor_px(c.spots, c.rig.cam1, 7) for c in cases]
        floor = float(np.median(floors))
        results: dict[str, list[list[detection.Score]]] = {}
        for name in names:
            fn = trackpy if name == "trackpy" else detectors[name]
            use = cases[:trackpy_draws] if name == "trackpy" else cases
            per_case, times = [], []
            for cs in use:
                cap = cs.capture
                t0 = time.perf_counter()
                found = [fn(cap.mask1, cap.base1), fn(cap.mask2, cap.base2)]  # type: ignore[misc]
                times.append(1e3 * (time.perf_counter() - t0))
                cams = (cs.rig.cam1, cs.rig.cam2)
                per_case.append(
                    [
                        detection.score(f, *cs.truth(k), cam)
                        for k, (f, cam) in enumerate(zip(found, cams, strict=True), 1)
                    ]
                )
            results[name] = per_case
            scores = [s for case_scores in per_case for s in case_scores]
            rms = detection.pooled_rms(scores)
            pooled[name].append(rms)
            case_rms = [detection.pooled_rms(c) for c in per_case]
            every_case[name] += case_rms
            common = ""
            if name != "best" and name != "trackpy":
                # best on the very dots this detector found: like with like
                mine = [
                    b.on(o.matched)
                    for bc, oc in zip(results["best"], per_case, strict=True)
                    for b, o in zip(bc, oc, strict=True)
                ]
                common = f"  (best on the same dots {detection.pooled_rms(mine):.3f})"
            print(
                f"   {kind:10s} {name:12s} {rms:7.3f} {np.nanmedian(case_rms):7.3f} "
                f"{np.nanmax(case_rms):7.3f} {min(s.recall for s in scores):7.3f} "
                f"{sum(s.false_dots for s in scores):5d} {floor:6.3f} "
                f"{statistics.median(times):6.1f}{common}"
            )
        clean = [
            no_grains_rms(cs, detectors["best"], rms)
            for cs, rms in zip(
                cases, (detection.pooled_rms(c) for c in results["best"]), strict=True
            )
        ]
        ref = [float(np.hypot(f, g)) for f, g in zip(floors, clean, strict=True)]
        reference += ref
        print(
            f"   {kind:10s} {'  no grains':12s} {'':>7s} {np.nanmedian(clean):7.3f} {np.nanmax(clean):7.3f}   ref: median case "
            f"{np.nanmedian(ref):.3f}, worst {np.nanmax(ref):.3f}"
        )
        crlb = [detection.bound_rms_px(cs, bound_dots) for cs in cases]
        bound += crlb
        best_rms = [detection.pooled_rms(c) for c in results["best"]]
        excess = [m / b for m, b in zip(best_rms, crlb, strict=True)]
        gap = [float(np.sqrt(max(m * m - b * b, 0.0))) for m, b in zip(best_rms, crlb, strict=True)]
        print(
            f"   {kind:10s} {'  CRLB':12s} {'':>7s} {np.nanmedian(crlb):7.3f} {np.nanmax(crlb):7.3f}   "
            f"best/CRLB median {np.nanmedian(excess):.2f}x, worst {np.nanmax(excess):.2f}x; "
            f"excess √(best²−CRLB²) median {np.nanmedian(gap):.3f}, worst {np.nanmax(gap):.3f}"
        )
        joint = [detection.bound_rms_px(cs, max(bound_dots // 2, 5), joint=True) for cs in cases]
        bound_joint += joint
        excess_j = [m / b for m, b in zip(best_rms, joint, strict=True)]
        print(
            f"   {kind:10s} {'  CRLB joint':12s} {'':>7s} {np.nanmedian(joint):7.3f} {np.nanmax(joint):7.3f}   "
            f"best/joint median {np.nanmedian(excess_j):.2f}x, worst {np.nanmax(excess_j):.2f}x"
        )
        print(
            "     per case (best / CRLB / joint): "
            + ", ".join(
                f"{m:.3f}/{b:.3f}/{j:.3f}" for m, b, j in zip(best_rms, crlb, joint, strict=True)
            )
        )
    print("   over the families (pooled RMS per family):")
    for name, values in pooled.items():
        v = np.asarray(values)
        print(f"     {name:12s} median {np.nanmedian(v):.3f} px, worst {np.nanmax(v):.3f} px")
    print("   over every case (one spot model each): median, worst decile (90th pct), worst")
    for name, values in [
        *every_case.items(),
        ("ref (best)", reference),
        ("CRLB", bound),
        ("CRLB joint", bound_joint),
    ]:
        v = np.asarray(values)
        print(
            f"     {name:12s} median {np.nanmedian(v):.3f} px, worst decile "
            f"{np.nanpercentile(v, 90):.3f} px, worst {np.nanmax(v):.3f} px ({len(v)} cases)"
        )


def no_grains_rms(cs: detection.Case, best: Detector, with_grains_rms: float) -> float:
    """best's RMS on the case rendered without grains (= ``with_grains_rms`` if it has none)."""
    if not detection.has_grains(cs.spots):
        return with_grains_rms
    clean = detection.case(cs.kind, cs.index, grains=False)  # type: ignore[arg-type]
    cap = clean.capture
    found = [best(cap.mask1, cap.base1), best(cap.mask2, cap.base2)]
    cams = (clean.rig.cam1, clean.rig.cam2)
    return detection.pooled_rms(
        [
            detection.score(f, *clean.truth(k), cam)
            for k, (f, cam) in enumerate(zip(found, cams, strict=True), 1)
        ]
    )


def standard_scene(repeats: int, detectors: dict[str, Detector], trackpy: Detector | None) -> None:
    """Section 2: the dense lattice scene of earlier runs, timed."""
    rig = StereoRig.nominal()
    xyz = ideal_lattice(30, 35, 0.07, 0.28).on_plane(rig.floor_depth_mm)
    print(
        f"\n2. Speed, standard scene: ideal_lattice(30, 35, 0.07, 0.28) on the floor, "
        f"{[int(c.in_disk(c.project(xyz)).sum()) for c in (rig.cam1, rig.cam2)]} dots in the "
        "disks, realistic options, seed 3; both cameras."
    )
    reps_render = max(repeats // 3, 5)
    lo, med = timed(
        lambda: render_capture(rig, xyz, RenderOptions.realistic(), seed=0), reps_render
    )
    print(f"   render_capture (realistic)  min {lo:6.1f} ms  median {med:6.1f} ms")
    cap = render_capture(rig, xyz, RenderOptions.realistic(), seed=3)
    truths = [
        visible_truth(c, c.project(xyz), detection.EDGE_MARGIN_PX) for c in (rig.cam1, rig.cam2)
    ]
    rows = dict(detectors)
    rows["thesis"] = lambda m, b: detect_dots(m, b, "thesis")
    if trackpy is not None:
        rows["trackpy"] = trackpy
    mins = {}
    print(
        f"   {'detector':12s} {'min ms':>7s} {'med ms':>7s} {'RMS px':>7s} {'recall':>7s} {'FP':>4s}"
    )
    for name, fn in rows.items():
        reps = repeats if name != "trackpy" else max(repeats // 10, 2)
        lo, med = timed(lambda fn=fn: (fn(cap.mask1, cap.base1), fn(cap.mask2, cap.base2)), reps)
        mins[name] = lo
        s = [
            detection.score(fn(m, b), t, np.ones(len(t), bool), cam)
            for (m, b, cam), t in zip(
                ((cap.mask1, cap.base1, rig.cam1), (cap.mask2, cap.base2, rig.cam2)),
                truths,
                strict=True,
            )
        ]
        print(
            f"   {name:12s} {lo:7.2f} {med:7.2f} {detection.pooled_rms(s):7.3f} "
            f"{min(x.recall for x in s):7.4f} {sum(x.false_dots for x in s):4d}"
        )
    ratios = ", ".join(f"{k} / best {mins[k] / mins['best']:.2f}x" for k in mins if k != "best")
    print(f"   ratios of min times (same run): {ratios}")


def oracle_check(repeats: int) -> None:
    """Section 3: vectorised thesis detector = its loop transcription."""
    sys.path.insert(0, str(ROOT / "tests" / "core"))
    from thesis_oracle import oracle_detect

    rig = StereoRig.nominal()
    xyz = ideal_lattice(30, 35, 0.07, 0.28).on_plane(rig.floor_depth_mm)
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
    t_fast, _ = timed(lambda: detect_dots(cap.mask1, cap.base1, "thesis"), repeats)
    fast = detect_dots(cap.mask1, cap.base1, "thesis")
    same = np.array_equal(np.array(slow, dtype=np.float64).reshape(-1, 3), fast)
    print(
        f"\n3. Thesis method, one camera: direct transcription {t_slow:.0f} ms, vectorised "
        f"{t_fast:.2f} ms (min), {t_slow / t_fast:.0f}x, same dots: {same} ({len(fast)})"
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=10, help="cases per spot family")
    ap.add_argument("--trackpy-draws", type=int, default=2, help="of them, for trackpy (slow)")
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--before", default=DEFAULT_BEFORE, help="git revision to compare with")
    ap.add_argument("--no-oracle", action="store_true", help="skip the slow direct transcription")
    ap.add_argument("--no-trackpy", action="store_true")
    ap.add_argument(
        "--bound-dots", type=int, default=40, help="isolated dots per camera for the CRLB"
    )
    ap.add_argument(
        "--learned-shape",
        action="store_true",
        help="also score best with the experimental learned-shape joint fit (omnid.core.spotshape)",
    )
    ap.add_argument(
        "--split-blends",
        action="store_true",
        help="also score best with the experimental two-spot split of blends (detect._split_blends)",
    )
    args = ap.parse_args()
    print(one_core(cv2))
    detectors: dict[str, Detector] = {"best": lambda m, b: detect_dots(m, b, "best")}
    old = load_module_at(args.before, "omnid/core/detect.py", "detect_before")
    if old is not None:
        detectors["best before"] = lambda m, b: old.detect_dots(m, b, "best")
    print(f"before = {args.before}" + ("" if old else " (not found: skipped)"))
    trackpy = None
    if not args.no_trackpy:
        try:
            minmass = tune_trackpy()
        except ImportError:
            print("trackpy not installed: skipped (pip install -e '.[bench]')")
        else:
            trackpy = trackpy_detector(minmass)
            print(f"trackpy: diameter 7, separation 5, minmass {minmass:g} (tuned on case 99)")
    spot_detectors = dict(detectors)
    if args.learned_shape:
        spot_detectors["learned shape"] = lambda m, b: _detect_best(
            m, b, DetectionParams(), learned_shape=True
        )
    if args.split_blends:
        detectors["split blends"] = lambda m, b: _detect_best(
            m, b, DetectionParams(), split_blends=True
        )
        spot_detectors["split blends"] = detectors["split blends"]
    spot_models(args.draws, spot_detectors, args.trackpy_draws, trackpy, args.bound_dots)
    standard_scene(args.repeats, detectors, trackpy)
    if not args.no_oracle:
        oracle_check(args.repeats)
    print(f"\nload average after: {load_average()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
